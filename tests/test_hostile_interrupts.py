"""Interrupted work: ``esmicp register --output`` interrupted mid-run (SIGINT) or killed while
writing (SIGINT, SIGTERM, SIGKILL) never leaves a half-written or temporary file behind, and an
existing output it was replacing stays intact.

The command runs in a child process; to interrupt it at a known moment, the child slows down one
step (every registration iteration sleeps a little, or the writer stops half-way) and touches a
"ready" file when it is there. The code that is interrupted is the real one.
"""

from __future__ import annotations

import errno
import functools
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import interruptible_child

import esmicp
from esmicp.core.procrustes import apply, to_matrix
from esmicp.io import atomic, read_points, write_points
from esmicp.shapes import asymmetric_shape

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")

CHILD = r"""
import contextlib, pathlib, sys, time
import esmicp.api, esmicp.cli, esmicp.io.text, esmicp.io.transform

where, ready, argv = sys.argv[1], pathlib.Path(sys.argv[2]), sys.argv[3:]
if where == "registering":
    real_register = esmicp.api.register

    def slow_register(*args, **kwargs):
        def every_iteration(state):
            ready.touch()
            time.sleep(0.05)

        kwargs["callback"] = every_iteration
        return real_register(*args, **kwargs)

    esmicp.api.register = slow_register
elif where == "writing-points":
    real_write = esmicp.io.text.write_text

    def half_then_wait(handle, points, **kwargs):
        real_write(handle, points[: len(points) // 2], **kwargs)
        handle.flush()
        ready.touch()
        time.sleep(60)
        real_write(handle, points[len(points) // 2 :], **kwargs)

    esmicp.io.text.write_text = half_then_wait
elif where == "writing-transform":
    real_atomic = esmicp.io.transform.atomic_write

    @contextlib.contextmanager
    def stalling_atomic_write(*args, **kwargs):
        with real_atomic(*args, **kwargs) as handle:
            real_handle_write = handle.write

            def write(text):
                real_handle_write(text[: len(text) // 2])
                handle.flush()
                ready.touch()
                time.sleep(60)
                return real_handle_write(text[len(text) // 2 :])

            handle.write = write
            yield handle

    esmicp.io.transform.atomic_write = stalling_atomic_write
sys.exit(esmicp.cli.main(argv))
"""


@pytest.fixture(scope="module")
def clouds(tmp_path_factory):
    """source.xyz and target.xyz in a folder of their own (3,000 points; source moved 20 degrees)."""
    folder = tmp_path_factory.mktemp("clouds")
    target = asymmetric_shape(3000, rng=5)
    angle = np.deg2rad(20.0)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    write_points(folder / "target.xyz", target)
    write_points(folder / "source.xyz", apply(to_matrix(rotation, [0.3, -0.1, 0.2]), target))
    return folder


def interrupt(clouds: Path, out: Path, where: str, sig: int, *extra: str, force: bool = False):
    """Run ``esmicp register`` in a child, send ``sig`` once it is ``where``; return the process."""
    ready = out.parent / f"ready-{where}-{sig}"
    argv = ["register", str(clouds / "source.xyz"), str(clouds / "target.xyz"), "--init", "identity",
            "--output", str(out), *extra, *(["--force"] if force else [])]
    process = subprocess.Popen(
        [sys.executable, "-c", CHILD, where, str(ready), *argv],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=interruptible_child,
    )
    deadline = time.monotonic() + 60
    while not ready.exists():
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            stdout, stderr = process.communicate()
            pytest.fail(f"the child never got {where}: {stdout}{stderr}")
        time.sleep(0.02)
    ready.unlink()
    process.send_signal(sig)
    stdout, stderr = process.communicate(timeout=60)
    return process.returncode, stdout, stderr


def entries(folder: Path) -> list[str]:
    return sorted(path.name for path in folder.iterdir())


def test_sigint_during_registration_writes_nothing(clouds, tmp_path):
    out = tmp_path / "aligned.xyz"
    code, _, stderr = interrupt(clouds, out, "registering", signal.SIGINT, "--transform-out", str(tmp_path / "T.txt"))
    assert code == 130, stderr
    assert "interrupted; no partial output was written" in stderr
    assert entries(tmp_path) == []


#: Exit status of an interrupted command, by signal: SIGINT 130, SIGTERM 143 (both handled: the
#: unfinished outputs removed), SIGKILL death by the signal.
STATUS = {signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGKILL: -signal.SIGKILL}


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL], ids=["SIGINT", "SIGTERM", "SIGKILL"])
def test_interrupted_while_writing_the_output_leaves_nothing(clouds, tmp_path, sig):
    out = tmp_path / "aligned.xyz"
    code, _, stderr = interrupt(clouds, out, "writing-points", sig)
    assert code == STATUS[sig], stderr
    if sig != signal.SIGKILL:
        word = "interrupted" if sig == signal.SIGINT else "terminated (SIGTERM)"
        assert stderr.splitlines()[-1] == f"esmicp register: {word}; no partial output was written", stderr
    assert entries(tmp_path) == [], "a half-written or temporary file was left behind"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_interrupted_while_replacing_an_output_keeps_the_old_one(clouds, tmp_path, sig):
    out = tmp_path / "aligned.xyz"
    out.write_text("old content\n")
    code, _, stderr = interrupt(clouds, out, "writing-points", sig, force=True)
    assert code == STATUS[sig], stderr
    assert entries(tmp_path) == ["aligned.xyz"]
    assert out.read_text() == "old content\n"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_interrupted_while_writing_the_transform_leaves_neither_output(clouds, tmp_path, sig):
    """The aligned cloud is complete when the transform is interrupted, but the two are published
    together: neither is there."""
    out, transform = tmp_path / "aligned.xyz", tmp_path / "T.txt"
    code, _, stderr = interrupt(clouds, out, "writing-transform", sig, "--transform-out", str(transform))
    assert code == STATUS[sig], stderr
    assert entries(tmp_path) == []


def test_an_uninterrupted_run_writes_both(clouds, tmp_path):
    """The same child set-up, left alone: the outputs are complete (the interrupts above are real)."""
    out, transform = tmp_path / "aligned.xyz", tmp_path / "T.txt"
    argv = ["register", str(clouds / "source.xyz"), str(clouds / "target.xyz"), "--init", "identity",
            "--output", str(out), "--transform-out", str(transform)]
    process = subprocess.run(
        [sys.executable, "-c", CHILD, "none", str(tmp_path / "unused"), *argv], capture_output=True, text=True, timeout=120
    )
    assert process.returncode == 0, process.stderr
    assert entries(tmp_path) == ["T.txt", "aligned.xyz"]
    np.testing.assert_allclose(read_points(out), read_points(clouds / "target.xyz"), atol=1e-6)
    assert esmicp.read_transform(transform).shape == (4, 4)


def test_without_unnamed_files_the_named_temporary_is_used_and_removed(tmp_path, monkeypatch):
    """Where an unnamed file cannot be given a name (EXDEV through /proc in some containers), the
    data is copied to a hidden named temporary file, and later writes use named ones directly."""

    def cannot_link(descriptor, destination):
        raise OSError(errno.EXDEV, "Invalid cross-device link")

    monkeypatch.setattr(atomic, "_link_descriptor", cannot_link)
    monkeypatch.setattr(atomic, "_UNNAMED_UNSUPPORTED", set())
    points = asymmetric_shape(500, rng=1)
    write_points(tmp_path / "first.ply", points)
    np.testing.assert_array_equal(read_points(tmp_path / "first.ply"), points)
    with atomic.atomic_write(tmp_path / "second.bin") as handle:
        handle.write(b"data")
        hidden = [name for name in entries(tmp_path) if name.startswith(".second.bin.")]
        assert len(hidden) == 1
    assert entries(tmp_path) == ["first.ply", "second.bin"]
    with pytest.raises(KeyboardInterrupt), atomic.atomic_write(tmp_path / "third.bin") as handle:
        handle.write(b"partial")
        raise KeyboardInterrupt
    assert entries(tmp_path) == ["first.ply", "second.bin"]


COINCIDENT_CHILD = r"""
import os, signal, sys, threading, time, warnings
import numpy as np
import esmicp

signal.signal(signal.SIGINT, signal.default_int_handler)
warnings.simplefilter("ignore")
count, init, fractions = int(sys.argv[1]), sys.argv[2], [float(f) for f in sys.argv[3].split(",")]
base = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
target = np.repeat(base, -(-count // 3), axis=0)[:count]
source = target + 0.01
warm = np.random.default_rng(0).normal(size=(500, 3))
esmicp.register(warm + 0.01, warm)  # the lazy imports: not what is measured


def timed():
    started = time.perf_counter()
    esmicp.register(source, target, init=None if init == "global" else init)
    return time.perf_counter() - started

# The first run of a million points is slower than the next ones (memory first touched): a delay
# taken from it alone can fall after the end of a later run, so with several fractions it is run twice.
durations = [timed() for _ in range(min(2, len(fractions)))]


def fire(sent):
    sent.append(time.perf_counter())
    os.kill(os.getpid(), signal.SIGINT)

# One line per fraction, each SIGINT into a registration of its own, after the interrupted one
# before it. A shared host's runs of one registration vary by more than 15%: when a run ends before
# the SIGINT, it is repeated with the delay cut to the fraction of the quickest run so far.
for fraction in fractions:
    sent = []
    for _ in range(3):
        delay = fraction * min(durations)  # into the same registration, whatever the host's speed
        timer, elapsed = threading.Timer(delay, fire, (sent,)), None
        try:
            timer.start()
            elapsed = timed()
            timer.cancel()
            timer.join()
        except KeyboardInterrupt:
            if elapsed is None:
                print(f"{fraction} interrupted {time.perf_counter() - sent[0]:.4f} {delay:.3f}", flush=True)
                break
        durations.append(elapsed)
    else:
        print(f"{fraction} finished {min(durations[1:]):.3f}", flush=True)
"""

#: The moments of the SIGINT, as fractions of the registration's uninterrupted time, per ``init``.
COINCIDENT_FRACTIONS = {"global": (0.15, 0.5, 0.85), "identity": (0.5,)}


@functools.lru_cache(maxsize=None)
def coincident_interrupt_latencies(count: int, init: str) -> dict[float, tuple[str, float, float]]:
    """Per fraction of :data:`COINCIDENT_FRACTIONS`: ``("interrupted", latency, delay)``, the
    seconds from a SIGINT to the ``KeyboardInterrupt`` of a registration of three points repeated
    to ``count`` (source + 0.01), the SIGINT sent ``delay`` s into it, or ``("finished", seconds,
    0)``. ``delay`` is the fraction of the quickest time the same registration took uninterrupted
    in the same process. Fractions, not fixed delays: on a faster host a fixed delay can fall after
    the end of the registration; and up to three tries, as a run can be quicker than the one before
    it (and end before the SIGINT at 85% of the first). One child per ``init``: it times the
    registration once, then interrupts one registration per fraction."""
    fractions = COINCIDENT_FRACTIONS[init]
    done = subprocess.run(
        [sys.executable, "-c", COINCIDENT_CHILD, str(count), init, ",".join(map(str, fractions))],
        capture_output=True, text=True, timeout=300 * len(fractions), preexec_fn=interruptible_child,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    found = {}
    for line in done.stdout.split("\n"):
        if line.strip():
            fraction, word, value, *delay = line.split()
            found[float(fraction)] = (word, float(value), float(delay[0]) if delay else 0.0)
    return found


@pytest.mark.parametrize("fraction, init", [(f, init) for init, fractions in COINCIDENT_FRACTIONS.items()
                                            for f in fractions])
def test_ctrl_c_stops_a_registration_of_a_million_coincident_points(fraction, init):
    """Ctrl-C on three points repeated to 1M: the kernels check for signals every 5 ms, so the
    interrupt arrives within the second wherever it falls; the bound here is generous for a shared
    CI machine (the measured latency: ``benchmarks/duplicates.py``, docs/reliability.md)."""
    word, latency, delay = coincident_interrupt_latencies(1_000_000, init)[fraction]
    assert word == "interrupted", (
        f"the registration ended ({latency} s) before the SIGINT at {fraction:.0%} of its time, three times")
    print(f"SIGINT at {delay:.3f} s ({fraction:.0%}, {init}): KeyboardInterrupt {latency:.3f} s later")
    assert latency < 1.0


POOL_CHILD = r"""
import multiprocessing, os, signal, sys, threading, time, warnings
import numpy as np
import esmicp
from esmicp.shapes import asymmetric_shape


def main():
    signal.signal(signal.SIGINT, signal.default_int_handler)
    warnings.simplefilter("ignore")
    to_group = sys.argv[1] == "group"
    light = asymmetric_shape(300, rng=1)
    heavy = asymmetric_shape(20_000, rng=2)
    # Pair 0 ends first (a second or two); the heavy pairs run for many seconds each.
    pairs = [(light + 0.01, light)] + [(heavy + 0.01 * k, heavy) for k in range(1, 6)]
    sent = []

    def fire():
        sent.append(time.perf_counter())
        if to_group:  # Ctrl-C in a terminal: the whole process group, the workers included
            os.killpg(0, signal.SIGINT)
        else:
            os.kill(os.getpid(), signal.SIGINT)

    def progress(done, total):
        if done == 1:
            fire()

    try:
        esmicp.register_many(pairs, processes=2, progress=progress)
        print("finished")
    except KeyboardInterrupt:
        latency = time.perf_counter() - sent[0]
        # a worker the pool was starting as Ctrl-C came may still be on its way out: allow it 2 s
        deadline = time.perf_counter() + 2.0
        while multiprocessing.active_children() and time.perf_counter() < deadline:
            time.sleep(0.05)
        print(f"interrupted {latency:.4f} {len(multiprocessing.active_children())}")


if __name__ == "__main__":
    main()
"""


@pytest.mark.parametrize("to", ["process", "group"])
def test_ctrl_c_stops_register_many_and_its_process_pool_at_once(tmp_path, to):
    """Ctrl-C during ``register_many`` on a pool (``esmicp merge``'s pairwise registrations) took
    6-10.5 s: leaving the pool waited for the registrations running in its workers. Now the
    workers ignore SIGINT (the parent handles it) and are terminated, queued jobs cancelled; the
    bound is generous for a shared CI machine."""
    script = tmp_path / "pool_child.py"
    script.write_text(POOL_CHILD)
    done = subprocess.run(
        [sys.executable, str(script), to], capture_output=True, text=True, timeout=600,
        start_new_session=True, preexec_fn=interruptible_child,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    word, *figures = done.stdout.split()
    assert word == "interrupted", done.stdout
    latency, children_left = float(figures[0]), int(figures[1])
    print(f"SIGINT to the {to}: KeyboardInterrupt {latency:.3f} s later")
    assert children_left == 0
    assert latency < 1.0
    assert "Traceback" not in done.stderr, done.stderr[-2000:]  # no worker printed its interrupt
