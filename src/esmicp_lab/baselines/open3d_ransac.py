"""``open3d-ransac-fpfh-icp``: Open3D's global registration pipeline, then point-to-point ICP.

With ``v`` the voxel size (given, or 1/40 of the target's bounding-box diagonal):

1. ``voxel_down_sample(v)`` of both clouds;
2. normals from ``KDTreeSearchParamHybrid(radius=2v, max_nn=30)``;
3. FPFH features from ``KDTreeSearchParamHybrid(radius=5v, max_nn=100)``;
4. ``registration_ransac_based_on_feature_matching`` with ``mutual_filter=False``, distance
   threshold ``1.5v``, ``ransac_n=3``, checkers edge length 0.9 and distance ``1.5v``, and
   ``RANSACConvergenceCriteria(100000, 0.999)`` (the settings of Open3D's global-registration
   tutorial);
5. point-to-point ``registration_icp`` on the full (not downsampled) clouds from the RANSAC pose,
   max correspondence distance ``1.5v``, at most ``max_iterations`` iterations
   (``refinement="point-to-plane"``, registered as ``open3d-ransac-fpfh-p2l``: point-to-plane
   ICP instead, target normals from a radius of ``2v``; ``refinement="none"``, registered as
   ``open3d-ransac-fpfh``: no refinement, the RANSAC pose as it is).

A global method: ``init`` is accepted for the common interface and ignored.

Open3D's RANSAC draws from Open3D's global generator, seeded here with
``o3d.utility.random.seed`` from ``rng``: the same seed gives the same result.
"""

from __future__ import annotations

import time

import numpy as np

from .base import BaselineResult
from ._common import (
    ICP_MAX_ITERATIONS,
    OPEN3D_NORMAL_RADIUS_VOXELS,
    OPEN3D_PACKAGE,
    check_refinement,
    checked_inputs,
    o3d_cloud,
    refine,
    require,
)

NAME = "open3d-ransac-fpfh-icp"
#: The name of the same pipeline refined by point-to-plane ICP.
NAME_PLANE = "open3d-ransac-fpfh-p2l"
#: The name of RANSAC + FPFH alone (no refinement).
NAME_ALONE = "open3d-ransac-fpfh"

#: Radii in voxels (Open3D's tutorial values); the normal radius, 2, is OPEN3D_NORMAL_RADIUS_VOXELS.
FPFH_RADIUS_VOXELS = 5.0
RANSAC_DISTANCE_VOXELS = 1.5
EDGE_LENGTH_RATIO = 0.9
RANSAC_MAX_ITERATIONS = 100_000
RANSAC_CONFIDENCE = 0.999


def fpfh(o3d, cloud, voxel: float):
    """Downsample ``cloud`` (an Open3D PointCloud), estimate normals, compute FPFH."""
    geometry = o3d.geometry
    down = cloud.voxel_down_sample(voxel)
    down.estimate_normals(geometry.KDTreeSearchParamHybrid(radius=OPEN3D_NORMAL_RADIUS_VOXELS * voxel, max_nn=30))
    feature = o3d.pipelines.registration.compute_fpfh_feature(
        down, geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS_VOXELS * voxel, max_nn=100)
    )
    return down, feature


def register(
    source,
    target,
    *,
    init=None,
    max_iterations: int = ICP_MAX_ITERATIONS,
    voxel_size: float | None = None,
    rng=None,
    refinement: str = "point-to-point",
) -> BaselineResult:
    """Register ``source`` onto ``target`` with Open3D RANSAC on FPFH matches, then ICP.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array-like
    voxel_size : float, optional
        Downsampling voxel (cloud units); all radii and thresholds scale with it. Default: 1/40 of
        the target's bounding-box diagonal.
    rng : None, int or numpy.random.Generator
        Seeds Open3D's RANSAC (``o3d.utility.random.seed``).
    max_iterations : int
        Cap on the ICP refinement's iterations.
    refinement : {"point-to-point", "point-to-plane", "none"}
        The ICP that refines the global pose (point-to-plane: target normals from a radius of
        2 voxels), or none. The result's ``method`` is ``"open3d-ransac-fpfh-p2l"`` for
        point-to-plane, ``"open3d-ransac-fpfh"`` for none.
    init : ignored (validated): a global method.

    Raises
    ------
    MissingDependencyError
        When open3d cannot be imported.
    """
    o3d = require("open3d", OPEN3D_PACKAGE)
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)  # init unused
    source_points, target_points, voxel = inputs.source, inputs.target, inputs.voxel
    refinement = check_refinement(refinement)
    registration = o3d.pipelines.registration

    start = time.perf_counter()
    o3d.utility.random.seed(inputs.seed)
    source_cloud = o3d_cloud(o3d, source_points)
    target_cloud = o3d_cloud(o3d, target_points)
    source_down, source_feature = fpfh(o3d, source_cloud, voxel)
    target_down, target_feature = fpfh(o3d, target_cloud, voxel)
    distance = RANSAC_DISTANCE_VOXELS * voxel
    coarse = registration.registration_ransac_based_on_feature_matching(
        source_down,
        target_down,
        source_feature,
        target_feature,
        mutual_filter=False,
        max_correspondence_distance=distance,
        estimation_method=registration.TransformationEstimationPointToPoint(False),
        ransac_n=3,
        checkers=[
            registration.CorrespondenceCheckerBasedOnEdgeLength(EDGE_LENGTH_RATIO),
            registration.CorrespondenceCheckerBasedOnDistance(distance),
        ],
        criteria=registration.RANSACConvergenceCriteria(RANSAC_MAX_ITERATIONS, RANSAC_CONFIDENCE),
    )
    transformation, refinement_note = refine(
        o3d, source_cloud, target_cloud, coarse.transformation, voxel, inputs.max_iterations, refinement
    )
    runtime = time.perf_counter() - start

    found = len(coarse.correspondence_set) >= 3
    notes = (
        f"voxel={voxel:.6g}, seed={inputs.seed}, downsampled {len(source_down.points)}/{len(target_down.points)} pts; "
        f"ransac fitness={coarse.fitness:.3f} inliers={len(coarse.correspondence_set)}; "
        f"{refinement_note}"
    )
    return BaselineResult(
        transformation=transformation,
        runtime_s=runtime,
        method={"point-to-point": NAME, "point-to-plane": NAME_PLANE, "none": NAME_ALONE}[refinement],
        converged=found,
        notes=notes,
    )
