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
``refinement="none"``, registered as ``kiss-matcher``: KISS-Matcher's pose as it is).

``refinement="gicp"``, registered as ``kiss-matcher-gicp``: the fast pipeline of both projects'
documentation, KISS-Matcher then small_gicp's GICP (``small_gicp.align`` from KISS-Matcher's pose,
downsampling ``v``, its defaults' correspondence distance and tolerances scaled to ``v``:
:func:`esmicp_lab.baselines.small_gicp.refine_gicp`), on every core (as KISS-Matcher and esmicp's
defaults run). KISS-Matcher draws no random numbers: ``rng`` is accepted for the common interface
and unused; a global method, it ignores ``init``.
"""

from __future__ import annotations

import os
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
#: The name of KISS-Matcher refined by small_gicp's GICP.
NAME_GICP = "kiss-matcher-gicp"
#: The refinement that hands KISS-Matcher's pose to small_gicp (besides Open3D's).
GICP = "gicp"


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
    refinement : {"point-to-point", "point-to-plane", "gicp", "none"}
        The ICP that refines the global pose (point-to-plane: target normals from a radius of
        2 voxels; gicp: small_gicp's GICP, see the module's docstring), or none. The result's
        ``method`` is ``"kiss-matcher-p2l"`` for point-to-plane, ``"kiss-matcher-gicp"`` for gicp,
        ``"kiss-matcher"`` for none.
    init : ignored (validated): a global method.

    Raises
    ------
    MissingDependencyError
        When kiss_matcher, or the refinement's library (open3d, small_gicp), cannot be imported.
    """
    kiss_matcher = require("kiss_matcher", "kiss-matcher")
    gicp = refinement == GICP
    refinement = "none" if gicp else check_refinement(refinement)
    small_gicp = require("small_gicp", "small-gicp") if gicp else None
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
    if gicp:
        from .small_gicp import refine_gicp

        transformation, _, refinement_note = refine_gicp(small_gicp, source_points, target_points, coarse, voxel,
                                                         inputs.max_iterations, os.cpu_count() or 1)
    else:
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
        method=NAME_GICP if gicp else {"point-to-point": NAME, "point-to-plane": NAME_PLANE, "none": NAME_ALONE}[refinement],
        converged=bool(solution.valid),
        notes=notes,
    )
