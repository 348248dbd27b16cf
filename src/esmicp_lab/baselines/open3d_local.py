"""Open3D's local registrations, from ``init``: ``open3d-icp`` (point-to-point ICP),
``open3d-icp-p2l`` (point-to-plane ICP) and ``open3d-gicp`` (generalized ICP). LOCAL methods.

All three call Open3D on the full clouds (no downsampling) with
``ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=max_iterations)``
and a max correspondence distance given by :func:`esmicp_lab.baselines._common.local_distance` (large
enough that every source point is paired at the start, as in classic ICP), unless
``max_correspondence_distance`` is given. Point-to-plane needs the target's normals, GICP the
covariances of both clouds: both from ``KDTreeSearchParamHybrid(radius=2v, max_nn=30)`` with ``v``
the voxel size (given, or 1/40 of the target's bounding-box diagonal); the voxel plays no other
role. Deterministic: ``rng`` is validated and unused.
"""

from __future__ import annotations

import time

import numpy as np

from .base import BaselineResult
from ._common import (
    OPEN3D_NORMAL_RADIUS_VOXELS,
    OPEN3D_PACKAGE,
    checked_inputs,
    local_distance,
    o3d_cloud,
    require,
)
from esmicp.types import as_positive

NAME_ICP = "open3d-icp"
NAME_ICP_PLANE = "open3d-icp-p2l"
NAME_GICP = "open3d-gicp"

#: Default iteration cap of the local methods (the same for every local adapter).
MAX_ITERATIONS = 50

_ESTIMATIONS = {
    NAME_ICP: "TransformationEstimationPointToPoint",
    NAME_ICP_PLANE: "TransformationEstimationPointToPlane",
    NAME_GICP: "TransformationEstimationForGeneralizedICP",
}


def _register(
    name: str, source, target, init, max_iterations, voxel_size, rng, max_correspondence_distance
) -> BaselineResult:
    o3d = require("open3d", OPEN3D_PACKAGE)
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)
    if max_correspondence_distance is None:
        distance = local_distance(inputs.source, inputs.target, inputs.init)
    else:
        distance = as_positive(max_correspondence_distance, "max_correspondence_distance")
    registration = o3d.pipelines.registration
    criteria = registration.ICPConvergenceCriteria(
        relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=inputs.max_iterations
    )

    start = time.perf_counter()
    source_cloud = o3d_cloud(o3d, inputs.source)
    target_cloud = o3d_cloud(o3d, inputs.target)
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=OPEN3D_NORMAL_RADIUS_VOXELS * inputs.voxel, max_nn=30)
    estimation = getattr(registration, _ESTIMATIONS[name])()
    if name == NAME_GICP:
        source_cloud.estimate_covariances(search)
        target_cloud.estimate_covariances(search)
        run = registration.registration_generalized_icp
    else:
        if name == NAME_ICP_PLANE:
            target_cloud.estimate_normals(search)
        run = registration.registration_icp
    result = run(source_cloud, target_cloud, distance, inputs.init, estimation, criteria)
    runtime = time.perf_counter() - start

    return BaselineResult(
        transformation=np.array(result.transformation, dtype=np.float64),
        runtime_s=runtime,
        method=name,
        converged=None,  # Open3D does not say whether the criteria or the cap stopped it
        notes=(
            f"voxel={inputs.voxel:.6g} (normals/covariances radius {OPEN3D_NORMAL_RADIUS_VOXELS:g}v); "
            f"max_correspondence_distance={distance:.6g}; max_iterations={inputs.max_iterations}; "
            f"fitness={result.fitness:.3f} rmse={result.inlier_rmse:.3g}"
        ),
    )


def icp(
    source,
    target,
    *,
    init=None,
    max_iterations: int = MAX_ITERATIONS,
    voxel_size: float | None = None,
    rng=None,
    max_correspondence_distance: float | None = None,
) -> BaselineResult:
    """Open3D point-to-point ICP from ``init`` (4x4 ``T_target_source``, None = identity).

    ``max_correspondence_distance`` (cloud units) overrides the default rule of the module's
    docstring. Raises :class:`MissingDependencyError` when open3d cannot be imported.
    """
    return _register(NAME_ICP, source, target, init, max_iterations, voxel_size, rng, max_correspondence_distance)


def icp_point_to_plane(
    source,
    target,
    *,
    init=None,
    max_iterations: int = MAX_ITERATIONS,
    voxel_size: float | None = None,
    rng=None,
    max_correspondence_distance: float | None = None,
) -> BaselineResult:
    """Open3D point-to-plane ICP from ``init`` (target normals from a radius of 2 voxels)."""
    return _register(
        NAME_ICP_PLANE, source, target, init, max_iterations, voxel_size, rng, max_correspondence_distance
    )


def gicp(
    source,
    target,
    *,
    init=None,
    max_iterations: int = MAX_ITERATIONS,
    voxel_size: float | None = None,
    rng=None,
    max_correspondence_distance: float | None = None,
) -> BaselineResult:
    """Open3D generalized ICP from ``init`` (covariances of both clouds from a radius of 2 voxels)."""
    return _register(NAME_GICP, source, target, init, max_iterations, voxel_size, rng, max_correspondence_distance)
