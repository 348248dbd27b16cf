"""Exact nearest neighbours near the target, in O(1) per query, from a voxel hash (compiled).

Local registration asks, every iteration, for the nearest target point of every source point, and
once the clouds are roughly aligned almost all of those lie within a few point spacings. A
:class:`VoxelHash` sorts the target points into cubic cells of edge ``cell`` (cloud units), keeps
the occupied cells in an open-addressing hash table, and answers a query by scanning the 3 x 3 x 3
block of cells around the query point, nearest cells first and pruned by the best distance found
so far (optionally seeded with a *warm start*: the distance to last iteration's neighbour).

Exactness: every target point within ``cell`` of a query lies in that block, so a result found
at a distance ``<= cell`` is THE nearest point (up to exact ties). Queries whose nearest point is
farther (misses) continue, in the same compiled loop, in a
:class:`~esmicp.core.compiled_tree.CompiledTree` of the target, seeded with the best point the
block gave. The answer is therefore exact everywhere; the hash only makes the common case (a point
near the target) cheap.

The kernels are C++ (:mod:`esmicp._kernels`, built at install time) and run on ``workers`` threads.
A cell holding more than ``_kernels.CELL_SCAN_MAX`` points (coincident points: a depth sensor's
invalid pixels stored as (0, 0, 0)) is not scanned: such queries go to the tree, whose cost stays
logarithmic, so duplicates cannot make the search quadratic.
"""

from __future__ import annotations

import numpy as np

from . import compiled_tree
from .procrustes import axis_bounds

from .. import _kernels


def available() -> bool:
    """True: the compiled kernels are built with the package."""
    return True


class VoxelHash:
    """Voxel hash over a target cloud for exact near-field nearest-neighbour queries.

    Parameters
    ----------
    target : (M, 3) float64 array
        Target points (target frame); copied in cell order.
    cell : float
        Cell edge (cloud units, > 0): queries whose nearest target point is within ``cell`` are
        answered exactly; farther ones are misses. A few target point spacings suits ICP.
    """

    def __init__(self, target: np.ndarray, cell: float):
        target = np.ascontiguousarray(target, dtype=np.float64)
        self.cell = float(cell)
        low, high = axis_bounds(target)
        self.low = low - self.cell
        extent = high + self.cell - self.low
        self.dims = np.maximum(np.ceil(extent / self.cell).astype(np.int64), 1)
        if float(np.prod(self.dims.astype(np.float64))) >= 2.0**62:
            raise ValueError(f"VoxelHash: cell {cell!r} is too small for the target's extent")
        # Each point's cell key, the points sorted stably by it (compiled: the permutation of a stable
        # argsort of the keys), and each point's rank in that order.
        sorted_keys = np.empty(len(target), dtype=np.int64)
        self.sorted_index = np.empty(len(target), dtype=np.int64)
        self.sorted_points = np.empty_like(target)
        self.rank = np.empty(len(target), dtype=np.int64)
        _kernels.cell_order(target, np.ascontiguousarray(self.low, dtype=np.float64), self.cell,
                            np.ascontiguousarray(self.dims, dtype=np.int64), sorted_keys, self.sorted_index,
                            self.sorted_points, self.rank)
        boundaries = np.flatnonzero(np.diff(sorted_keys)) + 1
        self.cell_starts = np.concatenate([[0], boundaries, [len(target)]]).astype(np.int64)
        cell_keys = sorted_keys[self.cell_starts[:-1]]
        table_bits = max(4, int(np.ceil(np.log2(2 * len(cell_keys)))))
        self.table_keys = np.empty(1 << table_bits, dtype=np.int64)
        self.table_cells = np.empty(1 << table_bits, dtype=np.int64)
        _kernels.build_table(np.ascontiguousarray(cell_keys, dtype=np.int64), self.table_keys, self.table_cells)
        self.low = np.ascontiguousarray(self.low, dtype=np.float64)
        self.dims = np.ascontiguousarray(self.dims, dtype=np.int64)
        self.occupied_cells = len(cell_keys)

    def query(
        self,
        points: np.ndarray,
        tree: "compiled_tree.CompiledTree",
        transform: np.ndarray | None = None,
        warm: np.ndarray | None = None,
        use_hash: bool = True,
        workers: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """``(distances, indices, misses)``: the nearest target point of each of ``points`` (mapped
        by the 4x4 ``transform`` first, if given), exact for every point. ``tree`` (a
        :class:`~esmicp.core.compiled_tree.CompiledTree` of the same target) answers the points
        whose neighbour is farther than ``cell`` (``misses`` counts them, with or without the
        hash), or every point when ``use_hash`` is False; ``warm`` (optional target indices) seeds each search."""
        points, rotation, translation, warm, distances, indices = compiled_tree.query_arguments(points, transform, warm)
        arguments = (
            points, rotation, translation, warm, self.rank, self.sorted_points,
            self.sorted_index, self.cell_starts, self.table_keys, self.table_cells, self.low,
            self.cell, self.dims, tree.points, tree.order, tree.rank, tree.starts, tree.ends, tree.lefts,
            tree.boxes, bool(use_hash), distances, indices, compiled_tree.threads(workers),
        )
        misses = _kernels.hash_query(*arguments)
        return distances, indices, int(misses)
