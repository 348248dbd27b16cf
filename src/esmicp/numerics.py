"""Numerical safety of a registration: a well-conditioned working frame, and a last check of the result.

Coordinates far from the origin relative to the cloud's size (UTM or ECEF coordinates, 1e8 m
away, of a scan 10 m across) carry rounding noise of about ``1e-16 x |coordinate|`` in every
point: larger than the convergence tolerance relative to the cloud, so the iterations could never
settle (measured: 100 iterations and ``converged=False`` at 1e8, for a pose still right to 1e-7
degrees). :func:`register <esmicp.register>` therefore works in a frame shifted by a point of the
target (its centroid) when the clouds are far from the origin, and maps the result back:
rigid registration is equivariant under a common shift, so only the rounding changes.

A shift by ``o`` turns a transform ``T_target_source`` into ``Tr(-o) @ T @ Tr(o)`` (same rotation,
translation ``R o + t - o``).

:func:`checked_refine` runs the local refinement only from a finite rigid start, and returns a
finite rigid pose in every case: a start or a result that is not one (NaN, a non-rotation) ends
in ``converged=False`` with the reason in the message, never in NaN.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .core.procrustes import bounding_box_diagonal
from .core.weights import effective_count
from .methods.base import Step
from .methods.local import LocalOutcome, refine

__all__ = [
    "FAR_FROM_ORIGIN",
    "checked_refine",
    "from_working",
    "rigidity_problem",
    "to_working",
    "uncentred_callback",
    "uncentred_history",
    "working_origin",
]

#: The clouds are registered in a shifted frame when the target's centroid is farther from the
#: origin than this many times the target's bounding-box diagonal (rounding noise then exceeds
#: ~1e-13 of the cloud's size; below, a shift would change nothing measurable).
FAR_FROM_ORIGIN = 1e3

#: Fewer effective pairs (Kish's count of the weights) than this cannot fix a rotation.
MIN_EFFECTIVE_PAIRS = 3.0

#: Tolerance on ``R^T R = I`` of a result (results are re-orthonormalised every iteration).
RESULT_RIGID_TOLERANCE = 1e-6


def working_origin(target: np.ndarray) -> np.ndarray | None:
    """The point to shift both clouds by (the target's centroid), or None when no shift is needed."""
    centroid = target.mean(axis=0)
    diagonal = bounding_box_diagonal(target)
    if float(np.linalg.norm(centroid)) > FAR_FROM_ORIGIN * diagonal:
        return centroid
    return None


def to_working(transform: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """``transform`` (4x4) expressed in the frame whose coordinates are ``x - origin``."""
    shifted = transform.copy()
    shifted[:3, 3] = transform[:3, :3] @ origin + transform[:3, 3] - origin
    return shifted


def from_working(transform: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_working`: back to the original coordinates."""
    original = transform.copy()
    original[:3, 3] = transform[:3, 3] + (origin - transform[:3, :3] @ origin)
    return original


def uncentred_callback(callback, origin: np.ndarray):
    """Wrap ``callback`` so that it sees states in the original coordinates."""
    if callback is None:
        return None

    def wrapped(state):
        return callback(
            dataclasses.replace(
                state,
                transformation=from_working(state.transformation, origin),
                moved_source=state.moved_source + origin,
            )
        )

    return wrapped


def uncentred_history(history, origin: np.ndarray):
    """Per-iteration records with their transformations in the original coordinates."""
    if history is None:
        return None
    return tuple(
        dataclasses.replace(record, transformation=from_working(record.transformation, origin))
        for record in history
    )


def rigidity_problem(transform: np.ndarray) -> str | None:
    """Why ``transform`` is not a finite 4x4 rigid transform, or None when it is one."""
    if transform.shape != (4, 4):
        return f"a matrix of shape {transform.shape}"
    if not np.isfinite(transform).all():
        return "a matrix with NaN or infinite entries"
    rotation = transform[:3, :3]
    if not np.allclose(transform[3], [0.0, 0.0, 0.0, 1.0]):
        return "a matrix whose last row is not [0 0 0 1]"
    deviation = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if deviation > RESULT_RIGID_TOLERANCE or np.linalg.det(rotation) <= 0:
        return f"a matrix that is not a rotation (max |R^T R - I| = {deviation:.3g})"
    return None


class _LastWeights:
    """A step estimator that remembers its last step (everything else delegated);
    :meth:`effective_pairs` counts that step's effective pairs once the run is over."""

    def __init__(self, estimator):
        self._estimator = estimator
        self._last: tuple[Step, int] | None = None  # the step and its number of pairs
        if hasattr(estimator, "step_placed"):
            self.step_placed = self._watched(estimator.step_placed)
        self.step = self._watched(estimator.step)

    def _watched(self, function):
        def watched(*args, **kwargs):
            step = function(*args, **kwargs)
            self._last = (step, len(args[-1]))  # args[-1]: the indices, one per pair
            return step

        return watched

    def effective_pairs(self) -> tuple[float | None, int]:
        """Kish's effective number of pairs of the last step (None where it has no weights) and
        its number of pairs."""
        if self._last is None:
            return None, 0
        step, count = self._last
        if step.weights is not None:
            return (effective_count(step.weights) if count else None), count
        return step.effective_pairs, count

    def __getattr__(self, name):
        return getattr(self._estimator, name)


def checked_refine(source, target, estimator, *, init: np.ndarray, **kwargs) -> LocalOutcome:
    """:func:`esmicp.methods.local.refine`, guarded: no NaN, and no false convergence.

    - A start that is not a finite rigid transform (e.g. a failed global search) is not refined:
      the outcome is the identity with ``converged=False`` and the reason.
    - A refined pose that is not a finite rigid transform is replaced by the start, again with
      ``converged=False`` and the reason.
    - A run whose last step gave fewer than :data:`MIN_EFFECTIVE_PAIRS` effective pairs (half the
      pairs for clouds under 6 points) did not fit the data: every Gaussian weight underflowed to
      0 (a fixed ``sigma`` far below the distances between the clouds, e.g. ``esm-paper``'s 1.0 on
      an object kilometres across), so its step could only align centroids, never rotate. It is
      reported as not converged.
    """
    problem = rigidity_problem(init)
    if problem is not None:
        return LocalOutcome(
            np.eye(4), False, 0, None, f"no pose: the refinement would have started from {problem}", None
        )
    watched = _LastWeights(estimator)
    outcome = refine(source, target, watched, init=init, **kwargs)
    problem = rigidity_problem(outcome.transformation)
    if problem is not None:
        return dataclasses.replace(
            outcome,
            transformation=init.copy(),
            converged=False,
            message=f"stopped: the refined pose was {problem}; the starting pose is returned instead",
        )
    effective, count = watched.effective_pairs()
    # (Half the pairs at most: a 3-point cloud with unequal weights has fewer than 3 effective ones.)
    if effective is not None and effective < min(MIN_EFFECTIVE_PAIRS, 0.5 * count):
        sigma = "" if outcome.sigma is None else f" (sigma {outcome.sigma:.3g})"
        return dataclasses.replace(
            outcome,
            converged=False,
            message=(
                f"no fit: in the last iteration every pair weighed (almost) 0{sigma}, the clouds are "
                f"too far apart for the kernel; use a larger sigma or method='esm' (sigma from the data)"
            ),
        )
    return outcome
