"""The iteration loop shared by every local method.

Each iteration: nearest neighbours of the source as currently placed, one increment from the
method's :class:`~esmicp.methods.base.StepEstimator`, composed on the left
(``T = T_delta @ T``). It stops when the increment becomes negligible, or when the RMS
correspondence distance stops changing, both relative to ``tolerance``.

Speed: nearest neighbours come from :meth:`~esmicp.core.correspondence.NearestNeighbors.query_near`
(exact: a compiled KD-tree and, near the target, a voxel hash in front of it, both warm-started
with the previous iteration's neighbours); the step gets its sums from one compiled pass. With
``coarse_points``, an estimator that has a coarse phase (``esm`` with the automatic sigma) runs
that phase on an evenly strided subset of the source, and the full source from its fine phase on:
the coarse phase only brings the clouds close, the full-resolution iterations decide the pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.correspondence import NearestNeighbors
from ..core.weights import effective_count
from ..core.pose_kernels import compose, motion_between
from ..core.procrustes import apply
from ..interrupts import keeps_keyboard_interrupt
from ..result import IterationRecord
from .acceleration import AndersonAccelerator
from .base import StepEstimator


#: From this many source points on, :func:`refine` queries the source in the target's spatial
#: order (:meth:`~esmicp.core.correspondence.NearestNeighbors.spatial_order`): it visits the
#: source in that order, or, for a callback or an order-dependent method (``esm-paper``), keeps
#: the source's order and only permutes the queries.
SPATIAL_ORDER_MIN = 2048


@dataclass(frozen=True)
class IterationState:
    """What a callback sees after each iteration (arrays are the solver's own: do not modify).

    ``moved_source`` is the source as placed BEFORE this iteration's increment, ``indices`` and
    ``distances`` its nearest target points, ``weights`` the weights the method gave each pair
    (None for unweighted methods), ``transformation`` the ``T_target_source`` AFTER the increment.
    """

    iteration: int
    transformation: np.ndarray
    moved_source: np.ndarray
    indices: np.ndarray
    distances: np.ndarray
    weights: np.ndarray | None
    sigma: float | None


#: Return True from a callback to stop the iterations.
Callback = Callable[[IterationState], "bool | None"]


@dataclass(frozen=True)
class LocalOutcome:
    transformation: np.ndarray
    converged: bool
    num_iterations: int
    sigma: float | None
    message: str
    history: tuple[IterationRecord, ...] | None


@keeps_keyboard_interrupt
def refine(
    source: np.ndarray,
    target: NearestNeighbors,
    estimator: StepEstimator,
    *,
    init: np.ndarray,
    max_iterations: int,
    tolerance: float,
    scale: float,
    callback: Callback | None = None,
    record_history: bool = False,
    coarse_points: int | None = None,
) -> LocalOutcome:
    """Iterate ``estimator`` from ``init`` (4x4 ``T_target_source``).

    ``scale`` (cloud units, e.g. the target's bounding-box diagonal) makes the translation part of
    the convergence test unit-free: the loop stops once an increment rotates by less than
    ``tolerance`` radians and translates by less than ``tolerance * scale``, or once the RMS
    correspondence distance changes by less than ``tolerance`` relative to itself.

    ``coarse_points`` (optional): while ``estimator.accelerated`` is False (the coarse phase of
    ``esm``'s automatic sigma), iterate on at most this many evenly strided source points; the
    full source is used from the fine phase on, and the run never ends during the coarse phase
    (its convergence moves it to the full source). Ignored when a ``callback`` is given, so that
    callbacks always see the whole source.
    """
    full_source = source
    coarse = (
        coarse_points is not None
        and callback is None
        and len(source) > coarse_points
        and getattr(estimator, "accelerated", True) is False
    )
    query_order = None
    if len(source) >= SPATIAL_ORDER_MIN and hasattr(target, "spatial_order"):
        order = target.spatial_order(apply(init, source))
        if callback is None and getattr(estimator, "order_invariant", True):
            # Visit the source points in spatial order (the result does not depend on the order).
            full_source = source[order]
        else:
            # The source keeps its order; only the queries are made in spatial order.
            query_order = order
    if coarse:
        source = full_source[np.linspace(0, len(full_source) - 1, coarse_points).astype(np.intp)]
    else:
        source = full_source
    near = getattr(target, "query_near", None)
    # Without a callback or a history nothing needs the per-point arrays: the placed source is
    # never formed, the query and the step map the source themselves.
    placed_step = getattr(estimator, "step_placed", None) if callback is None and not record_history else None

    def query(points, transform, warm):
        if near is None:
            return target.query(apply(transform, points))
        if query_order is None:
            return near(points, warm=warm, transform=transform)
        found_distances, found_indices = near(
            points[query_order], warm=None if warm is None else warm[query_order], transform=transform
        )
        distances, indices = np.empty_like(found_distances), np.empty_like(found_indices)
        distances[query_order], indices[query_order] = found_distances, found_indices
        return distances, indices

    indices = None
    transformation = init.copy()
    history: list[IterationRecord] | None = [] if record_history else None
    previous_rmse: float | None = None
    sigma: float | None = None
    accelerator = AndersonAccelerator(scale) if getattr(estimator, "accelerated", None) is not None else None
    fallback: np.ndarray | None = None  # the plain step, while an accelerated proposal is on trial
    objective_before = 0.0
    for iteration in range(1, max_iterations + 1):
        if coarse and estimator.accelerated:
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
        if placed_step is not None:
            moved = None
            step = placed_step(source, transformation, target.points, distances, indices)
        else:
            moved = apply(transformation, source)
            step = estimator.step(moved, target.points, distances, indices)
        if not (np.isfinite(step.rotation).all() and np.isfinite(step.translation).all()):
            return LocalOutcome(
                transformation, False, iteration - 1, sigma,
                f"stopped at iteration {iteration}: the increment was not finite", _freeze(history),
            )
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
        moved_angle, moved_distance = motion_between(transformation, following)
        transformation = following
        # (Not ``distances @ distances``: BLAS would wake its own threads, which then spin and
        # take the cores from the compiled kernels: measured 3x slower iterations at 100k points.)
        rmse = float(np.sqrt(np.mean(np.square(distances))))
        if history is not None:
            history.append(_record(iteration, transformation, rmse, step.weights, sigma, len(distances)))
        if callback is not None:
            state = IterationState(iteration, transformation.copy(), moved, indices, distances, step.weights, sigma)
            if callback(state):
                return LocalOutcome(
                    transformation, False, iteration, sigma, "stopped by the callback", _freeze(history)
                )
        small_step = moved_angle < tolerance and moved_distance < tolerance * scale
        settled = previous_rmse is not None and abs(previous_rmse - rmse) <= tolerance * previous_rmse
        if coarse and (small_step or settled):
            # Converged on the subset: continue on the full source, at the fine sigma.
            estimator.fine = True
        elif small_step or settled:
            reason = "increment below tolerance" if small_step else "RMS distance stopped changing"
            return LocalOutcome(
                transformation, True, iteration, sigma, f"converged after {iteration} iterations ({reason})",
                _freeze(history),
            )
        previous_rmse = rmse
    return LocalOutcome(
        transformation, False, max_iterations, sigma,
        f"reached max_iterations={max_iterations} before the tolerance {tolerance:g}", _freeze(history),
    )


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
