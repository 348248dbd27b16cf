"""The keypoints of a pair: both clouds voxel-downsampled at one voxel the data chooses, with a
compiled tree over each.

Every length at this scale is a multiple of the voxel, so a pair scaled by 1000 gives the same
keypoints up to that scale. The scan strategy of the global search
(:mod:`esmicp.globalreg.scan`) and the overlap confidence (:mod:`esmicp.trust.confidence`) work
on the same keypoints, so that the confidence judges a pose on the search's own scale.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .. import _kernels
from .compiled_tree import CompiledTree
from .correspondence import coincident_points
from .features import voxel_grid
from .procrustes import axis_bounds

@dataclass(frozen=True)
class Keypoints:
    """The keypoint clouds of a pair (voxel centroids, cloud units) and their voxel."""

    source: np.ndarray
    target: np.ndarray
    voxel: float

    @classmethod
    def of(cls, source: np.ndarray, target: np.ndarray, spacing: float, count: int,
           min_spacings: float) -> "Keypoints":
        """Both clouds voxel-downsampled at :func:`keypoint_voxel` of the target (``count``
        voxels: ``SearchConfig.keypoints``; at least ``min_spacings`` target point spacings:
        ``SearchConfig.scan.keypoint.min_voxel_spacings``)."""
        voxel = keypoint_voxel(target, max(spacing, 0.0), count, min_spacings)
        return cls(voxel_grid(source, voxel)[0], voxel_grid(target, voxel)[0], voxel)

    @cached_property
    def source_tree(self) -> CompiledTree:
        """A compiled tree over :attr:`source`, built once (every score of a pose queries it)."""
        return CompiledTree(self.source)

    @cached_property
    def target_tree(self) -> CompiledTree:
        """A compiled tree over :attr:`target`, built once."""
        return CompiledTree(self.target)


def keypoint_voxel(points: np.ndarray, spacing: float, count: int, min_spacings: float) -> float:
    """The voxel edge (cloud units) at which ``points`` occupy about ``count`` voxels
    (``SearchConfig.keypoints`` for the standard keypoints), at least ``min_spacings * spacing``
    (``spacing``: the points' median spacing; ``min_spacings``: a gain,
    ``SearchConfig.scan.keypoint.min_voxel_spacings``)."""
    floor = min_spacings * spacing
    low, high = axis_bounds(points)
    # Start from a surface guess (the bounding box's largest face) and correct by the 1/v^2 law.
    faces = np.sort(high - low)[1:]
    # Floor relative to the extent (a cloud on a line has no face): the voxel is scale-free.
    voxel = max(float(np.sqrt(faces[0] * faces[1] / count)), floor, 1e-12 * float(faces[1]))
    for _ in range(4):
        occupied = _occupied(points, voxel, low)
        if abs(occupied - count) <= 0.1 * count:
            break
        voxel = max(voxel * float(np.sqrt(occupied / count)), floor)
        if voxel == floor:
            break
    return voxel


def _occupied(points: np.ndarray, voxel: float, low: np.ndarray) -> int:
    """The number of voxels of edge ``voxel`` that ``points`` occupy, the grid's corner at
    ``low`` (the points' per-axis minimum, computed once by the caller): the distinct integer cell
    coordinates of :func:`~esmicp.core.features.voxel_grid`'s grid, counted by one compiled hash
    pass with no copy of the points (the voxel search makes up to 4 counts: ``docs/speed.md``)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    occupied = _kernels.voxel_count(points, np.ascontiguousarray(low, dtype=np.float64), float(voxel))
    if occupied >= 0:
        return int(occupied)
    # A cell coordinate beyond the compiled grid's 2^62: the distinct floored coordinates.
    cells = np.floor((points - low) / voxel)
    repeats, _, _, _ = coincident_points(cells)
    return len(cells) - repeats
