"""Approximate nearest neighbours in O(1) per query, from a precomputed voxel lookup table.

The global search moves thousands of hypotheses' points every iteration, most of them far from
the target, where KD-tree queries are slowest (about 1 microsecond each here). A
:class:`NearestGrid` instead covers the target's bounding box (plus a margin) with cells, marks
the cells that hold target points, and runs one exact Euclidean feature transform (the compiled
``_kernels.nearest_occupied``, what ``scipy.ndimage.distance_transform_edt`` with
``return_indices=True`` computes, without importing SciPy) to give every cell its nearest occupied
cell and so a target point. A query is then an array lookup; the returned distance is the exact distance to the
returned point, which is the nearest one up to about one cell size. Points outside the grid use
the border cell they project onto.
"""

from __future__ import annotations

import numpy as np

from .. import _kernels


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
        low = target.min(axis=0) - margin
        extent = target.max(axis=0) + margin - low
        cell = max(cell, float(np.prod(extent) / max_cells) ** (1.0 / 3.0), 1e-12 * float(extent.max()))
        self.cell = cell
        self.low = low
        self.shape = np.maximum(np.ceil(extent / cell).astype(np.intp), 1)
        cells = self._cell_index(target)
        occupied = np.zeros(int(np.prod(self.shape)), dtype=bool)
        occupied[cells] = True
        representative = np.empty(len(occupied), dtype=np.intp)
        representative[cells] = np.arange(len(target))
        nearest_cell = np.empty(len(occupied), dtype=np.int64)
        _kernels.nearest_occupied(occupied.view(np.uint8).reshape(self.shape), nearest_cell)
        #: ``(prod(shape),)`` int64: the target index of each cell (C order), what a query returns.
        self.lookup = representative[nearest_cell].astype(np.int64, copy=False)

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
