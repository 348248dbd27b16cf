"""The merge benchmark (benchmarks/merge_scans.py, merge_references.py) on a tiny subset, so that
it cannot rot: its error bookkeeping against the truth and its tables (esmicp_lab.bench.merge),
and both scripts run as a user runs them, every method on 4 frames of the kitchen walk. The
measured figures come from their full runs in docs/merge.md."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO_ROOT, require_module, require_shared
from scipy.spatial.transform import Rotation

import esmicp
from esmicp_lab.bench import merge


def _toy(count=5, ordered=True):
    """A walk of ``count`` tiny clouds with known poses (metres)."""
    rng = np.random.default_rng(0)
    truth = np.array([np.eye(4) for _ in range(count)])
    for k in range(count):
        truth[k, :3, :3] = Rotation.from_rotvec([0, 0, np.radians(4.0 * k)]).as_matrix()
        truth[k, :3, 3] = [0.1 * k, 0.03 * k * k, 0.05 * (k % 2)]  # not on a line: one best fit
    clouds = [rng.normal(size=(50, 3)) for _ in range(count)]
    data = merge.Dataset("toy", "toy walk", [f"f{k}" for k in range(count)], clouds, truth, 0, "cm", 100.0,
                               (5.0, 0.10), ordered=ordered)
    data.tree = [(k, k + 1) for k in range(count - 1)]
    return data


def test_evaluate_the_truth_in_another_world_frame_has_no_error():
    data = _toy()
    moved = np.eye(4)
    moved[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    moved[:3, 3] = [2.0, -1.0, 0.5]
    result = merge.evaluate(data, merge.Run("truth", moved @ data.truth, 1.0))
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
    result = merge.evaluate(data, merge.Run("some", poses, 1.0, status))
    assert (result["placed"], result["doubtful"], result["unplaced"]) == (3, 1, 1)
    assert result["wrong"] == 2 and result["silently_wrong"] == 1
    assert result["worst_rotation_deg"] == pytest.approx(20.0, abs=1e-6)
    # The errors are of the scans reported placed: the doubtful one's 50 cm is not among them; the
    # turned scan's is where its centroid went.
    centroid = np.asarray(data.clouds[2], dtype=np.float64).mean(axis=0)
    assert result["worst_translation"] == pytest.approx(np.linalg.norm(turn[:3, :3] @ centroid - centroid), abs=1e-9)
    assert result["rpe_pairs"] == 2  # (0,1), (1,2): frame 3 is doubtful, frame 4 unplaced
    table = "\n".join(merge.dataset_table({"unit": "cm", "scale": 100.0, "results": {"api": {"method": "x"} | result}}))
    assert "| 3 / 1 / 1 | 2 (1) | 20.00 |" in table


def test_a_scan_turned_about_its_centroid_far_from_its_origin_is_off_by_its_rotation_only():
    data = _toy()
    data.clouds[2] = data.clouds[2] + [0.0, 0.0, 50.0]  # stored 50 m from its frame's origin
    centroid = data.clouds[2].mean(axis=0)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec([0, np.radians(2.0), 0]).as_matrix()
    turn[:3, 3] = centroid - turn[:3, :3] @ centroid  # about the scan's own centroid
    poses = data.truth.copy()
    poses[2] = poses[2] @ turn
    result = merge.evaluate(data, merge.Run("turned", poses, 1.0, ["placed"] * 5))
    assert result["worst_rotation_deg"] == pytest.approx(2.0, abs=1e-6)
    assert result["worst_translation"] < 1e-9


def test_a_walk_is_judged_after_the_best_fit_not_from_the_reference():
    data = _toy(count=12)
    poses = data.truth.copy()
    tilt = np.eye(4)
    tilt[:3, :3] = Rotation.from_rotvec([np.radians(3.0), 0, 0]).as_matrix()
    tilt[:3, 3] = np.array([0.0, 3.0, 0.0]) - tilt[:3, :3] @ [0.0, 3.0, 0.0]  # about a point 3 m away
    poses[1:] = tilt @ poses[1:]  # frames 1-11 swung about a far point: a drift
    poses[5, :3, 3] += [0.0, 0.0, 0.4]  # frame 5 misplaced by 40 cm
    result = merge.evaluate(data, merge.Run("walk", poses, 1.0))
    assert result["wrong"] == 1  # only frame 5, however the drift looks from frame 0
    unordered = merge.evaluate(_toy(count=12, ordered=False), merge.Run("set", poses, 1.0))
    assert unordered["wrong"] > 1  # seen from the reference, the drift moves frames beyond 10 cm


def test_status_words_of_a_merge_result():
    class Scan:
        def __init__(self, status):
            self.status = status

    class Result:
        scans = [Scan("placed"), Scan("doubtful"), Scan("unplaced")]

    assert merge.scan_status(Result(), 3) == ["placed", "doubtful", "unplaced"]
    assert merge.scan_status(object(), 3) is None


def test_the_cli_pose_file_with_and_without_statuses(tmp_path):
    numbers = " ".join(["1", "0", "0", "0.5", "0", "1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1"])
    nan = " ".join(["nan"] * 16)
    old = tmp_path / "old.txt"
    old.write_text(f"# header\n0 a.ply {numbers}\n1 b.ply {nan}\n")
    poses, status = merge.read_poses_file(old, 2)
    assert status is None and poses[0, 0, 3] == 0.5 and np.isnan(poses[1]).all()
    new = tmp_path / "new.txt"
    new.write_text(f"# header\n0 a.ply placed {numbers}\n1 \"b c.ply\" doubtful {numbers}\n2 d.ply unplaced {nan}\n")
    poses, status = merge.read_poses_file(new, 3)
    assert status == ["placed", "doubtful", "unplaced"] and poses[1, 0, 3] == 0.5
    written = tmp_path / "written.txt"
    esmicp.write_poses(written, np.array(numbers.split(), float).reshape(1, 4, 4).repeat(2, axis=0),
                       names=["a.ply", "b c.ply"], status=["placed", "doubtful"])
    poses, status = merge.read_poses_file(written, 2)
    assert status == ["placed", "doubtful"] and poses[1, 0, 3] == 0.5


def test_the_doc_blocks_are_replaced_between_their_markers(tmp_path):
    (a_start, a_end), (b_start, b_end) = merge.markers("a"), merge.markers("b")
    doc = tmp_path / "merge.md"
    doc.write_text(f"# Title\n{a_start}\nold a\n{a_end}\nprose\n{b_start}\nold b\n{b_end}\nafter\n")
    merge.write_doc(doc, {"b": f"{b_start}\nnew b\n{b_end}"})
    assert doc.read_text() == f"# Title\n{a_start}\nold a\n{a_end}\nprose\n{b_start}\nnew b\n{b_end}\nafter\n"
    (tmp_path / "plain.md").write_text("no markers\n")
    with pytest.raises(SystemExit, match="markers"):
        merge.write_doc(tmp_path / "plain.md", {"a": "x"})


@pytest.fixture(scope="module")
def four_kitchen_frames(tmp_path_factory):
    """A shared data folder (for ``ESMICP_SHARED_DATA``) holding frames 0, 20, 40, 60 (raw 0-600)
    of the kitchen walk, 3,000 seeded points of each, with the walk's poses."""
    walk = require_shared("sequences/redkitchen_seq01_every10")
    data = tmp_path_factory.mktemp("shared")
    frames = data / "sequences" / walk.name / "frames"
    frames.mkdir(parents=True)
    (frames.parent / "poses.txt").write_bytes((walk / "poses.txt").read_bytes())
    rng = np.random.default_rng(0)
    for path in sorted((walk / "frames").glob("frame-*.npy"))[::2][:4]:
        cloud = np.load(path)
        np.save(frames / path.name, cloud[rng.choice(len(cloud), 3000, replace=False)])
    return data


def _run_script(name: str, *arguments: str, data) -> str:
    """Run ``benchmarks/<name>`` on the shared data folder ``data``; its standard output."""
    done = subprocess.run([sys.executable, str(REPO_ROOT / "benchmarks" / name), *arguments], capture_output=True,
                          text=True, env=os.environ | {"ESMICP_SHARED_DATA": str(data)})
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_every_method_on_four_kitchen_frames(four_kitchen_frames, tmp_path):
    require_module("open3d", "baselines")
    require_module("matplotlib", "viz")
    start, end = merge.markers("kitchen")
    doc = tmp_path / "merge.md"
    doc.write_text(f"# Merge\n{start}\nold\n{end}\nafter\n")
    figures = tmp_path / "figures.json"
    _run_script("merge_scans.py", "--datasets", "kitchen", "--frames", "4", "--loop-gap", "2", "--loop-stride", "1",
                "--json", str(figures), "--doc", str(doc), "--pictures", str(tmp_path), data=four_kitchen_frames)
    entry = json.loads(figures.read_text())["datasets"]["kitchen"]
    results = entry["results"]
    assert set(results) == {"api", "api-sequence", "open3d", "pairwise"}
    # The report keeps each run's poses and the truth, which the page's picture is drawn from.
    assert np.shape(entry["truth"]) == (4, 4, 4) and np.shape(results["api-sequence"]["poses"]) == (4, 4, 4)
    assert (tmp_path / "merge-kitchen-trajectory.png").read_bytes()[:4] == b"\x89PNG"
    for key in ("api", "open3d", "pairwise"):
        result = results[key]
        assert result["placed"] + result["doubtful"] + result["unplaced"] == 4
        assert result["seconds"] > 0 and np.isfinite(result["ate"])
    # Frames 20 raw frames apart overlap well: the pairs and Open3D's odometry place every frame
    # within the data set's "wrong" bound (5 deg, 10 cm); anything else is a harness error.
    assert results["pairwise"]["wrong"] == 0 and results["open3d"]["wrong"] == 0
    text = doc.read_text()
    assert text.startswith(f"# Merge\n{start}\n") and text.endswith(f"\n{end}\nafter\n")
    assert f"{start}\nold\n" not in text and text.count(start) == 1  # the block replaced, nothing else
    assert "\n| esmicp register_scans, shuffled | " in text and "\n| Open3D reconstruction system" in text
    assert "\n| esmicp register_scans, sequence=True | " in text  # its figures, or "not supported"


def test_the_reference_sweep_judges_each_run_from_its_own_reference(four_kitchen_frames):
    out = _run_script("merge_references.py", "--datasets", "kitchen", "--references", "2", data=four_kitchen_frames)
    rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in out.splitlines() if line.startswith("| `")]
    references = [row[0].strip("`") for row in rows]
    assert references[0] == "frame-000000" and len(set(references)) == 2  # the walk's own reference first
    for row in rows:
        assert sum(int(count) for count in row[1].split(" / ")) == 4  # placed / doubtful / unplaced
        assert row[2] == "0 (0)"  # none wrong: frames 20 raw frames apart, placed right from either reference
