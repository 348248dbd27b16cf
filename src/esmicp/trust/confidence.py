"""The overlap confidence: how sharply two clouds coincide where they overlap under a pose (the
bar a result must reach to be trusted is :attr:`esmicp.trust.policy.TrustPolicy.trusted`).

It judges a pose on the pair's keypoints (:class:`~esmicp.core.keypoints.Keypoints`, voxel
centroids at one scale the data chooses), so every length here is a multiple of that voxel and
the measure is the same at any scale. The global search uses it to stop and to choose among its
poses; :func:`esmicp.register` reports it as ``RegistrationResult.confidence``.

Transforms are ``T_target_source`` (``target ~= source @ R.T + t``).
"""

from __future__ import annotations

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
    "coincide"). ``workers``: threads of the compiled tree's queries (None: every core);
    ``config``: the ranges and the coincidence distance (a
    :class:`~esmicp.globalreg.config.SearchConfig`); ``policy``: the
    measure's other values (:class:`~esmicp.trust.policy.TrustPolicy`)."""
    if not np.isfinite(transformation).all() or min(len(keypoints.source), len(keypoints.target)) < 3:
        return 0.0
    rotation, translation = transformation[:3, :3], transformation[:3, 3]
    voxel = keypoints.voxel
    sharpness, coincident = [], []
    for moved, fixed, fixed_points in (
        (keypoints.source @ rotation.T + translation, keypoints.target_tree, keypoints.target),
        ((keypoints.target - translation) @ rotation, keypoints.source_tree, keypoints.source),
    ):
        distances, nearest = fixed.query(moved, workers=workers)  # the counts SciPy's tree gives, cheaper
        overlap = np.count_nonzero(distances <= policy.overlap_voxels * voxel)
        coincide = distances <= config.scan.keypoint.coincide_voxels * voxel
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
