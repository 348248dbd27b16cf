"""A built-in test shape, so that demos and benchmarks run with no data files.

The shape has no rotational or mirror symmetry, so every rigid transform of it is identifiable.
"""

from __future__ import annotations

import numpy as np

from .types import as_generator


def _sphere_directions(rng: np.random.Generator, count: int) -> np.ndarray:
    directions = rng.normal(size=(count, 3))
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)


def asymmetric_shape(num_points: int = 2000, rng=None) -> np.ndarray:
    """Sample ``num_points`` points on the surface of an asymmetric compound object.

    The object (about 2.4 units across, centred near the origin) is an ellipsoid body with radii
    1.0 / 0.6 / 0.4, a sphere "head" off one corner, a cylindrical "arm" and a small box, each
    placed off every symmetry axis of the others. Points are spread over the parts in proportion
    to their (approximate) surface areas.

    Parameters
    ----------
    num_points : int
        Number of points (>= 4).
    rng : None, int or numpy.random.Generator
        Seed or generator; the same seed gives the same points.

    Returns
    -------
    (num_points, 3) float64 array
    """
    if num_points < 4:
        raise ValueError(f"num_points: need at least 4, got {num_points}")
    rng = as_generator(rng)
    parts = [_ellipsoid, _head, _arm, _box]
    areas = np.array([8.0, 1.54, 0.7, 0.54])
    counts = rng.multinomial(num_points, areas / areas.sum())
    points = np.concatenate([part(rng, count) for part, count in zip(parts, counts)])
    return points[rng.permutation(len(points))]


def _ellipsoid(rng, count):
    return _sphere_directions(rng, count) * [1.0, 0.6, 0.4]


def _head(rng, count):
    return _sphere_directions(rng, count) * 0.35 + [0.9, 0.45, 0.25]


def _arm(rng, count):
    angle = rng.uniform(0, 2 * np.pi, count)
    along = rng.uniform(0.0, 0.9, count)
    # A cylinder of radius 0.12 along y, leaning in x, starting inside the body.
    return np.column_stack([-0.55 + 0.12 * np.cos(angle) + 0.3 * along, -0.2 - along, 0.15 + 0.12 * np.sin(angle)])


def _box(rng, count):
    half = np.array([0.25, 0.15, 0.1])
    face = rng.integers(0, 6, count)
    axis, sign = face // 2, np.where(face % 2 == 0, 1.0, -1.0)
    points = rng.uniform(-1.0, 1.0, (count, 3)) * half
    points[np.arange(count), axis] = sign * half[axis]
    return points + [0.1, 0.1, -0.45]
