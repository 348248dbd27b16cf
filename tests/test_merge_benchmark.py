"""The merge benchmark (benchmarks/merge_scans.py) on a tiny subset, so that it cannot rot: its
error bookkeeping against the truth, its tables, and one short run of every method on 4 frames
of the kitchen walk. The measured figures come from its full run in docs/merge.md."""

from __future__ import annotations

import argparse
import sys

import numpy as np
import pytest
from conftest import REPO_ROOT, require_module, require_shared
from scipy.spatial.transform import Rotation

import esmicp

sys.path.insert(0, str(REPO_ROOT / "benchmarks"))
import merge_scans  # noqa: E402


def _toy(count=5, ordered=True):
    """A walk of ``count`` tiny clouds with known poses (metres)."""
    rng = np.random.default_rng(0)
    truth = np.array([np.eye(4) for _ in range(count)])
    for k in range(count):
        truth[k, :3, :3] = Rotation.from_rotvec([0, 0, np.radians(4.0 * k)]).as_matrix()
        truth[k, :3, 3] = [0.1 * k, 0.03 * k * k, 0.05 * (k % 2)]  # not on a line: one best fit
    clouds = [rng.normal(size=(50, 3)) for _ in range(count)]
    data = merge_scans.Dataset("toy", "toy walk", [f"f{k}" for k in range(count)], clouds, truth, 0, "cm", 100.0,
                               (5.0, 0.10), ordered=ordered)
    data.tree = [(k, k + 1) for k in range(count - 1)]
    return data


def test_evaluate_the_truth_in_another_world_frame_has_no_error():
    data = _toy()
    moved = np.eye(4)
    moved[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    moved[:3, 3] = [2.0, -1.0, 0.5]
    result = merge_scans.evaluate(data, merge_scans.Run("truth", moved @ data.truth, 1.0))
    assert result["worst_rotation_deg"] < 1e-6 and result["worst_translation"] < 1e-9
    assert result["ate"] < 1e-9 and result["median_rpe_deg"] < 1e-6
    assert (result["placed"], result["doubtful"], result["unplaced"], result["wrong"]) == (5, 0, 0, 0)


def test_evaluate_counts_wrong_doubtful_and_unplaced_scans():
    data = _toy()
    poses = data.truth.copy()
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec([0, np.radians(20.0), 0]).as_matrix()
    poses[2] = poses[2] @ turn  # 20 degrees off, reported placed: silently wrong
    poses[3, :3, 3] += [0.0, 0.5, 0.0]  # 50 cm off, reported doubtful: wrong but flagged
    poses[4] = np.nan  # unplaced
    status = ["placed", "placed", "placed", "doubtful", "placed"]
    result = merge_scans.evaluate(data, merge_scans.Run("some", poses, 1.0, status))
    assert (result["placed"], result["doubtful"], result["unplaced"]) == (3, 1, 1)
    assert result["wrong"] == 2 and result["silently_wrong"] == 1
    assert result["worst_rotation_deg"] == pytest.approx(20.0, abs=1e-6)
    # The errors are of the scans reported placed: the doubtful one's 50 cm is not among them.
    assert result["worst_translation"] < 1e-9
    assert result["rpe_pairs"] == 2  # (0,1), (1,2): frame 3 is doubtful, frame 4 unplaced
    table = "\n".join(merge_scans.dataset_table({"unit": "cm", "scale": 100.0, "results": {"api": {"method": "x"} | result}}))
    assert "| 3 / 1 / 1 | 2 (1) | 20.00 |" in table


def test_a_walk_is_judged_after_the_best_fit_not_from_the_reference():
    data = _toy(count=12)
    poses = data.truth.copy()
    tilt = np.eye(4)
    tilt[:3, :3] = Rotation.from_rotvec([np.radians(3.0), 0, 0]).as_matrix()
    tilt[:3, 3] = np.array([0.0, 3.0, 0.0]) - tilt[:3, :3] @ [0.0, 3.0, 0.0]  # about a point 3 m away
    poses[1:] = tilt @ poses[1:]  # frames 1-11 swung about a far point: a drift
    poses[5, :3, 3] += [0.0, 0.0, 0.4]  # frame 5 misplaced by 40 cm
    result = merge_scans.evaluate(data, merge_scans.Run("walk", poses, 1.0))
    assert result["wrong"] == 1  # only frame 5, however the drift looks from frame 0
    unordered = merge_scans.evaluate(_toy(count=12, ordered=False), merge_scans.Run("set", poses, 1.0))
    assert unordered["wrong"] > 1  # seen from the reference, the drift moves frames beyond 10 cm


def test_status_words_of_a_merge_result():
    class Scan:
        def __init__(self, status):
            self.status = status

    class Result:
        scans = [Scan("placed"), Scan("doubtful"), Scan("unplaced")]

    assert merge_scans.scan_status(Result(), 3) == ["placed", "doubtful", "unplaced"]
    assert merge_scans.scan_status(object(), 3) is None


def test_the_cli_pose_file_with_and_without_statuses(tmp_path):
    numbers = " ".join(["1", "0", "0", "0.5", "0", "1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1"])
    nan = " ".join(["nan"] * 16)
    old = tmp_path / "old.txt"
    old.write_text(f"# header\n0 a.ply {numbers}\n1 b.ply {nan}\n")
    poses, status = merge_scans.read_poses_file(old, 2)
    assert status is None and poses[0, 0, 3] == 0.5 and np.isnan(poses[1]).all()
    new = tmp_path / "new.txt"
    new.write_text(f"# header\n0 a.ply placed {numbers}\n1 \"b c.ply\" doubtful {numbers}\n2 d.ply unplaced {nan}\n")
    poses, status = merge_scans.read_poses_file(new, 3)
    assert status == ["placed", "doubtful", "unplaced"] and poses[1, 0, 3] == 0.5
    written = tmp_path / "written.txt"
    esmicp.write_poses(written, np.array(numbers.split(), float).reshape(1, 4, 4).repeat(2, axis=0),
                       names=["a.ply", "b c.ply"], status=["placed", "doubtful"])
    poses, status = merge_scans.read_poses_file(written, 2)
    assert status == ["placed", "doubtful"] and poses[1, 0, 3] == 0.5


def test_the_doc_blocks_are_replaced_between_their_markers(tmp_path):
    (a_start, a_end), (b_start, b_end) = merge_scans.markers("a"), merge_scans.markers("b")
    doc = tmp_path / "merge.md"
    doc.write_text(f"# Title\n{a_start}\nold a\n{a_end}\nprose\n{b_start}\nold b\n{b_end}\nafter\n")
    merge_scans.write_doc(doc, {"b": f"{b_start}\nnew b\n{b_end}"})
    assert doc.read_text() == f"# Title\n{a_start}\nold a\n{a_end}\nprose\n{b_start}\nnew b\n{b_end}\nafter\n"
    (tmp_path / "plain.md").write_text("no markers\n")
    with pytest.raises(SystemExit, match="markers"):
        merge_scans.write_doc(tmp_path / "plain.md", {"a": "x"})


def test_every_method_on_four_kitchen_frames():
    require_shared("sequences/redkitchen_seq01_every10")
    require_module("open3d", "open3d")
    data = merge_scans.kitchen(frames=4, step=2)  # frames 0, 20, 40, 60 (raw 0-600)
    rng = np.random.default_rng(0)
    data.clouds = [cloud[rng.choice(len(cloud), 3000, replace=False)] for cloud in data.clouds]
    args = argparse.Namespace(
        seed=0, skip_peer=False, skip_pairwise=False, loop_gap=2, loop_stride=1, repeat=1)
    entry = merge_scans.run_dataset(data, args, log=lambda *_: None)
    results = entry["results"]
    assert set(results) == {"api", "api-sequence", "open3d", "pairwise"}
    for key in ("api", "open3d", "pairwise"):
        result = results[key]
        assert result["placed"] + result["doubtful"] + result["unplaced"] == 4
        assert result["seconds"] > 0 and np.isfinite(result["ate"])
    # Frames 20 raw frames apart overlap well: the pairs and Open3D's odometry place every frame
    # within the data set's "wrong" bound (5 deg, 10 cm); anything else is a harness error.
    assert results["pairwise"]["wrong"] == 0 and results["open3d"]["wrong"] == 0
    report = {"started": "now", "settings": {"command": "test"}, "versions": merge_scans.versions(),
              "datasets": {"kitchen": entry | {"load": [0.0, 0.0]}}}
    text = merge_scans.markdown(report)["kitchen"]
    start, end = merge_scans.markers("kitchen")
    assert text.startswith(start) and text.endswith(end)
    assert "\n| esmicp register_scans, shuffled | " in text and "\n| Open3D reconstruction system" in text
    assert "\n| esmicp register_scans, sequence=True | " in text  # its figures, or "not supported"


def test_the_reference_sweep_judges_each_run_from_its_own_reference():
    require_shared("sequences/redkitchen_seq01_every10")
    import merge_references

    data = merge_scans.kitchen(frames=4, step=2)  # frames 0, 20, 40, 60 (raw 0-600)
    rng = np.random.default_rng(0)
    data.clouds = [cloud[rng.choice(len(cloud), 3000, replace=False)] for cloud in data.clouds]
    chosen = merge_references.references(data, 3)
    assert chosen[0] == data.reference and len(set(chosen)) == 3
    assert merge_references.references(data, None) == [0, 1, 2, 3]
    found = merge_references.rows(data, 2, log=lambda *_, **__: None)
    assert [row["reference"] for row in found] == [data.names[k] for k in merge_references.references(data, 2)]
    for row in found:
        assert row["placed"] + row["doubtful"] + row["unplaced"] == 4
        assert row["wrong"] == 0  # frames 20 raw frames apart: placed right from either reference
    lines = merge_references.table(data, found)
    assert len(lines) == 4 and lines[2].startswith(f"| `{data.names[chosen[0]]}` | ")
