"""``register_many()``: register many (source, target) pairs on all cores, or on a Dask cluster.

Each pair is registered by :func:`esmicp.register` with the same keyword arguments, on a thread of
a local thread pool (the default: the compiled kernels release the GIL, and a thread pool works from
any script, notebook, ``python -c`` or stdin, with no ``if __name__ == "__main__":`` guard), in a
worker process (``processes=``, a spawned pool, which re-imports the caller's ``__main__``) or a
Dask worker (when a ``dask.distributed.Client`` is given).
Results come back in input order. A pair that fails (bad input, or any error inside
``register``) is returned as a :class:`RegistrationFailure` in its place, so one bad scan never
costs the others. ``register`` is deterministic (its default global-search seed is fixed), so the
results equal those of calling it pair by pair (the compiled kernels sum in a fixed order, so their
number of threads does not change a bit).

Each worker runs its kernels on one thread (``workers=1`` of :func:`esmicp.register`, unless the
caller's keyword arguments say otherwise): the pool's threads or processes themselves use the
cores, and a pool each starting a thread per core would oversubscribe them.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

from .errors import InvalidInputError
from .interrupts import stops_pool_on_interrupt
from .pools import pool_error, process_pool, quiet_pool_teardown
from .result import RegistrationResult

logger = logging.getLogger(__name__)

#: How to install the optional Dask scale-out.
DASK_INSTALL_HINT = "pip install 'esmicp[dask]' (dask[distributed])"


@dataclass(frozen=True)
class RegistrationFailure:
    """Stands in the results of :func:`register_many` for a pair whose registration raised.

    ``index`` is the pair's position in the input, ``error_type`` the exception's class name and
    ``message`` its text (e.g. ``"source: expected (N, 3) points, got (5, 2)"``).
    """

    index: int
    error_type: str
    message: str

    def __str__(self) -> str:
        return f"pair {self.index}: {self.error_type}: {self.message}"


def _register_one(index: int, source, target, kwargs: dict, init=None) -> "RegistrationResult | RegistrationFailure":
    from .api import register

    try:
        if init is not None:
            kwargs = {**kwargs, "init": init}
        return register(source, target, **kwargs)
    except Exception as exc:  # one failing pair must not lose the others: report it in its place
        return RegistrationFailure(index, type(exc).__name__, str(exc))


def per_process_kwargs(register_kwargs: dict) -> dict:
    """``register_kwargs`` for a registration in one of several parallel threads, processes or
    Dask tasks: ``workers=1`` unless the caller chose a number of threads."""
    if "workers" in register_kwargs:
        return register_kwargs
    return {**register_kwargs, "workers": 1}


def register_many(
    pairs: Iterable[Sequence],
    *,
    threads: int | None = None,
    processes: int | None = None,
    client=None,
    progress: Callable[[int, int], None] | None = None,
    inits: Sequence | None = None,
    **register_kwargs,
) -> list["RegistrationResult | RegistrationFailure"]:
    """Register every ``(source, target)`` pair; results (or failures) in input order.

    Parameters
    ----------
    pairs : iterable of (source, target)
        Each element is two (N, 3) / (M, 3) array-likes, as :func:`esmicp.register` takes them.
    threads : int, optional
        Threads of the local thread pool, the default way (default: all cores). 1 registers in
        this thread, one pair after the other. Ignored when ``processes`` or ``client`` is given.
    processes : int, optional
        Run on a pool of this many spawned worker processes instead of threads (the caller's
        script must then guard its top level with ``if __name__ == "__main__":``, as every
        spawned pool needs). 1 registers in this process, one pair after the other. Ignored
        when ``client`` is given.
    client : dask.distributed.Client, optional
        Run the registrations on this Dask cluster instead (Dask is an optional dependency:
        ``pip install 'esmicp[dask]'``); the clouds are sent to the workers with the tasks.
    progress : callable, optional
        ``progress(done, total)`` in this process after every finished pair (in finishing order);
        for a progress bar.
    inits : sequence, optional
        One ``init`` per pair (None: the ``init`` of ``register_kwargs``, else the global search):
        e.g. a predicted ``T_target_source`` for a local refinement of that pair only.
    **register_kwargs
        Passed to every :func:`esmicp.register` call (``method``, ``init``, ``max_iterations``,
        ...). A callback must be picklable to reach worker processes. ``workers`` (threads per
        registration) defaults to 1 when several registrations run at once, every core otherwise.

    Returns
    -------
    list
        One :class:`~esmicp.result.RegistrationResult` per pair, or a :class:`RegistrationFailure`
        where that pair's registration raised.

    Raises
    ------
    InvalidInputError
        When ``pairs`` is not a sequence of pairs, ``inits`` not one per pair, or ``threads`` /
        ``processes`` not a positive integer.
    PoolError
        ``processes``: the worker processes could not run (the caller's script read from standard
        input, or not guarded by ``if __name__ == "__main__":``), or one ended abruptly.
    """
    items = _as_pairs(pairs)
    if inits is None:
        inits = [None] * len(items)
    else:
        inits = list(inits)
        if len(inits) != len(items):
            raise InvalidInputError(f"inits: expected one per pair ({len(items)}), got {len(inits)}")
    if progress is not None and not callable(progress):
        raise InvalidInputError(f"progress: expected a callable(done, total), got {type(progress).__name__}")
    report = progress or (lambda done, total: None)
    if client is not None:
        return _on_dask(client, items, inits, per_process_kwargs(register_kwargs), report)
    pool_kind, size = "threads", threads
    if processes is not None:
        pool_kind, size = "processes", processes
    if size is None:
        size = os.cpu_count() or 1
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise InvalidInputError(f"{pool_kind}: expected a positive integer, got {size!r}")
    size = min(size, max(len(items), 1))
    if size == 1:
        results = []
        for i, ((source, target), init) in enumerate(zip(items, inits)):
            results.append(_register_one(i, source, target, register_kwargs, init))
            report(i + 1, len(items))
    else:
        kwargs = per_process_kwargs(register_kwargs)
        if pool_kind == "processes":
            # "spawn": the caller may hold threads of other libraries (BLAS, torch) that fork() would not survive.
            # Its workers ignore Ctrl-C and end with this process (esmicp.pools).
            pool = process_pool(size, f"processes={size}")
        else:
            pool = ThreadPoolExecutor(size, thread_name_prefix="esmicp-register")
        # Ctrl-C: the queued jobs cancelled and worker processes ended at once, not after their jobs.
        with quiet_pool_teardown(), pool, stops_pool_on_interrupt(pool):
            futures = {
                pool.submit(_register_one, i, source, target, kwargs, init): i
                for i, ((source, target), init) in enumerate(zip(items, inits))
            }
            results = [None] * len(items)
            try:
                for done, future in enumerate(as_completed(futures), 1):
                    results[futures[future]] = future.result()
                    report(done, len(items))
            except BrokenProcessPool as error:
                raise pool_error(f"processes={size}", error) from None
    _log_failures(results)
    return results


def dask_client(address: str, *, timeout_s: float = 30.0):
    """A ``dask.distributed.Client`` connected to the running scheduler at ``address`` (for the
    ``client=`` of :func:`register_many` and :func:`esmicp.register_scans`; the caller closes it).

    Raises
    ------
    MissingDependencyError
        Dask is not installed (the message has the install hint).
    InvalidInputError
        No scheduler answers at ``address`` within ``timeout_s``.
    """
    try:
        from distributed import Client
    except ImportError as exc:
        from .errors import MissingDependencyError

        raise MissingDependencyError(f"a Dask scheduler needs dask.distributed ({exc}): {DASK_INSTALL_HINT}") from None
    try:
        return Client(address, timeout=timeout_s)
    except (OSError, TimeoutError, ValueError) as exc:
        raise InvalidInputError(f"scheduler: cannot connect to {address!r} ({exc})") from None


def _on_dask(client, items, inits, register_kwargs, report):
    try:
        from distributed import as_completed as dask_completed  # the client's own package
    except ImportError:  # pragma: no cover - a client cannot exist without it
        from .errors import MissingDependencyError

        raise MissingDependencyError(f"register_many(client=...) needs Dask: {DASK_INSTALL_HINT}") from None
    futures = {
        client.submit(_register_one, i, source, target, register_kwargs, init, pure=False): i
        for i, ((source, target), init) in enumerate(zip(items, inits))
    }
    results = [None] * len(items)
    try:
        for done, future in enumerate(dask_completed(futures), 1):
            results[futures[future]] = future.result()
            report(done, len(items))
    except BaseException:  # Ctrl-C, SIGTERM (esmicp.interrupts) or an error: the cluster drops the jobs
        client.cancel(list(futures))
        raise
    _log_failures(results)
    return results


def _as_pairs(pairs) -> list[tuple]:
    try:
        items = [tuple(pair) for pair in pairs]
    except TypeError:
        raise InvalidInputError(f"pairs: expected an iterable of (source, target) pairs, got {type(pairs).__name__}") from None
    for index, item in enumerate(items):
        if len(item) != 2:
            raise InvalidInputError(f"pairs[{index}]: expected a (source, target) pair, got {len(item)} items")
    return items


def _log_failures(results) -> None:
    for result in results:
        if isinstance(result, RegistrationFailure):
            logger.warning("register_many: %s", result)
