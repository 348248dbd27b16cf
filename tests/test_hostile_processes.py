"""Worker processes: SIGTERM ends a merge on a process pool as Ctrl-C does, workers never outlive
their parent, a pool that cannot start says why in one line, and an address-space limit gives a
result or a one-line error, never a traceback or a hang.

Each test runs the command (or a script) in a child process of its own session; the children of
that child are listed with psutil (or, without it, from /proc) and are killed by the test if any
outlives what the test expects.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import require_module

from esmicp.io import write_points
from esmicp.shapes import asymmetric_shape

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals, /proc, RLIMIT_AS")

#: Seconds a test waits for processes to end (a bound for a loaded CI machine; they end in
#: milliseconds).
ENDS_WITHIN_S = 10.0


def descendants(pid: int) -> set[int]:
    """The pids of every living descendant of ``pid``."""
    try:
        import psutil
    except ImportError:
        psutil = None
    if psutil is not None:
        try:
            return {child.pid for child in psutil.Process(pid).children(recursive=True)}
        except psutil.NoSuchProcess:
            return set()
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def alive(pids) -> set[int]:
    """Those of ``pids`` still running (zombies count as ended)."""
    living = set()
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            living.add(pid)
    return living


def wait_until_gone(pids, seconds: float = ENDS_WITHIN_S) -> set[int]:
    """Wait up to ``seconds`` for ``pids`` to end; return those still running (killed, so that a
    failing test leaves nothing behind)."""
    deadline = time.monotonic() + seconds
    while alive(pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = alive(pids)
    for pid in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return left


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """Four 8,000-point views of one shape: a merge whose pairwise registrations keep two worker
    processes busy for seconds."""
    from esmicp.core.procrustes import apply, to_matrix

    folder = tmp_path_factory.mktemp("scans")
    shape = asymmetric_shape(8000, rng=3)
    paths = []
    for k in range(4):
        angle = np.deg2rad(15.0 * k)
        rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        paths.append(folder / f"s{k}.npy")
        write_points(paths[-1], apply(to_matrix(rotation, [0.05 * k, 0.0, 0.0]), shape))
    return paths


def start_merge_on_processes(scans, out: Path) -> tuple[subprocess.Popen, set[int]]:
    """``esmicp merge ... --processes 2`` in a session of its own, once its two workers run: the
    process and its descendants then (workers, multiprocessing's resource tracker)."""
    process = subprocess.Popen(
        [sys.executable, "-m", "esmicp", "merge", *map(str, scans), "-o", str(out), "--processes", "2", "--no-progress"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    deadline = time.monotonic() + 120
    while True:
        children = descendants(process.pid)
        workers = [pid for pid in children if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text(errors="replace")
                   .replace("\0", " ")] if children else []
        if len(workers) >= 2:
            break
        if process.poll() is not None or time.monotonic() > deadline:
            wait_until_gone(children, 0)
            process.kill()
            pytest.fail(f"the merge never ran two workers: {process.communicate()}")
        time.sleep(0.02)
    time.sleep(0.5)  # the workers importing, or at their first registrations
    if process.poll() is not None:
        pytest.fail(f"the merge ended before the signal: {process.communicate()}")
    return process, descendants(process.pid)


def test_sigterm_ends_a_merge_on_processes_and_its_workers(scans, tmp_path):
    """``kill`` of a merge on ``--processes 2`` left its 2 workers and the resource tracker alive for
    good, holding the parent's stderr open (a caller reading it hung). Now SIGTERM is handled as
    Ctrl-C: the workers are ended, exit status 143, nothing written."""
    out = tmp_path / "m.ply"
    process, children = start_merge_on_processes(scans, out)
    process.send_signal(signal.SIGTERM)
    try:
        _, err = process.communicate(timeout=ENDS_WITHIN_S)  # stderr closes: no worker holds it
    except subprocess.TimeoutExpired:
        wait_until_gone(children | {process.pid}, 0)
        pytest.fail("the merge did not end within the bound, or something still holds its stderr")
    left = wait_until_gone(children)
    assert process.returncode == 143, err
    assert err.splitlines()[-1] == "esmicp merge: terminated (SIGTERM); no partial output was written", err
    assert not left, f"{len(left)} of its processes outlived the merge"
    assert "Traceback" not in err, err
    assert not out.exists()


def test_workers_end_when_their_parent_is_killed(scans, tmp_path):
    """SIGKILL gives the parent no chance to end its workers: they must notice and end."""
    process, children = start_merge_on_processes(scans, tmp_path / "m.ply")
    process.kill()
    process.wait(timeout=ENDS_WITHIN_S)  # not communicate(): a surviving worker holds the pipes open
    left = wait_until_gone(children)
    process.stdout.close()
    process.stderr.close()
    assert not left, f"{len(left)} worker(s) outlived their parent"


NO_GUARD = """
import esmicp
from esmicp.shapes import asymmetric_shape

a = asymmetric_shape(300, rng=1)
try:
    esmicp.register_many([(a + 0.01, a), (a + 0.02, a)], processes=2)
    print("finished")
except Exception as error:
    print(f"{type(error).__name__}: {error}")
"""


def test_processes_from_an_unguarded_script_is_one_clear_error(tmp_path):
    """``processes=2`` from a script without ``if __name__ == "__main__":`` died with
    ``BrokenProcessPool`` and 41-157 lines of the workers' tracebacks: now each worker says why in
    one line, and the call raises PoolError saying to add the guard or use the default threads."""
    script = tmp_path / "unguarded.py"
    script.write_text(NO_GUARD)
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                          start_new_session=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("PoolError: processes=2: "), done.stdout
    assert "__main__" in done.stdout and "thread" in done.stdout
    assert "Traceback" not in done.stderr and "BrokenProcessPool" not in done.stderr, done.stderr
    assert done.stderr and all(line.startswith("esmicp: ") and "__main__" in line for line in done.stderr.splitlines())


def test_processes_from_a_script_on_standard_input_is_refused_at_once(tmp_path):
    done = subprocess.run([sys.executable, "-"], input=NO_GUARD, capture_output=True, text=True, timeout=300,
                          start_new_session=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("PoolError: processes=2: worker processes re-import the main script"), done.stdout
    assert "thread" in done.stdout
    assert done.stderr == "", done.stderr  # no worker was started


def test_the_default_threads_work_from_standard_input():
    done = subprocess.run([sys.executable, "-"], input=NO_GUARD.replace("processes=2", "threads=2"),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout == "finished\n", done.stderr


#: An address-space limit (``ulimit -v``) this far above what the command holds once its libraries
#: are loaded: the 512 MB of the report on a machine where that is about 350 MB.
HEADROOM_MB = 160

MEASURE = textwrap.dedent("""
    import esmicp.cli, esmicp.multiview, esmicp.io, scipy.spatial, scipy.optimize
    for line in open("/proc/self/status"):
        if line.startswith("VmSize:"):
            print(int(line.split()[1]) // 1024)
""")


@pytest.mark.parametrize("where", [["--processes", "2"], ["--threads", "8"]], ids=["processes", "threads"])
def test_a_merge_under_an_address_space_limit_ends_in_a_result_or_one_line(scans, tmp_path, where):
    """Under ``ulimit -v`` a 3-scan merge spun for minutes inside OpenBLAS or failed with "can't
    start new thread" and a traceback (each thread took a 64 MB malloc arena of address space). Now
    it completes, or at worst says in one line that a thread could not start (exit status 2)."""
    imported = int(subprocess.run([sys.executable, "-c", MEASURE], capture_output=True, text=True, check=True,
                                  timeout=120).stdout)
    limit = (imported + HEADROOM_MB) << 20

    def capped():
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    out = tmp_path / "m.ply"
    argv = [sys.executable, "-m", "esmicp", "merge", *map(str, scans[:3]), "-o", str(out), *where, "--no-progress"]
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=capped,
                               start_new_session=True)
    try:
        _, err = process.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        wait_until_gone(descendants(process.pid) | {process.pid}, 0)
        pytest.fail(f"no result within 240 s under a {limit >> 20} MB address-space limit")
    assert "Traceback" not in err, err[-3000:]
    if process.returncode == 0:
        assert out.exists()
    else:
        assert process.returncode == 2, err
        assert err.splitlines()[-1].startswith("esmicp merge: error: "), err
        assert not out.exists()


THREADS_CHILD = r"""
import pathlib, sys
import esmicp.api, esmicp.cli

ready, argv = pathlib.Path(sys.argv[1]), sys.argv[2:]
real_register = esmicp.api.register


def register_and_say_so(*args, **kwargs):  # the first registration of the pool tells the test
    ready.touch()
    return real_register(*args, **kwargs)


esmicp.api.register = register_and_say_so
sys.exit(esmicp.cli.main(argv))
"""


def test_sigterm_ends_a_merge_on_threads(scans, tmp_path):
    """The default thread pool: SIGTERM is handled as Ctrl-C too (it killed the process, status
    -15, with no message): the queued registrations are dropped, exit status 143."""
    out, ready = tmp_path / "m.ply", tmp_path / "ready"
    argv = ["merge", *map(str, scans), "-o", str(out), "--threads", "2", "--no-progress"]
    process = subprocess.Popen([sys.executable, "-c", THREADS_CHILD, str(ready), *argv], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 120
    while not ready.exists():
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            pytest.fail(f"the merge never registered a pair: {process.communicate()}")
        time.sleep(0.01)
    process.send_signal(signal.SIGTERM)
    try:
        _, err = process.communicate(timeout=ENDS_WITHIN_S)
    except subprocess.TimeoutExpired:
        process.kill()
        pytest.fail("the merge did not end within the bound")
    assert process.returncode == 143, err
    assert err.splitlines()[-1] == "esmicp merge: terminated (SIGTERM); no partial output was written", err
    assert not out.exists()


def test_an_interrupt_cancels_the_jobs_left_on_a_dask_cluster():
    """Ctrl-C or SIGTERM (here raised where their handlers raise them: in the caller's thread,
    while it waits; SIGTERM's ``Terminated`` is a ``KeyboardInterrupt``) during
    ``register_many(client=...)``: the jobs not finished are cancelled on the cluster, not left
    running for nobody."""
    distributed = require_module("distributed", "dask")

    heavy = asymmetric_shape(8000, rng=2)
    pairs = [(heavy + 0.01 * k, heavy) for k in range(1, 7)]

    def progress(done, total):
        raise KeyboardInterrupt

    with distributed.Client(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as client:
        # the caller still holds the interrupt (and its traceback, with the futures) while it cleans up
        with pytest.raises(KeyboardInterrupt) as interrupt:
            esmicp_register_many(pairs, client=client, progress=progress)
        deadline = time.monotonic() + ENDS_WITHIN_S
        left = client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks))
        while left and time.monotonic() < deadline:
            time.sleep(0.05)
            left = client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks))
        assert left == 0, f"{left} job(s) still on the cluster"
        assert interrupt.traceback


def esmicp_register_many(*args, **kwargs):
    import esmicp

    return esmicp.register_many(*args, **kwargs)


def test_sigterm_ends_a_bench_on_a_dask_cluster_keeping_its_rows(tmp_path):
    """``esmicp bench --workers 2`` runs on a local Dask cluster of worker processes: SIGTERM to the
    command alone is handled as Ctrl-C (exit status 143, the finished rows kept whole, the way to
    resume printed), and the cluster's processes end with it."""
    require_module("distributed", "dask")
    out = tmp_path / "run"
    argv = [sys.executable, "-m", "esmicp", "bench", "--datasets", "synthetic", "--protocols", "copy", "--methods",
            "esm", "--trials", "200", "--points", "400", "--workers", "2", "--no-progress", "--out", str(out)]
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    rows = out / "rows.jsonl"
    deadline = time.monotonic() + 120
    while not (rows.exists() and rows.read_bytes().count(b"\n") >= 2):
        if process.poll() is not None or time.monotonic() > deadline:
            wait_until_gone(descendants(process.pid), 0)
            process.kill()
            pytest.fail(f"the bench wrote no rows: {process.communicate()}")
        time.sleep(0.05)
    children = descendants(process.pid)
    process.send_signal(signal.SIGTERM)
    try:
        _, err = process.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        wait_until_gone(children | {process.pid}, 0)
        pytest.fail("the bench did not end after SIGTERM, or its workers hold its stderr")
    left = wait_until_gone(children)
    assert process.returncode == 143, err[-3000:]
    assert "esmicp bench: terminated (SIGTERM); " in err and "--resume" in err, err[-3000:]
    assert rows.read_bytes().endswith(b"\n")
    assert not left, f"{len(left)} of its processes outlived the bench"
