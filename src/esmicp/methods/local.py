"""The iteration loop shared by every local method.

Each iteration: nearest neighbours of the source as currently placed, one increment from the
method's :class:`~esmicp.methods.base.Estimator`, composed on the left (``T = T_delta @ T``),
until the :class:`~esmicp.methods.base.ConvergenceCriteria` are met. The loop reads the
estimator's declared capabilities (compiled step, point order, coarse phase, acceleration).

Speed: nearest neighbours come from :meth:`~esmicp.core.correspondence.NearestNeighbors.query_near`
(exact: a compiled KD-tree and, near the target, a voxel hash in front of it, both warm-started
with the previous iteration's neighbours); the step gets its sums from one compiled pass. With
``coarse_points``, an estimator that has a coarse phase (``esm`` with the automatic sigma) runs
that phase on an evenly strided subset of the source, and the full source from its fine phase on:
the coarse phase only brings the clouds close, the full-resolution iterations decide the pose.

A callback or a history observes the run and never changes it (:class:`Observer`): the loop takes
the same path, on the same points, in the same order, with or without one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .. import _kernels
from ..core.correspondence import NearestNeighbors
from ..core.weights import effective_count
from ..core.pose_kernels import compose, motion_between
from ..core.procrustes import apply
from ..interrupts import keeps_keyboard_interrupt
from ..result import IterationRecord
from .acceleration import AndersonAccelerator
from .base import ConvergenceCriteria, Estimator, Step
from .config import LoopConfig


@dataclass(frozen=True)
class IterationState:
    """What a callback sees after each iteration (its own arrays: the run never reads them).

    ``moved_source`` is the whole source, in its own order, as placed BEFORE this iteration's
    increment, ``indices`` and ``distances`` its nearest target points, ``weights`` the weight the
    method gives each of those pairs at this iteration's ``sigma`` (None for unweighted methods),
    ``transformation`` the ``T_target_source`` AFTER the increment, ``placement`` the one BEFORE it
    (that placed ``moved_source``; the first iteration's is the run's start). On a large source some
    iterations compute their increment on a strided subset of the points (the coarse phase, the
    strided stages of :func:`esmicp.register`); the state still describes every point at that
    iteration's pose. ``iteration`` counts from 1 over every stage of a run; it starts again at 1
    when :func:`esmicp.register` tries a second run from the same start (see its ``init``).
    """

    iteration: int
    transformation: np.ndarray
    moved_source: np.ndarray
    indices: np.ndarray
    distances: np.ndarray
    weights: np.ndarray | None
    sigma: float | None
    placement: np.ndarray | None = None


#: Return True from a callback to stop the iterations.
Callback = Callable[[IterationState], "bool | None"]

#: The message of a run its callback stopped.
STOPPED_BY_CALLBACK = "stopped by the callback"


class Observer:
    """The callback and the history of a run, kept apart from it: every iteration is reported by
    a query of its own on the whole ``source`` (working frame, caller's order) at the pose the
    iteration started from, so that the run itself takes the same path, on the same points, with
    or without an observer (the same pose, bitwise).

    One observer may watch several :func:`refine` calls (the stages of :func:`esmicp.register`):
    ``iteration`` then counts over all of them. ``stopped`` is True once the callback returned a
    true value; the caller then runs no further stage.
    """

    def __init__(self, source: np.ndarray, target: NearestNeighbors, callback: "Callback | None" = None,
                 record_history: bool = False):
        self.source, self.target, self.callback = source, target, callback
        self.history: list[IterationRecord] | None = [] if record_history else None
        self.iteration = 0
        self.stopped = False
        self._warm: np.ndarray | None = None

    def __call__(self, estimator: Estimator, before: np.ndarray, after: np.ndarray, sigma: float | None) -> bool:
        """Report one iteration that moved the source from ``before`` to ``after`` (4x4) at
        ``sigma``; True when the callback asks to stop."""
        self.iteration += 1
        distances, indices = self._query(before)
        weights = estimator.pair_weights(distances, sigma)
        if self.history is not None:
            rmse = float(np.sqrt(np.mean(np.square(distances))))
            self.history.append(_record(self.iteration, after, rmse, weights, sigma, len(distances)))
        if self.callback is not None:
            moved = apply(before, self.source)
            state = IterationState(self.iteration, after.copy(), moved, indices, distances, weights, sigma,
                                   before.copy())
            self.stopped = bool(self.callback(state))
        return self.stopped

    def recorded(self) -> tuple[IterationRecord, ...] | None:
        """The history so far (None when none is kept)."""
        return _freeze(self.history)

    def new_run(self) -> tuple[IterationRecord, ...] | None:
        """Start counting a new run from the same start; returns the history of the previous one."""
        previous = self.recorded()
        self.iteration, self.history = 0, (None if self.history is None else [])
        return previous

    def _query(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # The exact tree's own query: the index's near-query statistics, which steer the run's
        # own queries (speed only, yet the tie between two equidistant targets), stay untouched.
        tree = getattr(self.target, "exact_tree", None)
        if tree is None:
            distances, indices = self.target.query_near(self.source, warm=self._warm, transform=pose)
        else:
            distances, indices = tree().query(self.source, transform=pose, warm=self._warm,
                                              workers=getattr(self.target, "workers", None))
        self._warm = indices
        return distances, indices


@dataclass(frozen=True)
class RefinementOutcome:
    """What :func:`refine` ends with (:func:`esmicp.register` turns it into a
    :class:`~esmicp.result.RegistrationResult`).

    ``effective_pairs`` is Kish's effective number of pairs of the last step (None where it is not
    known, or there were no pairs), ``pairs`` that step's number of pairs (0: no step).
    ``neighbours``: the nearest target index of every source point (the source's own order) at
    the last pose the loop queried, one step before ``transformation``, where the one-call loop
    ended on the whole source; else None. A warm start for queries near the final pose (any
    index gives exact answers; a near one makes them cheap).
    """

    transformation: np.ndarray
    converged: bool
    num_iterations: int
    sigma: float | None
    message: str
    history: tuple[IterationRecord, ...] | None
    effective_pairs: float | None = None
    pairs: int = 0
    neighbours: np.ndarray | None = None


@keeps_keyboard_interrupt
def refine(
    source: np.ndarray,
    target: NearestNeighbors,
    estimator: Estimator,
    *,
    init: np.ndarray,
    criteria: ConvergenceCriteria,
    scale: float,
    callback: Callback | None = None,
    record_history: bool = False,
    coarse_points: int | None = None,
    observer: Observer | None = None,
    loop: LoopConfig | None = None,
) -> RefinementOutcome:
    """Iterate ``estimator`` from ``init`` (4x4 ``T_target_source``) until ``criteria`` are met.

    ``target`` is the target's index (:class:`~esmicp.core.correspondence.NearestNeighbors`, or
    anything with its ``points``, ``query_near`` and ``spatial_order``); every compiled call of
    the loop runs on its ``workers`` threads (None, or no such attribute: every core). ``scale`` (cloud units,
    e.g. the target's bounding-box diagonal) makes the translation part of the convergence test
    unit-free.

    ``coarse_points`` (optional): while ``estimator.coarse`` (the coarse phase of ``esm``'s
    automatic sigma), iterate on at most this many evenly strided source points; the run never
    ends there: once the coarse iterations converge, the loop ends the estimator's coarse phase
    (:meth:`~esmicp.methods.base.Estimator.end_coarse_phase`) and continues on the full source.

    ``callback`` / ``record_history``: as in :func:`esmicp.register` (an :class:`Observer` of this
    call); or ``observer``, one shared by several calls. Neither changes the run.

    ``loop``: the loop's values (:class:`~esmicp.methods.config.LoopConfig`, None: the defaults).
    From ``loop.spatial_order_min`` source points on, the source is queried in the target's
    spatial order (:meth:`~esmicp.core.correspondence.NearestNeighbors.spatial_order`): visited in
    that order, or, for an order-dependent method (``esm-paper``), kept in its order with only the
    queries permuted.
    """
    loop = LoopConfig() if loop is None else loop
    if observer is None and (callback is not None or record_history):
        observer = Observer(source, target, callback, record_history)
    full_source = source
    coarse = coarse_points is not None and len(source) > coarse_points and estimator.coarse
    workers = getattr(target, "workers", None)
    query_order = visit_order = None
    if len(source) >= loop.spatial_order_min:
        order = target.spatial_order(apply(init, source, workers))
        if estimator.order_invariant:
            # Visit the source points in spatial order (the result does not depend on the order).
            full_source, visit_order = source[order], order
        else:
            # The source keeps its order; only the queries are made in spatial order.
            query_order = order
    if coarse:
        source = full_source[np.linspace(0, len(full_source) - 1, coarse_points).astype(np.intp)]
    else:
        source = full_source
    # The placed source is never formed where the step has a compiled pass: the query and the
    # step map the source themselves.
    placed = estimator.compiled_step
    # With no per-point array needed and the queries in the source's order, one compiled call per
    # iteration finds the pairs and computes the increment (``NearestNeighbors.step``).
    fused = placed and estimator.fused_step and query_order is None and hasattr(target, "step")

    def query(points, transform, warm):
        if query_order is None:
            return target.query_near(points, warm=warm, transform=transform)
        found_distances, found_indices = target.query_near(
            points[query_order], warm=None if warm is None else warm[query_order], transform=transform
        )
        distances, indices = np.empty_like(found_distances), np.empty_like(found_indices)
        distances[query_order], indices[query_order] = found_distances, found_indices
        return distances, indices

    indices = None
    transformation = init.copy()
    previous_rmse: float | None = None
    sigma: float | None = None
    accelerator = AndersonAccelerator(scale, loop.acceleration_window) if estimator.accelerable else None
    fallback: np.ndarray | None = None  # the plain step, while an accelerated proposal is on trial
    objective_before = 0.0
    step: Step | None = None

    def outcome(transformation, converged, iterations, message) -> RefinementOutcome:
        effective, pairs = _last_pairs(step, len(source))
        history = None if observer is None else observer.recorded()
        return RefinementOutcome(transformation, converged, iterations, sigma, message, history, effective, pairs)

    if fused:
        return _refine_fused(full_source, source, target, estimator, coarse, init, criteria, scale, accelerator,
                             visit_order, observer)
    for iteration in range(1, criteria.max_iterations + 1):
        if coarse and not estimator.coarse:
            coarse, source, indices, previous_rmse = False, full_source, None, None
        distances, indices = query(source, transformation, indices)
        objective = None  # the estimator's objective at this pose, once computed
        if fallback is not None:
            objective = estimator.objective(distances)
            if objective < objective_before:
                # The accelerated proposal fits worse than the pose it came from: take the plain step.
                transformation, fallback, objective = fallback, None, None
                accelerator.reset()
                distances, indices = query(source, transformation, indices)
            fallback = None
        if placed:
            moved = None
            step = estimator.step_placed(source, transformation, target.points, distances, indices, workers)
        else:
            moved = apply(transformation, source)
            step = estimator.step(moved, target.points, distances, indices)
        if not (np.isfinite(step.rotation).all() and np.isfinite(step.translation).all()):
            return outcome(transformation, False, iteration - 1, f"stopped at iteration {iteration}: the increment was not finite")
        sigma = step.sigma
        plain = compose(step.rotation, step.translation, transformation)
        following = plain
        if accelerator is not None:
            if estimator.accelerated:
                objective_before = estimator.objective(distances) if objective is None else objective
                following = accelerator.propose(transformation, plain)
                if following is not plain:
                    fallback = plain
            else:
                accelerator.reset()
        if following is plain:
            moved_angle, moved_distance = motion_between(transformation, following)
        else:
            moved_angle, moved_distance = accelerator.motion
        before, transformation = transformation, following
        # (Not ``distances @ distances``: BLAS would wake its own threads, which then spin and
        # take the cores from the compiled kernels: measured 3x slower iterations at 100k points.)
        rmse = float(np.sqrt(np.mean(np.square(distances))))
        if observer is not None and observer(estimator, before, transformation, sigma):
            return outcome(transformation, False, iteration, STOPPED_BY_CALLBACK)
        message = _converged(criteria, estimator, coarse, iteration, moved_angle, moved_distance, scale,
                             previous_rmse, rmse)
        if message is not None:
            return outcome(transformation, True, iteration, message)
        previous_rmse = rmse
    return outcome(transformation, False, criteria.max_iterations, _budget_spent(criteria))


def _refine_fused(full_source, source, target, estimator, coarse, init, criteria, scale, accelerator,
                  visit_order=None, observer: Observer | None = None) -> RefinementOutcome:
    """:func:`refine`'s loop with one compiled call per iteration (the source in the order it is
    queried: ``full_source`` is the caller's source permuted by ``visit_order``, None for none):
    the same decisions on the same numbers as the loop above."""
    full_source = np.ascontiguousarray(full_source, dtype=np.float64)
    source = np.ascontiguousarray(source, dtype=np.float64)
    out = np.empty(_kernels.STEP_OUT)
    indices, distances, warm = np.empty(len(source), dtype=np.int64), np.empty(len(source)), False
    objective_sigma = estimator.objective_sigma if accelerator is not None else 0.0
    transformation = np.ascontiguousarray(init, dtype=np.float64).copy()
    previous_rmse: float | None = None
    fallback: np.ndarray | None = None
    objective_before = 0.0
    sigma = None
    effective = None
    done = 0

    weighting, described = np.empty(5), None

    def iterate(pose, reject_below=-np.inf):
        nonlocal described
        now = estimator.weighting()
        if now != described:  # the phase changed: refill the kernel's copy
            described = now
            weighting[:] = now
        return target.step(source, pose, indices, distances, out, warm=warm, weighting=weighting,
                           objective_sigma=objective_sigma, reject_below=reject_below)

    def finish(transformation, converged, iterations, message):
        neighbours = None
        if done and not coarse:  # the last queries were of every point: back to the caller's order
            neighbours = np.empty_like(indices)
            neighbours[slice(None) if visit_order is None else visit_order] = indices
        history = None if observer is None else observer.recorded()
        return RefinementOutcome(transformation, converged, iterations, sigma, message, history,
                                 effective if done else None, len(source) if done else 0, neighbours)

    for iteration in range(1, criteria.max_iterations + 1):
        if coarse and not estimator.coarse:
            coarse, source, previous_rmse, warm = False, full_source, None, False
            indices, distances = np.empty(len(source), dtype=np.int64), np.empty(len(source))
        # On trial of an accelerated proposal, the kernel stops after the queries if it fits worse.
        iterate(transformation, -np.inf if fallback is None else objective_before)
        warm = True
        if fallback is not None:
            if out[39]:
                # The accelerated proposal fits worse than the pose it came from: take the plain step.
                transformation, fallback = fallback, None
                accelerator.reset()
                iterate(transformation)
            fallback = None
        done += 1
        values = out.tolist()  # Python floats: a few microseconds less per iteration than NumPy scalars
        effective = values[4]
        if not all(map(math.isfinite, values[7:19])):
            return finish(transformation, False, iteration - 1,
                          f"stopped at iteration {iteration}: the increment was not finite")
        sigma = None if math.isnan(values[0]) else values[0]
        estimator.took_step(Step(out[7:16].reshape(3, 3).copy(), out[16:19].copy(), sigma=sigma,
                                 effective_pairs=effective))
        plain = out[19:35].reshape(4, 4).copy()
        following = plain
        if accelerator is not None:
            if estimator.accelerated:
                objective_before = values[2]
                following = accelerator.propose(transformation, plain)
                if following is not plain:
                    fallback = plain
            else:
                accelerator.reset()
        if following is plain:
            moved_angle, moved_distance = values[35], values[36]
        else:
            moved_angle, moved_distance = accelerator.motion
        before, transformation = transformation, following
        rmse = values[1]
        if observer is not None and observer(estimator, before, transformation, sigma):
            return finish(transformation, False, iteration, STOPPED_BY_CALLBACK)
        message = _converged(criteria, estimator, coarse, iteration, moved_angle, moved_distance, scale,
                             previous_rmse, rmse)
        if message is not None:
            return finish(transformation, True, iteration, message)
        previous_rmse = rmse
    return finish(transformation, False, criteria.max_iterations, _budget_spent(criteria))


def _last_pairs(step: Step | None, count: int) -> tuple[float | None, int]:
    """Kish's effective number of pairs of the last step (None where it has no weights and no
    count) and its number of pairs."""
    if step is None:
        return None, 0
    if step.weights is not None:
        return (effective_count(step.weights) if count else None), count
    return step.effective_pairs, count


def _record(iteration, transformation, rmse, weights, sigma, count) -> IterationRecord:
    if weights is None:
        weight_mean = weight_min = weight_max = 1.0
        effective = float(count)
    else:
        weight_mean, weight_min, weight_max = float(weights.mean()), float(weights.min()), float(weights.max())
        effective = effective_count(weights)
    return IterationRecord(
        iteration, transformation.copy(), rmse, sigma, weight_mean, weight_min, weight_max, effective
    )


def _freeze(history):
    return tuple(history) if history is not None else None


def _converged(criteria, estimator, coarse, iteration, moved_angle, moved_distance, scale, previous_rmse, rmse):
    """The stop message when the criteria are met on the full source, else None.

    Met during the coarse phase, they end it instead (the loop continues on the full source at the
    fine sigma), so both loops switch phases the same way.
    """
    reason = criteria.reason(moved_angle, moved_distance, scale, previous_rmse, rmse)
    if reason is None:
        return None
    if coarse:
        estimator.end_coarse_phase()
        return None
    return f"converged after {iteration} iterations ({reason})"


def _budget_spent(criteria) -> str:
    return f"reached max_iterations={criteria.max_iterations} before the tolerance {criteria.tolerance:g}"
