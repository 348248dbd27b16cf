"""Ctrl-C stays a ``KeyboardInterrupt`` through compiled code.

An extension function that calls back into Python while a Ctrl-C is pending can end in
``SystemError: ... returned a result with an exception set``, with the ``KeyboardInterrupt`` only
in its cause chain; a caller's ``except Exception`` then swallows the user's interrupt (measured
with the earlier JIT-compiled kernels: ``esmicp bench`` ignored 4 of 8 interrupts).
:func:`keeps_keyboard_interrupt` turns such an error back into the ``KeyboardInterrupt`` it is;
the library's entry points (:func:`esmicp.register`, :func:`esmicp.methods.local.refine`) carry
it. (The compiled kernels of :mod:`esmicp._kernels` raise the ``KeyboardInterrupt`` itself.)

A process pool is stopped by its parent: its workers ignore Ctrl-C (:func:`ignore_interrupts`, part
of :func:`esmicp.pools.start_worker`, which also ends them with their parent), and
:func:`stops_pool_on_interrupt` terminates them when Ctrl-C (or any error) leaves the pool.

SIGTERM (what ``kill``, ``timeout``, systemd and container runtimes send) is Ctrl-C's twin where
:func:`terminate_as_interrupt` is active (the command line, for the whole command): it raises
:class:`Terminated`, a ``KeyboardInterrupt``, so that everything that cleans up after Ctrl-C (the
pools, the temporary files of unfinished outputs) does so after SIGTERM too.
"""

from __future__ import annotations

import contextlib
import functools
import signal
import threading
from collections.abc import Callable
from typing import ParamSpec, TypeVar

_P = ParamSpec("_P")
_R = TypeVar("_R")


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived while :func:`terminate_as_interrupt` was active: handled as Ctrl-C is."""


def _interrupt_in(error: BaseException) -> KeyboardInterrupt | None:
    """The ``KeyboardInterrupt`` that ``error`` is or has in its cause / context chain, or None."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return error
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return None


def caused_by_interrupt(error: BaseException) -> bool:
    """True when ``error`` is a ``KeyboardInterrupt`` or has one in its cause / context chain."""
    return _interrupt_in(error) is not None


def _raise_terminated(number, frame):
    raise Terminated(f"signal {number}")


@contextlib.contextmanager
def terminate_as_interrupt():
    """While the block runs, SIGTERM raises :class:`Terminated` (a ``KeyboardInterrupt``) in the
    main thread, as Ctrl-C raises ``KeyboardInterrupt``; the previous handler is restored after.
    Outside the main thread (where Python cannot set handlers), or where SIGTERM is ignored or
    handled by non-Python code, nothing is changed."""
    number = getattr(signal, "SIGTERM", None)
    previous = signal.getsignal(number) if number is not None else None
    if threading.current_thread() is not threading.main_thread() or previous in (None, signal.SIG_IGN):
        yield
        return
    signal.signal(number, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(number, previous)


def keeps_keyboard_interrupt(function: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorator: a ``SystemError`` caused by a ``KeyboardInterrupt`` is raised as that interrupt
    (the signature, and so the types, of ``function`` kept)."""

    @functools.wraps(function)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        try:
            return function(*args, **kwargs)
        except SystemError as error:
            interrupt = _interrupt_in(error)
            if interrupt is not None:
                raise type(interrupt)(*interrupt.args) from None
            raise

    return wrapper


#: Seconds to wait for each terminated worker process to end.
WORKER_EXIT_WAIT_S = 1.0


def ignore_interrupts() -> None:
    """Initializer of worker processes: SIGINT ignored. Ctrl-C in a terminal signals the whole
    process group; the parent alone handles it, and ends its workers (:func:`stops_pool_on_interrupt`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def stops_pool_on_interrupt(pool):
    """Context manager for the body of a ``with ProcessPoolExecutor(...) as pool`` block: when an
    exception (Ctrl-C above all) leaves the body, the pool's queued jobs are cancelled and its
    worker processes terminated, so that the pool's own ``__exit__`` does not wait for the jobs
    still running (each a registration of seconds)."""
    try:
        yield pool
    except BaseException:
        workers = list((getattr(pool, "_processes", None) or {}).values())  # private, but the only handle
        jobs = getattr(pool, "_call_queue", None)  # private too; shutdown drops it
        manager = getattr(pool, "_executor_manager_thread", None)  # private too; shutdown drops it
        pool.shutdown(wait=False, cancel_futures=True)
        for worker in workers:
            worker.terminate()
        for worker in workers:
            worker.join(WORKER_EXIT_WAIT_S)
        # The pool's feeder thread may be blocked writing a large job into the pipe the ended
        # workers read; with every read end closed its write fails at once, and the pool's exit
        # (which waits for that thread) does not hang.
        reader = getattr(jobs, "_reader", None)
        if reader is not None and not getattr(pool, "_broken", False):  # a broken pool's manager closes it
            with contextlib.suppress(OSError):
                reader.close()
        # The pool's manager thread tears the pool down too (it may close that pipe a second time:
        # esmicp.pools.quiet_pool_teardown keeps that quiet while it runs): it ends here, not after.
        if manager is not None:
            manager.join(WORKER_EXIT_WAIT_S)
        raise
