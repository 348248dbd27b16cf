"""The methods a benchmark runs, behind one call: ours (through :func:`esmicp.register`) and the
adapters of :mod:`esmicp_lab.baselines`.

Local methods (``esm``, ``esm-paper``, ``icp`` and the baselines of kind ``local``) all get the
same start (``init``: a 4x4 ``T_target_source``) and the same iteration budget; global ones
(``esm-global``, the library's default ``register(source, target, rng=seed)``, and the baselines
of kind ``global``) get neither. A missing optional library or missing weights is reported, never
hidden: :class:`Unavailable`.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np

#: Our methods and their kinds.
OUR_METHODS = {"esm": "local", "esm-paper": "local", "icp": "local", "esm-global": "global"}

#: Substrings of learned baselines' names (excluded from the geometric default of ``--paper``).
LEARNED_MARKERS = ("pointnetlk", "dcp", "rpm", "deepgmr", "learned")

#: Methods whose ``sigma`` a sigma sweep sets.
SIGMA_METHODS = ("esm", "esm-paper")


class Unavailable(Exception):
    """The method cannot run here (library or weights missing); the message says what to do."""


@dataclass(frozen=True)
class MethodOutcome:
    """What a method returned: the estimated ``T_target_source`` and what it said about it."""

    transformation: np.ndarray
    time_s: float
    iterations: int | None
    converged: bool | None
    notes: str
    ambiguous: bool | None = None


def _baselines():
    from .. import baselines

    return baselines


def method_names() -> list[str]:
    """Every method name the bench knows: ours, then the baselines'."""
    return [*OUR_METHODS, *_baselines().BASELINES]


def method_kind(name: str) -> str:
    """``local`` or ``global``."""
    if name in OUR_METHODS:
        return OUR_METHODS[name]
    return _baselines().BASELINE_KINDS.get(name, "global")


#: Methods that take about a second or more per trial (Go-ICP's branch-and-bound; CPD's EM, O(N x M)
#: per iteration; ICP-NL's Levenberg-Marquardt), run on a budget of trials
#: (:attr:`esmicp_lab.bench.config.BenchConfig.slow_trials`; their cost in docs/bench-paper.md, "Run time").
SLOW_METHODS = ("go-icp", "cpd", "icp-nl")
#: Slow methods run on the paper's printed cases without outliers only (unless ``slow_trials`` is
#: 0): Go-ICP, seconds to tens of seconds per trial, which never ends within its time limit on a
#: source with outliers (the adapter runs it untrimmed).
SLOW_ON_PRINTED_ONLY = ("go-icp",)


def is_learned(name: str) -> bool:
    return any(marker in name.lower() for marker in LEARNED_MARKERS)


def check_methods(names) -> None:
    """Raise :class:`~esmicp.errors.InvalidInputError` naming any unknown method."""
    from esmicp.errors import InvalidInputError

    known = method_names()
    for name in names:
        if name not in known:
            raise InvalidInputError(f"methods: unknown method {name!r}; choose from {', '.join(known)}")


def run_method(
    name: str, source, target, *, init: np.ndarray, max_iterations: int, sigma: float | None, seed: int,
    workers: int | None = None,
) -> MethodOutcome:
    """Run ``name`` once; only the registration call is timed (``time.perf_counter``).

    ``workers``: threads of esmicp's own kernels (``register(workers=...)``; None: every core); the
    baselines keep their libraries' own settings.

    Raises :class:`Unavailable` for a missing library / weights; any other exception is the
    method's own failure.
    """
    if name in OUR_METHODS:
        return _run_ours(name, source, target, init, max_iterations, sigma, seed, workers)
    return _run_baseline(name, source, target, init, max_iterations, seed)


def _run_ours(name, source, target, init, max_iterations, sigma, seed, workers) -> MethodOutcome:
    from esmicp.api import register
    from esmicp.errors import IndexAlignmentWarning

    with warnings.catch_warnings():
        # esm-paper on clouds that are not index-aligned is part of what the bench measures.
        warnings.simplefilter("ignore", IndexAlignmentWarning)
        if name != "esm-global":
            start_from = "identity" if np.array_equal(init, np.eye(4)) else init
        start = time.perf_counter()
        if name == "esm-global":
            result = register(source, target, rng=seed, workers=workers)
        else:
            result = register(source, target, method=name, init=start_from, sigma=sigma, max_iterations=max_iterations,
                              workers=workers)
        elapsed = time.perf_counter() - start
    return MethodOutcome(
        result.transformation, elapsed, int(result.num_iterations), bool(result.converged),
        f"init={result.init} fitness={result.fitness:.4f} {result.message}",
        bool(result.ambiguous) if name == "esm-global" else None,
    )


def _run_baseline(name, source, target, init, max_iterations, seed) -> MethodOutcome:
    baselines = _baselines()
    adapter = baselines.get_baseline(name)
    kwargs = {"rng": seed}
    if method_kind(name) == "local":
        kwargs["max_iterations"] = max_iterations
        kwargs["init"] = init
    start = time.perf_counter()
    try:
        result = adapter(source, target, **kwargs)
    except baselines.MissingDependencyError as exc:
        raise Unavailable(str(exc)) from exc
    elapsed = time.perf_counter() - start
    return MethodOutcome(np.asarray(result.transformation, dtype=np.float64), elapsed, None, result.converged,
                         result.notes)
