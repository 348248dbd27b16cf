"""Worker processes that never outlive their parent, and a plain error when they cannot run.

:func:`process_pool` is the spawned ``ProcessPoolExecutor`` of :func:`esmicp.register_many`. Each
worker is started by :func:`start_worker`, which

- ignores Ctrl-C (SIGINT): the parent handles it, cancels the queued jobs and ends the workers
  (:func:`esmicp.interrupts.stops_pool_on_interrupt`); SIGTERM, where the parent turns it into an
  interrupt (the command line does), ends them the same way;
- ends with its parent, however the parent ends (SIGKILL, a crash): on Linux the kernel sends the
  worker SIGKILL when its parent goes (``prctl(PR_SET_PDEATHSIG)``); on other POSIX systems a
  daemon thread of the worker checks every :data:`PARENT_POLL_S` seconds whether its parent is
  still the process that started it, and ends the worker when not;
- under an address-space limit (``ulimit -v``, ``RLIMIT_AS``), caps the C library's malloc arenas
  and starts with one OpenBLAS thread (:func:`fit_address_space_limit`).

A spawned worker re-imports the caller's main script. Where that cannot work (Python reading the
script from standard input) :func:`process_pool` refuses at once; where the script starts the pool
from its unguarded top level, each worker stops with one line saying so (:func:`start_worker`
cannot run first, so :func:`refuse_in_a_starting_worker` does), and the parent raises
:class:`PoolError` instead of ``BrokenProcessPool`` (:func:`pool_error`).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from concurrent.futures.process import BrokenProcessPool

from .errors import PoolError
from .interrupts import ignore_interrupts

__all__ = ["PARENT_POLL_S", "PoolError", "fit_address_space_limit", "pool_error", "process_pool", "quiet_pool_teardown",
           "start_worker"]

#: Seconds between a worker's checks that its parent is alive, where the kernel cannot tell it
#: (not Linux).
PARENT_POLL_S = 0.5

#: glibc malloc arenas allowed under an address-space limit. glibc gives each thread that
#: allocates its own arena, reserving 64 MB of address space each on 64-bit systems, and OpenBLAS
#: reserves a buffer of tens of MB per thread of its own (one per core by default): under a limit of
#: 160 MB above what ``esmicp merge`` holds once its libraries are loaded (471 MB on a 2-core
#: machine), a 3-scan merge failed with "can't start new thread" both with ``--processes 2`` and
#: ``--threads 8``; with 2 arenas and one OpenBLAS thread both complete.
MALLOC_ARENAS_UNDER_LIMIT = 2

#: How to choose another pool, for the errors.
_USE_THREADS = "use the default thread pool (threads, no processes=) instead"

_PR_SET_PDEATHSIG = 1
_M_ARENA_MAX = -8


def fit_address_space_limit(*, children: bool = False) -> bool:
    """Under an address-space limit (``RLIMIT_AS``, ``ulimit -v``), cap glibc's malloc arenas at
    :data:`MALLOC_ARENAS_UNDER_LIMIT`; True when a cap was set. ``children``: also for the
    processes started later, and for OpenBLAS where it is not loaded yet (``MALLOC_ARENA_MAX`` and
    ``OPENBLAS_NUM_THREADS=1`` in the environment, unless already set: esmicp's matrices are too
    small for BLAS threads to matter). Without a limit, or on another C library, nothing is
    changed. Best called before NumPy is imported."""
    try:
        import resource
    except ImportError:  # pragma: no cover - not POSIX
        return False
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY or not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes
        import platform

        if platform.libc_ver()[0] != "glibc":
            return False
        if children:
            os.environ.setdefault("MALLOC_ARENA_MAX", str(MALLOC_ARENAS_UNDER_LIMIT))
            os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        return ctypes.CDLL(None).mallopt(_M_ARENA_MAX, MALLOC_ARENAS_UNDER_LIMIT) == 1
    except (OSError, AttributeError, ValueError):  # pragma: no cover - no mallopt here
        return False


def _end_with_parent(parent: int) -> None:
    """Make this process end when ``parent`` (the pid that started it) does."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0:
                if os.getppid() != parent:  # the parent ended before the request was made
                    os._exit(1)
                return
        except (OSError, AttributeError):  # pragma: no cover - no prctl: the thread below
            pass
    if os.name != "posix":  # pragma: no cover - a parent's pid does not change when it ends there
        return

    def watch():
        while True:
            if os.getppid() != parent:
                os._exit(1)
            threading.Event().wait(PARENT_POLL_S)

    threading.Thread(target=watch, name="esmicp-parent-watch", daemon=True).start()


def start_worker(parent: int) -> None:
    """Initializer of each worker process of :func:`process_pool` (see the module docstring)."""
    ignore_interrupts()
    _end_with_parent(parent)
    fit_address_space_limit()


def refuse_in_a_starting_worker(what: str) -> None:
    """Stop a worker process that is re-running the caller's main script while it starts (the
    script starts a pool from its unguarded top level): one line on stderr, no traceback, no
    second pool. Nothing happens anywhere else."""
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        line = (f"esmicp: {what} was called again by a worker process re-running the main script: guard the "
                f"script's top level with `if __name__ == \"__main__\":`, or {_USE_THREADS}\n")
        # one write: the other workers write theirs at the same time, and lines must not interleave
        os.write(2, line.encode("utf-8", "backslashreplace"))
        raise SystemExit(1)


def process_pool(size: int, what: str) -> ProcessPoolExecutor:
    """A spawned pool of ``size`` worker processes (see the module docstring); ``what`` names the
    caller's argument in errors (``"processes=2"``).

    Raises
    ------
    PoolError
        The workers could not re-import the main script (Python reads it from standard input).
    """
    refuse_in_a_starting_worker(what)
    fit_address_space_limit(children=True)  # the workers start with it
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if getattr(main, "__spec__", None) is None and isinstance(path, str) and not os.path.isfile(path):
        raise PoolError(f"{what}: worker processes re-import the main script, and {path!r} is not a file "
                        f"(a script read from standard input?): {_USE_THREADS}, or run it from a file")
    return ProcessPoolExecutor(size, mp_context=multiprocessing.get_context("spawn"), initializer=start_worker,
                               initargs=(os.getpid(),))


def pool_error(what: str, error: BrokenProcessPool) -> PoolError:
    """The :class:`PoolError` for a pool whose worker ended abruptly."""
    return PoolError(
        f"{what}: a worker process ended abruptly: in a script, the workers re-run its top level, which must be "
        f"guarded by `if __name__ == \"__main__\":` (or {_USE_THREADS}); else the system may have ended it (out of "
        "memory)")


#: Seconds to wait for a process pool's manager thread to end when the pool is left (it ends within
#: milliseconds once the pool's workers have ended; the wait only bounds a stuck one).
MANAGER_EXIT_WAIT_S = 5.0


@contextmanager
def quiet_pool_teardown():
    """While a pool runs: an ``OSError`` raised in the standard library's process-pool manager thread
    as it tears down a pool whose worker ended (CPython closes a queue's pipe twice there, a race
    seen under load) is not printed as a thread traceback; the caller reports the broken pool once,
    as :class:`PoolError` (:func:`pool_error`). Every other thread exception is printed as before."""
    previous = threading.excepthook

    def hook(args):
        if isinstance(args.exc_value, OSError) and type(args.thread).__module__ == "concurrent.futures.process":
            return
        previous(args)

    threading.excepthook = hook
    try:
        yield
    finally:
        # a pool shut down without waiting (an interrupt, a broken pool) leaves its manager thread
        # ending on its own: it ends while the hook is in place
        for thread in threading.enumerate():
            if type(thread).__module__ == "concurrent.futures.process" and thread is not threading.current_thread():
                thread.join(MANAGER_EXIT_WAIT_S)
        threading.excepthook = previous
