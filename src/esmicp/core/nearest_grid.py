"""Approximate nearest neighbours in O(1) per query, from a precomputed voxel lookup table.

The global search moves thousands of hypotheses' points every iteration, most of them far from
the target, where KD-tree queries are slowest (about 1 microsecond each here). A
:class:`NearestGrid` instead covers the target's bounding box (plus a margin) with cells, marks
the cells that hold target points, and runs one Euclidean feature transform to give every cell
its nearest occupied cell and so a target point (compiled, ``_kernels.nearest_grid``: the
separable transform that ``scipy.ndimage.distance_transform_edt`` computes, ties resolved as
SciPy resolves them, so the table equals the one SciPy's transform gives, at a fraction of its
cost: ``docs/speed.md``, "First call"). A query is then an array lookup; the returned distance is the
exact distance to the returned point, which is the nearest one up to about one cell size. Points
outside the grid use the border cell they project onto.
"""

from __future__ import annotations

import numpy as np

from .. import _kernels
from .procrustes import axis_bounds


class NearestGrid:
    """Nearest-target-point lookup table over a regular grid.

    Parameters
    ----------
    target : (M, 3) float64 array
        Target points (kept by reference).
    cell : float
        Cell edge length (cloud units); the approximation error of a query is at most about
        ``sqrt(3) * cell``.
    margin : float
        How far beyond the target's bounding box the grid extends (cloud units).
    max_cells : int
        Upper bound on the number of cells; ``cell`` grows if needed to respect it.
    """

    def __init__(self, target: np.ndarray, cell: float, *, margin: float, max_cells: int = 2_000_000):
        self.points = target
        low, high = axis_bounds(target)
        low = low - margin
        extent = high + margin - low
        cell = max(cell, float(np.prod(extent) / max_cells) ** (1.0 / 3.0), 1e-12 * float(extent.max()))
        self.cell = cell
        self.low = low
        self.shape = np.maximum(np.ceil(extent / cell).astype(np.intp), 1)
        #: ``(prod(shape),)`` int64: the target index of each cell (C order), what a query returns:
        #: the last target point (in input order) of the cell's nearest occupied cell.
        self.lookup = np.empty(int(np.prod(self.shape)), dtype=np.int64)
        _kernels.nearest_grid(np.ascontiguousarray(target, dtype=np.float64),
                              np.ascontiguousarray(low, dtype=np.float64), float(cell), self.shape.astype(np.int64),
                              self.lookup)

    def __len__(self) -> int:
        return len(self.points)

    def _cell_index(self, points: np.ndarray) -> np.ndarray:
        ijk = np.floor((points - self.low) / self.cell).astype(np.intp)
        np.clip(ijk, 0, self.shape - 1, out=ijk)
        return np.ravel_multi_index(tuple(ijk.T), tuple(self.shape))

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(distances, indices)`` of each point's (approximately) nearest target point."""
        indices = self.lookup[self._cell_index(points)]
        distances = np.linalg.norm(points - self.points[indices], axis=1)
        return distances, indices
