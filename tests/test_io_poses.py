"""Pose files (esmicp.write_poses / esmicp.read_poses): the matrix, TUM and KITTI formats
round-trip what they hold, each reads in the tools its users have (np.loadtxt), and a bad file is
one error naming the file and the line."""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import esmicp
from esmicp.errors import InvalidInputError, OutputExistsError, PointCloudFileError
from esmicp.io import POSE_FORMATS

NAMES = ("scans/a.ply", "scans/b c.ply", 'odd "quoted".ply', " leading space.ply", "x.ply")
STATUS = ("placed", "doubtful", "unplaced", "placed", "placed")


def _poses(count=5, seed=0, missing=(2,)):
    """Random rigid T_world_scan, translations far from the origin (georeferenced-like), NaN for
    the ``missing`` scans."""
    rng = np.random.default_rng(seed)
    poses = np.empty((count, 4, 4))
    for k in range(count):
        poses[k] = np.eye(4)
        poses[k, :3, :3] = Rotation.random(random_state=rng).as_matrix()
        poses[k, :3, 3] = rng.normal(size=3) * 1e5
    poses[0] = np.eye(4)
    poses[list(missing)] = np.nan
    return poses


@pytest.mark.parametrize("format", POSE_FORMATS)
def test_every_format_round_trips_what_it_holds(tmp_path, format):
    poses = _poses()
    path = tmp_path / f"poses.{format}"
    esmicp.write_poses(path, poses, format=format, names=NAMES, status=STATUS, reference=0)
    read = esmicp.read_poses(path)  # the format found from the content
    assert read.format == format and len(read) == len(poses)
    assert np.isnan(read.poses[2]).all()  # the scan with no pose
    if format == "tum":  # through a quaternion: to the last bits, not bit for bit
        np.testing.assert_allclose(read.poses, poses, rtol=0, atol=1e-10)
        np.testing.assert_array_equal(read.timestamps, np.arange(len(poses)))
    else:
        np.testing.assert_array_equal(read.poses, poses)
    if format == "kitti":  # 12 numbers a line and nothing else
        assert read.names is None and read.status is None
    else:
        assert read.names == NAMES and read.status == STATUS and read.reference == 0
    assert esmicp.read_poses(path, format=format).format == format


def test_tum_rotation_matches_the_matrix_and_quaternion_convention(tmp_path):
    """TUM: tx ty tz is the translation of T_world_scan, qx qy qz qw its rotation (scalar last)."""
    poses = _poses(3, seed=4, missing=())
    path = tmp_path / "poses.txt"
    esmicp.write_poses(path, poses, format="tum")
    rows = np.loadtxt(path, comments="#")
    assert rows.shape == (3, 8)
    for row, T in zip(rows, poses):
        np.testing.assert_array_equal(row[1:4], T[:3, 3])
        np.testing.assert_allclose(Rotation.from_quat(row[4:]).as_matrix(), T[:3, :3], atol=1e-12)


def test_numpy_reads_the_matrix_and_kitti_files_and_tum_omits_the_scans_with_no_pose(tmp_path):
    poses = _poses()
    for format, expected in (("matrix", poses.reshape(-1, 16)), ("kitti", poses[:, :3].reshape(-1, 12))):
        path = tmp_path / f"{format}.txt"
        esmicp.write_poses(path, poses, format=format, names=NAMES, status=STATUS)
        np.testing.assert_array_equal(np.loadtxt(path), expected)
    kitti = (tmp_path / "kitti.txt").read_text().splitlines()
    assert len(kitti) == len(poses) and not any(line.startswith("#") for line in kitti)
    path = tmp_path / "tum.txt"
    esmicp.write_poses(path, poses, format="tum", names=NAMES, status=STATUS)
    np.testing.assert_array_equal(np.loadtxt(path)[:, 0], [0, 1, 3, 4])  # the timestamps: scan indices


def test_tum_timestamps_given_place_each_line_on_its_scan(tmp_path):
    poses = _poses()
    stamps = [1403636579.763555527, 1403636580.5, 17.25, 1e-3, 99.0]
    path = tmp_path / "poses.tum"
    esmicp.write_poses(path, poses, format="tum", names=NAMES, timestamps=stamps)
    read = esmicp.read_poses(path)
    np.testing.assert_array_equal(read.timestamps, stamps)
    np.testing.assert_allclose(read.poses, poses, rtol=0, atol=1e-10)
    assert read.status is None and read.names == NAMES


def test_trajectories_written_elsewhere_read_in_their_line_order(tmp_path):
    poses = _poses(4, seed=2, missing=())
    tum = tmp_path / "groundtruth.txt"
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, T in zip((0.5, 0.6, 0.7, 0.8), poses):
        q = np.round(Rotation.from_matrix(T[:3, :3]).as_quat(), 6)  # six decimals: normalised on reading
        lines.append(" ".join(f"{v:.6f}" for v in (t, *T[:3, 3], *q)))
    tum.write_text("\n".join(lines) + "\n")
    read = esmicp.read_poses(tum)
    assert read.format == "tum" and read.names is None
    np.testing.assert_allclose(read.timestamps, [0.5, 0.6, 0.7, 0.8])
    np.testing.assert_allclose(read.poses, poses, atol=5e-6)
    kitti = tmp_path / "00.txt"
    kitti.write_text("".join(" ".join(f"{v:.9e}" for v in T[:3].ravel()) + "\n" for T in poses))
    read = esmicp.read_poses(kitti)
    assert read.format == "kitti"
    np.testing.assert_allclose(read.poses, poses, rtol=1e-9)


BAD = {
    "a word": ("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n1 0 0 0 0 1 0 zero 0 0 1 0 0 0 0 1\n", 2, "not a number"),
    "a short line": ("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n\n1 0 0 0 0 1 0 0 0 0 1 0 0 0 0\n", 3, "15 values"),
    "five numbers": ("# poses\n1 2 3 4 5\n", 2, "5 values"),
    "half nan": ("1 0 0 0 0 1 0 0 0 0 1 nan\n", 1, "NaN"),
    "not a rotation": ("2 0 0 0 0 1 0 0 0 0 1 0\n", 1, "orthonormal"),
    "a reflection": ("-1 0 0 0 0 1 0 0 0 0 1 0\n", 1, "reflection"),
    "a bad quaternion": ("0 1 2 3 0 0 0 2\n", 1, "norm"),
    "lines out of order": ("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1 # 1 placed b.ply\n", 1, "scan order"),
    "a timestamp of no scan": ("# scan 0 0 placed a.ply\n# scan 1 1 placed b.ply\n0 0 0 0 0 0 0 1\n5 0 0 0 0 0 0 1\n",
                               4, "none of the scans"),
    "a scan twice": ("# scan 0 0 placed a.ply\n0 0 0 0 0 0 0 1\n0 1 0 0 0 0 0 1\n", 3, "second pose"),
}


@pytest.mark.parametrize("case", BAD)
def test_a_bad_file_is_one_error_naming_the_file_and_the_line(tmp_path, case):
    text, line, problem = BAD[case]
    path = tmp_path / "poses.txt"
    path.write_text(text)
    with pytest.raises(PointCloudFileError) as error:
        esmicp.read_poses(path)
    message = str(error.value)
    assert message.startswith(str(path)) and f"line {line}:" in message and problem in message
    assert "\n" not in message


def test_empty_missing_or_comment_only_files_are_named(tmp_path):
    for text in ("", "# only a comment\n"):
        path = tmp_path / "poses.txt"
        path.write_text(text)
        with pytest.raises(PointCloudFileError, match="poses.txt"):
            esmicp.read_poses(path)
    with pytest.raises(PointCloudFileError, match="no such file"):
        esmicp.read_poses(tmp_path / "absent.txt")
    with pytest.raises(InvalidInputError, match="format"):
        esmicp.read_poses(path, format="csv")


def test_write_refuses_bad_poses_and_existing_files_and_writes_nothing(tmp_path):
    path = tmp_path / "poses.txt"
    sheared = _poses(3, missing=())
    sheared[1, 0, 1] += 0.1
    half = _poses(3, missing=())
    half[2, 0, 0] = np.nan
    for poses, kwargs, word in ((sheared, {}, "poses[1]"), (half, {}, "poses[2]"),
                                (_poses(3), {"names": ["a"]}, "names"), (_poses(3), {"format": "ply"}, "format"),
                                (_poses(3), {"timestamps": [0, 0, 1], "format": "tum"}, "timestamps"),
                                (_poses(3), {"timestamps": [0, 1, 2]}, "timestamps"),
                                (np.eye(4), {}, "shape")):
        with pytest.raises(InvalidInputError, match=re.escape(word)):
            esmicp.write_poses(path, poses, **kwargs)
        assert not path.exists()
    esmicp.write_poses(path, _poses(3))
    with pytest.raises(OutputExistsError):
        esmicp.write_poses(path, _poses(3), format="kitti")
    assert esmicp.read_poses(path).format == "matrix"
    esmicp.write_poses(path, _poses(3), format="kitti", overwrite=True)
    assert esmicp.read_poses(path).format == "kitti"


def test_a_point_cloud_given_by_mistake_is_refused_at_its_first_line(tmp_path):
    points = np.random.default_rng(0).normal(size=(20000, 3))
    for name in ("merged.xyz", "merged.ply"):
        path = tmp_path / name
        esmicp.write_points(path, points)
        with pytest.raises(PointCloudFileError) as error:
            esmicp.read_poses(path)
        assert str(error.value).startswith(str(path)) and "\n" not in str(error.value)
    with pytest.raises(PointCloudFileError, match="line 1: 3 values"):
        esmicp.read_poses(tmp_path / "merged.xyz")
