"""The overlap confidence: how sharply two clouds coincide where they overlap under a pose (the
bar a result must reach to be trusted is :attr:`esmicp.trust.policy.TrustPolicy.trusted`).

It judges a pose on the pair's keypoints (:class:`~esmicp.core.keypoints.Keypoints`, voxel
centroids at one scale the data chooses), so every length here is a multiple of that voxel and
the measure is the same at any scale. The global search uses it to stop and to choose among its
poses; :func:`esmicp.register` reports it as ``RegistrationResult.confidence``.

Transforms are ``T_target_source`` (``target ~= source @ R.T + t``).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ..core.compiled_tree import CompiledTree
from ..core.features import estimate_normals
from ..core.keypoints import Keypoints
from .policy import DEFAULT_POLICY, TrustPolicy


class ConfidenceRanges(Protocol):
    """The tuned ranges :func:`overlap_confidence` maps its measures from, each a ``(low, high)``
    pair mapped linearly onto 0-1, and the keypoints' values (``scan.keypoint``: when two
    coincide); held by :class:`esmicp.globalreg.config.SearchConfig`."""

    @property
    def scan(self) -> Any: ...

    @property
    def sharpness_range(self) -> tuple[float, float]: ...

    @property
    def spread_range(self) -> tuple[float, float]: ...

    @property
    def third_range(self) -> tuple[float, float]: ...


def overlap_confidence(transformation: np.ndarray, keypoints: Keypoints, workers: int | None = None, *,
                       config: ConfidenceRanges, policy: TrustPolicy = DEFAULT_POLICY) -> float:
    """How sharply the clouds coincide where they overlap under ``transformation``
    (``T_target_source``), 0-1: of the keypoints within ``policy.overlap_voxels`` of the other
    cloud, the fraction within ``config.scan.keypoint.coincide_voxels``, the smaller of the two directions, mapped from
    ``config.sharpness_range``; or, when smaller and when less than ``policy.spread_below`` of
    either cloud coincides, how well the coincident part's normals hold the pose
    (:func:`coincident_spread`: its middle eigenvalue mapped from ``config.spread_range``, its
    smallest from ``config.third_range``), the smallest of these in either direction. 0 when fewer
    than ``policy.min_coincident`` keypoints of either cloud coincide (too little evidence: clouds
    that sparse cannot resolve the pose at the keypoint voxel, never finer than
    ``SearchConfig.scan.keypoint.min_voxel_spacings`` spacings, where a pose tens of degrees off still makes every point
    "coincide").

    A cloud that carries scattered points (:func:`surface_part`, read from its own keypoints
    before any pose) is measured on its surface: only its surface keypoints count among those
    that must coincide, and the distances to it are read at the spacing of that surface (the
    scattered points stand between its surface samples, so the keypoint voxel would be finer than
    the surface it sampled). A cloud without scattered points is measured on every keypoint at
    the keypoint voxel.

    ``workers``: threads of the compiled tree's queries (None: every core);
    ``config``: the ranges and the coincidence distance (a
    :class:`~esmicp.globalreg.config.SearchConfig`); ``policy``: the
    measure's other values (:class:`~esmicp.trust.policy.TrustPolicy`)."""
    if not np.isfinite(transformation).all() or min(len(keypoints.source), len(keypoints.target)) < 3:
        return 0.0
    rotation, translation = transformation[:3, :3], transformation[:3, 3]
    voxel = keypoints.voxel
    spacings = config.scan.keypoint.min_voxel_spacings
    source_part = surface_part(keypoints.source, keypoints.source_tree, voxel, spacings, workers, policy=policy)
    target_part = surface_part(keypoints.target, keypoints.target_tree, voxel, spacings, workers, policy=policy)
    sharpness, coincident = [], []
    for moved, fixed, fixed_points, moved_part, fixed_part in (
        (keypoints.source @ rotation.T + translation, keypoints.target_tree, keypoints.target, source_part,
         target_part),
        ((keypoints.target - translation) @ rotation, keypoints.source_tree, keypoints.source, target_part,
         source_part),
    ):
        if moved_part.surface is not None:
            moved = moved[moved_part.surface]
        distances, nearest = fixed.query(moved, workers=workers)  # the counts SciPy's tree gives, cheaper
        unit = voxel * fixed_part.scale
        overlap = np.count_nonzero(distances <= policy.overlap_voxels * unit)
        coincide = distances <= config.scan.keypoint.coincide_voxels * unit
        if np.count_nonzero(coincide) < policy.min_coincident:
            return 0.0
        sharpness.append(np.count_nonzero(coincide) / overlap)
        coincident.append((fixed_points, fixed, nearest[coincide], np.count_nonzero(coincide) / len(moved)))
    held = 1.0
    if min(share for *_, share in coincident) < policy.spread_below:
        for points, tree, touched, _ in coincident:
            third, second = coincident_spread(points, tree, touched, voxel, workers, policy=policy)
            held = min(held, _ramp(second, config.spread_range), _ramp(third, config.third_range))
    return float(min(_ramp(min(sharpness), config.sharpness_range), held))


@dataclass(frozen=True, eq=False)
class SurfacePart:
    """Which keypoints of a cloud lie on its surface, and the spacing of that surface.

    Attributes
    ----------
    scattered : float
        The share (0-1) of the cloud's keypoints with no keypoint of their own within
        ``TrustPolicy.isolated_voxels`` keypoint voxels.
    surface : (N,) bool array or None
        The keypoints on the cloud's surface (within ``TrustPolicy.surface_band_voxels`` of the
        plane their own neighbours fit); None when the cloud carries no scattered points (more
        than ``TrustPolicy.max_scattered`` of them isolated): every keypoint counts.
    scale : float
        The surface's sampling spacing over the spacing the keypoint voxel was made for (at least
        1; 1 without scattered points): distances to this cloud are read in keypoint voxels times
        this (gain).
    """

    scattered: float
    surface: np.ndarray | None
    scale: float


_PARTS: dict[tuple, tuple[weakref.ref, SurfacePart]] = {}


def surface_part(points: np.ndarray, tree: CompiledTree, voxel: float, spacings: float, workers: int | None = None,
                 *, policy: TrustPolicy = DEFAULT_POLICY) -> SurfacePart:
    """The :class:`SurfacePart` of keypoints ``points`` (``tree`` is over them, ``voxel`` their
    voxel, ``spacings`` the point spacings a keypoint voxel is at least:
    ``SearchConfig.scan.keypoint.min_voxel_spacings``), read from the points alone.

    A cloud carries scattered points when more than ``policy.max_scattered`` of its keypoints
    have no keypoint of their own within ``policy.isolated_voxels`` voxels (a sampled surface,
    however sparse at the keypoint voxel, leaves almost none so alone). Its surface keypoints are
    then those that lie within ``policy.surface_band_voxels`` of the plane fitted to their own
    nearest ``policy.surface_neighbours`` within ``policy.surface_radius_voxels``, refitted
    ``policy.surface_fits`` times on the neighbours within that band of the last plane, with at
    least ``policy.surface_min_neighbours`` of them in the band: a scattered point near a surface
    fits the surface's plane, not its own. The surface's spacing is the median distance from a
    surface keypoint to its nearest keypoint, times ``spacings``. Computed once per ``tree``
    and policy."""
    key = (id(tree), voxel, spacings, policy.isolated_voxels, policy.max_scattered, policy.surface_neighbours,
           policy.surface_radius_voxels, policy.surface_band_voxels, policy.surface_min_neighbours,
           policy.surface_fits)
    known = _PARTS.get(key)
    if known is not None and known[0]() is tree:
        return known[1]
    part = _surface_part(points, tree, voxel, spacings, workers, policy)
    _PARTS[key] = (weakref.ref(tree), part)
    weakref.finalize(tree, _PARTS.pop, key, None)
    return part


def _surface_part(points: np.ndarray, tree: CompiledTree, voxel: float, spacings: float, workers: int | None,
                  policy: TrustPolicy) -> SurfacePart:
    if len(points) < 2:
        return SurfacePart(0.0, None, 1.0)
    distances, _ = tree.query_k(points, 2, workers=workers)  # the nearest is the point itself
    scattered = float(np.mean(distances[:, 1] > policy.isolated_voxels * voxel))
    if scattered <= policy.max_scattered:
        return SurfacePart(scattered, None, 1.0)
    count = min(policy.surface_neighbours + 1, len(points))
    distances, indices = tree.query_k(points, count, workers=workers)
    distances, neighbours = distances[:, 1:], points[indices[:, 1:]]
    near = distances <= policy.surface_radius_voxels * voxel
    weights = near.astype(np.float64)
    band = policy.surface_band_voxels * voxel
    for fit in range(policy.surface_fits + 1):
        total = np.maximum(weights.sum(axis=1), 1.0)
        centre = np.einsum("nk,nki->ni", weights, neighbours) / total[:, None]
        spread = neighbours - centre[:, None, :]
        moment = np.einsum("nk,nki,nkj->nij", weights, spread, spread)
        normal = np.linalg.eigh(moment)[1][:, :, 0]
        if fit < policy.surface_fits:
            weights = (near & (np.abs(np.einsum("nki,ni->nk", spread, normal)) <= band)).astype(np.float64)
    offset = np.abs(np.einsum("ni,ni->n", points - centre, normal))
    surface = (weights.sum(axis=1) >= policy.surface_min_neighbours) & (offset <= band)
    if not surface.any():
        return SurfacePart(scattered, surface, 1.0)
    scale = max(1.0, spacings * float(np.median(distances[surface, 0])) / voxel)
    return SurfacePart(scattered, surface, scale)


def _ramp(value: float, bounds: tuple[float, float]) -> float:
    """``value`` mapped linearly from ``bounds`` onto 0-1, clipped."""
    low, high = bounds
    return float(np.clip((value - low) / (high - low), 0.0, 1.0))


def coincident_spread(points: np.ndarray, tree: CompiledTree, touched: np.ndarray, voxel: float,
                      workers: int | None = None, *, policy: TrustPolicy = DEFAULT_POLICY) -> tuple[float, float]:
    """How many directions the normals of ``points[touched]`` span: the smallest and the middle
    eigenvalue of their second moment (the middle one 0 when they are all parallel, as on one
    plane; the smallest 0 when they lie in one plane's worth of directions, as on two planes; both
    1/3 when they point every way). At most ``policy.spread_points`` of ``touched`` (evenly strided),
    each normal from its ``policy.spread_normal_neighbours`` nearest of ``points`` (``tree`` is over
    them) within ``policy.spread_normal_radius_voxels * voxel``."""
    if len(touched) > policy.spread_points:
        touched = touched[np.linspace(0, len(touched) - 1, policy.spread_points).astype(np.intp)]
    normals = estimate_normals(points, k=policy.spread_normal_neighbours,
                               radius=policy.spread_normal_radius_voxels * voxel, at=points[touched], tree=tree,
                               workers=workers)
    values = np.linalg.eigvalsh(normals.T @ normals / len(normals))
    return float(values[0]), float(values[1])
