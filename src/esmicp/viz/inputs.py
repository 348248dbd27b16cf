"""Small inputs for the pictures: a few well-spread points of a cloud, and the paper's protocol
(the source is a moved copy of the target, in the same point order).

Every transform is ``T_target_source`` (``target ~= source @ R.T + t``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..core.procrustes import apply, bounding_box_diagonal, rigid_inverse, to_matrix
from ..errors import InvalidInputError
from ..shapes import asymmetric_shape
from ..types import as_count, as_points, as_real

#: Points of the built-in shape when no file is given (before any downsampling).
BUILTIN_POINTS = 1000


@dataclass(frozen=True, eq=False)
class PicturePair:
    """A source / target pair for the pictures, with a description for the figure titles.

    ``T_target_source`` is the true pose when known (moved copies), else None.
    """

    source: np.ndarray
    target: np.ndarray
    description: str
    T_target_source: np.ndarray | None = None


def farthest_point_subset(points, count: int) -> np.ndarray:
    """Indices (sorted) of ``count`` well-spread points: farthest-point sampling, deterministic.

    Starts at the point farthest from the centroid, then repeatedly adds the point farthest from
    the chosen ones. All indices when ``count >= len(points)``. O(count * N).
    """
    points = as_points(points, "points")
    count = as_count(count, "count")
    if count >= len(points):
        return np.arange(len(points))
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))
    nearest = np.linalg.norm(points - points[chosen[0]], axis=1)
    for k in range(1, count):
        chosen[k] = int(np.argmax(nearest))
        nearest = np.minimum(nearest, np.linalg.norm(points - points[chosen[k]], axis=1))
    return np.sort(chosen)


def downsample(points, count: int | None) -> np.ndarray:
    """``count`` well-spread points of ``points`` (:func:`farthest_point_subset`); None keeps all."""
    points = as_points(points, "points")
    if count is None:
        return points
    return points[farthest_point_subset(points, count)]


def moved_copy(cloud, *, angle_deg: float = 30.0, seed: int = 0, name: str = "cloud") -> PicturePair:
    """The paper's protocol: target = ``cloud``; source = the same points, same order, rotated by
    ``angle_deg`` degrees about a random axis (drawn from ``seed``) through the centroid and
    shifted by 5% of the diagonal. The pair is index-aligned, as ``esm-paper`` requires."""
    target = as_points(cloud, "cloud")
    angle = as_real(angle_deg, "angle_deg")
    if not 0.0 <= angle <= 180.0:
        raise InvalidInputError(f"angle_deg: expected a number in [0, 180], got {angle_deg!r}")
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rotation = Rotation.from_rotvec(np.radians(angle) * axis).as_matrix()
    direction = rng.normal(size=3)
    shift = 0.05 * bounding_box_diagonal(target) * direction / np.linalg.norm(direction)
    centroid = target.mean(axis=0)
    moved_by = to_matrix(rotation, centroid - rotation @ centroid + shift)
    source = apply(moved_by, target)
    description = f"{name}, {len(target)} points, source = copy rotated {angle:g} deg (same point order)"
    return PicturePair(source, target, description, rigid_inverse(moved_by))


def builtin_pair(*, points: int | None = None, angle_deg: float = 30.0, seed: int = 0) -> PicturePair:
    """:func:`moved_copy` of the built-in asymmetric shape (:mod:`esmicp.shapes`), downsampled to
    ``points`` well-spread points (None: :data:`BUILTIN_POINTS`)."""
    cloud = asymmetric_shape(BUILTIN_POINTS, np.random.default_rng(seed))
    cloud = downsample(cloud, points)
    return moved_copy(cloud, angle_deg=angle_deg, seed=seed, name="built-in shape")
