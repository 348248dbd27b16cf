"""``cpd``: rigid Coherent Point Drift (Myronenko & Song 2010) from probreg 0.3.8. A LOCAL method.

probreg's ``RigidCPD(source, update_scale=False).registration(target, w=0.0, maxiter=max_iterations,
tol=1e-5)`` on the source moved by ``init``: the source points are the centroids of an equal-weight
Gaussian mixture of shared isotropic variance ``sigma^2`` (started at the mean squared distance
between all pairs, so CPD sees the whole cloud, not only nearby points), fitted to the target by EM
(probreg's E-step and loop); each M-step is a weighted Procrustes (rotation, translation; scale
fixed at 1: a rigid registration).

One fix: with ``update_scale=False`` probreg 0.3.8's M-step updates the variance as
``(tr(X'P1X) + tr(Y'P1Y) - tr(A'R)) / (Np D)``, missing the factor 2 of the cross term of
``sum P ||x - R y - t||^2`` (Myronenko & Song 2010, Fig. 2, with ``s = 1``): the variance then
stays near the cloud's own spread and CPD stops short (4 degrees off on a chair at 10 degrees,
measured). The adapter's subclass :class:`_RigidCPD` replaces that M-step by the paper's
(written in the project), with the correct ``(tr(X'P1X) - 2 tr(A'R) + tr(Y'P1Y)) / (Np D)``. ``w``
is the uniform-outlier weight (probreg's default, 0). The EM is O(N x M) in time and memory per
iteration. probreg's result maps the moved source onto the target: the adapter composes it with
``init`` into ``T_target_source``. Deterministic: ``rng`` and ``voxel_size`` are validated and
unused. probreg 0.3.8 is source-only and its requirements pull the full ``open3d`` wheel: install it
with ``pip install --no-deps probreg==0.3.8`` and then ``pip install 'esmicp[cpd]'``
(docs/baselines.md).
"""

from __future__ import annotations

import time

import numpy as np

from .base import BaselineResult
from esmicp.core.procrustes import apply
from ._common import PROBREG_HINT, checked_inputs, require

NAME = "cpd"

#: Default iteration cap of the local methods (the same for every local adapter).
MAX_ITERATIONS = 50

#: EM stops when the change of the objective falls below this (probreg's ``tol``).
TOLERANCE = 1e-5

#: Uniform-outlier weight of the mixture (probreg's default).
OUTLIER_WEIGHT = 0.0


def register(
    source,
    target,
    *,
    init=None,
    max_iterations: int = MAX_ITERATIONS,
    voxel_size: float | None = None,
    rng=None,
    outlier_weight: float = OUTLIER_WEIGHT,
) -> BaselineResult:
    """Register ``source`` onto ``target`` with probreg's rigid CPD from ``init``.

    ``outlier_weight`` is CPD's ``w`` in ``[0, 1)``. Raises :class:`MissingDependencyError` when
    probreg cannot be imported.
    """
    probreg_cpd = require("probreg.cpd", "probreg", PROBREG_HINT)
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)
    if not 0.0 <= float(outlier_weight) < 1.0:
        from esmicp.errors import InvalidInputError

        raise InvalidInputError(f"outlier_weight: expected a value in [0, 1), got {outlier_weight!r}")

    start = time.perf_counter()
    moved = apply(inputs.init, inputs.source)
    solver = _rigid_cpd_class(probreg_cpd)(
        moved, update_scale=False, tf_init_params={"rot": np.identity(3), "t": np.zeros(3)}
    )
    iterations = []
    solver.set_callbacks([lambda _: iterations.append(1)])
    result = solver.registration(inputs.target, w=float(outlier_weight), maxiter=inputs.max_iterations, tol=TOLERANCE)
    runtime = time.perf_counter() - start

    step = np.eye(4)
    step[:3, :3] = np.asarray(result.transformation.rot, dtype=np.float64)
    step[:3, 3] = np.asarray(result.transformation.t, dtype=np.float64)
    return BaselineResult(
        transformation=step @ inputs.init,
        runtime_s=runtime,
        method=NAME,
        converged=len(iterations) < inputs.max_iterations,  # tol met before the budget ran out
        notes=(
            f"w={float(outlier_weight):g}; max_iterations={inputs.max_iterations}; iterations={len(iterations)}; "
            f"tol={TOLERANCE:g}; "
            f"final sigma2={float(result.sigma2):.4g}; scale fixed at 1"
        ),
    )


def _rigid_cpd_class(probreg_cpd):
    """probreg's RigidCPD with the paper's rigid M-step (scale 1); see the module's docstring."""

    class _RigidCPD(probreg_cpd.RigidCPD):
        def maximization_step(self, target, estep_res, sigma2_p=None):
            source = self._source[:, :3]
            target = target[:, :3]
            pt1, p1, px, n_p = estep_res  # P^T 1, P 1, P X, sum of P
            mu_x = px.sum(axis=0) / n_p
            mu_y = source.T @ p1 / n_p
            source_hat = source - mu_y
            target_hat = target - mu_x
            a = px.T @ source_hat - np.outer(mu_x, p1 @ source_hat)  # X_hat^T P^T Y_hat
            u, _, vh = np.linalg.svd(a)
            correction = np.ones(3)
            correction[-1] = np.linalg.det(u @ vh)
            rotation = (u * correction) @ vh
            translation = mu_x - rotation @ mu_y
            tr_a_r = float(np.trace(a.T @ rotation))
            tr_x = float(np.sum(pt1 * np.sum(target_hat**2, axis=1)))
            tr_y = float(np.sum(p1 * np.sum(source_hat**2, axis=1)))
            sigma2 = max((tr_x - 2.0 * tr_a_r + tr_y) / (n_p * 3), float(np.finfo(np.float32).eps))
            q = (tr_x - 2.0 * tr_a_r + tr_y) / (2.0 * sigma2) + 1.5 * n_p * np.log(sigma2)
            transformation = probreg_cpd.tf.RigidTransformation(rotation, translation, 1.0)
            return probreg_cpd.MstepResult(transformation, sigma2, q)

    return _RigidCPD
