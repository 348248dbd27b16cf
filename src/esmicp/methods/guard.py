"""The guard around the local refinement: no NaN, and no false convergence.

:func:`guarded_refine` runs :func:`~esmicp.methods.local.refine` only from a finite rigid start, and
returns a finite rigid pose in every case: a start or a result that is not one (NaN, a
non-rotation) ends in ``converged=False`` with the reason in the message, never in NaN.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .config import LoopConfig
from .local import RefinementOutcome, refine

#: Tolerance on the entries of ``R^T R - I`` of a result (absolute; results are re-orthonormalised
#: every iteration, so anything above rounding is not a rotation).
RESULT_RIGID_TOLERANCE = 1e-6


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


def guarded_refine(source, target, estimator, *, init: np.ndarray, loop: LoopConfig | None = None,
                   **kwargs) -> RefinementOutcome:
    """:func:`esmicp.methods.local.refine` (same arguments; ``loop``: the loop's values, None: the
    defaults), guarded.

    - A start that is not a finite rigid transform (e.g. a failed global search) is not refined:
      the outcome is the identity with ``converged=False`` and the reason.
    - A refined pose that is not a finite rigid transform is replaced by the start, again with
      ``converged=False`` and the reason.
    - A run whose last step gave fewer than ``loop.min_effective_pairs`` effective pairs (half the
      pairs for clouds under 6 points) did not fit the data: every Gaussian weight underflowed to
      0 (a fixed ``sigma`` far below the distances between the clouds, e.g. ``esm-paper``'s 1.0 on
      an object kilometres across), so its step could only align centroids, never rotate. It is
      reported as not converged.
    """
    problem = rigidity_problem(init)
    if problem is not None:
        return RefinementOutcome(
            np.eye(4), False, 0, None, f"no pose: the refinement would have started from {problem}", None
        )
    loop = LoopConfig() if loop is None else loop
    outcome = refine(source, target, estimator, init=init, loop=loop, **kwargs)
    problem = rigidity_problem(outcome.transformation)
    if problem is not None:
        return dataclasses.replace(
            outcome,
            transformation=init.copy(),
            converged=False,
            message=f"stopped: the refined pose was {problem}; the starting pose is returned instead",
        )
    effective = outcome.effective_pairs
    # (Half the pairs at most: a 3-point cloud with unequal weights has fewer than 3 effective ones.)
    if effective is not None and effective < min(loop.min_effective_pairs, 0.5 * outcome.pairs):
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
