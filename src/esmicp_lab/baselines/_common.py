"""What the adapters share: input checks, the default voxel size, seeds, lazy imports, Open3D ICP."""

from __future__ import annotations

import importlib
from dataclasses import dataclass

import numpy as np

from esmicp.errors import InvalidInputError
from esmicp.types import as_count, as_generator, as_points, as_positive, as_transform, check_not_degenerate
from esmicp.core.procrustes import apply, bounding_box_diagonal
from esmicp.errors import MissingDependencyError
from .base import INSTALL_HINT

#: Default voxel size, as a fraction of the target's bounding-box diagonal. ModelNet40 objects
#: (diagonal 2.2-3) get 0.05-0.08, the Stanford bunny (0.25 m) 6 mm, a bunny range scan ~5 mm.
#: At 2,000 points on an object this is 2-2.5x the median point spacing (4.4x on the airplane,
#: whose points crowd on its fuselage): downsampling keeps 500-1,400 points, and FPFH (radius
#: 5 voxels = 1/8 of the diagonal) still describes local shape. 1/20, 1/30 and 1/60 did no
#: better on the resampled / outlier protocols (1/60 triples Open3D's time).
VOXEL_FRACTION_OF_DIAGONAL = 1.0 / 40.0

#: ICP refinement after a global step: max correspondence distance, in voxels.
ICP_DISTANCE_VOXELS = 1.5

#: Normal-estimation radius, in voxels (Open3D's tutorial value).
OPEN3D_NORMAL_RADIUS_VOXELS = 2.0

#: Default cap on the ICP refinement's iterations.
ICP_MAX_ITERATIONS = 50


#: The package name to ask for when Open3D cannot be imported.
OPEN3D_PACKAGE = "open3d (PyPI: open3d-cpu or open3d)"


#: Install hints of the libraries that need more than ``pip install 'esmicp[baselines]'``
#: (docs/baselines.md and .ci/run give the same commands).
PROBREG_HINT = (
    "pip install --no-deps probreg==0.3.8 && pip install 'esmicp[cpd]' "
    "(--no-deps: probreg's own requirements pull the full 400 MB open3d on top of open3d-cpu)"
)
GOICP_HINT = (
    "pip install 'esmicp[go-icp-build]' && pip install --no-build-isolation py-goicp==0.0.4 "
    "(py-goicp builds only with cython 0.29.37 and autowrap 0.22.11)"
)
TORCH_HINT = "pip install 'esmicp[learned]' (CPU torch, pinned to torch==2.13.0)"


def require(module: str, package: str, hint: str = INSTALL_HINT):
    """Import ``module`` now, or raise :class:`MissingDependencyError` naming ``package`` and
    how to install it (``hint``)."""
    try:
        return importlib.import_module(module)
    except (ImportError, OSError) as exc:  # OSError: a shared library (libusb for open3d) missing
        raise MissingDependencyError(
            f"{package} is needed for this baseline but cannot be imported ({exc}); install it with: "
            f"{hint}"
        ) from exc


def prepare(source, target) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 ``(N, 3)`` copies of both clouds (as :func:`esmicp.register` checks them)."""
    source_points = as_points(source, "source")
    target_points = as_points(target, "target")
    check_not_degenerate(source_points, "source")
    check_not_degenerate(target_points, "target")
    return source_points, target_points


def voxel_for(target: np.ndarray, voxel_size: float | None) -> float:
    """``voxel_size`` checked, or :data:`VOXEL_FRACTION_OF_DIAGONAL` of the target's diagonal."""
    if voxel_size is None:
        return VOXEL_FRACTION_OF_DIAGONAL * bounding_box_diagonal(target)
    return as_positive(voxel_size, "voxel_size")


@dataclass(frozen=True)
class Inputs:
    """An adapter's arguments, checked: clouds, voxel (cloud units), iteration cap, library seed,
    initial guess (4x4 ``T_target_source``; the identity when none was given)."""

    source: np.ndarray
    target: np.ndarray
    voxel: float
    max_iterations: int
    seed: int
    init: np.ndarray


def checked_inputs(source, target, voxel_size, max_iterations, rng, init=None) -> Inputs:
    """Every adapter's argument checks, in one place (see :func:`prepare`, :func:`voxel_for`,
    :func:`seed_from`, :func:`checked_init`)."""
    source_points, target_points = prepare(source, target)
    return Inputs(
        source_points,
        target_points,
        voxel_for(target_points, voxel_size),
        as_count(max_iterations, "max_iterations"),
        seed_from(rng),
        checked_init(init),
    )


def checked_init(init) -> np.ndarray:
    """``init`` as a rigid 4x4 ``T_target_source``; None is the identity."""
    if init is None:
        return np.eye(4)
    return as_transform(init, "init")


def local_distance(source: np.ndarray, target: np.ndarray, init: np.ndarray) -> float:
    """The max correspondence distance of the local methods: ``diag(source) + diag(target) +
    |centroid(init * source) - centroid(target)|`` (cloud units).

    No nearest-neighbour distance at the start can exceed it, so every source point has a
    correspondence, as in classic ICP (and as ``esm`` / ``icp`` pair every point): a smaller
    bound would cripple the local methods from far starts (the paper's protocol starts them from
    the identity under any rotation and translations of up to 1,000 object sizes), where the
    clouds do not even touch.
    """
    offset = float(np.linalg.norm(apply(init, source).mean(axis=0) - target.mean(axis=0)))
    return bounding_box_diagonal(source) + bounding_box_diagonal(target) + offset


def seed_from(rng) -> int:
    """A 31-bit seed for a library's own generator, drawn from ``rng`` (None, int or Generator).

    The same int gives the same seed; None gives a fresh one.
    """
    return int(as_generator(rng).integers(0, 2**31 - 1))


def o3d_cloud(o3d, points: np.ndarray):
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))


#: Refinements the global adapters offer after their global step.
#: ``"none"``: the global step's pose as it is (``open3d-ransac-fpfh``, ``kiss-matcher``).
REFINEMENTS = ("point-to-point", "point-to-plane", "none")


def check_refinement(refinement: str) -> str:
    if refinement not in REFINEMENTS:
        raise InvalidInputError(f"refinement: expected one of {', '.join(REFINEMENTS)}, got {refinement!r}")
    return refinement


def o3d_icp(
    o3d,
    source_cloud,
    target_cloud,
    init: np.ndarray,
    distance: float,
    max_iterations: int,
    *,
    refinement: str = "point-to-point",
    normal_radius: float | None = None,
):
    """Open3D ICP from ``init``; returns Open3D's RegistrationResult.

    ``point-to-plane`` first estimates the target's normals (hybrid search, ``normal_radius``,
    at most 30 neighbours) on the cloud given, which it modifies.
    """
    registration = o3d.pipelines.registration
    if refinement == "point-to-plane":
        target_cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
        estimation = registration.TransformationEstimationPointToPlane()
    else:
        estimation = registration.TransformationEstimationPointToPoint()
    return registration.registration_icp(
        source_cloud,
        target_cloud,
        distance,
        np.asarray(init, dtype=np.float64),
        estimation,
        registration.ICPConvergenceCriteria(
            relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=max_iterations
        ),
    )


def refine(
    o3d, source_cloud, target_cloud, coarse: np.ndarray, voxel: float, max_iterations: int, refinement: str
) -> tuple[np.ndarray, str]:
    """A global step's pose ``coarse`` refined by Open3D ICP (``refinement``: point-to-point or
    point-to-plane, max correspondence distance :data:`ICP_DISTANCE_VOXELS` voxels), or kept as it
    is (``"none"``). Returns the 4x4 ``T_target_source`` and a note for the result."""
    if refinement == "none":
        return np.array(coarse, dtype=np.float64), "no refinement"
    fine = o3d_icp(
        o3d,
        source_cloud,
        target_cloud,
        coarse,
        ICP_DISTANCE_VOXELS * voxel,
        max_iterations,
        refinement=refinement,
        normal_radius=OPEN3D_NORMAL_RADIUS_VOXELS * voxel,
    )
    note = f"{refinement} icp fitness={fine.fitness:.3f} rmse={fine.inlier_rmse:.3g}"
    return np.array(fine.transformation, dtype=np.float64), note
