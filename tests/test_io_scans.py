"""Tests of the scan readers: headerless float32 ``.bin`` (KITTI velodyne) and LAS / LAZ."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest
from conftest import require_shared

from esmicp.cli import main
from esmicp.errors import InvalidInputError, MissingDependencyError, PointCloudFileError
from esmicp.io import READ_EXTENSIONS, read_points


def cloud(seed: int, count: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(scale=20.0, size=(count, 3))


def write_bin(path, points: np.ndarray, columns: int) -> np.ndarray:
    """Write ``points`` as float32 ``columns``-column records; return the float64 x y z to expect."""
    records = np.zeros((len(points), columns), dtype="<f4")
    records[:, :3] = points
    if columns == 4:
        records[:, 3] = np.linspace(0.0, 1.0, len(points))  # intensity
    records.tofile(path)
    return records[:, :3].astype(np.float64)


def assert_file_error(excinfo, path, *words):
    message = str(excinfo.value)
    assert message.startswith(str(path)), message
    assert "\n" not in message
    for word in words:
        assert word in message, (word, message)


def test_new_extensions_are_listed():
    assert {".bin", ".las", ".laz"} <= set(READ_EXTENSIONS)


# ---- .bin ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("columns", [3, 4])
def test_bin_round_trip_with_columns_given(tmp_path, columns):
    path = tmp_path / "scan.bin"
    expected = write_bin(path, cloud(columns, 1001), columns)
    points = read_points(path, bin_columns=columns)
    assert points.dtype == np.float64 and points.shape == (1001, 3)
    np.testing.assert_array_equal(points, expected)


@pytest.mark.parametrize(("columns", "count"), [(4, 1001), (3, 1001), (4, 7), (3, 5)])
def test_bin_layout_from_an_unambiguous_size(tmp_path, columns, count):
    # 1001 points: 12012 bytes (3 columns, not a multiple of 16) or 16016 bytes (not of 12).
    path = tmp_path / "scan.bin"
    expected = write_bin(path, cloud(count, count), columns)
    np.testing.assert_array_equal(read_points(path), expected)


def test_bin_ambiguous_size_needs_the_option(tmp_path):
    # 1000 points x 3 columns = 12000 bytes = 750 x 16 bytes: either layout fits.
    path = tmp_path / "scan.bin"
    expected = write_bin(path, cloud(0, 1000), 3)
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "12000 bytes", "both", "bin_columns", "--bin-columns")
    np.testing.assert_array_equal(read_points(path, bin_columns=3), expected)
    assert read_points(path, bin_columns=4).shape == (750, 3)


@pytest.mark.parametrize("size", [12014, 12020, 40, 3])
def test_bin_size_fitting_neither_layout(tmp_path, size):
    assert size % 12 and size % 16
    path = tmp_path / "scan.bin"
    path.write_bytes(b"\x00" * size)
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "fits neither", "truncated")


def test_bin_size_not_fitting_the_columns_given_says_which_fits(tmp_path):
    path = tmp_path / "scan.bin"
    write_bin(path, cloud(1, 1001), 3)  # 12012 bytes: 3 columns only
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path, bin_columns=4)
    assert_file_error(excinfo, path, "12012 bytes", "4-column", "bin_columns=3")


@pytest.mark.parametrize("bad", [2, 5, 0, "3", True, 3.0])
def test_bin_columns_validated(tmp_path, bad):
    path = tmp_path / "scan.bin"
    write_bin(path, cloud(2, 10), 3)
    with pytest.raises(InvalidInputError, match="bin_columns"):
        read_points(path, bin_columns=bad)


def test_bin_columns_ignored_for_other_formats(tmp_path):
    path = tmp_path / "cloud.npy"
    np.save(path, cloud(3, 20))
    assert read_points(path, bin_columns=4).shape == (20, 3)


def test_bin_non_finite_rows_dropped(tmp_path):
    path = tmp_path / "scan.bin"
    points = cloud(4, 11)
    points[3] = np.nan
    write_bin(path, points, 4)
    with pytest.warns(UserWarning):
        assert read_points(path).shape == (10, 3)


def test_bin_cli_register(tmp_path, capsys):
    target = cloud(5, 401)
    angle = np.radians(20.0)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    source = (target - [1.0, 2.0, 0.5]) @ rotation  # target = R source + t
    write_bin(tmp_path / "t.bin", target, 3)
    write_bin(tmp_path / "s.bin", source[:400], 3)  # 400 points: ambiguous without the flag
    code = main(["register", str(tmp_path / "s.bin"), str(tmp_path / "t.bin"), "--json"])
    err = capsys.readouterr().err
    assert code == 2 and "s.bin" in err and "--bin-columns" in err
    code = main(["register", str(tmp_path / "s.bin"), str(tmp_path / "t.bin"), "--bin-columns", "3", "--json"])
    assert code == 0, capsys.readouterr().err


def test_shared_scans_read_with_three_columns():
    folder = require_shared("real_pairs/newer_college_01")
    path = folder / "planes_000000.bin"
    points = read_points(path, bin_columns=3)
    assert 19_968 <= len(points) <= 21_085
    assert path.stat().st_size == 12 * len(points)
    extent = points.max(axis=0) - points.min(axis=0)
    assert 10.0 < extent.max() < 500.0  # metres: a campus scan, not garbage floats


# ---- LAS / LAZ ---------------------------------------------------------------------------------------

if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
    import laspy  # CI installs the `las` extra: its absence there is a broken setup, not a skip
else:
    laspy = pytest.importorskip("laspy")


def write_las(path, points: np.ndarray, scale: float = 0.001, offset=(1000.0, 2000.0, 10.0)) -> np.ndarray:
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.full(3, scale)
    header.offsets = np.asarray(offset, dtype=np.float64)
    data = laspy.LasData(header)
    data.x, data.y, data.z = (points[:, axis] + offset[axis] for axis in range(3))
    data.write(path)
    return np.stack([np.asarray(data.x), np.asarray(data.y), np.asarray(data.z)], axis=1)


@pytest.mark.parametrize("name", ["survey.las", "survey.laz", "SURVEY.LAZ"])
def test_las_round_trip(tmp_path, name):
    path = tmp_path / name
    expected = write_las(path, cloud(6, 500))
    points = read_points(path)
    assert points.dtype == np.float64 and points.shape == (500, 3)
    np.testing.assert_array_equal(points, expected)
    # scaled coordinates, not the raw integers: within the scale of what was written
    np.testing.assert_allclose(points - [1000.0, 2000.0, 10.0], cloud(6, 500), atol=0.001)


def test_las_read_in_chunks(tmp_path, monkeypatch):
    import esmicp.io.las as las_module

    monkeypatch.setattr(las_module, "CHUNK_POINTS", 64)
    path = tmp_path / "survey.laz"
    expected = write_las(path, cloud(7, 300))
    np.testing.assert_array_equal(read_points(path), expected)


def test_las_missing_laspy_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "survey.las"
    write_las(path, cloud(8, 10))
    monkeypatch.setitem(sys.modules, "laspy", None)  # import laspy now raises ImportError
    with pytest.raises(MissingDependencyError) as excinfo:
        read_points(path)
    message = str(excinfo.value)
    assert message.startswith(str(path)) and "laspy" in message and "esmicp[las]" in message
    assert "\n" not in message


def test_laz_without_backend_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "survey.laz"
    write_las(path, cloud(9, 10))
    monkeypatch.setattr(laspy.LazBackend, "detect_available", staticmethod(lambda: ()))
    with pytest.raises(MissingDependencyError, match=r"LAZ backend.*esmicp\[las\]"):
        read_points(path)


@pytest.mark.parametrize(
    ("damage", "words"),
    [
        (lambda data: b"NOPE" + data[4:], ["not a valid LAS"]),
        (lambda data: data[:100], ["LAS"]),  # header cut in half
        (lambda data: data[:-340], ["truncated", "500 points"]),  # 10 of 500 points cut off
        (lambda data: b"hello world, not a LAS file\n" * 20, ["not a valid LAS"]),
    ],
)
def test_corrupt_las_is_one_clear_error(tmp_path, damage, words):
    path = tmp_path / "bad.las"
    write_las(path, cloud(10, 500))
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, *words)


def test_las_header_declaring_too_many_points_is_refused_before_reading(tmp_path):
    path = tmp_path / "liar.las"
    write_las(path, cloud(11, 50))
    data = bytearray(path.read_bytes())
    data[107:111] = (10**9).to_bytes(4, "little")  # LAS 1.2 legacy point count
    path.write_bytes(bytes(data))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "truncated", "1000000000 points")


def test_corrupt_laz_data_is_one_clear_error(tmp_path):
    path = tmp_path / "bad.laz"
    write_las(path, cloud(12, 2000))
    data = bytearray(path.read_bytes())
    cut = len(data) // 2
    path.write_bytes(bytes(data[:cut]))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "corrupt or truncated LAZ point data")
