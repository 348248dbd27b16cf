"""``small-gicp``: small_gicp's generalized ICP from the identity. A LOCAL method.

``small_gicp.align(target, source, registration_type="GICP", downsampling_resolution=v,
max_correspondence_distance=10v, max_iterations=...)`` with ``v`` the voxel size (given, or 1/40
of the target's bounding-box diagonal): both clouds voxel-downsampled by ``v``, covariances from
their neighbours, GICP iterations from the identity. It has no global step, so it fails on poses
far from the identity (every protocol of :mod:`esmicp.protocols` moves the source by up to 5
diagonals); it is here as the local reference. Deterministic: one thread, ``rng`` unused.
"""

from __future__ import annotations

import time

import numpy as np

from . import BaselineResult
from ._common import checked_inputs, require

NAME = "small-gicp"

#: Max correspondence distance, in voxels (1/4 of the diagonal with the default voxel).
CORRESPONDENCE_DISTANCE_VOXELS = 10.0


def register(
    source, target, *, voxel_size: float | None = None, rng=None, max_iterations: int = 50
) -> BaselineResult:
    """Register ``source`` onto ``target`` with small_gicp's GICP, starting from the identity.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array-like
    voxel_size : float, optional
        Downsampling resolution (cloud units). Default: 1/40 of the target's bounding-box diagonal.
    rng : None, int or numpy.random.Generator
        Validated, unused (deterministic).
    max_iterations : int
        Cap on GICP iterations.

    Raises
    ------
    MissingDependencyError
        When small_gicp cannot be imported.
    """
    small_gicp = require("small_gicp", "small-gicp")
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng)  # the seed goes unused
    source_points, target_points, voxel = inputs.source, inputs.target, inputs.voxel

    start = time.perf_counter()
    result = small_gicp.align(
        target_points,
        source_points,
        registration_type="GICP",
        downsampling_resolution=float(voxel),
        max_correspondence_distance=float(CORRESPONDENCE_DISTANCE_VOXELS * voxel),
        num_threads=1,
        max_iterations=inputs.max_iterations,
        translation_epsilon=float(1e-3 * voxel),
    )
    runtime = time.perf_counter() - start

    return BaselineResult(
        transformation=np.array(result.T_target_source, dtype=np.float64),
        runtime_s=runtime,
        method=NAME,
        converged=bool(result.converged),
        notes=f"voxel={voxel:.6g}; iterations={result.iterations} inliers={result.num_inliers} error={result.error:.4g}",
    )
