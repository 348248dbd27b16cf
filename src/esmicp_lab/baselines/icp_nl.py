"""``icp-nl``: Levenberg-Marquardt point-to-point ICP with a robust (Huber) loss, in the project.
A LOCAL method (after Fitzgibbon, "Robust registration of 2D and 3D point sets", 2003).

Each outer iteration (at most ``max_iterations``, from ``init``):

1. every source point, moved by the current pose, is paired with its nearest target point
   (a KD-tree on the target), if it lies within the max correspondence distance of every local
   adapter (:func:`esmicp_lab.baselines._common.local_distance`: all points at the start);
2. the Huber scale is ``k = 1.345 x 1.4826 x median pair distance`` (Huber's 95%-efficiency
   constant on a robust estimate of the residuals' spread), floored at the target's median point
   spacing so that it does not collapse on exact copies;
3. the 6-vector pose increment ``(rotation vector, translation)`` applied on the left of the
   current pose minimises ``sum_i rho(|R s_i + t - q_i|)`` by ``scipy.optimize.least_squares``
   with ``method="lm"`` (MINPACK's Levenberg-Marquardt) on the residual vectors scaled by
   ``sqrt(w_i)``, the Huber weights ``w_i = min(1, k / |r_i|)`` of the pairs at the start of the
   iteration (iteratively reweighted: MINPACK's LM takes no robust loss itself), with the analytic
   Jacobian at the increment's origin and at most 20 evaluations;
4. the run stops when the increment falls below 1e-7 rad and 1e-7 target diagonals.

Deterministic: ``rng`` is validated and unused; ``voxel_size`` is validated and unused (the
method uses every point).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .base import BaselineResult
from esmicp.core.procrustes import apply, bounding_box_diagonal, skew
from ._common import checked_inputs, local_distance
from esmicp.types import as_positive

NAME = "icp-nl"

#: Default iteration cap of the local methods (the same for every local adapter).
MAX_ITERATIONS = 50

#: Huber's tuning constant (95% efficiency on Gaussian residuals) and the normal-consistent MAD.
HUBER_CONSTANT = 1.345
MAD_TO_SIGMA = 1.4826

#: Stopping rule on one outer iteration's increment (radians; target diagonals).
STEP_TOLERANCE = 1e-7

#: Function evaluations per Levenberg-Marquardt solve.
LM_MAX_EVALUATIONS = 20


def _left_jacobian(rotation_vector: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian ``I + (1 - cos a)/a^2 [w]_x + (a - sin a)/a^3 [w]_x^2``."""
    angle = float(np.linalg.norm(rotation_vector))
    cross = skew(rotation_vector)
    if angle < 1e-8:
        return np.eye(3) + 0.5 * cross
    return (
        np.eye(3)
        + (1.0 - np.cos(angle)) / angle**2 * cross
        + (angle - np.sin(angle)) / angle**3 * (cross @ cross)
    )


def _increment(moved: np.ndarray, matched: np.ndarray, sqrt_weights: np.ndarray) -> np.ndarray:
    """LM solve of the weighted point-to-point residuals; returns the 6-vector increment."""
    centre = moved.mean(axis=0)  # rotate about the centroid: better conditioned far from the origin
    local = moved - centre

    def residuals(x):
        rotated = local @ Rotation.from_rotvec(x[:3]).as_matrix().T + centre + x[3:]
        return ((rotated - matched) * sqrt_weights[:, None]).ravel()

    def jacobian(x):
        # d(R(x) p)/dx = -[R(x) p]_x J_left(x), exactly (J_left: SO(3)'s left Jacobian).
        rotated = local @ Rotation.from_rotvec(x[:3]).as_matrix().T
        rotation_block = -skew(rotated) @ _left_jacobian(x[:3])  # d(R p)/d(rotation vector) at 0: -[p]_x
        block = np.concatenate([rotation_block, np.broadcast_to(np.eye(3), (len(local), 3, 3))], axis=2)
        return (block * sqrt_weights[:, None, None]).reshape(-1, 6)

    solution = least_squares(
        residuals, np.zeros(6), jac=jacobian, method="lm", max_nfev=LM_MAX_EVALUATIONS, x_scale="jac"
    )
    step = solution.x.copy()
    # Back to an increment about the origin: R (p - c) + c + t = R p + (c - R c + t).
    rotation = Rotation.from_rotvec(step[:3]).as_matrix()
    step_translation = centre - rotation @ centre + step[3:]
    return np.concatenate([step[:3], step_translation])


def register(
    source,
    target,
    *,
    init=None,
    max_iterations: int = MAX_ITERATIONS,
    voxel_size: float | None = None,
    rng=None,
    max_correspondence_distance: float | None = None,
) -> BaselineResult:
    """Register ``source`` onto ``target`` by robust Levenberg-Marquardt ICP from ``init``.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array-like
    init : (4, 4) array-like, optional
        Initial ``T_target_source``; None is the identity.
    max_iterations : int
        Outer iterations (correspondence searches), at most.
    voxel_size, rng
        Validated, unused.
    max_correspondence_distance : float, optional
        Pairs farther apart are dropped (cloud units); default: the rule of the module's docstring.
    """
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)
    source_points, target_points = inputs.source, inputs.target

    start = time.perf_counter()
    distance = (
        local_distance(source_points, target_points, inputs.init)
        if max_correspondence_distance is None
        else as_positive(max_correspondence_distance, "max_correspondence_distance")
    )
    tree = cKDTree(target_points)
    spacing = float(np.median(tree.query(target_points[: min(len(target_points), 5000)], k=2)[0][:, 1]))
    scale = bounding_box_diagonal(target_points)
    transform = inputs.init.copy()
    converged = False
    iterations = 0
    pairs = 0
    for iterations in range(1, inputs.max_iterations + 1):
        moved = apply(transform, source_points)
        distances, index = tree.query(moved, distance_upper_bound=distance)
        paired = np.isfinite(distances)
        pairs = int(paired.sum())
        if pairs < 3:
            break
        huber = max(HUBER_CONSTANT * MAD_TO_SIGMA * float(np.median(distances[paired])), spacing)
        weights = np.minimum(1.0, huber / np.maximum(distances[paired], 1e-300))
        step = _increment(moved[paired], target_points[index[paired]], np.sqrt(weights))
        delta = np.eye(4)
        delta[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix()
        delta[:3, 3] = step[3:]
        transform = delta @ transform
        if np.linalg.norm(step[:3]) < STEP_TOLERANCE and np.linalg.norm(step[3:]) < STEP_TOLERANCE * scale:
            converged = True
            break
    runtime = time.perf_counter() - start

    return BaselineResult(
        transformation=transform,
        runtime_s=runtime,
        method=NAME,
        converged=converged,
        notes=(
            f"max_correspondence_distance={distance:.6g}; max_iterations={inputs.max_iterations}; "
            f"iterations={iterations}; pairs={pairs}; huber from median distance, floor {spacing:.4g}"
        ),
    )
