"""Exact nearest neighbours near the target, in O(1) per query, from a voxel hash (numba).

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

The kernels are compiled by numba on first use (cached on disk) and run on all cores
(``numba.prange``). Without numba, :func:`available` is False and callers use scipy's KD-tree.
"""

from __future__ import annotations

import numpy as np

from . import compiled_tree

try:  # numba is a dependency, but the library still works (slower) without it.
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

#: Fibonacci hashing multiplier (2^64 / golden ratio) for the cell keys.
_HASH_MULTIPLIER = np.uint64(0x9E3779B97F4A7C15)


def available() -> bool:
    """True when numba is importable, i.e. when :class:`VoxelHash` can be used."""
    return numba is not None


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def _slot(key, shift):
        return np.intp((np.uint64(key) * _HASH_MULTIPLIER) >> np.uint64(shift))

    @numba.njit(cache=True, nogil=True)
    def _build_table(cell_keys, table_bits):
        size = 1 << table_bits
        shift = 64 - table_bits
        mask = size - 1
        table_keys = np.full(size, -1, dtype=np.int64)
        table_cells = np.empty(size, dtype=np.int64)
        for cell in range(len(cell_keys)):
            slot = _slot(cell_keys[cell], shift)
            while table_keys[slot] != -1:
                slot = (slot + 1) & mask
            table_keys[slot] = cell_keys[cell]
            table_cells[slot] = cell
        return table_keys, table_cells

    @numba.njit(cache=True, nogil=True)
    def _find(table_keys, table_cells, key, shift, mask):
        slot = _slot(key, shift)
        while True:
            stored = table_keys[slot]
            if stored == key:
                return table_cells[slot]
            if stored == -1:
                return -1
            slot = (slot + 1) & mask

    @numba.njit(cache=True, nogil=True)
    def _hash_search(qx, qy, qz, best, best_index, sorted_points, cell_starts, table_keys, table_cells, low, cell,
                     dims, shift, mask):
        """Scan the 3 x 3 x 3 block of cells around ``(qx, qy, qz)``; returns the best
        ``(squared distance, sorted row)`` found, seeded by ``best`` / ``best_index``."""
        inverse_cell = 1.0 / cell
        limit = cell * cell
        fx = (qx - low[0]) * inverse_cell
        fy = (qy - low[1]) * inverse_cell
        fz = (qz - low[2]) * inverse_cell
        cx = np.int64(np.floor(fx))
        cy = np.int64(np.floor(fy))
        cz = np.int64(np.floor(fz))
        # Offsets of the query inside its cell, in cell units, for the box-distance bound.
        ox = fx - cx
        oy = fy - cy
        oz = fz - cz
        bound = limit if best > limit else best
        for dz in range(-1, 2):
            z = cz + dz
            if z < 0 or z >= dims[2]:
                continue
            gz = 0.0 if dz == 0 else ((oz if dz < 0 else 1.0 - oz) * cell)
            for dy in range(-1, 2):
                y = cy + dy
                if y < 0 or y >= dims[1]:
                    continue
                gy = 0.0 if dy == 0 else ((oy if dy < 0 else 1.0 - oy) * cell)
                for dx in range(-1, 2):
                    x = cx + dx
                    if x < 0 or x >= dims[0]:
                        continue
                    gx = 0.0 if dx == 0 else ((ox if dx < 0 else 1.0 - ox) * cell)
                    if gx * gx + gy * gy + gz * gz > bound:
                        continue
                    found = _find(table_keys, table_cells, x + dims[0] * (y + dims[1] * z), shift, mask)
                    if found < 0:
                        continue
                    for k in range(cell_starts[found], cell_starts[found + 1]):
                        ex = sorted_points[k, 0] - qx
                        ey = sorted_points[k, 1] - qy
                        ez = sorted_points[k, 2] - qz
                        squared = ex * ex + ey * ey + ez * ez
                        if squared < best:
                            best = squared
                            best_index = k
                            if squared < bound:
                                bound = squared
        return best, best_index

    @numba.njit(cache=True, parallel=True, nogil=True)
    def _query(
        queries, rotation, translation, warm, rank, sorted_points, sorted_index, cell_starts,
        table_keys, table_cells, low, cell, dims, tree_points, tree_order, tree_rank, tree_starts, tree_ends,
        tree_lefts, tree_boxes, use_hash, chunks, out_distances, out_indices,
    ):
        """Nearest target point of ``queries @ rotation.T + translation`` (rows), always exact:
        the hash block when the neighbour is within ``cell`` (and ``use_hash``), otherwise the
        compiled KD-tree, seeded with the best point seen. ``warm[i] >= 0`` is a candidate target
        index whose distance seeds the search (warm start). Returns the number of queries whose
        neighbour is farther than ``cell`` (those the hash cannot answer)."""
        table_bits = 0
        while (1 << table_bits) < len(table_keys):
            table_bits += 1
        shift = 64 - table_bits
        mask = len(table_keys) - 1
        limit = cell * cell
        count = queries.shape[0]
        misses = 0
        for chunk in numba.prange(chunks):
            stack_nodes = np.empty(compiled_tree.STACK, dtype=np.int64)
            stack_bounds = np.empty(compiled_tree.STACK, dtype=np.float64)
            chunk_misses = 0
            for i in range(chunk * count // chunks, (chunk + 1) * count // chunks):
                qx, qy, qz = compiled_tree.mapped(queries, i, rotation, translation)
                best = np.inf
                best_index = -1
                if warm[i] >= 0:
                    # Seed the bound with last iteration's neighbour (any target point gives a bound).
                    k = rank[warm[i]]
                    ex = sorted_points[k, 0] - qx
                    ey = sorted_points[k, 1] - qy
                    ez = sorted_points[k, 2] - qz
                    best = ex * ex + ey * ey + ez * ez
                    best_index = k
                if use_hash:
                    best, best_index = _hash_search(
                        qx, qy, qz, best, best_index, sorted_points, cell_starts, table_keys, table_cells, low,
                        cell, dims, shift, mask,
                    )
                if best <= limit and use_hash:
                    out_distances[i] = np.sqrt(best)
                    out_indices[i] = sorted_index[best_index]
                    continue
                slot = -1 if best_index < 0 else tree_rank[sorted_index[best_index]]
                best, slot = compiled_tree.nearest(
                    qx, qy, qz, best, slot, tree_points, tree_starts, tree_ends, tree_lefts, tree_boxes,
                    stack_nodes, stack_bounds,
                )
                if best > limit:
                    chunk_misses += 1
                out_distances[i] = np.sqrt(best)
                out_indices[i] = tree_order[slot] if slot >= 0 else tree_order.shape[0]  # none: M
            misses += chunk_misses
        return misses


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
        if numba is None:  # pragma: no cover
            raise RuntimeError("VoxelHash needs numba: pip install numba")
        target = np.ascontiguousarray(target, dtype=np.float64)
        self.cell = float(cell)
        self.low = target.min(axis=0) - self.cell
        extent = target.max(axis=0) + self.cell - self.low
        self.dims = np.maximum(np.ceil(extent / self.cell).astype(np.int64), 1)
        if float(np.prod(self.dims.astype(np.float64))) >= 2.0**62:
            raise ValueError(f"VoxelHash: cell {cell!r} is too small for the target's extent")
        ijk = np.floor((target - self.low) / self.cell).astype(np.int64)
        keys = ijk[:, 0] + self.dims[0] * (ijk[:, 1] + self.dims[1] * ijk[:, 2])
        order = np.argsort(keys, kind="stable")
        sorted_keys = keys[order]
        self.sorted_points = np.ascontiguousarray(target[order])
        self.sorted_index = order.astype(np.int64)
        self.rank = np.empty(len(target), dtype=np.int64)
        self.rank[order] = np.arange(len(target))
        boundaries = np.flatnonzero(np.diff(sorted_keys)) + 1
        self.cell_starts = np.concatenate([[0], boundaries, [len(target)]]).astype(np.int64)
        cell_keys = sorted_keys[self.cell_starts[:-1]]
        table_bits = max(4, int(np.ceil(np.log2(2 * len(cell_keys)))))
        self.table_keys, self.table_cells = _build_table(cell_keys, table_bits)
        self.occupied_cells = len(cell_keys)

    def query(
        self,
        points: np.ndarray,
        tree: "compiled_tree.CompiledTree",
        transform: np.ndarray | None = None,
        warm: np.ndarray | None = None,
        use_hash: bool = True,
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
            tree.boxes, bool(use_hash), compiled_tree.chunk_count(len(points)), distances, indices,
        )
        misses = compiled_tree.run_parallel(_query, *arguments)
        return distances, indices, int(misses)
