"""``kiss-matcher-icp``: KISS-Matcher's global registration, then Open3D point-to-point ICP.

KISS-Matcher (Python package ``kiss-matcher``, module ``kiss_matcher``) downsamples both clouds
with a voxel grid, matches faster-PFH features, prunes the matches with ROBIN (a max-clique on
pairwise-consistent matches) and solves the pose with GNC-TLS:
``KISSMatcher(KISSMatcherConfig(voxel_size=v)).estimate(src, tgt)`` returns a solution with
``rotation`` (3x3), ``translation`` (3) and ``valid``. Its defaults are kept (normal radius 3v,
FPFH radius 5v, ROBIN noise bound 1v, solver noise bound 0.75v, no Quatro, i.e. full 3D
rotations). ``v``: given, or 1/40 of the target's bounding-box diagonal.

KISS-Matcher is tuned for LiDAR maps in metres: it refuses a voxel below 5 mm and clamps its noise
bounds to at most 1 (absolute units). So both clouds are centred and divided by ``v`` before they
are passed (as float32), and KISS-Matcher runs with a voxel of exactly 1: the same problem in
voxel units, whatever the clouds' units; the pose is mapped back.

Its pose is refined exactly as in :mod:`esmicp_lab.baselines.open3d_ransac`: point-to-point
``registration_icp`` on the full clouds, max correspondence distance ``1.5v``
(``refinement="point-to-plane"``, registered as ``kiss-matcher-p2l``: point-to-plane ICP;
``refinement="none"``, registered as ``kiss-matcher``: KISS-Matcher's pose as it is). KISS-Matcher
draws no random numbers: ``rng`` is accepted for the common interface and unused; a global method,
it ignores ``init``.
"""

from __future__ import annotations

import time

import numpy as np

from .base import BaselineResult
from ._common import (
    ICP_MAX_ITERATIONS,
    OPEN3D_PACKAGE,
    check_refinement,
    checked_inputs,
    o3d_cloud,
    refine,
    require,
)

NAME = "kiss-matcher-icp"
#: The name of the same pipeline refined by point-to-plane ICP.
NAME_PLANE = "kiss-matcher-p2l"
#: The name of KISS-Matcher alone (no refinement).
NAME_ALONE = "kiss-matcher"


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
    """Register ``source`` onto ``target`` with KISS-Matcher, then ICP.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array-like
    voxel_size : float, optional
        KISS-Matcher's resolution (cloud units); the ICP distance is 1.5x it. Default: 1/40 of
        the target's bounding-box diagonal.
    rng : None, int or numpy.random.Generator
        Validated, unused (the method is deterministic).
    max_iterations : int
        Cap on the ICP refinement's iterations.
    refinement : {"point-to-point", "point-to-plane", "none"}
        The ICP that refines the global pose (point-to-plane: target normals from a radius of
        2 voxels), or none. The result's ``method`` is ``"kiss-matcher-p2l"`` for point-to-plane,
        ``"kiss-matcher"`` for none.
    init : ignored (validated): a global method.

    Raises
    ------
    MissingDependencyError
        When kiss_matcher or open3d cannot be imported.
    """
    kiss_matcher = require("kiss_matcher", "kiss-matcher")
    refinement = check_refinement(refinement)
    o3d = None if refinement == "none" else require("open3d", OPEN3D_PACKAGE)
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)  # seed, init unused
    source_points, target_points, voxel = inputs.source, inputs.target, inputs.voxel

    start = time.perf_counter()
    # Centred (float32 keeps the precision of far-from-origin coordinates: the trials move
    # sources by up to 5 diagonals) and in voxel units (see the module's docstring).
    source_centre = source_points.mean(axis=0)
    target_centre = target_points.mean(axis=0)
    source_32 = np.ascontiguousarray((source_points - source_centre) / voxel, dtype=np.float32)
    target_32 = np.ascontiguousarray((target_points - target_centre) / voxel, dtype=np.float32)
    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel_size=1.0))
    solution = matcher.estimate(source_32, target_32)
    rotation = np.asarray(solution.rotation, dtype=np.float64)
    translation = voxel * np.asarray(solution.translation, dtype=np.float64).reshape(3)
    coarse = np.eye(4)
    coarse[:3, :3] = rotation
    coarse[:3, 3] = translation + target_centre - rotation @ source_centre
    transformation, refinement_note = refine(
        o3d,
        None if o3d is None else o3d_cloud(o3d, source_points),
        None if o3d is None else o3d_cloud(o3d, target_points),
        coarse,
        voxel,
        inputs.max_iterations,
        refinement,
    )
    runtime = time.perf_counter() - start

    notes = (
        f"voxel={voxel:.6g}; kiss valid={bool(solution.valid)} "
        f"rotation_inliers={matcher.get_num_rotation_inliers()} final_inliers={matcher.get_num_final_inliers()}; "
        f"{refinement_note}"
    )
    return BaselineResult(
        transformation=transformation,
        runtime_s=runtime,
        method={"point-to-point": NAME, "point-to-plane": NAME_PLANE, "none": NAME_ALONE}[refinement],
        converged=bool(solution.valid),
        notes=notes,
    )
