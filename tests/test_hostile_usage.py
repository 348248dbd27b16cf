"""Careless and hostile use: tiny sigmas, far starts, outputs that collide or dangle, permissions
lost by --force, out of memory, full disks, two runs on one results folder, and results folders
whose rows would make table names escape the folder.

docs/reliability.md ("Careless and hostile use") lists each case and what it returns.
"""

from __future__ import annotations

import errno
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import esmicp
from esmicp_lab.bench import BenchConfig, RunOptions, read_rows, run_bench
from esmicp.cli import EXIT_BAD_INPUT, EXIT_OK, main
from esmicp.errors import InvalidInputError
from esmicp.io import write_points


def _pair(seed: int = 0, points: int = 300):
    rng = np.random.default_rng(seed)
    target = rng.normal(size=(points, 3)) * [3.0, 2.0, 1.0]
    return target + [0.01, -0.02, 0.005], target


@pytest.fixture
def files(tmp_path):
    source, target = _pair()
    write_points(tmp_path / "s.xyz", source)
    write_points(tmp_path / "t.xyz", target)
    return tmp_path / "s.xyz", tmp_path / "t.xyz"


def _one_line(capsys, prefix: str) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(prefix), err
    return err


# --- Item 5: tiny sigmas ------------------------------------------------------------------------

@pytest.mark.parametrize("method", ["esm", "esm-paper", "icp"])
def test_every_positive_sigma_ends_like_a_small_one(method):
    source, target = _pair()
    outcomes = set()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow / divide warning either
        for sigma in (1e-30, 1e-155, 1e-200, 1e-300, 5e-324):
            result = esmicp.register(source, target, method=method, init="identity", sigma=sigma)
            assert np.isfinite(result.transformation).all(), sigma
            outcomes.add((result.converged, result.message.split(" (")[0].split(":")[0]))
    assert len(outcomes) == 1, outcomes


def test_tiny_sigma_on_the_command_line_is_not_a_traceback(files, capsys):
    source, target = files
    assert main(["register", str(source), str(target), "--init", "identity", "--sigma", "1e-200", "--json"]) == EXIT_OK
    report = json.loads(capsys.readouterr().out)
    assert np.isfinite(report["transformation"]).all()


# --- Minor: a start translation of 1e200 ----------------------------------------------------------

def test_a_start_beyond_float64_geometry_is_refused_not_converged_wrong():
    source, target = _pair()
    start = np.eye(4)
    start[0, 3] = 1e200
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InvalidInputError, match=r"^init: its translation \(1e\+200\)"):
            esmicp.register(source, target, init=start)
    start[0, 3] = 1e3  # far, but representable: still registered
    assert esmicp.register(source, target, init=start, method="icp").transformation.shape == (4, 4)


# --- Item 8 and minors: outputs ---------------------------------------------------------------

@pytest.mark.parametrize("force", [False, True])
def test_transform_out_equal_to_output_is_refused_before_any_work(files, capsys, monkeypatch, force):
    source, target = files
    out = source.parent / "aligned.xyz"
    called = []
    monkeypatch.setattr("esmicp.api.register", lambda *a, **k: called.append(1))
    argv = ["register", str(source), str(target), "--output", str(out),
            "--transform-out", str(source.parent / "." / "aligned.xyz")] + (["--force"] if force else [])
    assert main(argv) == EXIT_BAD_INPUT
    _one_line(capsys, "esmicp register: error: --transform-out ")
    assert not out.exists() and not called


def test_transform_out_hard_linked_to_output_is_refused(files, capsys):
    source, target = files
    out, link = source.parent / "aligned.xyz", source.parent / "T.txt"
    out.write_text("old\n")
    os.link(out, link)
    assert main(["register", str(source), str(target), "--output", str(out), "--transform-out", str(link),
                 "--force"]) == EXIT_BAD_INPUT
    _one_line(capsys, "esmicp register: error: --transform-out ")
    assert out.read_text() == "old\n"


def test_dangling_symlink_output_is_refused_before_the_registration(files, capsys, monkeypatch):
    source, target = files
    out = source.parent / "aligned.xyz"
    out.symlink_to(source.parent / "missing" / "x.xyz")
    called = []
    monkeypatch.setattr("esmicp.api.register", lambda *a, **k: called.append(1))
    assert main(["register", str(source), str(target), "--output", str(out)]) == EXIT_BAD_INPUT
    _one_line(capsys, f"esmicp register: error: {out}: is a dangling symbolic link")
    assert not called and out.is_symlink()


@pytest.mark.skipif(os.name != "posix", reason="POSIX permission bits")
def test_force_keeps_the_mode_of_the_file_it_replaces(files, capsys):
    source, target = files
    out = source.parent / "aligned.xyz"
    out.write_text("old\n")
    os.chmod(out, 0o600)
    assert main(["register", str(source), str(target), "--init", "identity", "--output", str(out),
                 "--force"]) == EXIT_OK
    assert (out.stat().st_mode & 0o777) == 0o600
    assert len(esmicp.read_points(out)) == 300


def test_out_of_memory_in_the_registration_is_one_line_exit_2(files, capsys, monkeypatch):
    source, target = files

    def exhausted(*args, **kwargs):
        raise MemoryError("Unable to allocate 4.00 GiB for an array with shape (179000000, 3)")

    monkeypatch.setattr("esmicp.api.register", exhausted)
    assert main(["register", str(source), str(target)]) == EXIT_BAD_INPUT
    _one_line(capsys, "esmicp register: error: out of memory")


# --- Item 6, item 7 and the full disk: esmicp bench ------------------------------------------

def small(**changes) -> BenchConfig:
    values = dict(protocols=("copy",), datasets=("synthetic",), methods=("icp",), trials=2, points=(100,),
                  max_iterations=10)
    values.update(changes)
    return BenchConfig(**values)


def serial(out: Path, **changes) -> RunOptions:
    return RunOptions(out_dir=out, workers=1, progress=False, **changes)


def test_a_second_run_on_a_locked_folder_is_refused(tmp_path):
    import fcntl

    from esmicp_lab.bench.results import LOCK

    run_bench(small(), serial(tmp_path))
    rows_path = tmp_path / "rows.jsonl"
    rows_path.write_bytes(rows_path.read_bytes().splitlines(keepends=True)[0])  # one trial left to resume
    before = rows_path.read_bytes()
    with open(tmp_path / LOCK, "a") as held:  # another run holds the folder
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(InvalidInputError, match="another esmicp bench is running on this folder"):
            run_bench(small(), serial(tmp_path, resume=True))
    assert rows_path.read_bytes() == before
    outcome = run_bench(small(), serial(tmp_path, resume=True))  # released: resumes
    assert outcome.rows_written == 1 and outcome.rows_total == 2


def test_rows_appended_twice_count_once(tmp_path):
    run_bench(small(), serial(tmp_path))
    rows_path = tmp_path / "rows.jsonl"
    rows_path.write_bytes(rows_path.read_bytes() * 2)  # what two concurrent --resume left
    rows = read_rows(rows_path)
    assert len(rows) == 2
    from esmicp_lab.bench import write_tables

    write_tables(tmp_path)
    assert "(2 trials)" in (tmp_path / "summary.md").read_text()
    assert ",2,2," in (tmp_path / "summary.csv").read_text()  # rows, ok


def test_resumed_rows_cannot_write_tables_outside_the_folder(tmp_path):
    out = tmp_path / "results"
    run_bench(small(protocols=("paper",)), serial(out))
    escape = tmp_path / "escaped"
    rows = read_rows(out / "rows.jsonl")
    rows[0]["case"] = f"x/../../{escape.name}"  # a handed-over folder with a crafted row
    (out / "rows.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    from esmicp_lab.bench import write_tables

    written = write_tables(out)
    assert not list(tmp_path.glob("escaped*")) and not list(tmp_path.glob("*.md"))
    for path in written:
        assert path.parent == out, path


def test_bench_on_a_full_disk_is_one_line(tmp_path, capsys, monkeypatch):
    from esmicp_lab.bench import results

    def full(self, row):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(results.RowWriter, "write", full)
    code = main(["bench", "--datasets", "synthetic", "--protocols", "copy", "--methods", "icp", "--trials", "1",
                 "--points", "100", "--workers", "1", "--no-progress", "--out", str(tmp_path / "out")])
    assert code == EXIT_BAD_INPUT
    assert "No space left on device" in _one_line(capsys, "esmicp bench: error: ")


# --- esmicp merge: outputs that are one file, or one of the scans ---------------------------------

MERGE_QUICK = ["--processes", "1", "--pair-points", "100", "--no-progress"]


def _folder_state(folder: Path) -> dict:
    return {path.name: (path.is_symlink(), path.read_bytes() if path.is_file() else None) for path in folder.iterdir()}


def _merge_case(folder: Path, case: str) -> list[str]:
    """Arguments of ``esmicp merge`` for ``case`` (two small scans a.xyz, b.xyz in ``folder``)."""
    source, target = _pair()
    scans = [folder / "a.xyz", folder / "b.xyz"]
    write_points(scans[0], source)
    write_points(scans[1], target)
    merged, poses, view = folder / "merged.ply", folder / "poses.txt", folder / "view.html"
    if case == "poses-out is output":
        return [*map(str, scans), "-o", str(merged), "--poses-out", str(merged)]
    if case == "view is poses-out":
        return [*map(str, scans), "-o", str(merged), "--poses-out", str(view), "--view", str(view)]
    if case == "view is output, a hard link":
        write_points(merged, source)
        os.link(merged, view)
        return [*map(str, scans), "-o", str(merged), "--view", str(view)]
    if case == "output is a scan":
        return [*map(str, scans), "-o", str(scans[0])]
    if case == "output is a scan, spelled otherwise":
        (folder / "sub").mkdir()
        return [*map(str, scans), "-o", str(folder / "sub" / ".." / "b.xyz")]
    if case == "poses-out is a scan":
        return [*map(str, scans), "-o", str(merged), "--poses-out", str(scans[1])]
    if case == "view is a scan, a symbolic link":
        view.symlink_to(scans[0])
        return [*map(str, scans), "-o", str(merged), "--view", str(view)]
    raise AssertionError(case)


@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("case", [
    "poses-out is output", "view is poses-out", "view is output, a hard link", "output is a scan",
    "output is a scan, spelled otherwise", "poses-out is a scan", "view is a scan, a symbolic link",
])
def test_merge_outputs_that_are_one_file_are_refused_before_anything_is_written(tmp_path, capsys, case, force):
    argv = _merge_case(tmp_path, case)
    before = _folder_state(tmp_path)
    assert main(["merge", *argv, *MERGE_QUICK, *(["--force"] if force else [])]) == EXIT_BAD_INPUT
    err = _one_line(capsys, "esmicp merge: error: ")
    assert "is the same file as" in err or "is the input file" in err, err
    assert _folder_state(tmp_path) == before  # nothing written, no scan replaced


def test_register_output_that_is_its_source_is_refused_even_with_force(files, capsys):
    source, target = files
    before = source.read_bytes()
    assert main(["register", str(source), str(target), "--output", str(source), "--force"]) == EXIT_BAD_INPUT
    err = _one_line(capsys, "esmicp register: error: ")
    assert "is the input file" in err, err
    assert source.read_bytes() == before


# --- esmicp merge --skip-bad: --reference names the scan given on the command line -----------------

def _merge_scans(folder: Path) -> list[Path]:
    """a.xyz, an unreadable broken.xyz, b.xyz (a shifted copy of a) and c.xyz (noise: not placeable)."""
    from esmicp.shapes import asymmetric_shape

    shape = asymmetric_shape(400, rng=3)
    paths = [folder / name for name in ("a.xyz", "broken.xyz", "b.xyz", "c.xyz")]
    write_points(paths[0], shape)
    paths[1].write_text("not a point cloud\n")
    write_points(paths[2], shape + [0.05, -0.02, 0.01])
    write_points(paths[3], np.random.default_rng(4).normal(size=(400, 3)) * 50.0)
    return paths


def _pose_rows(path: Path) -> dict:
    written = esmicp.read_poses(path)
    return {Path(name).name: T for name, T in zip(written.names, written.poses)}


def test_merge_reference_after_a_skipped_scan_is_the_scan_named(tmp_path, capsys):
    scans = _merge_scans(tmp_path)
    poses = tmp_path / "poses.txt"
    argv = ["merge", *map(str, scans[:3]), "-o", str(tmp_path / "m.ply"), "--poses-out", str(poses),
            "--skip-bad", "--reference", "2", *MERGE_QUICK]
    assert main(argv) == EXIT_OK, capsys.readouterr().err
    rows = _pose_rows(poses)
    np.testing.assert_array_equal(rows["b.xyz"], np.eye(4))  # b.xyz, the scan at index 2, is the world
    assert not np.array_equal(rows["a.xyz"], np.eye(4))


def test_merge_reference_that_was_skipped_is_an_error_naming_it(tmp_path, capsys):
    scans = _merge_scans(tmp_path)
    out = tmp_path / "m.ply"
    argv = ["merge", *map(str, scans[:3]), "-o", str(out), "--skip-bad", "--reference", "1", *MERGE_QUICK]
    assert main(argv) == EXIT_BAD_INPUT
    last = capsys.readouterr().err.splitlines()[-1]
    assert last.startswith("esmicp merge: error: --reference 1: ") and "broken.xyz" in last, last
    assert not out.exists()


def test_merge_reference_out_of_range_is_refused_before_reading(tmp_path, capsys):
    scans = _merge_scans(tmp_path)
    argv = ["merge", *map(str, scans), "-o", str(tmp_path / "m.ply"), "--reference", "4", *MERGE_QUICK]
    assert main(argv) == EXIT_BAD_INPUT
    err = _one_line(capsys, "esmicp merge: error: --reference")  # broken.xyz not even read
    assert "[0, 4)" in err, err


def test_merge_unplaced_scan_lines_all_carry_the_command_prefix(tmp_path):
    """In a fresh process, as a user runs it (pytest's own log handlers would hide the library's
    log lines)."""
    import subprocess
    import sys

    scans = _merge_scans(tmp_path)
    argv = ["merge", str(scans[0]), str(scans[2]), str(scans[3]), "-o", str(tmp_path / "m.ply"), *MERGE_QUICK, "--allow-partial"]
    done = subprocess.run([sys.executable, "-m", "esmicp", *argv], capture_output=True, text=True, timeout=300)
    assert done.returncode == EXIT_OK, done.stderr
    err = done.stderr.splitlines()
    assert any("c.xyz" in line and "unplaced" in line for line in err), err
    assert err and all(line.startswith("esmicp merge: ") for line in err), err


# --- The command line names the file whose numbers float64 geometry cannot use ---------------------

@pytest.mark.parametrize("case", ["source 1e20 times its target", "a float64 .bin read as float32"])
def test_register_names_the_file_whose_numbers_are_beyond_float64(tmp_path, capsys, case):
    source, target = _pair(points=500)
    if case == "source 1e20 times its target":
        paths = [tmp_path / "huge.xyz", tmp_path / "t.xyz"]
        write_points(paths[0], source * 1e20)
        write_points(paths[1], target)
        words, extra = [f"{paths[0]}: spans", "units"], []
    else:
        paths = [tmp_path / "doubles.bin", tmp_path / "t.bin"]
        source.astype("<f8").tofile(paths[0])  # float64 records: read as float32, each double is two floats
        target.astype("<f4").tofile(paths[1])
        words, extra = [f"{paths[0]}: its points span", "wrong layout"], ["--bin-columns", "3"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the NaN halves of the doubles, dropped with a warning
        assert main(["register", *map(str, paths), *extra]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.startswith("esmicp register: error: "), err
    for word in words:
        assert word in err, err


def test_closed_standard_output_ends_quietly(files):
    """``esmicp register ... | head -0``: the reader closed the pipe; no "error: Broken pipe"."""
    import subprocess
    import sys

    source, target = files
    process = subprocess.Popen([sys.executable, "-m", "esmicp", "register", str(source), str(target)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()  # the reader goes away before any output
    err = process.stderr.read().decode()
    status = process.wait(timeout=300)
    assert status in (0, 141), (status, err)
    assert "Broken pipe" not in err and "Traceback" not in err and "Exception ignored" not in err, err


# --- Arguments a merge cannot work with, refused before the work ------------------------------------

@pytest.mark.parametrize("name", ["pair_points", "refine_points"])
@pytest.mark.parametrize("value", [1, 2])
def test_register_scans_needs_at_least_three_points_per_subset(name, value):
    """``register_scans(pair_points=1)`` ended in a LinAlgError traceback (2: every pair failed);
    a registration needs 3 points."""
    from esmicp.shapes import asymmetric_shape

    clouds = [asymmetric_shape(200, rng=k) for k in range(2)]
    with pytest.raises(InvalidInputError, match=rf"^{name}: expected a whole number >= 3, got {value}$"):
        esmicp.register_scans(clouds, threads=1, **{name: value})


@pytest.mark.parametrize("flag", ["--pair-points", "--refine-points"])
def test_merge_pair_points_below_three_is_one_line(tmp_path, capsys, flag):
    scans = _merge_scans(tmp_path)
    with pytest.raises(SystemExit) as usage:  # argparse's usage error
        main(["merge", str(scans[0]), str(scans[2]), "-o", str(tmp_path / "m.ply"), flag, "1"])
    assert usage.value.code == EXIT_BAD_INPUT
    err = _one_line(capsys, "esmicp merge: error: argument ")
    assert flag in err and ">= 3" in err, err


@pytest.mark.parametrize("voxel", ["1e300", "50"])
def test_merge_voxel_larger_than_the_scans_is_refused_before_the_merge(tmp_path, capsys, monkeypatch, voxel):
    """``--voxel 1e300`` ran the whole merge, then blamed "need at least 3 finite points"."""
    scans = _merge_scans(tmp_path)
    called = []
    monkeypatch.setattr("esmicp.multiview.register_scans", lambda *a, **k: called.append(1))
    out = tmp_path / "m.ply"
    assert main(["merge", str(scans[0]), str(scans[2]), "-o", str(out), "--voxel", voxel, *MERGE_QUICK]) == EXIT_BAD_INPUT
    err = _one_line(capsys, f"esmicp merge: error: --voxel {float(voxel):g}: ")
    assert "largest scan" in err, err
    assert not called and not out.exists()


@pytest.mark.parametrize("bar", [float("nan"), -0.1, 1.5, "0.5", True, [0.5]],
                         ids=["nan", "negative", "above-1", "string", "bool", "list"])
def test_doubts_refuses_a_bar_that_is_not_a_confidence(bar):
    """``doubts(nan)`` / ``doubts(-1)`` trusted the pose at any confidence; a string raised a bare
    TypeError."""
    source, target = _pair()
    result = esmicp.register(source, target, init="identity")
    with pytest.raises(InvalidInputError, match=r"^bar: expected a"):
        result.doubts(bar)
    for accepted in (0.0, 1.0, np.float32(0.3), 1):  # the bounds and NumPy numbers are bars
        assert isinstance(result.doubts(accepted), list)


# --- Scan names that are not UTF-8 ----------------------------------------------------------------------

@pytest.mark.skipif(sys.platform == "win32" or sys.platform == "darwin", reason="byte file names (Linux)")
def test_merge_of_a_scan_whose_name_is_not_utf8_prints_and_writes(tmp_path):
    """A scan called ``b'bad\\xff.xyz'`` crashed after the cloud was written (UnicodeEncodeError on a
    strict UTF-8 output): the table shows the name with an escape, and the poses file keeps it so
    that it names the same file when read back."""
    import subprocess

    scans = _merge_scans(tmp_path)
    odd = os.fsdecode(bytes(tmp_path) + b"/bad\xff.xyz")
    os.rename(scans[2], odd)
    argv = [sys.executable, "-m", "esmicp", "merge", str(scans[0]), odd, "-o", str(tmp_path / "m.ply"),
            "--poses-out", str(tmp_path / "p.txt"), *MERGE_QUICK]
    done = subprocess.run(argv, capture_output=True, timeout=300, env={**os.environ, "PYTHONIOENCODING": "utf-8:strict"})
    assert done.returncode == EXIT_OK, done.stderr.decode(errors="replace")
    assert b"bad\\xff.xyz" in done.stdout and b"Traceback" not in done.stderr
    names = esmicp.read_poses(tmp_path / "p.txt").names
    assert os.fsencode(names[1]) == os.fsencode(odd)


# --- --skip-bad: everything refers to the scans as listed ---------------------------------------------

def test_merge_skip_bad_reports_the_scans_as_listed(tmp_path, capsys):
    """With --skip-bad the poses file, its "world = scan k" header, --reference and --json counted
    only the readable scans (``--reference 2`` was reported back as 1)."""
    import plyfile

    scans = _merge_scans(tmp_path)
    out, poses = tmp_path / "m.ply", tmp_path / "p.txt"
    argv = ["merge", *map(str, scans[:3]), "-o", str(out), "--poses-out", str(poses), "--skip-bad", "--reference",
            "2", "--json", *MERGE_QUICK]
    assert main(argv) == EXIT_OK
    report = json.loads(capsys.readouterr().out)
    assert report["reference"] == 2 and report["files"] == list(map(str, scans[:3]))
    assert [scan["status"] for scan in report["scans"]] == ["placed", "unreadable", "placed"]
    assert report["unplaced"] == [1] and report["placed"] == [True, False, True]
    assert all({edge["i"], edge["j"]} <= {0, 2} for edge in report["edges"]) and report["edges"]
    assert report["poses"][1] is None and np.array_equal(report["poses"][2], np.eye(4))
    written = esmicp.read_poses(poses)
    assert written.reference == 2 and written.names == tuple(map(str, scans[:3]))
    assert written.status == ("placed", "unreadable", "placed") and np.isnan(written.poses[1]).all()
    labels = np.asarray(plyfile.PlyData.read(str(out))["vertex"]["scan_index"])
    assert set(labels.tolist()) == {0, 2}
