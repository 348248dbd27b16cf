"""The command line driven end to end: outputs parsed back, every bad input refused cleanly."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import require_module

from esmicp.cli import main
from esmicp.core.procrustes import apply, to_matrix
from esmicp.metrics import random_rotation, rotation_error_deg
from esmicp.shapes import asymmetric_shape


@pytest.fixture
def pair(tmp_path):
    """A source/target pair of files (independent samples of the built-in shape, 20 degrees apart)."""
    rng = np.random.default_rng(7)
    target = asymmetric_shape(1500, rng)
    moved_by = to_matrix(random_rotation(rng, 20.0), [0.1, -0.2, 0.05])
    source = apply(moved_by, asymmetric_shape(1500, rng))
    source_path, target_path = tmp_path / "source.xyz", tmp_path / "target.pcd"
    np.savetxt(source_path, source)
    _write_ascii_pcd(target_path, target)
    return source_path, target_path, np.linalg.inv(moved_by), source


def _write_ascii_pcd(path, points):
    header = (
        "VERSION .7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA ascii\n"
    )
    with open(path, "w") as handle:
        handle.write(header)
        np.savetxt(handle, points, fmt="%.17g")


def run(capsys, *argv):
    """Run the CLI in-process; returns (exit status, stdout, stderr), argparse exits included."""
    try:
        code = main(list(argv))
    except SystemExit as exit_:
        code = exit_.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_register_json_is_parsed_back_and_recovers_the_transform(pair, capsys):
    source, target, truth, _ = pair
    code, out, err = run(capsys, "register", str(source), str(target), "--json")
    assert code == 0, err
    report = json.loads(out)
    for key in ("transformation", "converged", "num_iterations", "fitness", "inlier_rmse", "runtime_s", "method",
                "trusted", "doubts"):
        assert key in report
    assert report["trusted"] is True and report["doubts"] == []  # trusted: nothing casts doubt
    estimate = np.array(report["transformation"])
    assert estimate.shape == (4, 4)
    assert rotation_error_deg(estimate, truth) < 2.0
    assert report["method"] == "esm"
    assert report["source_points"] == 1500


def test_register_summary_and_outputs(pair, tmp_path, capsys):
    source, target, truth, source_points = pair
    aligned, transform = tmp_path / "aligned.ply", tmp_path / "T.txt"
    code, out, err = run(
        capsys, "register", str(source), str(target), "--method", "icp",
        "--output", str(aligned), "--transform-out", str(transform),
    )
    assert code == 0, err
    lines = out.splitlines()
    # Three lines a user reads: the verdict, the pose (its deviations: it is trusted), the run with the
    # overlap's fitness labelled as what it measures; then the matrix. No stage detail.
    assert "(trusted: >= " in lines[0] and "LOW" not in out  # a whole shape on itself
    assert lines[1].startswith("pose: rotation ") and "standard deviation" in lines[1]
    assert lines[2].startswith("icp ") and "overlap (not a verdict): fitness" in lines[2]
    assert lines[3] == "T_target_source ="
    assert "candidate poses verified" not in out and "iterations (" not in out and "std rotation" not in out
    from esmicp import read_points, read_transform

    estimate = read_transform(transform)
    assert rotation_error_deg(estimate, truth) < 2.0
    np.testing.assert_allclose(read_points(aligned), apply(estimate, source_points), atol=1e-5)


def test_register_summary_calls_low_what_is_below_the_trust_bar(pair, capsys):
    """LOW follows the trust bar the result was judged by (``result.policy.trusted``), not the
    search's own ``confident``: the same right pose is LOW once the bar is set above its confidence."""
    from esmicp import read_points, register
    from esmicp.cli.register import verdict
    from esmicp.config import RegistrationConfig
    from esmicp.trust.policy import TrustPolicy

    source, target, _, _ = pair
    code, out, err = run(capsys, "register", str(source), str(target), "--method", "icp", "--json")
    assert code == 0, err
    confidence = json.loads(out)["confidence"]
    assert confidence >= TrustPolicy().trusted and confidence + 1e-6 <= 1.0
    strict = register(read_points(source), read_points(target), method="icp",
                      config=RegistrationConfig(trust=TrustPolicy(trusted=confidence + 1e-6)))
    assert strict.confidence == confidence and not strict.trusted
    assert f"LOW: below {confidence + 1e-6:g}, do not trust this pose" in verdict(strict)


def test_register_summary_says_when_the_pose_is_not_to_be_trusted(tmp_path, capsys):
    """Two clouds that do not overlap anywhere (a shape, and a distant box of noise): whatever pose
    comes back, the summary must say its overlap confidence is low, as ``result.confidence`` does."""
    rng = np.random.default_rng(4)
    source, target = tmp_path / "shape.xyz", tmp_path / "noise.xyz"
    np.savetxt(source, asymmetric_shape(600, rng))  # a search that finds nothing runs every strategy:
    np.savetxt(target, rng.uniform(-5.0, 5.0, size=(600, 3)))  # 0.2 s at 600 points, 2.5 s at 1,500
    code, out, err = run(capsys, "register", str(source), str(target), "-v")
    assert code == 0, err
    assert "LOW: below" in out and "do not trust this pose" in out
    verdict = out.splitlines()[1]  # after the line naming the files
    # No standard deviations beside a pose in doubt, even with -v: they would claim a precision it has not.
    assert "standard deviation" not in out and "std rotation" not in out and "std translation" not in out
    code, out, err = run(capsys, "register", str(source), str(target), "--json")
    report = json.loads(out)
    assert report["confidence"] < 0.5
    assert report["trusted"] is False and any("below" in doubt for doubt in report["doubts"])
    # The verdict line names every reason not to trust the pose, not only the first.
    assert all(doubt in verdict for doubt in report["doubts"] if not doubt.startswith("confidence "))
    # For scripts: --min-confidence turns the verdict into exit status 3 (the outputs still written).
    transform = tmp_path / "T.txt"
    code, out, err = run(capsys, "register", str(source), str(target), "--min-confidence", "--transform-out",
                         str(transform))
    assert code == 3 and "below" in err and transform.is_file()


def test_register_min_confidence_passes_a_trusted_pose_and_refuses_a_bad_bar(pair, capsys):
    source, target, _, _ = pair
    code, out, err = run(capsys, "register", str(source), str(target), "--min-confidence", "--json")
    assert code == 0, err
    assert json.loads(out)["trusted"] is True
    code, _, err = run(capsys, "register", str(source), str(target), "--min-confidence", "1.5")
    assert code == 2 and "--min-confidence" in err


def test_register_quiet_prints_nothing_but_writes_and_verbose_adds_the_detail(pair, tmp_path, capsys):
    """``-q``: no summary line on stdout, the outputs asked for written, the exit status kept; ``-v``:
    the three lines of the summary and, before the matrix, the run's detail (the files, why it
    stopped, each axis's deviation)."""
    source, target, truth, _ = pair
    init = tmp_path / "init.txt"
    np.savetxt(init, truth)
    argv = ["register", str(source), str(target), "--init", str(init), "--method", "icp"]
    code, normal, err = run(capsys, *argv)
    assert code == 0, err
    transform = tmp_path / "T.txt"
    code, out, err = run(capsys, *argv, "-q", "--transform-out", str(transform), "--min-confidence")
    assert code == 0, err
    assert out == "" and err == ""
    assert transform.is_file()
    code, verbose, err = run(capsys, *argv, "--verbose")
    assert code == 0, err
    assert verbose.splitlines()[0].startswith(f"{source} (1500 points) -> {target}")
    assert "std rotation" in verbose and "std translation" in verbose and "converged after" in verbose
    assert len(verbose.splitlines()) > len(normal.splitlines())
    code, _, err = run(capsys, *argv, "-q", "-v")
    assert code == 2 and "not allowed with" in err


def test_init_file_is_used(pair, tmp_path, capsys):
    source, target, truth, _ = pair
    init = tmp_path / "init.txt"
    np.savetxt(init, truth)
    code, out, err = run(capsys, "register", str(source), str(target), "--init", str(init), "--json")
    assert code == 0, err
    assert rotation_error_deg(np.array(json.loads(out)["transformation"]), truth) < 1.0


def test_existing_output_is_refused_unless_forced(pair, tmp_path, capsys):
    source, target, _, _ = pair
    existing = tmp_path / "keep.txt"
    existing.write_text("precious\n")
    code, out, err = run(capsys, "register", str(source), str(target), "--transform-out", str(existing))
    assert code == 2
    assert "keep.txt" in err and "exists" in err and len(err.strip().splitlines()) == 1
    assert existing.read_text() == "precious\n"
    code, _, err = run(capsys, "register", str(source), str(target), "--transform-out", str(existing), "--force")
    assert code == 0, err
    assert existing.read_text() != "precious\n"


def _bad_cases(tmp_path, good):
    """(description, argv tail, text the error must contain)."""
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\xffnot a ply file at all\x13\x37" * 10)
    truncated = tmp_path / "truncated.ply"
    count = 100
    truncated.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n" % count + np.zeros(3 * count // 2, dtype="<f4").tobytes()
    )
    unknown = tmp_path / "cloud.abc"
    unknown.write_text("1 2 3\n")
    two_columns = tmp_path / "two.xyz"
    two_columns.write_text("1 2\n3 4\n5 6\n7 8\n")
    two_points = tmp_path / "few.xyz"
    two_points.write_text("0 0 0\n1 1 1\n")
    identical = tmp_path / "same.xyz"
    identical.write_text("1 2 3\n" * 10)
    collinear = tmp_path / "line.xyz"
    np.savetxt(collinear, np.outer(np.arange(10.0), [1.0, 2.0, 3.0]))
    all_nan = tmp_path / "nan.xyz"
    all_nan.write_text("nan nan nan\n" * 5)
    scaled = tmp_path / "scaled.txt"
    np.savetxt(scaled, np.diag([2.0, 2.0, 2.0, 1.0]))
    malformed = tmp_path / "malformed.txt"
    malformed.write_text("1 0 0\n0 1 0\n")
    return [
        ("missing file", [str(tmp_path / "nope.ply"), good], "nope.ply"),
        ("a directory", [str(tmp_path), good], str(tmp_path)),
        ("garbage", [str(garbage), good], "garbage.ply"),
        ("truncated", [str(truncated), good], "truncated.ply"),
        ("unknown extension", [str(unknown), good], "cloud.abc"),
        ("wrong shape", [str(two_columns), good], "two.xyz"),
        ("fewer than 3 points", [str(two_points), good], "few.xyz"),
        ("all NaN", [str(all_nan), good], "nan.xyz"),
        ("identical points", [str(identical), good], "identical"),
        ("collinear points", [str(collinear), good], "collinear"),
        ("non-rigid init", [good, good, "--init", str(scaled)], "scaled.txt"),
        ("malformed init", [good, good, "--init", str(malformed)], "malformed.txt"),
        ("sigma zero", [good, good, "--sigma", "0"], "--sigma"),
        ("sigma negative", [good, good, "--sigma", "-1"], "--sigma"),
        ("unknown method", [good, good, "--method", "magic"], "--method"),
    ]


BAD_CASES = [
    "missing file", "a directory", "garbage", "truncated", "unknown extension", "wrong shape",
    "fewer than 3 points", "all NaN", "identical points", "collinear points", "non-rigid init",
    "malformed init", "sigma zero", "sigma negative", "unknown method",
]


@pytest.mark.parametrize("name", BAD_CASES)
def test_bad_input_gives_one_line_and_exit_2_and_writes_nothing(pair, tmp_path, capsys, name):
    _, target, _, _ = pair
    cases = {description: (tail, expected) for description, tail, expected in _bad_cases(tmp_path, str(target))}
    assert set(cases) == set(BAD_CASES)
    tail, expected = cases[name]
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code, _, err = run(capsys, "register", *tail, "--output", str(out_dir / "aligned.npy"))
    assert code == 2, name
    _assert_one_line_error(err, expected, name)
    assert list(out_dir.iterdir()) == [], f"{name}: something was written"


def _assert_one_line_error(err, expected, description):
    lines = err.strip().splitlines()
    assert lines, f"{description}: no error printed"
    assert "Traceback" not in err, f"{description}: traceback printed"
    errors = [line for line in lines if "error" in line]
    assert len(errors) == 1, f"{description}: expected one error line, got {lines}"
    assert expected in errors[0], f"{description}: {errors[0]!r} does not mention {expected!r}"


def test_nan_rows_are_dropped_with_a_warning(pair, tmp_path, capsys):
    _, target, _, source_points = pair
    with_nan = tmp_path / "with_nan.xyz"
    points = source_points.copy()
    points[::50] = np.nan
    np.savetxt(with_nan, points)
    code, out, err = run(capsys, "register", str(with_nan), str(target), "--json")
    assert code == 0, err
    assert "warning" in err and "NaN" in err
    assert json.loads(out)["source_points"] == len(points) - len(points[::50])


def test_esm_paper_warns_on_clouds_of_different_sizes(pair, capsys):
    source, target, _, _ = pair
    code, _, err = run(capsys, "register", str(source), str(target), "--method", "esm-paper", "--max-iterations", "3")
    assert code == 0
    assert "warning" in err and "index-aligned" in err


def test_demo_recovers_the_transform(capsys):
    code, out, err = run(capsys, "demo", "--seed", "3")
    assert code == 0, out + err
    assert "recovered" in out and "NOT recovered" not in out


def test_demo_json_is_seeded(capsys):
    first = json.loads(run(capsys, "demo", "--seed", "5", "--json")[1])
    second = json.loads(run(capsys, "demo", "--seed", "5", "--json")[1])
    assert first["true_transformation"] == second["true_transformation"]
    assert first["transformation"] == second["transformation"]
    assert first["recovered"] and first["rotation_error_deg"] < 2.0


def test_demo_paper_method_on_copy_and_its_failure_when_resampled(capsys):
    code, out, _ = run(capsys, "demo", "--method", "esm-paper", "--copy", "--init", "identity", "--json")
    assert code == 0 and json.loads(out)["rotation_error_deg"] < 1e-4
    code, out, err = run(capsys, "demo", "--method", "esm-paper", "--seed", "3", "--json")
    report = json.loads(out)
    assert code == 1 and not report["recovered"], "esm-paper unexpectedly recovered a resampled pair"
    assert "index-aligned" in err


def test_console_script_version_and_help():
    env = dict(os.environ)
    version = subprocess.run([sys.executable, "-m", "esmicp.cli", "--version"], capture_output=True, text=True, env=env)
    assert version.returncode == 0 and version.stdout.startswith("esmicp ")
    for command in ([], ["register"], ["demo"]):
        shown = subprocess.run(
            [sys.executable, "-m", "esmicp.cli", *command, "--help"], capture_output=True, text=True, env=env
        )
        assert shown.returncode == 0 and "usage: esmicp" in shown.stdout
        assert "exit status:" in shown.stdout


def test_every_exit_status_of_every_command_is_in_its_help():
    """Each status a command returns is listed in its ``--help`` (and the top-level one lists all of
    them, merge's 3 included): the statuses the code uses, from their constants."""
    from esmicp.cli import args, build_parser

    parser = build_parser()
    commands = next(action for action in parser._actions if action.__class__.__name__ == "_SubParsersAction").choices
    common = {args.EXIT_OK, args.EXIT_BAD_INPUT, args.EXIT_INTERRUPTED, args.EXIT_BROKEN_PIPE, args.EXIT_TERMINATED}
    own = {"register": {args.EXIT_UNTRUSTED}, "merge": {args.EXIT_PARTIAL}, "demo": {args.EXIT_FAILED}}

    def listed(text: str) -> set[int]:
        return {int(line.split()[0]) for line in text.split("exit status:")[1].splitlines()[1:]
                if line[:7].strip().isdigit()}

    everything = set()
    for name, command in commands.items():
        if not command.add_help:  # the bench placeholder without the lab
            continue
        statuses = listed(command.format_help())
        assert statuses >= common | own.get(name, set()), name
        everything |= statuses
    assert listed(parser.format_help()) == everything >= common | {3, args.EXIT_FAILED}
    merge_help = commands["merge"].format_help().split("exit status:")[1]
    assert "doubtful or unplaced" in merge_help


def _spy(monkeypatch, target):
    """Replace ``target`` ("module.function") by a wrapper that records its keyword arguments."""
    import importlib

    module_name, name = target.rsplit(".", 1)
    module = importlib.import_module(module_name)
    original = getattr(module, name)
    seen = []

    def spy(*args, **kwargs):
        seen.append(kwargs)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, spy)
    return seen


def test_workers_reaches_register_and_one_or_two_threads_give_the_same_pose(pair, capsys, monkeypatch):
    source, target, _, _ = pair
    seen = _spy(monkeypatch, "esmicp.api.register")
    poses = []
    for workers in ("1", "2"):
        code, out, err = run(capsys, "register", str(source), str(target), "--workers", workers, "--json")
        assert code == 0, err
        poses.append(np.array(json.loads(out)["transformation"]))
    code, _, err = run(capsys, "register", str(source), str(target), "--json")
    assert code == 0, err
    assert [kwargs["workers"] for kwargs in seen] == [1, 2, None]
    np.testing.assert_allclose(poses[1], poses[0], rtol=0, atol=1e-12)


def test_workers_reaches_the_demo_and_merge_registrations(pair, tmp_path, capsys, monkeypatch):
    seen = _spy(monkeypatch, "esmicp.api.register")
    code, out, err = run(capsys, "demo", "--seed", "3", "--workers", "1")
    assert code == 0, out + err
    assert [kwargs["workers"] for kwargs in seen] == [1]
    source, target, _, _ = pair
    merged = _spy(monkeypatch, "esmicp.multiview.register_scans")
    common = [str(source), str(target), "--processes", "1", "--pair-points", "300", "--no-progress", "--force"]
    for extra, expected in (([], {}), (["--workers", "2", "-v"], {"workers": 2})):
        code, out, err = run(capsys, "merge", *common, "-o", str(tmp_path / "merged.ply"), *extra)
        assert code == 0, err
        assert {key: merged[-1][key] for key in merged[-1] if key == "workers"} == expected
        # -v adds one line per pairwise registration (scan 0 registered with scan 1 at least).
        assert ("pairwise registrations (" in out) == ("-v" in extra)
        assert ("  0-1 " in out or "  1-0 " in out) == ("-v" in extra)


@pytest.mark.parametrize("command", ["register", "demo", "merge"])
@pytest.mark.parametrize("bad", ["0", "-3", "x", "1.5"])
def test_a_bad_workers_value_is_one_line_and_exit_2(pair, tmp_path, capsys, command, bad):
    source, target, _, _ = pair
    files = [] if command == "demo" else [str(source), str(target)]
    out = tmp_path / "merged.ply"
    tail = ["-o", str(out)] if command == "merge" else []
    code, _, err = run(capsys, command, *files, *tail, "--workers", bad)
    assert code == 2
    _assert_one_line_error(err, "--workers", f"{command} --workers {bad}")
    assert bad in err
    assert not out.exists()


@pytest.fixture
def three_scans(tmp_path):
    """Three files of independent samples of the built-in shape, each in its own frame."""
    rng = np.random.default_rng(11)
    paths = []
    for k in range(3):
        path = tmp_path / f"scan {k}.xyz"  # a space in the name: the pose file still names it
        np.savetxt(path, apply(to_matrix(random_rotation(rng, 25.0), rng.normal(size=3)), asymmetric_shape(1500, rng)))
        paths.append(path)
    return paths


def test_merge_writes_the_scan_index_and_colours_and_poses_that_place_the_points(three_scans, tmp_path, capsys):
    """The merged .ply holds, per point, the scan it came from and that scan's colour; the TUM
    poses read back by esmicp.read_poses move each scan's points onto its part of the cloud."""
    import plyfile

    from esmicp import read_points, read_poses
    from esmicp.io import scan_palette

    merged, poses = tmp_path / "merged.ply", tmp_path / "poses.tum"
    code, out, err = run(capsys, "merge", *map(str, three_scans), "-o", str(merged), "--poses-out", str(poses),
                         "--poses-format", "tum", "--threads", "1", "--pair-points", "300", "--no-progress", "--json")
    assert code == 0, err
    report = json.loads(out)
    written = read_poses(poses)
    assert written.format == "tum" and written.names == tuple(map(str, three_scans))
    assert list(written.status) == [scan["status"] for scan in report["scans"]] == ["placed"] * 3
    vertex = plyfile.PlyData.read(str(merged))["vertex"]
    labels = np.asarray(vertex["scan_index"])
    cloud = np.stack([vertex[c] for c in "xyz"], axis=1)
    np.testing.assert_array_equal(read_points(merged), cloud)
    colours = np.stack([vertex[c] for c in ("red", "green", "blue")], axis=1)
    np.testing.assert_array_equal(colours, scan_palette(3)[labels])
    for k, path in enumerate(three_scans):
        T = written.poses[k]
        np.testing.assert_allclose(cloud[labels == k], apply(T, read_points(path)), rtol=0, atol=1e-9)


def test_merge_to_a_plain_format_says_what_it_leaves_out_and_kitti_poses_read_back(three_scans, tmp_path, capsys):
    from esmicp import read_points, read_poses

    merged, poses = tmp_path / "merged.xyz", tmp_path / "poses.txt"
    code, out, err = run(capsys, "merge", *map(str, three_scans), "-o", str(merged), "--poses-out", str(poses),
                         "--poses-format", "kitti", "--threads", "1", "--pair-points", "300", "-q")
    assert code == 0, err
    assert out == ""  # -q: no table, no summary (and no progress bar on stderr)
    assert "scan_index" in err and "warning" in err  # the scan index is not silently lost, even with -q
    assert "pairs" not in err
    assert read_points(merged).shape[1] == 3 and np.loadtxt(merged).shape[1] == 3
    written = read_poses(poses)
    assert written.format == "kitti" and len(written) == 3
    np.testing.assert_array_equal(written.poses[0], np.eye(4))


def test_poses_format_without_poses_out_is_refused_before_any_work(three_scans, tmp_path, capsys):
    out = tmp_path / "merged.ply"
    code, _, err = run(capsys, "merge", *map(str, three_scans), "-o", str(out), "--poses-format", "tum")
    assert code == 2
    _assert_one_line_error(err, "--poses-format", "--poses-format without --poses-out")
    assert not out.exists()


STAGES = [("pairs", 0, 4), ("pairs", 1, 4), ("pairs", 4, 4), ("pose graph", 0, 1), ("pose graph", 1, 1),
          ("more pairs (round 2)", 0, 2), ("more pairs (round 2)", 2, 2), ("joint refinement", 0, 1),
          ("joint refinement", 1, 1)]


@pytest.mark.parametrize("with_tqdm", [True, False])
def test_merge_progress_shows_one_bar_per_stage_with_its_label_and_total(capsys, monkeypatch, with_tqdm):
    from esmicp.cli.merge import _progress

    if with_tqdm:
        require_module("tqdm", "bench")
    else:
        monkeypatch.setitem(sys.modules, "tqdm", None)  # the fallback without the 'bench' extra
    report, close = _progress(True)
    for call in STAGES:
        report(*call)
    close()
    err = capsys.readouterr().err
    for stage, _, total in STAGES:
        assert f"{stage}" in err and f"{total}/{total}" in err
    assert "4/4" in err.split("pose graph")[0]  # the pairs' bar ends full before the next stage


def test_register_min_confidence_refuses_a_run_stopped_before_it_converged(pair, capsys):
    """A refinement cut short by ``--max-iterations`` is not trusted however sharp its overlap: the
    summary says NOT CONVERGED and ``--min-confidence`` exits 3, whatever bar is asked for."""
    source, target, _, _ = pair
    argv = ("register", str(source), str(target), "--init", "identity", "--method", "icp", "--max-iterations", "12")
    code, out, err = run(capsys, *argv, "--json")
    assert code == 0, err
    assert json.loads(out)["converged"] is False and json.loads(out)["trusted"] is False
    code, out, err = run(capsys, *argv)
    assert code == 0 and "NOT CONVERGED" in out
    for bar in ((), ("0",)):
        code, _, err = run(capsys, *argv, "--min-confidence", *bar)
        assert code == 3 and "not converged" in err
