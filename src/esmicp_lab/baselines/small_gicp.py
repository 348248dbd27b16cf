"""``small-gicp`` / ``small-vgicp``: small_gicp's generalized ICP and voxelized GICP from ``init``.
LOCAL methods.

``small_gicp.align(target, source, init_T_target_source=init,
registration_type="GICP" | "VGICP", downsampling_resolution=v, max_correspondence_distance=d,
max_iterations=...)`` with ``v`` the voxel size (given, or 1/40 of the target's bounding-box
diagonal): both clouds voxel-downsampled by ``v``, covariances from their 10 nearest neighbours
(small_gicp's default), then GICP iterations from ``init`` (VGICP: the target's covariances merged
per voxel of size ``4v``, one voxel lookup per source point instead of a nearest-neighbour search;
voxels of ``v`` hold too few points on 1,000-2,000-point objects, small_gicp's own defaults have the
same 4:1 ratio). ``d`` follows the rule of every local adapter
(:func:`esmicp_lab.baselines._common.local_distance`: every source point paired at the start) unless
``max_correspondence_distance`` is given; VGICP has no correspondence distance (a point whose voxel
is empty in the target is simply unpaired), so from far starts it cannot move. Deterministic: one
thread, ``rng`` validated and unused.
"""

from __future__ import annotations

import time

import numpy as np

from .base import BaselineResult
from ._common import checked_inputs, local_distance, require
from esmicp.errors import InvalidInputError
from esmicp.types import as_positive

NAME = "small-gicp"
NAME_VGICP = "small-vgicp"

#: VGICP's voxel, in downsampling voxels.
VGICP_VOXEL_VOXELS = 4.0

#: Default iteration cap of the local methods (the same for every local adapter).
MAX_ITERATIONS = 50

_NAMES = {"GICP": NAME, "VGICP": NAME_VGICP}

#: small_gicp's own defaults, in its downsampling voxels: ``align``'s ``max_correspondence_distance``
#: (1.0) and ``translation_epsilon`` (1e-3) are given for its default ``downsampling_resolution``
#: (0.25, metres of a LiDAR scan), so at a voxel ``v`` they are these multiples of ``v``. Used by
#: the refinement after a global step (:func:`refine_gicp`), whose start is already within a few
#: voxels; the LOCAL adapter keeps its own distance rule.
DOCS_DISTANCE_VOXELS = 1.0 / 0.25
DOCS_TRANSLATION_EPSILON_VOXELS = 1e-3 / 0.25


def register(
    source,
    target,
    *,
    init=None,
    max_iterations: int = MAX_ITERATIONS,
    voxel_size: float | None = None,
    rng=None,
    registration_type: str = "GICP",
    max_correspondence_distance: float | None = None,
) -> BaselineResult:
    """Register ``source`` onto ``target`` with small_gicp, starting from ``init``.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array-like
    init : (4, 4) array-like, optional
        Initial ``T_target_source``; None is the identity.
    max_iterations : int
        Cap on GICP iterations.
    voxel_size : float, optional
        Downsampling resolution (cloud units); VGICP's voxel is 4x it. Default: 1/40 of the target's
        bounding-box diagonal.
    rng : None, int or numpy.random.Generator
        Validated, unused (deterministic).
    registration_type : {"GICP", "VGICP"}
        ``"VGICP"`` is registered as ``small-vgicp``.
    max_correspondence_distance : float, optional
        GICP's correspondence distance (cloud units); default: the module's rule.

    Raises
    ------
    MissingDependencyError
        When small_gicp cannot be imported.
    """
    if registration_type not in _NAMES:
        raise InvalidInputError(f"registration_type: expected GICP or VGICP, got {registration_type!r}")
    small_gicp = require("small_gicp", "small-gicp")
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)  # the seed goes unused
    source_points, target_points, voxel = inputs.source, inputs.target, inputs.voxel
    if max_correspondence_distance is None:
        distance = local_distance(source_points, target_points, inputs.init)
    else:
        distance = as_positive(max_correspondence_distance, "max_correspondence_distance")

    start = time.perf_counter()
    result = small_gicp.align(
        target_points,
        source_points,
        init_T_target_source=inputs.init,
        registration_type=registration_type,
        voxel_resolution=float(VGICP_VOXEL_VOXELS * voxel),
        downsampling_resolution=float(voxel),
        max_correspondence_distance=float(distance),
        num_threads=1,
        max_iterations=inputs.max_iterations,
        translation_epsilon=float(1e-3 * voxel),
    )
    runtime = time.perf_counter() - start

    distance_note = "none (voxel lookup)" if registration_type == "VGICP" else f"{distance:.6g}"
    return BaselineResult(
        transformation=np.array(result.T_target_source, dtype=np.float64),
        runtime_s=runtime,
        method=_NAMES[registration_type],
        converged=bool(result.converged),
        notes=(
            f"voxel={voxel:.6g}; max_correspondence_distance={distance_note}; "
            f"max_iterations={inputs.max_iterations}; iterations={result.iterations} "
            f"inliers={result.num_inliers} error={result.error:.4g}"
        ),
    )


def refine_gicp(small_gicp, source: np.ndarray, target: np.ndarray, coarse: np.ndarray, voxel: float,
                max_iterations: int, num_threads: int) -> tuple[np.ndarray, bool, str]:
    """A global step's pose ``coarse`` (``T_target_source``) refined by small_gicp's GICP as its
    documentation runs it (``small_gicp.align(target, source, init_T_target_source=coarse,
    downsampling_resolution=voxel)``), its distance and translation tolerance at its defaults'
    multiples of the voxel (:data:`DOCS_DISTANCE_VOXELS`, :data:`DOCS_TRANSLATION_EPSILON_VOXELS`),
    its rotation tolerance (0.1 degree) as it is. Returns the refined 4x4 pose, GICP's
    ``converged`` and a note."""
    result = small_gicp.align(
        target,
        source,
        init_T_target_source=np.asarray(coarse, dtype=np.float64),
        registration_type="GICP",
        downsampling_resolution=float(voxel),
        max_correspondence_distance=float(DOCS_DISTANCE_VOXELS * voxel),
        num_threads=int(num_threads),
        max_iterations=int(max_iterations),
        translation_epsilon=float(DOCS_TRANSLATION_EPSILON_VOXELS * voxel),
    )
    note = (f"small_gicp GICP distance={DOCS_DISTANCE_VOXELS * voxel:.6g} threads={num_threads} "
            f"iterations={result.iterations} inliers={result.num_inliers} converged={bool(result.converged)}")
    return np.array(result.T_target_source, dtype=np.float64), bool(result.converged), note
