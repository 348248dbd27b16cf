"""Tests of the headerless float32 ``.bin`` reader (KITTI velodyne); LAS / LAZ: test_io_las.py."""

from __future__ import annotations


import numpy as np
import pytest
from conftest import assert_file_error, random_cloud, require_shared

from esmicp.cli import main
from esmicp.errors import InvalidInputError, PointCloudFileError
from esmicp.io import READ_EXTENSIONS, read_points


def write_bin(path, points: np.ndarray, columns: int) -> np.ndarray:
    """Write ``points`` as float32 ``columns``-column records; return the float64 x y z to expect."""
    records = np.zeros((len(points), columns), dtype="<f4")
    records[:, :3] = points
    if columns == 4:
        records[:, 3] = np.linspace(0.0, 1.0, len(points))  # intensity
    records.tofile(path)
    return records[:, :3].astype(np.float64)


def test_new_extensions_are_listed():
    assert {".bin", ".las", ".laz"} <= set(READ_EXTENSIONS)


# ---- .bin ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("columns", [3, 4])
def test_bin_round_trip_with_columns_given(tmp_path, columns):
    path = tmp_path / "scan.bin"
    expected = write_bin(path, random_cloud(columns, 1001), columns)
    points = read_points(path, bin_columns=columns)
    assert points.dtype == np.float64 and points.shape == (1001, 3)
    np.testing.assert_array_equal(points, expected)


@pytest.mark.parametrize(("columns", "count"), [(4, 1001), (3, 1001), (4, 7), (3, 5)])
def test_bin_layout_from_an_unambiguous_size(tmp_path, columns, count):
    # 1001 points: 12012 bytes (3 columns, not a multiple of 16) or 16016 bytes (not of 12).
    path = tmp_path / "scan.bin"
    expected = write_bin(path, random_cloud(count, count), columns)
    np.testing.assert_array_equal(read_points(path), expected)


def street(seed: int, count: int) -> np.ndarray:
    """A LiDAR-like scene (metres): a road 80 m long and 20 m wide, two facades 5 m high, the sensor
    1.7 m above the road: x, y and z span different ranges, as a scan's do."""
    rng = np.random.default_rng(seed)
    road = count // 2
    x = rng.uniform(-40.0, 40.0, count)
    y = np.where(np.arange(count) < road, rng.uniform(-10.0, 10.0, count), rng.choice([-10.0, 10.0], count))
    z = np.where(np.arange(count) < road, -1.7, rng.uniform(-1.7, 3.3, count)) + rng.normal(0.0, 0.02, count)
    return np.column_stack([x, y, z])


@pytest.mark.parametrize(("columns", "count"), [(3, 4000), (4, 3000)])
def test_bin_layout_told_by_the_values_when_the_size_fits_both(tmp_path, columns, count):
    """48,000 bytes: 4,000 points of 3 columns or 3,000 of 4. Read with the wrong count, each row
    shifts by one value; the reader takes the layout whose values read as points."""
    path = tmp_path / "scan.bin"
    expected = write_bin(path, street(columns, count), columns)
    assert path.stat().st_size % 48 == 0
    np.testing.assert_array_equal(read_points(path), expected)
    np.testing.assert_array_equal(read_points(path, bin_columns=columns), expected)  # the same when said


def test_bin_whose_values_read_as_points_either_way_needs_the_option(tmp_path):
    """An isotropic blob (x, y, z drawn alike) reads as points in both layouts: refused, the
    message naming the file and the option; with the option it is read."""
    path = tmp_path / "blob.bin"
    expected = write_bin(path, random_cloud(0, 4000), 3)  # 48,000 bytes
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "48000 bytes", "both", "either way", "bin_columns", "--bin-columns")
    np.testing.assert_array_equal(read_points(path, bin_columns=3), expected)


def test_bin_ambiguous_size_with_too_few_points_to_tell_needs_the_option(tmp_path):
    # 1000 points x 3 columns = 12000 bytes = 750 x 16 bytes: either layout fits, too few to tell.
    path = tmp_path / "scan.bin"
    expected = write_bin(path, street(0, 1000), 3)
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "12000 bytes", "both", "too few", "bin_columns", "--bin-columns")
    np.testing.assert_array_equal(read_points(path, bin_columns=3), expected)
    assert read_points(path, bin_columns=4).shape == (750, 3)


def test_float64_values_in_a_bin_read_as_points_neither_way(tmp_path):
    """Doubles are no float32 scan: neither layout reads them as points, so the file is refused."""
    path = tmp_path / "doubles.bin"
    street(1, 3000).astype("<f8").tofile(path)  # 72,000 bytes
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "72000 bytes", "--bin-columns")


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
    write_bin(path, random_cloud(1, 1001), 3)  # 12012 bytes: 3 columns only
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path, bin_columns=4)
    assert_file_error(excinfo, path, "12012 bytes", "4-column", "bin_columns=3")


@pytest.mark.parametrize("bad", [2, 5, 0, "3", True, 3.0])
def test_bin_columns_validated(tmp_path, bad):
    path = tmp_path / "scan.bin"
    write_bin(path, random_cloud(2, 10), 3)
    with pytest.raises(InvalidInputError, match="bin_columns"):
        read_points(path, bin_columns=bad)


def test_bin_columns_ignored_for_other_formats(tmp_path):
    path = tmp_path / "cloud.npy"
    np.save(path, random_cloud(3, 20))
    assert read_points(path, bin_columns=4).shape == (20, 3)


def test_bin_non_finite_rows_dropped(tmp_path):
    path = tmp_path / "scan.bin"
    points = random_cloud(4, 11)
    points[3] = np.nan
    write_bin(path, points, 4)
    with pytest.warns(UserWarning):
        assert read_points(path).shape == (10, 3)


def test_bin_cli_register(tmp_path, capsys):
    target = random_cloud(5, 401)
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


@pytest.mark.parametrize("scan", ["newer_college_01/planes_000000.bin", "kitti_00/000000.bin"])
def test_shared_scans_whose_size_fits_both_layouts_are_read_by_their_values(tmp_path, scan):
    """The real 3-column scans whose size fits 4 columns too are read as 3 columns without being
    told; the same points with an intensity column appended (KITTI's velodyne layout) as 4."""
    path = require_shared("real_pairs") / scan
    assert path.stat().st_size % 48 == 0
    points = read_points(path, bin_columns=3)
    np.testing.assert_array_equal(read_points(path), points)
    four = tmp_path / "xyzi.bin"
    intensity = np.random.default_rng(0).uniform(0.0, 1.0, len(points))
    np.column_stack([points, intensity]).astype("<f4")[: len(points) // 3 * 3].tofile(four)  # also fits both
    np.testing.assert_array_equal(read_points(four), points[: len(points) // 3 * 3])


def test_shared_scans_read_with_three_columns():
    folder = require_shared("real_pairs/newer_college_01")
    path = folder / "planes_000000.bin"
    points = read_points(path, bin_columns=3)
    assert 19_968 <= len(points) <= 21_085
    assert path.stat().st_size == 12 * len(points)
    extent = points.max(axis=0) - points.min(axis=0)
    assert 10.0 < extent.max() < 500.0  # metres: a campus scan, not garbage floats
