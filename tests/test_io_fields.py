"""Per-point fields of a written cloud (esmicp.write_points(scan_index=, colors=)): a merged cloud
keeps which scan each point came from, and a colour per scan, in the files CloudCompare, Open3D
and PCL read; esmicp.read_points still reads their x y z exactly."""

from __future__ import annotations

import warnings

import numpy as np
import plyfile
import pytest
from conftest import require_module

import esmicp
from esmicp.errors import InvalidInputError
from esmicp.io import FIELD_EXTENSIONS, DroppedFieldsWarning, scan_palette


def _merged(count=600, scans=14, seed=0):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(count, 3)) * 1e3
    labels = rng.integers(0, scans, count)
    return points, labels, scan_palette(scans)[labels]


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_a_merged_ply_keeps_the_scan_index_and_the_colours(tmp_path, encoding):
    points, labels, colours = _merged()
    path = tmp_path / "merged.ply"
    esmicp.write_points(path, points, scan_index=labels, colors=colours, ply_format=encoding)
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    assert {p.name: p.val_dtype for p in vertex.properties}["scan_index"] in ("i4", "int32")
    np.testing.assert_array_equal(vertex["scan_index"], labels)
    np.testing.assert_array_equal(np.stack([vertex[c] for c in ("red", "green", "blue")], axis=1), colours)
    np.testing.assert_array_equal(np.stack([vertex[c] for c in "xyz"], axis=1), points)
    np.testing.assert_array_equal(esmicp.read_points(path), points)


@pytest.mark.parametrize("encoding", ["binary", "ascii", "binary_compressed"])
def test_a_merged_pcd_keeps_the_scan_index_and_the_colours(tmp_path, encoding):
    from pypcd4 import PointCloud

    points, labels, colours = _merged()
    path = tmp_path / "merged.pcd"
    esmicp.write_points(path, points, scan_index=labels, colors=colours, pcd_format=encoding)
    cloud = PointCloud.from_path(path)
    assert cloud.fields == ("x", "y", "z", "rgb", "scan_index")
    np.testing.assert_array_equal(cloud.numpy(("scan_index",))[:, 0], labels)
    packed = cloud.numpy(("rgb",))[:, 0].astype(np.uint32)
    np.testing.assert_array_equal(np.stack([packed >> 16, (packed >> 8) & 255, packed & 255], axis=1), colours)
    np.testing.assert_array_equal(esmicp.read_points(path), points)


def test_open3d_reads_the_colours_and_the_scan_index(tmp_path):
    o3d = require_module("open3d", "baselines")
    points, labels, colours = _merged()
    ply, pcd = tmp_path / "merged.ply", tmp_path / "merged.pcd"
    esmicp.write_points(ply, points, scan_index=labels, colors=colours)
    esmicp.write_points(pcd, points, scan_index=labels, colors=colours)
    cloud = o3d.io.read_point_cloud(str(ply))
    np.testing.assert_array_equal(np.asarray(cloud.points), points)
    np.testing.assert_array_equal(np.round(np.asarray(cloud.colors) * 255).astype(np.uint8), colours)
    for path in (ply, pcd):  # the tensor API: float64 coordinates and every field
        cloud = o3d.t.io.read_point_cloud(str(path))
        np.testing.assert_array_equal(cloud.point.positions.numpy(), points)
        np.testing.assert_array_equal(cloud.point.scan_index.numpy().ravel(), labels)
        colours_read = cloud.point.colors.numpy()
        if colours_read.dtype.kind == "f":
            colours_read = np.round(colours_read * 255)
        np.testing.assert_array_equal(colours_read.astype(np.uint8), colours)


@pytest.mark.parametrize("extension", [".xyz", ".csv", ".npy"])
def test_plain_formats_hold_x_y_z_only_and_say_so(tmp_path, extension):
    points, labels, colours = _merged()
    path = tmp_path / f"merged{extension}"
    with pytest.warns(DroppedFieldsWarning):
        esmicp.write_points(path, points, scan_index=labels, colors=colours)
    np.testing.assert_array_equal(esmicp.read_points(path), points)
    assert extension not in FIELD_EXTENSIONS
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fields asked for: nothing to say
        esmicp.write_points(tmp_path / f"plain{extension}", points)


def test_points_dropped_as_non_finite_take_their_fields_with_them(tmp_path):
    points, labels, colours = _merged(50)
    points[[3, 17]] = np.nan
    path = tmp_path / "merged.ply"
    with pytest.warns(esmicp.NonFinitePointsWarning):
        esmicp.write_points(path, points, scan_index=labels, colors=colours)
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    keep = np.isfinite(points).all(axis=1)
    np.testing.assert_array_equal(vertex["scan_index"], labels[keep])
    np.testing.assert_array_equal(vertex["red"], colours[keep, 0])


def test_fields_that_are_not_one_valid_value_per_point_are_refused(tmp_path):
    points, labels, colours = _merged(50)
    path = tmp_path / "merged.ply"
    for kwargs in ({"scan_index": labels[:-1]}, {"scan_index": labels - 1}, {"scan_index": labels + 0.5},
                   {"colors": colours[:, :2]}, {"colors": colours.astype(int) + 200}, {"scan_index": "abc"}):
        with pytest.raises(InvalidInputError):
            esmicp.write_points(path, points, **kwargs)
        assert not path.exists()


def test_the_scan_palette_gives_every_scan_its_own_colour():
    for count in (0, 1, 10, 100, 2000):
        palette = scan_palette(count)
        assert palette.shape == (count, 3) and palette.dtype == np.uint8
        assert len({tuple(c) for c in palette.tolist()}) == count
    np.testing.assert_array_equal(scan_palette(100)[:30], scan_palette(30))  # a scan keeps its colour
    with pytest.raises(InvalidInputError):
        scan_palette(-1)
