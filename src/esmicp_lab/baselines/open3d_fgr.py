"""``fgr``: Open3D's Fast Global Registration (Zhou, Park & Koltun 2016) on FPFH matches. Global.

With ``v`` the voxel size (given, or 1/40 of the target's bounding-box diagonal), both clouds are
downsampled and described exactly as for ``open3d-ransac-fpfh``
(:func:`esmicp_lab.baselines.open3d_ransac.fpfh`: voxel ``v``, normals radius ``2v``, FPFH radius
``5v``), then ``registration_fgr_based_on_feature_matching`` runs with
``FastGlobalRegistrationOption(maximum_correspondence_distance=0.5v)`` (Open3D's tutorial value)
and Open3D's other defaults (64 iterations of graduated non-convexity, tuple test on). FGR's pose is
returned as it is, without ICP refinement. Its tuple sampling draws from Open3D's global
generator, seeded from ``rng``. ``init`` and ``max_iterations`` are validated and ignored (a
global method; FGR's own iteration count is fixed at 64).
"""

from __future__ import annotations

import time

import numpy as np

from .base import BaselineResult
from ._common import OPEN3D_PACKAGE, checked_inputs, o3d_cloud, require
from .open3d_ransac import fpfh

NAME = "fgr"

#: FGR's max correspondence distance, in voxels (Open3D's tutorial value).
FGR_DISTANCE_VOXELS = 0.5


def register(
    source, target, *, init=None, max_iterations: int = 64, voxel_size: float | None = None, rng=None
) -> BaselineResult:
    """Register ``source`` onto ``target`` with Open3D's FGR; see the module's docstring.

    Raises :class:`MissingDependencyError` when open3d cannot be imported.
    """
    o3d = require("open3d", OPEN3D_PACKAGE)
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)  # init unused
    voxel = inputs.voxel
    registration = o3d.pipelines.registration

    start = time.perf_counter()
    o3d.utility.random.seed(inputs.seed)
    source_down, source_feature = fpfh(o3d, o3d_cloud(o3d, inputs.source), voxel)
    target_down, target_feature = fpfh(o3d, o3d_cloud(o3d, inputs.target), voxel)
    result = registration.registration_fgr_based_on_feature_matching(
        source_down,
        target_down,
        source_feature,
        target_feature,
        registration.FastGlobalRegistrationOption(maximum_correspondence_distance=FGR_DISTANCE_VOXELS * voxel),
    )
    runtime = time.perf_counter() - start

    return BaselineResult(
        transformation=np.array(result.transformation, dtype=np.float64),
        runtime_s=runtime,
        method=NAME,
        converged=None,
        notes=(
            f"voxel={voxel:.6g}, seed={inputs.seed}, "
            f"downsampled {len(source_down.points)}/{len(target_down.points)} pts; "
            f"fgr distance={FGR_DISTANCE_VOXELS * voxel:.6g} fitness={result.fitness:.3f} rmse={result.inlier_rmse:.3g}"
        ),
    )
