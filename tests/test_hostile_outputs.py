"""Outputs that must not be clobbered, and outputs published together.

- An existing output that is not a regular file (a FIFO, a device node, a dangling symbolic link, a
  link to a FIFO) is refused before any work, ``--force`` or not, by every command that writes; a
  link to a regular file is written through (the file it points to replaced, the link kept); the
  streams a user names (``-``, ``/dev/stdout``, ``/dev/null``) are written through, never renamed
  over.
- ``esmicp merge`` publishes its cloud, poses and view together or not at all (a write that fails,
  an interrupt while writing), checks every output path (dangling links included) before reading a
  scan, and its interrupt message says truly what was written.

The FIFOs, links and device nodes are made in a temporary folder (a device node only when the test
runs as root: a copy of /dev/null's numbers); the system's own nodes are never written to.
"""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import interruptible_child, require_module

import esmicp
from esmicp.cli import EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_OK, main
from esmicp.io import read_points, write_points
from esmicp.shapes import asymmetric_shape

pytestmark = pytest.mark.skipif(os.name != "posix", reason="FIFOs, symbolic links and device nodes")

#: A merge quick enough for a test: one process, small pairwise subsets.
MERGE_QUICK = ["--processes", "1", "--pair-points", "150", "--refine-points", "400", "--no-progress"]


@pytest.fixture
def scans(tmp_path):
    """Three overlapping scans of one shape (turned and shifted copies), s0.npy to s2.npy."""
    from esmicp.core.procrustes import apply, to_matrix

    shape = asymmetric_shape(400, rng=3)
    paths = []
    for k in range(3):
        angle = np.deg2rad(20.0 * k)
        rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        paths.append(tmp_path / f"s{k}.npy")
        write_points(paths[-1], apply(to_matrix(rotation, [0.1 * k, 0.0, 0.0]), shape))
    return paths


def _node(folder: Path, kind: str, name: str) -> Path:
    """Make a ``kind`` of non-regular file called ``name`` in ``folder``."""
    path = folder / name
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "device":
        if os.geteuid() != 0:
            pytest.skip("making a device node needs root")
        os.mknod(path, stat.S_IFCHR | 0o666, os.stat("/dev/null").st_rdev)  # a copy of /dev/null's numbers
    elif kind == "dangling-link":
        path.symlink_to(folder / "missing-folder" / name)
    elif kind == "link-to-fifo":
        os.mkfifo(folder / f"fifo-{name}")
        path.symlink_to(folder / f"fifo-{name}")
    else:  # pragma: no cover - a test's typo
        raise ValueError(kind)
    return path


def _fingerprint(path: Path) -> tuple:
    """What the node is, without opening it (a FIFO would block)."""
    info = os.lstat(path)
    return stat.S_IFMT(info.st_mode), info.st_ino, info.st_rdev, os.readlink(path) if path.is_symlink() else None


#: (command, output flag, output name): every output of every command that writes one.
OUTPUTS = [
    ("register", "--output", "aligned.xyz"),
    ("register", "--transform-out", "T.txt"),
    ("merge", "-o", "merged.ply"),
    ("merge", "--poses-out", "poses.txt"),
    ("merge", "--view", "merged.html"),
    ("view", "-o", "view.html"),
    ("heatmap", "-o", "heat.png"),
    ("animate", "-o", "anim.gif"),
]


def _argv(command: str, flag: str, path: Path, scans: list[Path]) -> list[str]:
    if command == "register":
        return ["register", str(scans[1]), str(scans[0]), "--init", "identity", flag, str(path)]
    if command == "merge":
        return ["merge", *map(str, scans), *MERGE_QUICK, *(["-o", str(path.parent / "m.ply")] if flag != "-o" else []),
                flag, str(path)]
    if command == "view":
        return ["view", str(scans[1]), str(scans[0]), "--as-is", flag, str(path)]
    return [command, str(scans[0]), "--points", "12", "--max-iterations", "2", flag, str(path)]


@pytest.mark.parametrize("kind", ["fifo", "device", "dangling-link", "link-to-fifo"])
@pytest.mark.parametrize("command, flag, name", OUTPUTS, ids=[f"{c}{f}" for c, f, _ in OUTPUTS])
def test_an_output_that_is_not_a_regular_file_is_refused_before_any_work(scans, capsys, monkeypatch, command, flag,
                                                                         name, kind):
    """``--force`` renamed a regular file over a FIFO, a device node or a link: now each is refused,
    before any registration, in one line naming it, and stays what it was."""
    if command in ("heatmap", "animate"):
        require_module("matplotlib", "viz")
    if command in ("view",) or flag == "--view":
        require_module("plotly", "viz")
    folder = scans[0].parent
    node = _node(folder, kind, name)
    before = _fingerprint(node)
    entries = sorted(p.name for p in folder.iterdir())
    called = []
    monkeypatch.setattr("esmicp.api.register", lambda *a, **k: called.append(1))
    monkeypatch.setattr("esmicp.multiview.register_scans", lambda *a, **k: called.append(1))
    assert main([*_argv(command, flag, node, scans), "--force"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"esmicp {command}: error: {node}: is "), err
    assert not called, "the work ran before the output was refused"
    assert _fingerprint(node) == before
    assert sorted(p.name for p in folder.iterdir()) == entries  # nothing else written either


def test_a_link_to_a_regular_file_is_written_through(scans, capsys):
    """A symbolic link to a regular file is an output like the file: refused without --force; with
    it, the file the link points to is replaced and the link stays."""
    folder = scans[0].parent
    real = folder / "real-T.txt"
    real.write_text("old\n")
    link = folder / "T.txt"
    link.symlink_to(real.name)
    argv = _argv("register", "--transform-out", link, scans)
    assert main(argv) == EXIT_BAD_INPUT
    assert "already exists" in capsys.readouterr().err
    assert main([*argv, "--force"]) == EXIT_OK
    assert link.is_symlink() and os.readlink(link) == real.name
    assert esmicp.read_transform(real).shape == (4, 4)


def test_dash_writes_the_transform_to_standard_output(scans, capsys):
    folder = scans[0].parent
    entries = sorted(p.name for p in folder.iterdir())
    assert main([*_argv("register", "--transform-out", Path("-"), scans), "--json"]) == EXIT_OK
    lines = capsys.readouterr().out.splitlines()
    report = json.loads(next(line for line in lines if line.startswith("{")))
    matrix = np.loadtxt([line for line in lines if not line.startswith(("{", "#"))])
    np.testing.assert_array_equal(matrix, report["transformation"])
    assert sorted(p.name for p in folder.iterdir()) == entries  # no file called "-"


@pytest.mark.parametrize("stdout_kind", ["pipe", "file"])
def test_dev_stdout_is_written_through_not_replaced(scans, tmp_path, stdout_kind):
    """``--poses-out /dev/stdout`` (no --force: that would have replaced the system's node) writes
    the poses to the standard output the command has, a pipe or a file it appends to."""
    argv = [sys.executable, "-m", "esmicp", "merge", *map(str, scans), *MERGE_QUICK, "-o", str(tmp_path / "m.ply"),
            "--poses-out", "/dev/stdout", "--json"]
    if stdout_kind == "pipe":
        done = subprocess.run(argv, capture_output=True, text=True, timeout=300)
        out = done.stdout
    else:
        with open(tmp_path / "out.txt", "w") as handle:
            handle.write("before\n")
            handle.flush()
            done = subprocess.run(argv, stdout=handle, stderr=subprocess.PIPE, text=True, timeout=300)
        out = (tmp_path / "out.txt").read_text()
        assert out.startswith("before\n")  # appended, not truncated nor replaced
    assert done.returncode == EXIT_OK, done.stderr
    assert "# esmicp poses, format matrix" in out and '"reference": 0' in out
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_dev_null_takes_every_output(scans, capsys):
    argv = ["register", str(scans[1]), str(scans[0]), "--init", "identity", "--transform-out", "/dev/null"]
    assert main(argv) == EXIT_OK, capsys.readouterr().err
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


# --- esmicp merge: all outputs or none ------------------------------------------------------------

@pytest.mark.parametrize("flag", ["-o", "--poses-out", "--view"])
@pytest.mark.parametrize("force", [False, True], ids=["", "force"])
def test_merge_refuses_a_dangling_output_link_before_reading_a_scan(scans, capsys, monkeypatch, flag, force):
    """A dangling ``-o`` was refused only after the whole merge ran (``exists()`` where
    ``lexists()`` is meant), and with --force replaced by the cloud."""
    name = {"-o": "m.ply", "--poses-out": "p.txt", "--view": "v.html"}[flag]
    folder = scans[0].parent
    link = _node(folder, "dangling-link", name)
    read = []
    real_read = esmicp.io.read_points
    monkeypatch.setattr("esmicp.io.read_points", lambda *a, **k: read.append(1) or real_read(*a, **k))
    argv = ["merge", *map(str, scans), *MERGE_QUICK, *([] if flag == "-o" else ["-o", str(folder / "out.ply")]),
            flag, str(link), *(["--force"] if force else [])]
    assert main(argv) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{link}: is a dangling symbolic link" in err, err
    assert not read
    assert link.is_symlink() and not (folder / "out.ply").exists()


def _limited_file_size(limit: int):
    def preexec():
        import resource

        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return preexec


def test_merge_whose_last_output_cannot_be_written_writes_none(scans):
    """Under a file-size limit (1 MB) the cloud and the poses fit, the view (plotly.js inlined,
    about 4 MB) does not: the merge wrote the cloud and the poses, then failed; now it writes none."""
    require_module("plotly", "viz")
    folder = scans[0].parent
    argv = [sys.executable, "-m", "esmicp", "merge", *map(str, scans), *MERGE_QUICK, "-o", str(folder / "m.ply"),
            "--poses-out", str(folder / "p.txt"), "--view", str(folder / "v.html")]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=300, preexec_fn=_limited_file_size(1 << 20))
    assert done.returncode == EXIT_BAD_INPUT, done.stderr
    last = done.stderr.splitlines()[-1]
    assert last.startswith(f"esmicp merge: error: {folder / 'v.html'}: cannot write: "), done.stderr
    assert sorted(p.name for p in folder.iterdir()) == ["s0.npy", "s1.npy", "s2.npy"]


def test_merge_replacing_outputs_restores_them_all_when_one_fails(scans):
    """With --force over older outputs: a failure on the last leaves every older file as it was."""
    require_module("plotly", "viz")
    folder = scans[0].parent
    old = {name: f"old {name}\n" for name in ("m.xyz", "p.txt", "v.html")}
    for name, text in old.items():
        (folder / name).write_text(text)
    argv = [sys.executable, "-m", "esmicp", "merge", *map(str, scans), *MERGE_QUICK, "-o", str(folder / "m.xyz"),
            "--poses-out", str(folder / "p.txt"), "--view", str(folder / "v.html"), "--force"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=300, preexec_fn=_limited_file_size(1 << 20))
    assert done.returncode == EXIT_BAD_INPUT, done.stderr
    assert {name: (folder / name).read_text() for name in old} == old
    assert sorted(p.name for p in folder.iterdir()) == sorted(["s0.npy", "s1.npy", "s2.npy", *old])


CHILD = r"""
import pathlib, sys, time
import esmicp.cli, esmicp.io

ready, argv = pathlib.Path(sys.argv[1]), sys.argv[2:]
real_write_poses = esmicp.io.write_poses


def write_poses_slowly(*args, **kwargs):  # the cloud is written; the poses stall
    ready.touch()
    time.sleep(60)
    return real_write_poses(*args, **kwargs)


esmicp.io.write_poses = write_poses_slowly
sys.exit(esmicp.cli.main(argv))
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_merge_interrupted_between_its_outputs_writes_none_and_says_so(scans, tmp_path, sig):
    """SIGINT while the poses were being written (the cloud done) gave exit 130 and "no partial
    output was written" with the cloud in place; now nothing is there, and the message is true."""
    out = tmp_path / "out"
    out.mkdir()
    ready = tmp_path / "ready"
    argv = ["merge", *map(str, scans), *MERGE_QUICK, "-o", str(out / "m.ply"), "--poses-out", str(out / "p.txt")]
    process = subprocess.Popen([sys.executable, "-c", CHILD, str(ready), *argv], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, preexec_fn=interruptible_child)
    deadline = time.monotonic() + 120
    while not ready.exists():
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            pytest.fail(f"the child never reached the poses: {process.communicate()}")
        time.sleep(0.02)
    ready.unlink()
    process.send_signal(sig)
    _, err = process.communicate(timeout=60)
    assert process.returncode == (EXIT_INTERRUPTED if sig == signal.SIGINT else 143), err
    assert err.splitlines()[-1].endswith("no partial output was written"), err
    assert list(out.iterdir()) == []


def test_an_interrupt_after_the_outputs_names_them(scans, capsys, monkeypatch):
    """Ctrl-C after the outputs were published (here: while the table is printed) says they were
    written, not "no partial output was written"."""
    folder = scans[0].parent

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("esmicp.cli.merge.scan_table", interrupted)
    argv = ["merge", *map(str, scans), *MERGE_QUICK, "-o", str(folder / "m.ply"), "--poses-out", str(folder / "p.txt")]
    assert main(argv) == EXIT_INTERRUPTED
    last = capsys.readouterr().err.splitlines()[-1]
    assert last == f"esmicp merge: interrupted; written before that: {folder / 'm.ply'}, {folder / 'p.txt'}", last
    assert read_points(folder / "m.ply").shape[0] >= 3 and esmicp.read_poses(folder / "p.txt").poses.shape == (3, 4, 4)


def test_a_set_whose_last_file_cannot_be_named_takes_back_the_others(tmp_path):
    """``published_together``: the files are named at the end; when one cannot be (here another
    program created it meanwhile, and overwriting was not asked), those already named are taken
    back: a new one removed, a replaced one restored; no hidden file is left."""
    from esmicp.errors import OutputExistsError
    from esmicp.io.atomic import atomic_write, published_together

    (tmp_path / "replaced.txt").write_text("old\n")
    with pytest.raises(OutputExistsError), published_together():
        with atomic_write(tmp_path / "replaced.txt", overwrite=True, mode="w") as handle:
            handle.write("new\n")
        with atomic_write(tmp_path / "new.txt", mode="w") as handle:
            handle.write("new\n")
        with atomic_write(tmp_path / "raced.txt", mode="w") as handle:
            handle.write("ours\n")
        (tmp_path / "raced.txt").write_text("theirs\n")  # appears before the set is named
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raced.txt", "replaced.txt"]
    assert (tmp_path / "replaced.txt").read_text() == "old\n"
    assert (tmp_path / "raced.txt").read_text() == "theirs\n"


@pytest.mark.parametrize("flag", ["--force", "--resume"])
def test_bench_refuses_a_results_folder_whose_rows_file_is_a_fifo(tmp_path, flag):
    """``esmicp bench --out DIR --force`` (or ``--resume``) with ``DIR/rows.jsonl`` a FIFO blocked
    for good reading it: refused in one line, the FIFO left as it was."""
    out = tmp_path / "run"
    out.mkdir()
    rows = _node(out, "fifo", "rows.jsonl")
    (out / "config.json").write_text("{}\n")
    argv = [sys.executable, "-m", "esmicp", "bench", "--datasets", "synthetic", "--protocols", "copy", "--methods",
            "esm", "--trials", "2", "--points", "100", "--workers", "1", "--no-progress", "--out", str(out), flag]
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        pytest.fail("esmicp bench blocked on the FIFO")
    assert done.returncode == EXIT_BAD_INPUT, done.stderr
    assert done.stderr.splitlines()[-1].startswith(f"esmicp bench: error: {rows}: is a FIFO"), done.stderr
    assert stat.S_ISFIFO(os.lstat(rows).st_mode)
