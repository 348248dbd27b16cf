"""Tests of the real-pairs benchmark's pure parts: pairs.csv, criteria, the turned variant, the
partial-overlap protocol, and the scan benchmark end to end on a tiny folder."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import require_shared

from esmicp_lab.bench.real_pairs import (
    KIND_CRITERIA,
    crop_to_overlap,
    estimate_in_pair_frame,
    load_pair,
    pair_errors,
    partial_trial,
    plane_cut,
    read_pairs,
    turn_source,
)
from esmicp_lab.bench.scans import ScanBenchConfig, partial_markdown, real_pairs_markdown, run_scan_bench
from esmicp.cli import main
from esmicp.core.procrustes import apply, rigid_inverse, to_matrix
from esmicp.errors import InvalidInputError, PointCloudFileError
from esmicp.metrics import random_rotation
from esmicp.shapes import asymmetric_shape

HEADER = "dataset,pair,kind,target,source,T_target_source\n"


def rotation_about_z(degrees: float) -> np.ndarray:
    angle = np.radians(degrees)
    return np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])


def make_folder(tmp_path, kind="LiDAR", rows=None):
    """A real-pairs folder with one pair: target = R source + t (metres)."""
    rng = np.random.default_rng(0)
    target = asymmetric_shape(3000, rng) * 10.0
    truth = to_matrix(rotation_about_z(20.0), np.array([1.0, -0.5, 0.2]))
    source = apply(rigid_inverse(truth), target)
    np.save(tmp_path / "target.npy", target)
    records = np.zeros((len(source), 3), dtype="<f4")
    records[:] = source
    records.tofile(tmp_path / "source.bin")
    np.savetxt(tmp_path / "T.txt", truth)
    lines = rows if rows is not None else [f"demo,p0,{kind},target.npy,source.bin,T.txt\n"]
    (tmp_path / "pairs.csv").write_text(HEADER + "".join(lines))
    return truth


# ---- criteria -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kind", "rotation", "translation", "expected"),
    [
        ("3DMatch", 14.9, 0.29, True),
        ("3DMatch", 15.1, 0.1, False),
        ("3DMatch", 1.0, 0.31, False),
        ("LiDAR", 4.9, 0.59, True),
        ("LiDAR", 5.1, 0.1, False),
        ("LiDAR", 1.0, 0.61, False),
        ("LiDAR-coarse-GT", 4.0, 0.5, True),
    ],
)
def test_kind_criteria(kind, rotation, translation, expected):
    assert KIND_CRITERIA[kind].success(rotation, translation) is expected


def test_peer_voxels_by_kind():
    assert KIND_CRITERIA["3DMatch"].voxel_m == 0.05
    assert KIND_CRITERIA["LiDAR"].voxel_m == 0.3


def test_pair_errors_are_the_3dmatch_convention():
    truth = to_matrix(rotation_about_z(10.0), np.array([1.0, 2.0, 3.0]))
    estimate = to_matrix(rotation_about_z(13.0), np.array([1.0, 2.4, 3.3]))
    rotation, translation = pair_errors(estimate, truth)
    assert rotation == pytest.approx(3.0)
    assert translation == pytest.approx(0.5)


# ---- the turned variant -------------------------------------------------------------------------


def test_turned_truth_maps_the_turned_source_onto_the_target():
    rng = np.random.default_rng(3)
    source = rng.normal(size=(200, 3)) * 5.0 + [30.0, -4.0, 2.0]
    truth = to_matrix(random_rotation(rng), rng.normal(size=3))
    turned, turned_truth, moved_by = turn_source(source, truth, np.random.default_rng(7))
    np.testing.assert_allclose(apply(turned_truth, turned), apply(truth, source), atol=1e-9)
    np.testing.assert_allclose(apply(moved_by, source), turned, atol=1e-12)
    # turned about the centroid: the centroid stays, the cloud really turns
    np.testing.assert_allclose(turned.mean(axis=0), source.mean(axis=0), atol=1e-9)
    assert np.abs(turned - source).max() > 1.0
    # an exact estimate on the turned pair is exact in the pair's own frame
    rotation, translation = pair_errors(estimate_in_pair_frame(turned_truth, moved_by), truth)
    assert rotation < 1e-6 and translation < 1e-9
    # and the wrong composition (M instead of M^-1) would not be
    wrong = truth @ moved_by
    assert np.abs(apply(wrong, turned) - apply(truth, source)).max() > 1.0


def test_turn_is_seeded():
    source = np.random.default_rng(0).normal(size=(50, 3))
    first = turn_source(source, np.eye(4), np.random.default_rng(5))[0]
    again = turn_source(source, np.eye(4), np.random.default_rng(5))[0]
    other = turn_source(source, np.eye(4), np.random.default_rng(6))[0]
    np.testing.assert_array_equal(first, again)
    assert not np.allclose(first, other)


# ---- pairs.csv ----------------------------------------------------------------------------------


def test_read_and_load_a_pair(tmp_path):
    truth = make_folder(tmp_path)
    (pair,) = read_pairs(tmp_path)
    assert pair.name == "demo/p0" and pair.kind == "LiDAR" and pair.line == 2
    source, target, loaded_truth = load_pair(pair, bin_columns=3)
    np.testing.assert_allclose(loaded_truth, truth, atol=1e-12)
    np.testing.assert_allclose(apply(truth, source), target, atol=1e-3)  # float32 source


@pytest.mark.parametrize(
    ("rows", "words"),
    [
        (["demo,p0,Kinect,target.npy,source.bin,T.txt\n"], ["line 2", "unknown kind", "Kinect"]),
        (["demo,p0,LiDAR,target.npy,missing.bin,T.txt\n"], ["line 2", "source", "missing.bin", "not found"]),
        (["demo,p0,LiDAR,target.npy,source.bin,T.txt\n", "demo,p1,LiDAR,target.npy\n"], ["line 3", "4 fields"]),
        (["demo,p0,LiDAR,target.npy,source.bin,\n"], ["line 2", "T_target_source", "empty"]),
        ([], ["no pairs"]),
    ],
)
def test_pairs_csv_errors_name_the_file_and_line(tmp_path, rows, words):
    make_folder(tmp_path, rows=rows)
    with pytest.raises(PointCloudFileError) as excinfo:
        read_pairs(tmp_path)
    message = str(excinfo.value)
    assert message.startswith(str(tmp_path / "pairs.csv")) and "\n" not in message
    for word in words:
        assert word in message, (word, message)


def test_pairs_csv_missing_column_and_missing_file(tmp_path):
    with pytest.raises(PointCloudFileError, match="pairs.csv: no such file"):
        read_pairs(tmp_path)
    (tmp_path / "pairs.csv").write_text("kind,target,source\nLiDAR,a,b\n")
    with pytest.raises(PointCloudFileError, match="line 1: the header lacks the column.*T_target_source"):
        read_pairs(tmp_path)


def test_shared_real_pairs_parse_and_overlap():
    folder = require_shared("real_pairs")
    pairs = read_pairs(folder)
    assert len(pairs) >= 11
    assert {pair.kind for pair in pairs} <= set(KIND_CRITERIA)
    from esmicp_lab.bench.protocols import scan_overlap

    lidar = next(pair for pair in pairs if pair.kind == "LiDAR")
    source, target, truth = load_pair(lidar, bin_columns=3)
    assert scan_overlap(source, target, truth) > 0.6  # the README: 78-89 % within 2 spacings
    assert scan_overlap(source, target, np.eye(4)) < scan_overlap(source, target, truth)


# ---- the partial-overlap protocol ---------------------------------------------------------------


def test_plane_cut_keeps_the_fraction_on_one_side():
    points = np.random.default_rng(1).normal(size=(1000, 3))
    mask, normal, offset = plane_cut(points, 0.7, np.random.default_rng(2))
    assert mask.sum() == 700
    assert np.all(points[mask] @ normal >= offset) and np.all(points[~mask] @ normal <= offset)
    with pytest.raises(InvalidInputError):
        plane_cut(points, 1.5, np.random.default_rng(2))


@pytest.mark.parametrize("keep", [0.7, 0.5])
def test_partial_trial_truth_and_overlap(keep):
    cloud = asymmetric_shape(8000, np.random.default_rng(4))
    trial = partial_trial(cloud, keep, np.random.default_rng(9), points=2000)
    assert len(trial.source) == len(trial.target) == round(keep * 2000)
    placed = apply(trial.T_target_source, trial.source)
    # the placed source lies on the object, and the overlap says how much of it on the target's part
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(cloud).query(placed)
    assert np.median(distance) < 0.05
    near, _ = cKDTree(trial.target).query(placed)
    spacing = np.median(cKDTree(trial.target).query(trial.target, k=2)[0][:, 1])
    measured = float(np.mean(near < 3 * spacing))
    assert 0.0 <= trial.overlap <= 1.0
    assert abs(measured - trial.overlap) < 0.15


def _plane_pair(rng):
    """Two overlapping patches of a wavy surface (metres): target x in [0, 2], source x in [1, 3]
    in the target frame, the source moved by a known pose."""
    grid = np.stack(np.meshgrid(np.linspace(0, 3, 121), np.linspace(0, 1, 41)), axis=-1).reshape(-1, 2)
    surface = np.column_stack([grid, 0.1 * np.sin(3 * grid[:, 0]) * np.cos(2 * grid[:, 1])])
    target = surface[surface[:, 0] <= 2.0]
    truth = to_matrix(rotation_about_z(30.0), np.array([0.5, -0.2, 0.1]))
    source = apply(rigid_inverse(truth), surface[surface[:, 0] >= 1.0])
    return source, target, truth


@pytest.mark.parametrize("overlap", [0.3, 0.2, 0.1])
def test_crop_to_overlap_reaches_the_overlap_it_reports(overlap):
    source, target, truth = _plane_pair(np.random.default_rng(0))
    cropped = crop_to_overlap(source, target, truth, overlap, np.random.default_rng(3))
    # kept points are subsets of the originals, and each cloud lost points
    from scipy.spatial import cKDTree

    assert np.all(cKDTree(source).query(cropped.source)[0] == 0.0)
    assert np.all(cKDTree(target).query(cropped.target)[0] == 0.0)
    assert len(cropped.source) < len(source) and len(cropped.target) <= len(target)
    # the reported overlap is the fraction measured independently, and close to the request
    spacing = np.median(cKDTree(cropped.target).query(cropped.target, k=2)[0][:, 1])
    near, _ = cKDTree(cropped.target).query(apply(truth, cropped.source))
    measured = float(np.mean(near <= 3 * spacing))
    assert abs(measured - cropped.source_overlap) < 0.02
    assert abs(cropped.source_overlap - overlap) < 0.05
    back, _ = cKDTree(apply(truth, cropped.source)).query(cropped.target)
    assert 0.0 < cropped.target_overlap <= 1.0
    assert abs(float(np.mean(back <= 3 * np.median(cKDTree(cropped.source).query(cropped.source, k=2)[0][:, 1])))
               - cropped.target_overlap) < 0.02
    # the cut: the kept source lies above the slab's lower face, the kept target below its upper face
    assert np.all(apply(truth, cropped.source) @ cropped.normal >= cropped.offset - 0.5 * cropped.width - 1e-9)
    assert np.all(cropped.target @ cropped.normal <= cropped.offset + 0.5 * cropped.width + 1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_crop_to_overlap_reports_exactly_the_overlap_scan_overlap_measures(seed):
    """The bisection judges each width without measuring every kept point again; what it reports
    is still exactly the kept source's fraction within 3 spacings (of the whole target) of the kept
    target, as :func:`scan_overlap` measures it."""
    from esmicp_lab.bench.protocols import median_spacing, scan_overlap

    source, target, truth = _plane_pair(np.random.default_rng(0))
    for overlap in (0.1, 0.25, 0.4):
        cropped = crop_to_overlap(source, target, truth, overlap, np.random.default_rng(seed))
        assert cropped.source_overlap == scan_overlap(cropped.source, cropped.target, truth,
                                                      3.0 * median_spacing(target))


def test_crop_to_overlap_is_seeded_and_rejects_bad_input():
    source, target, truth = _plane_pair(np.random.default_rng(0))
    first = crop_to_overlap(source, target, truth, 0.2, np.random.default_rng(5))
    again = crop_to_overlap(source, target, truth, 0.2, np.random.default_rng(5))
    assert np.array_equal(first.source, again.source) and np.array_equal(first.target, again.target)
    with pytest.raises(InvalidInputError, match="overlap"):
        crop_to_overlap(source, target, truth, 1.2, np.random.default_rng(5))
    far = to_matrix(np.eye(3), np.array([100.0, 0.0, 0.0])) @ truth
    with pytest.raises(InvalidInputError, match="overlaps nowhere"):
        crop_to_overlap(source, target, far, 0.2, np.random.default_rng(5))


def test_partial_overlaps_vary_and_are_lower_at_50():
    cloud = asymmetric_shape(8000, np.random.default_rng(4))
    overlaps = {keep: [partial_trial(cloud, keep, np.random.default_rng(s)).overlap for s in range(20)]
                for keep in (0.7, 0.5)}
    assert np.median(overlaps[0.5]) < np.median(overlaps[0.7])
    assert np.ptp(overlaps[0.7]) > 0.05


# ---- end to end ---------------------------------------------------------------------------------


def test_scan_bench_on_a_tiny_folder(tmp_path):
    make_folder(tmp_path)
    config = ScanBenchConfig(real_pairs_dir=str(tmp_path), methods=("esm-global",), partial_trials=0)
    rows = run_scan_bench(config, tmp_path / "rows.jsonl")
    assert [(r["variant"], r["method"]) for r in rows] == [("as-recorded", "esm-global"), ("turned", "esm-global")]
    for row in rows:
        assert row["status"] == "ok" and row["success"], row
        assert row["rotation_error_deg"] < 1.0 and row["translation_error_m"] < 0.05
    assert rows[1]["initial_rotation_deg"] != pytest.approx(rows[0]["initial_rotation_deg"])
    assert len((tmp_path / "rows.jsonl").read_text().splitlines()) == 2
    table = real_pairs_markdown(rows)
    assert "demo/p0" in table and "esmicp default" in table


def test_scan_bench_cropped_variant_reports_the_cropped_overlap(tmp_path):
    from esmicp_lab.bench.scans import CROPPED_OVERLAP

    make_folder(tmp_path)
    config = ScanBenchConfig(real_pairs_dir=str(tmp_path), methods=("esm-global",), partial_trials=0,
                             variants=("as-recorded", "cropped"))
    recorded, cropped = run_scan_bench(config)
    assert cropped["variant"] == "cropped" and recorded["overlap"] > 0.9
    assert abs(cropped["overlap"] - CROPPED_OVERLAP) < 0.05
    assert cropped["points_source"] < recorded["points_source"]
    assert cropped["status"] == "ok" and cropped["rotation_error_deg"] is not None
    assert "cropped" in real_pairs_markdown([recorded, cropped])


def test_scan_bench_judges_a_wrong_pose_as_failure(tmp_path, monkeypatch):
    import esmicp_lab.bench.scans as scans

    make_folder(tmp_path)
    monkeypatch.setattr(scans, "run_global", lambda *args: (np.eye(4), "identity", None, None, None))
    rows = run_scan_bench(ScanBenchConfig(real_pairs_dir=str(tmp_path), methods=("esm-global",), partial_trials=0))
    assert all(not row["success"] and row["rotation_error_deg"] > 19.0 for row in rows)


def test_partial_rows_and_table(tmp_path, monkeypatch):
    import esmicp_lab.bench.scans as scans

    clouds = {"shape": asymmetric_shape(3000, np.random.default_rng(0))}
    monkeypatch.setattr(scans, "_modelnet_clouds", lambda data_dir: clouds)
    config = ScanBenchConfig(real_pairs_dir=None, methods=("esm-global",), partial_trials=2, partial_points=500)
    rows = run_scan_bench(config)
    assert [r["protocol"] for r in rows] == ["partial-70", "partial-70", "partial-50", "partial-50"]
    assert all(0.0 < r["overlap"] <= 1.0 for r in rows)
    table = partial_markdown(rows)
    assert "partial-70" in table and "overlap" in table


def test_partial_rows_judge_success_up_to_the_objects_symmetry(monkeypatch):
    """An open cylinder about the z axis: a pose turned 90 degrees about that axis from the truth
    places the source's half on the cylinder as well as the truth does, so it succeeds up to the
    object's symmetry; judged on the kept points alone it fails, as their cut does not share the
    symmetry. Fails if the rows judge the kept points only, or if any pose passes."""
    import esmicp_lab.bench.scans as scans

    rng = np.random.default_rng(3)
    angles, heights = rng.uniform(0.0, 2.0 * np.pi, 40_000), rng.uniform(-1.0, 1.0, 40_000)
    cylinder = np.column_stack([np.cos(angles), np.sin(angles), heights])
    monkeypatch.setattr(scans, "_modelnet_clouds", lambda data_dir: {"cylinder": cylinder})
    made = []

    def remembered_trial(*args):
        made.append(partial_trial(*args))
        return made[-1]

    monkeypatch.setattr(scans, "partial_trial", remembered_trial)
    about_x = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    turn = {"about the axis": to_matrix(rotation_about_z(90.0), np.zeros(3)),
            "about x": to_matrix(about_x, np.zeros(3))}
    for name, move in turn.items():
        monkeypatch.setattr(scans, "run_global", lambda *args: (move @ made[-1].T_target_source, name, None, None, None))
        rows = []
        scans.partial_rows(ScanBenchConfig(real_pairs_dir=None, methods=("esm-global",), partial_trials=1,
                                           partial_keeps=(0.7,)), rows.append)
        assert rows[0]["rotation_error_deg"] > 89.0
        assert rows[0]["success"] == (name == "about the axis"), (name, rows[0])
        assert not rows[0]["success_kept_points"] and not rows[0]["success_strict"]


def test_the_partial_table_counts_the_trials_that_still_overlap():
    """The last table counts only the trials overlapping by at least ``COUNTED_OVERLAP``, per
    method; fails if a barely overlapping trial is counted or a success is missed."""
    def row(protocol, method, overlap, success):
        return {"protocol": protocol, "method": method, "overlap": overlap, "success": success,
                "success_strict": success, "success_kept_points": success, "rotation_error_deg": 1.0,
                "translation_error": 0.01, "time_s": 0.1, "status": "ok"}

    rows = [row("partial-50", "esm-global", 0.1, True), row("partial-50", "kiss-matcher-icp", 0.1, True),
            row("partial-50", "esm-global", 0.3, True), row("partial-50", "kiss-matcher-icp", 0.3, False),
            row("partial-50", "esm-global", 0.6, False), row("partial-50", "kiss-matcher-icp", 0.6, False)]
    last = partial_markdown(rows).strip().splitlines()[-1]
    assert last.split("|")[1:-1] == [" partial-50 ", " 2 ", " 1/2 ", " 0/2 "]


def test_cli_scan_bench(tmp_path, capsys):
    make_folder(tmp_path / "pairs_dir" if (tmp_path / "pairs_dir").mkdir() is None else tmp_path)
    out = tmp_path / "out"
    code = main(["bench", "--datasets", "real-pairs", "--real-pairs-dir", str(tmp_path / "pairs_dir"),
                 "--methods", "esm-global", "--protocols", "turned", "--out", str(out), "--no-progress"])
    assert code == 0, capsys.readouterr().err
    rows = [json.loads(line) for line in (out / "rows.jsonl").read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["variant"] == "turned" and rows[0]["success"]
    assert "demo/p0" in (out / "real-scans.md").read_text()
    assert main(["bench", "--datasets", "real-pairs", "--real-pairs-dir", str(tmp_path / "pairs_dir"),
                 "--methods", "esm-global", "--out", str(out)]) == 2  # rows exist, no --force
    assert main(["bench", "--datasets", "real-pairs,synthetic", "--out", str(out), "--force"]) == 2


def test_quick_table_times_esmicp_against_the_fastest_peer_that_succeeds():
    """``benchmarks/scan_pairs_quick.py``'s ratio column (``quick_markdown_table``): a peer that
    fails on a row is no bar to beat (KISS-Matcher failing fast on a 3DMatch pair once made esmicp
    look 4x slower)."""
    from esmicp_lab.bench.real_pairs import quick_markdown_table

    rows = [
        ("a", "turned", "esm", True, 1.0, 0.01, 1.0),
        ("a", "turned", "fast-but-wrong", False, 90.0, 2.0, 0.1),
        ("a", "turned", "slow-but-right", True, 2.0, 0.02, 2.0),
        ("b", "turned", "esm", True, 1.0, 0.01, 1.0),
        ("b", "turned", "fast-but-wrong", False, 90.0, 2.0, 0.1),
        ("b", "turned", "slow-but-right", False, 90.0, 2.0, 2.0),
    ]
    table = quick_markdown_table(rows, ["esm", "fast-but-wrong", "slow-but-right"])
    lines = table.splitlines()
    assert lines[2].endswith("| 0.50 |")
    assert lines[3].endswith("| no peer succeeds |")
    assert "fastest successful peer: median 0.50, max 0.50" in table


def test_the_scan_summary_divides_every_time_by_each_kiss_matcher_pipeline_run():
    """The summary's time ratios are per trial, one column per KISS-Matcher pipeline present
    (Open3D ICP, small_gicp GICP), and absent for a peer that was not run."""
    from esmicp_lab.bench.scans import real_pairs_markdown

    def row(method, time_s, pair):
        return {"protocol": "real-pairs", "pair": pair, "variant": "turned", "kind": "3DMatch", "overlap": 0.4,
                "method": method, "status": "ok", "success": True, "rotation_error_deg": 1.0,
                "translation_error_m": 0.01, "time_s": time_s}

    rows = [row("esm-global", 2.0, "a"), row("kiss-matcher-icp", 4.0, "a"), row("kiss-matcher-gicp", 1.0, "a"),
            row("esm-global", 3.0, "b"), row("kiss-matcher-icp", 1.0, "b"), row("kiss-matcher-gicp", 3.0, "b")]
    table = real_pairs_markdown(rows)
    assert "time / KISS-Matcher + ICP" in table and "time / KISS-Matcher + small_gicp GICP" in table
    ours = next(line for line in table.splitlines() if line.startswith("| 3DMatch / turned | esmicp default"))
    # per-trial ratios: (2/4, 3/1) -> median 1.75; (2/1, 3/3) -> median 1.5
    assert ours.rstrip(" |").split("|")[-2:] == [" 1.75 ", " 1.50"]
    without = real_pairs_markdown([r for r in rows if r["method"] != "kiss-matcher-gicp"])
    assert "small_gicp" not in without
