"""``ndt``: the 3D Normal Distributions Transform (point-to-distribution), in the project, in numpy.
A LOCAL method.

From Biber & Strasser, "The normal distributions transform: a new approach to laser scan
matching" (IROS 2003) and Magnusson, "The three-dimensional normal-distributions transform" (PhD
thesis, Orebro 2009, chapter 6), no Python package of which works:

- **Target model.** The target is cut into cubic cells of side ``c``; every cell with at least
  :data:`MIN_POINTS_PER_CELL` points becomes a Gaussian (mean ``mu``, covariance ``Sigma``, whose
  eigenvalues are floored at :data:`EIGENVALUE_FLOOR` x the largest, Magnusson's regularisation of
  flat cells).
- **Score.** A source point ``x`` moved by the pose ``p`` scores
  ``-d1 exp(-d2/2 q^T Sigma^-1 q)``, ``q = T(p) x - mu``, summed over the Gaussians whose means lie
  within ``c`` of it (at most 8, found with a KD-tree on the means: the cell containing it and its
  neighbours); ``d1``, ``d2`` fit a Gaussian plus a uniform outlier density (outlier ratio
  :data:`OUTLIER_RATIO`, Magnusson eq. 6.8, PCL's default ratio) to the negative log-likelihood.
- **Optimisation.** Newton's method on the 6 pose parameters (rotation vector and translation of
  an increment applied on the left of the current pose), with the exact gradient and Hessian of the
  score (Magnusson eqs. 6.12-6.13; second derivatives of the rotation at the increment's origin),
  the Hessian made positive definite when it is not (its eigenvalues replaced by their absolute
  values, floored at 1e-3 of the largest), the step limited to 0.2 rad and half a cell, and a
  backtracking line search that only accepts a better score.
- **Coarse to fine.** Three resolutions, ``c = 4v, 2v, v`` with ``v`` = ``voxel_size`` or
  1/20 of the target's bounding-box diagonal (the default voxel of the other adapters, 1/40,
  leaves ModelNet-size clouds of 1,000-2,000 points with too few points per cell), each level
  starting where the previous one stopped. ``max_iterations`` Newton iterations in total, split
  evenly between the levels. A level stops when the increment falls below 1e-6 rad and 1e-6 cell.

NDT only sees target Gaussians within a cell of the moved source points: from a start where the
clouds do not overlap (the paper's protocol with translations of up to 1,000 object sizes) it
cannot move, and says so (``converged=False``, ``notes``). Deterministic: ``rng`` is unused.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .base import BaselineResult
from esmicp.core.procrustes import apply, axis_bounds, bounding_box_diagonal
from ._common import checked_inputs
from esmicp.types import as_positive

NAME = "ndt"

#: Default iteration cap of the local methods (the same for every local adapter).
MAX_ITERATIONS = 50

#: Default finest cell side, as a fraction of the target's bounding-box diagonal.
CELL_FRACTION_OF_DIAGONAL = 1.0 / 20.0
#: Cell sides of the coarse-to-fine levels, in finest cells.
LEVELS = (4.0, 2.0, 1.0)
MIN_POINTS_PER_CELL = 5
EIGENVALUE_FLOOR = 1e-3
OUTLIER_RATIO = 0.55
#: Gaussians a point is scored against (the nearest means within one cell side).
NEIGHBOUR_CELLS = 8
STEP_TOLERANCE = 1e-6
LINE_SEARCH_HALVINGS = 12
#: Largest rotation of one Newton step, in radians (the translation's limit is half a cell).
MAX_ROTATION_STEP = 0.2

# The generators of so(3): E[k] @ x = e_k x x.
_GENERATORS = np.array(
    [
        [[0, 0, 0], [0, 0, -1], [0, 1, 0]],
        [[0, 0, 1], [0, 0, 0], [-1, 0, 0]],
        [[0, -1, 0], [1, 0, 0], [0, 0, 0]],
    ],
    dtype=np.float64,
)
# Second derivatives of exp(w) x at w = 0: (E_i E_j + E_j E_i) / 2.
_PRODUCTS = np.einsum("iab,jbc->ijac", _GENERATORS, _GENERATORS)  # E_i E_j
_SECOND = 0.5 * (_PRODUCTS + _PRODUCTS.transpose(1, 0, 2, 3))


class _Gaussians:
    """The target's cells of side ``cell``, as Gaussians (means, inverse covariances)."""

    def __init__(self, target: np.ndarray, cell: float):
        keys = np.floor((target - axis_bounds(target)[0]) / cell).astype(np.int64)
        _, label, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        label = label.ravel()
        keep = counts >= MIN_POINTS_PER_CELL
        order = np.argsort(label, kind="stable")
        starts = np.concatenate([[0], np.cumsum(counts)])
        means, inverses = [], []
        for cell_index in np.flatnonzero(keep):
            members = target[order[starts[cell_index] : starts[cell_index + 1]]]
            mean = members.mean(axis=0)
            covariance = np.cov(members, rowvar=False)
            values, vectors = np.linalg.eigh(covariance)
            values = np.maximum(values, EIGENVALUE_FLOOR * max(values[-1], 1e-300))
            means.append(mean)
            inverses.append((vectors / values) @ vectors.T)
        self.cell = cell
        self.count = len(means)
        self.means = np.array(means).reshape(-1, 3)
        self.inverses = np.array(inverses).reshape(-1, 3, 3)
        self.tree = cKDTree(self.means) if self.count else None
        # Magnusson (2009), eq. 6.8: Gaussian + uniform outliers fitted by a Gaussian of the log.
        c1 = 10.0 * (1.0 - OUTLIER_RATIO)
        c2 = OUTLIER_RATIO / cell**3
        d3 = -np.log(c2)
        self.d1 = -np.log(c1 + c2) - d3
        self.d2 = -2.0 * np.log((-np.log(c1 * np.exp(-0.5) + c2) - d3) / self.d1)

    def pairs(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(point index, Gaussian index) of every Gaussian within a cell side of every point."""
        if self.tree is None:
            return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
        k = min(NEIGHBOUR_CELLS, self.count)
        distances, index = self.tree.query(points, k=k, distance_upper_bound=self.cell)
        distances, index = distances.reshape(len(points), k), index.reshape(len(points), k)
        found = np.isfinite(distances)
        return np.nonzero(found)[0], index[found]

    def score(self, points: np.ndarray, with_derivatives: bool):
        """Score (to minimise, <= 0), and its gradient and Hessian in the left increment."""
        point_index, gaussian_index = self.pairs(points)
        x = points[point_index]
        q = x - self.means[gaussian_index]
        inverse = self.inverses[gaussian_index]
        inverse_q = np.einsum("nab,nb->na", inverse, q)
        exponent = np.exp(-0.5 * self.d2 * np.einsum("na,na->n", q, inverse_q))
        # d1 < 0, so every term lies in [d1, 0]: lower is better.
        value = float(self.d1 * exponent.sum())
        if not with_derivatives:
            return value, len(np.unique(point_index))
        # dq/dp: rotation columns E_k x, then the identity.
        rotation_part = np.einsum("kab,nb->nak", _GENERATORS, x)
        jacobian = np.concatenate([rotation_part, np.broadcast_to(np.eye(3), (len(x), 3, 3))], axis=2)
        projected = np.einsum("na,nak->nk", inverse_q, jacobian)  # q^T S^-1 dq/dp_k
        factor = -self.d1 * self.d2 * exponent  # > 0
        gradient = np.einsum("n,nk->k", factor, projected)
        curvature = np.einsum("nak,nab,nbl->nkl", jacobian, inverse, jacobian)
        second = np.zeros((len(x), 6, 6))
        second[:, :3, :3] = np.einsum("na,ijab,nb->nij", inverse_q, _SECOND, x)
        hessian = np.einsum(
            "n,nkl->kl", factor, -self.d2 * projected[:, :, None] * projected[:, None, :] + curvature + second
        )
        return value, gradient, hessian, len(np.unique(point_index))


def _increment_matrix(step: np.ndarray) -> np.ndarray:
    delta = np.eye(4)
    delta[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix()
    delta[:3, 3] = step[3:]
    return delta


def _newton(gaussians: _Gaussians, source: np.ndarray, transform: np.ndarray, iterations: int):
    """Newton iterations at one resolution; returns (transform, iterations run, converged, points seen)."""
    done = 0
    seen = 0
    for done in range(1, iterations + 1):
        moved = apply(transform, source)
        value, gradient, hessian, seen = gaussians.score(moved, with_derivatives=True)
        if seen == 0:
            return transform, done, False, 0
        # Far from the optimum the Hessian is often indefinite: its eigenvalues are replaced by
        # their absolute values (floored at 1e-3 of the largest), so the step always descends.
        values, vectors = np.linalg.eigh(hessian)
        values = np.maximum(np.abs(values), 1e-3 * float(np.abs(values).max()) + 1e-300)
        step = -(vectors / values) @ (vectors.T @ gradient)
        # A trust region: at most MAX_ROTATION_STEP rad and half a cell per iteration.
        shrink = max(
            1.0,
            float(np.linalg.norm(step[:3])) / MAX_ROTATION_STEP,
            float(np.linalg.norm(step[3:])) / (0.5 * gaussians.cell),
        )
        step = step / shrink
        for _ in range(LINE_SEARCH_HALVINGS):
            candidate = _increment_matrix(step) @ transform
            if gaussians.score(apply(candidate, source), with_derivatives=False)[0] < value:
                break
            step = 0.5 * step
        else:
            return transform, done, True, seen  # no step improves the score: a (local) optimum
        transform = candidate
        if np.linalg.norm(step[:3]) < STEP_TOLERANCE and np.linalg.norm(step[3:]) < STEP_TOLERANCE * gaussians.cell:
            return transform, done, True, seen
    return transform, done, False, seen


def register(
    source,
    target,
    *,
    init=None,
    max_iterations: int = MAX_ITERATIONS,
    voxel_size: float | None = None,
    rng=None,
) -> BaselineResult:
    """Register ``source`` onto ``target`` with NDT from ``init``; see the module's docstring.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array-like
    init : (4, 4) array-like, optional
        Initial ``T_target_source``; None is the identity.
    max_iterations : int
        Newton iterations in total over the three resolutions.
    voxel_size : float, optional
        The finest cell side (cloud units); default 1/20 of the target's bounding-box diagonal.
    rng
        Validated, unused.
    """
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)
    cell = (
        CELL_FRACTION_OF_DIAGONAL * bounding_box_diagonal(inputs.target)
        if voxel_size is None
        else as_positive(voxel_size, "voxel_size")
    )

    start = time.perf_counter()
    transform = inputs.init.copy()
    shares = np.full(len(LEVELS), inputs.max_iterations // len(LEVELS))
    shares[-1] += inputs.max_iterations - shares.sum()
    level_notes = []
    converged = False
    blind = False  # some level saw no source point near any target Gaussian
    for factor, share in zip(LEVELS, shares):
        if share == 0:
            continue
        gaussians = _Gaussians(inputs.target, factor * cell)
        transform, ran, converged, seen = _newton(gaussians, inputs.source, transform, int(share))
        level_notes.append(f"c={factor * cell:.4g}: {gaussians.count} cells, {ran} it, {seen} pts seen")
        blind = blind or seen == 0
    runtime = time.perf_counter() - start

    return BaselineResult(
        transformation=transform,
        runtime_s=runtime,
        method=NAME,
        converged=bool(converged) and not blind,
        notes=(
            f"cell={cell:.6g}; max_iterations={inputs.max_iterations}; " + "; ".join(level_notes)
            + ("; no source point near a target Gaussian at some level (no overlap)" if blind else "")
        ),
    )
