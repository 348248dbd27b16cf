"""Handedness: does a mirror image of the source fit the target better than any rotation of it?

A rigid pose is a proper rotation and a translation; it can never turn a left hand into a right
one. When one cloud is a mirror image of the other (a scan written with one axis flipped, a
left-handed coordinate convention, a mesh exported mirrored), the best proper pose still lands
the source on the target where the shape is nearly mirror-symmetric (an animal, a chair), and
the overlap confidence of that pose can be high. The test here compares the pose with the best
*improper* one near it: the source keypoints reflected through a plane through their centroid
(each of the three planes their principal axes span), each reflection then fitted to the target
keypoints by a short trimmed point-to-point ICP, and the pose itself fitted the same way. When
the best reflection coincides with the target on a clearly larger share of the overlap than the
pose does, the input is mirrored. A mirror-symmetric shape fits both ways alike and is not
doubted; that is right: no data can tell its handedness.

Every length is a multiple of the keypoint voxel (:class:`~esmicp.core.keypoints.Keypoints`), so
the test is the same at any scale. Transforms are ``T_target_source`` (``target ~= source @ R.T + t``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import _kernels
from ..core.compiled_tree import threads
from ..core.keypoints import Keypoints
from ..core.sampling import evenly_strided
from .policy import DEFAULT_POLICY, TrustPolicy


@dataclass(frozen=True)
class Handedness:
    """The outcome of :func:`handedness`: ``proper``, the share (0-1) of the overlapping keypoints
    that coincide at the pose (fitted on keypoints), and ``improper``, the same share at the best
    mirror image of the source (the smaller of the two directions each; None when not measured:
    ``proper`` is within the policy's ``mirror_margin`` of 1, so no mirror image can beat it);
    ``mirrored``, whether ``improper`` exceeds ``proper`` by more than that margin."""

    proper: float
    improper: float | None
    mirrored: bool


def handedness(transformation: np.ndarray, keypoints: Keypoints, workers: int | None = None, *,
               coincide_voxels: float, policy: TrustPolicy = DEFAULT_POLICY) -> Handedness | None:
    """:class:`Handedness` of the pose ``transformation`` (4x4 ``T_target_source``) on
    ``keypoints``, two keypoints coinciding within ``coincide_voxels`` keypoint voxels (the
    overlap confidence's distance, ``SearchConfig.scan.keypoint.coincide_voxels``); None when
    either cloud has fewer than ``policy.min_coincident`` keypoints (too few to tell).

    The mirror planes pass through the source keypoints' centroid; their normals are the three
    principal axes and ``policy.mirror_planes`` directions spread evenly over a hemisphere. Each
    mirror image starts at ``transformation`` itself (which maps it to the pose's placement
    mirrored through the plane's image: the improper pose nearest the pose) and is fitted by
    ``policy.mirror_coarse_iterations`` iterations of ICP on ``policy.mirror_coarse_points``
    source keypoints, every mirror image in one compiled batch; the ``policy.mirror_candidates``
    that coincide best are fitted on by ``policy.mirror_iterations`` on ``policy.mirror_points``
    keypoints, as the pose itself is; the
    pose and those fits are judged on ``policy.mirror_share_points`` keypoints of each cloud
    (evenly strided subsets throughout). A fit leaves the batch once it has converged. Cost: at
    most ``(policy.mirror_planes + 3) * policy.mirror_coarse_points *
    (policy.mirror_coarse_iterations + 1) + (policy.mirror_candidates + 1) *
    (policy.mirror_points * policy.mirror_iterations + 2 * policy.mirror_share_points)`` keypoint
    queries."""
    source, target = keypoints.source, keypoints.target
    if min(len(source), len(target)) < policy.min_coincident or not np.isfinite(transformation).all():
        return None
    fine, coarse = (_strided(source, count) for count in (policy.mirror_points, policy.mirror_coarse_points))
    centre = source.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((source - centre).T))
    normals = np.vstack([axes.T, _hemisphere(policy.mirror_planes) @ axes.T])
    # Householder reflections through the planes through ``centre``, as 4x4 maps of the source.
    reflections = np.tile(np.eye(4), (len(normals), 1, 1))
    reflections[:, :3, :3] -= 2.0 * normals[:, :, None] * normals[:, None, :]
    reflections[:, :3, 3] = 2.0 * (normals @ centre)[:, None] * normals
    # Each mirror image's start, as a map of the unreflected source: the pose after its reflection.
    poses = transformation @ reflections

    judged = (_strided(source, policy.mirror_share_points), _strided(target, policy.mirror_share_points))
    pose = _fit(np.asarray(transformation, dtype=np.float64)[None], fine, keypoints, workers, policy,
                policy.mirror_iterations)
    proper = float(_shares(pose, *judged, keypoints, workers, policy, coincide_voxels)[0])
    if proper + policy.mirror_margin >= 1.0:  # no mirror image can beat it by the margin
        return Handedness(proper, None, False)
    coarse_poses = _fit(poses, coarse, keypoints, workers, policy, policy.mirror_coarse_iterations)
    coarse_shares = _shares(coarse_poses, coarse, None, keypoints, workers, policy, coincide_voxels)
    best = np.argsort(-coarse_shares, kind="stable")[:policy.mirror_candidates]
    fitted = _fit(coarse_poses[best], fine, keypoints, workers, policy, policy.mirror_iterations)
    improper = float(_shares(fitted, *judged, keypoints, workers, policy, coincide_voxels).max())
    return Handedness(proper, improper, improper > proper + policy.mirror_margin)


def _strided(points: np.ndarray, count: int) -> np.ndarray:
    """At most ``count`` of ``points``, evenly strided."""
    return points[evenly_strided(len(points), count)]


def _hemisphere(count: int) -> np.ndarray:
    """``count`` unit vectors spread evenly over the upper hemisphere (a Fibonacci lattice)."""
    index = np.arange(count) + 0.5
    height = 1.0 - index / count
    angle = np.pi * (3.0 - np.sqrt(5.0)) * index
    radius = np.sqrt(1.0 - height**2)
    return np.column_stack([radius * np.cos(angle), radius * np.sin(angle), height])


def _fit(maps: np.ndarray, source: np.ndarray, keypoints: Keypoints, workers: int | None,
         policy: TrustPolicy, iterations: int) -> np.ndarray:
    """Each of the 4x4 ``maps`` ``(K, 4, 4)`` of ``source`` (improper ones included) refined by at
    most ``iterations`` of trimmed point-to-point ICP onto the target keypoints, in one compiled
    call (the maps in parallel, each independent of the others and of the thread count): pairs
    within twice the median pair distance, and never fewer than those within
    ``policy.overlap_voxels`` keypoint voxels (far from the fit, the median reaches across the
    overlap; near it, the overlap alone). The fitted rotation is proper, composed on the left of
    the map, so a map keeps its handedness. A fit stops once no entry of its map moves by a
    hundredth of a voxel or it keeps fewer than ``policy.min_coincident`` pairs."""
    maps = np.array(maps, dtype=np.float64)
    rotations = np.ascontiguousarray(maps[:, :3, :3].reshape(-1, 9))
    translations = np.ascontiguousarray(maps[:, :3, 3])
    tree = keypoints.target_tree
    _kernels.trimmed_icp_tree(np.ascontiguousarray(source, dtype=np.float64), rotations, translations,
                              int(iterations), float(policy.overlap_voxels * keypoints.voxel), 2.0,
                              int(policy.min_coincident), 1e-2 * keypoints.voxel, False, np.empty(len(maps), dtype=np.int64),
                              np.ascontiguousarray(keypoints.target, dtype=np.float64), tree.rank, tree.points,
                              tree.order, tree.starts, tree.ends, tree.lefts, tree.boxes, threads(workers))
    maps[:, :3, :3] = rotations.reshape(-1, 3, 3)
    maps[:, :3, 3] = translations
    return maps


def _shares(maps: np.ndarray, source: np.ndarray, target: np.ndarray | None, keypoints: Keypoints,
            workers: int | None, policy: TrustPolicy, coincide_voxels: float) -> np.ndarray:
    """For each 4x4 map ``(K, 4, 4)`` of ``source`` (source keypoints), of the keypoints within
    ``policy.overlap_voxels`` voxels of the other cloud, the share within ``coincide_voxels``
    voxels: the smaller of the two directions, the reverse one of ``target`` (target keypoints)
    mapped back into the source tree; ``target`` None: the source's direction alone (a cheaper
    ranking). 0 where nothing overlaps."""
    voxel = keypoints.voxel
    bound = max(policy.overlap_voxels, coincide_voxels) * voxel  # no farther neighbour counts
    queries = [_within(keypoints.target_tree, source, maps, bound, workers)]
    if target is not None:
        queries.append(_within(keypoints.source_tree, target, np.linalg.inv(maps), bound, workers))
    shares = np.full(len(maps), np.inf)
    for distances in queries:
        overlap = np.count_nonzero(distances <= policy.overlap_voxels * voxel, axis=1)
        coincide = np.count_nonzero(distances <= coincide_voxels * voxel, axis=1)
        shares = np.minimum(shares, np.where(overlap > 0, coincide / np.maximum(overlap, 1), 0.0))
    return shares


def _within(tree, points: np.ndarray, maps: np.ndarray, bound: float, workers: int | None) -> np.ndarray:
    """``(K, N)``: the distance of each of ``points`` ``(N, 3)`` mapped by each 4x4 map ``(K, 4, 4)``
    to its nearest point of ``tree`` (a :class:`~esmicp.core.compiled_tree.CompiledTree`), where
    within ``bound`` (cloud units); infinity where none is (a search bounded from the start: far
    points cost little)."""
    distances = np.empty((len(maps), len(points)))
    _kernels.tree_within(np.ascontiguousarray(points, dtype=np.float64),
                         np.ascontiguousarray(maps[:, :3, :3].reshape(-1, 9)), np.ascontiguousarray(maps[:, :3, 3]),
                         float(bound), distances, tree.points, tree.order, tree.starts, tree.ends, tree.lefts,
                         tree.boxes, threads(workers))
    return distances
