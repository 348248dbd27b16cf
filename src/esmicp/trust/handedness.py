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

from ..core.keypoints import Keypoints
from ..core.procrustes import weighted_procrustes
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
    source keypoints; the ``policy.mirror_candidates`` that coincide best are fitted on by
    ``policy.mirror_iterations`` on ``policy.mirror_points`` keypoints, as the pose itself is
    (evenly strided subsets). Cost: about ``(policy.mirror_planes + 3) *
    policy.mirror_coarse_iterations`` queries of the coarse subset and ``(policy.mirror_candidates
    + 1) * policy.mirror_iterations`` of the finer one."""
    source, target = keypoints.source, keypoints.target
    if min(len(source), len(target)) < policy.min_coincident or not np.isfinite(transformation).all():
        return None
    fine, coarse = (source[np.linspace(0, len(source) - 1, min(len(source), count)).astype(np.intp)]
                    for count in (policy.mirror_points, policy.mirror_coarse_points))
    centre = source.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((source - centre).T))
    normals = np.vstack([axes.T, _hemisphere(policy.mirror_planes) @ axes.T])

    def mirror(points, normal):
        return points - 2.0 * np.outer((points - centre) @ normal, normal)

    pose = _fit(transformation, fine, keypoints, workers, policy, policy.mirror_iterations)
    proper = _coincident_share(pose, fine, keypoints, workers, policy, coincide_voxels)
    if proper + policy.mirror_margin >= 1.0:  # no mirror image can beat it by the margin
        return Handedness(proper, None, False)
    ranked = []
    for normal in normals:
        fitted = _fit(transformation, mirror(coarse, normal), keypoints, workers, policy,
                      policy.mirror_coarse_iterations)
        ranked.append((_coincident_share(fitted, mirror(coarse, normal), keypoints, workers, policy, coincide_voxels,
                                         both=False),
                       fitted, normal))
    improper = 0.0
    for _, fitted, normal in sorted(ranked, key=lambda entry: -entry[0])[:policy.mirror_candidates]:
        fitted = _fit(fitted, mirror(fine, normal), keypoints, workers, policy, policy.mirror_iterations)
        improper = max(improper, _coincident_share(fitted, mirror(fine, normal), keypoints, workers, policy,
                                                   coincide_voxels, centre, normal))
    return Handedness(proper, improper, improper > proper + policy.mirror_margin)


def _hemisphere(count: int) -> np.ndarray:
    """``count`` unit vectors spread evenly over the upper hemisphere (a Fibonacci lattice)."""
    index = np.arange(count) + 0.5
    height = 1.0 - index / count
    angle = np.pi * (3.0 - np.sqrt(5.0)) * index
    radius = np.sqrt(1.0 - height**2)
    return np.column_stack([radius * np.cos(angle), radius * np.sin(angle), height])


def _fit(transformation: np.ndarray, source: np.ndarray, keypoints: Keypoints, workers: int | None,
         policy: TrustPolicy, iterations: int) -> np.ndarray:
    """``transformation`` refined by at most ``iterations`` of trimmed point-to-point ICP of
    ``source`` onto the target keypoints: pairs within twice the median pair distance, and never
    fewer than those within ``policy.overlap_voxels`` keypoint voxels (far from the fit, the
    median reaches across the overlap; near it, the overlap alone)."""
    floor = policy.overlap_voxels * keypoints.voxel
    pose = np.array(transformation, dtype=np.float64)
    nearest = None
    for _ in range(iterations):
        distances, nearest = keypoints.target_tree.query(source, pose, warm=nearest, workers=workers)
        near = distances <= max(floor, 2.0 * float(np.median(distances)))
        if np.count_nonzero(near) < policy.min_coincident:
            return pose
        rotation, translation = weighted_procrustes(source[near], keypoints.target[nearest[near]])
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = rotation, translation
        moved = np.abs(step - pose).max()
        pose = step
        if moved < 1e-2 * keypoints.voxel:
            break
    return pose


def _coincident_share(pose: np.ndarray, source: np.ndarray, keypoints: Keypoints, workers: int | None,
                      policy: TrustPolicy, coincide_voxels: float, centre: np.ndarray | None = None,
                      normal: np.ndarray | None = None,
                      both: bool = True) -> float:
    """Of the keypoints within ``policy.overlap_voxels`` voxels of the other cloud at ``pose``, the
    share within ``coincide_voxels`` voxels, the smaller of the two directions. ``source``: the
    source keypoints, or their mirror image through the plane through ``centre`` with ``normal``
    (the reverse direction queries the source keypoints' tree at the target mirrored back).
    ``both=False``: the source's direction alone (a cheaper ranking)."""
    voxel = keypoints.voxel
    shares = []
    queries = [lambda: keypoints.target_tree.query(source, pose, workers=workers)[0]]
    if both:
        back = (keypoints.target - pose[:3, 3]) @ pose[:3, :3]
        if normal is not None:
            back = back - 2.0 * np.outer((back - centre) @ normal, normal)
        queries.append(lambda: keypoints.source_tree.query(back, workers=workers)[0])
    for query in queries:
        distances = query()
        overlap = np.count_nonzero(distances <= policy.overlap_voxels * voxel)
        if overlap == 0:
            return 0.0
        shares.append(np.count_nonzero(distances <= coincide_voxels * voxel) / overlap)
    return float(min(shares))

