"""A KD-tree compiled by numba: exact nearest neighbours, warm-started, on all cores.

Local registration asks every iteration for the nearest target point of every source point, and
last iteration's neighbour is a good guess: its distance bounds the search from the start, so only
the few nodes nearer than that bound are visited. :class:`CompiledTree` is built once per target
(median splits, so its depth is ``log2(M / LEAF_SIZE)`` whatever the data, duplicates included)
and answers in compiled code, with no Python per query and no miss to hand elsewhere: it is exact
for every query, near the target or not, dense or sparse (a LiDAR scan's density varies with
range by orders of magnitude, which defeats any single voxel size).

Points are stored in tree order (each leaf contiguous in memory), each node with its bounding box;
a node is skipped when its box is farther than the best distance found so far.
"""

from __future__ import annotations

import warnings

import numpy as np

try:  # numba is a dependency, but the library still works (slower) without it.
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

#: Points per leaf (at most).
LEAF_SIZE = 8

#: Queries of fewer points than this run on one thread. Measured here on the bunny (warm
#: starts): 1,000 points 100 us on one thread, 52 us on both.
PARALLEL_MIN = 512

#: Depth of the search stack: median splits give depth log2(M / LEAF_SIZE) + 1 (27 for 1e9 points).
STACK = 96


def available() -> bool:
    """True when numba is importable, i.e. when :class:`CompiledTree` can be used."""
    return numba is not None


if numba is not None:

    @numba.njit(cache=True, nogil=True, inline="always")
    def mapped(points, i, rotation, translation):
        """``rotation @ points[i] + translation`` as three floats (the point placed by a pose)."""
        x = rotation[0, 0] * points[i, 0] + rotation[0, 1] * points[i, 1] + rotation[0, 2] * points[i, 2] + translation[0]
        y = rotation[1, 0] * points[i, 0] + rotation[1, 1] * points[i, 1] + rotation[1, 2] * points[i, 2] + translation[1]
        z = rotation[2, 0] * points[i, 0] + rotation[2, 1] * points[i, 1] + rotation[2, 2] * points[i, 2] + translation[2]
        return x, y, z

    @numba.njit(cache=True, nogil=True)
    def _select(order, coordinates, start, end, nth):
        """Reorder ``order[start:end]`` so that ``order[nth]`` holds the element of rank ``nth`` by
        ``coordinates`` (smaller before, larger-or-equal after); three-way partitions, so runs
        of equal values (duplicated points) cost linear time."""
        low, high = start, end - 1
        while high > low:
            a, b, c = coordinates[order[low]], coordinates[order[(low + high) // 2]], coordinates[order[high]]
            pivot = max(min(a, b), min(max(a, b), c))  # median of three
            less, i, greater = low, low, high
            while i <= greater:
                value = coordinates[order[i]]
                if value < pivot:
                    order[less], order[i] = order[i], order[less]
                    less += 1
                    i += 1
                elif value > pivot:
                    order[greater], order[i] = order[i], order[greater]
                    greater -= 1
                else:
                    i += 1
            if nth < less:
                high = less - 1
            elif nth > greater:
                low = greater + 1
            else:
                return

    @numba.njit(cache=True, nogil=True)
    def _build(points, leaf_size):
        count = points.shape[0]
        capacity = 1
        while capacity * leaf_size < count:
            capacity *= 2
        capacity = 2 * capacity + 1
        starts = np.empty(capacity, dtype=np.int64)
        ends = np.empty(capacity, dtype=np.int64)
        lefts = np.full(capacity, -1, dtype=np.int64)
        boxes = np.empty((capacity, 6), dtype=np.float64)
        order = np.arange(count, dtype=np.int64)
        columns = np.ascontiguousarray(points.T)
        stack = np.empty(2 * STACK, dtype=np.int64)
        starts[0], ends[0] = 0, count
        nodes = 1
        depth = 1
        stack[0] = 0
        while depth > 0:
            depth -= 1
            node = stack[depth]
            start, end = starts[node], ends[node]
            for axis in range(3):
                low, high = np.inf, -np.inf
                for k in range(start, end):
                    value = columns[axis, order[k]]
                    low = min(low, value)
                    high = max(high, value)
                boxes[node, axis], boxes[node, 3 + axis] = low, high
            if end - start <= leaf_size:
                continue
            axis = 0
            for candidate in range(1, 3):
                if boxes[node, 3 + candidate] - boxes[node, candidate] > boxes[node, 3 + axis] - boxes[node, axis]:
                    axis = candidate
            middle = (start + end) // 2
            _select(order, columns[axis], start, end, middle)
            left = nodes
            nodes += 2
            lefts[node] = left
            starts[left], ends[left] = start, middle
            starts[left + 1], ends[left + 1] = middle, end
            stack[depth] = left
            stack[depth + 1] = left + 1
            depth += 2
        tree_points = np.empty((count, 3), dtype=np.float64)
        for k in range(count):
            tree_points[k, 0] = points[order[k], 0]
            tree_points[k, 1] = points[order[k], 1]
            tree_points[k, 2] = points[order[k], 2]
        return tree_points, order, starts[:nodes], ends[:nodes], lefts[:nodes], boxes[:nodes]

    @numba.njit(cache=True, nogil=True, inline="always")
    def _box_distance(boxes, node, x, y, z):
        total = 0.0
        gap = boxes[node, 0] - x
        if gap > 0.0:
            total += gap * gap
        else:
            gap = x - boxes[node, 3]
            if gap > 0.0:
                total += gap * gap
        gap = boxes[node, 1] - y
        if gap > 0.0:
            total += gap * gap
        else:
            gap = y - boxes[node, 4]
            if gap > 0.0:
                total += gap * gap
        gap = boxes[node, 2] - z
        if gap > 0.0:
            total += gap * gap
        else:
            gap = z - boxes[node, 5]
            if gap > 0.0:
                total += gap * gap
        return total

    @numba.njit(cache=True, nogil=True)
    def nearest(x, y, z, best, best_slot, tree_points, starts, ends, lefts, boxes, stack_nodes, stack_bounds):
        """Nearest tree point of ``(x, y, z)``: ``(squared distance, slot)`` (slot = row of
        ``tree_points``). ``best`` / ``best_slot`` seed the search (``np.inf`` / -1 for none): any
        point's squared distance and slot are correct seeds, a close one makes the search short.
        ``stack_nodes`` / ``stack_bounds``: scratch arrays of ``STACK`` entries (one per thread)."""
        stack_nodes[0] = 0
        stack_bounds[0] = _box_distance(boxes, 0, x, y, z)
        depth = 1
        while depth > 0:
            depth -= 1
            node = stack_nodes[depth]
            if stack_bounds[depth] >= best:
                continue
            left = lefts[node]
            if left < 0:
                for k in range(starts[node], ends[node]):
                    ex = tree_points[k, 0] - x
                    ey = tree_points[k, 1] - y
                    ez = tree_points[k, 2] - z
                    squared = ex * ex + ey * ey + ez * ez
                    if squared < best:
                        best = squared
                        best_slot = k
                continue
            near_bound = _box_distance(boxes, left, x, y, z)
            far_bound = _box_distance(boxes, left + 1, x, y, z)
            near, far = left, left + 1
            if far_bound < near_bound:
                near, far = far, near
                near_bound, far_bound = far_bound, near_bound
            if far_bound < best:
                stack_nodes[depth] = far
                stack_bounds[depth] = far_bound
                depth += 1
            if near_bound < best:
                stack_nodes[depth] = near
                stack_bounds[depth] = near_bound
                depth += 1
        return best, best_slot

    @numba.njit(cache=True, nogil=True, inline="always")
    def _query_one(i, queries, rotation, translation, warm, rank, tree_points, order, starts, ends, lefts, boxes,
                   out_distances, out_indices, stack_nodes, stack_bounds):
        x, y, z = mapped(queries, i, rotation, translation)
        best, slot = np.inf, -1
        if warm[i] >= 0:
            slot = rank[warm[i]]
            ex = tree_points[slot, 0] - x
            ey = tree_points[slot, 1] - y
            ez = tree_points[slot, 2] - z
            best = ex * ex + ey * ey + ez * ez
        best, slot = nearest(x, y, z, best, slot, tree_points, starts, ends, lefts, boxes, stack_nodes, stack_bounds)
        out_distances[i] = np.sqrt(best)
        # No point found (a NaN query): index M, as scipy's tree answers, so that it cannot pass
        # for a neighbour.
        out_indices[i] = order[slot] if slot >= 0 else order.shape[0]

    @numba.njit(cache=True, parallel=True, nogil=True)
    def _query(queries, rotation, translation, warm, rank, tree_points, order, starts, ends, lefts, boxes,
               out_distances, out_indices, chunks):
        count = queries.shape[0]
        for chunk in numba.prange(chunks):
            stack_nodes = np.empty(STACK, dtype=np.int64)
            stack_bounds = np.empty(STACK, dtype=np.float64)
            for i in range(chunk * count // chunks, (chunk + 1) * count // chunks):
                _query_one(i, queries, rotation, translation, warm, rank, tree_points, order, starts, ends, lefts,
                           boxes, out_distances, out_indices, stack_nodes, stack_bounds)


_threads_started = False


def run_parallel(kernel, *arguments):
    """``kernel(*arguments)``; on the process's first parallel call, numba picks its threading
    layer and warns when it finds an old TBB (which some wheels bring) before settling on OpenMP:
    not the user's concern, so that warning is silenced."""
    global _threads_started
    if _threads_started:
        return kernel(*arguments)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TBB.*")
        value = kernel(*arguments)
    _threads_started = True
    return value


def query_arguments(points: np.ndarray, transform: np.ndarray | None, warm: np.ndarray | None):
    """``(points, rotation, translation, warm, distances, indices)`` as the query kernels take them:
    contiguous float64 points, the rotation and translation of the 4x4 ``transform`` (identity for
    None), the warm-start indices (-1: none) and the two output arrays."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if transform is None:
        rotation, translation = np.eye(3), np.zeros(3)
    else:
        rotation = np.ascontiguousarray(transform[:3, :3], dtype=np.float64)
        translation = np.ascontiguousarray(transform[:3, 3], dtype=np.float64)
    warm = np.full(len(points), -1, dtype=np.int64) if warm is None else np.asarray(warm, dtype=np.int64)
    return points, rotation, translation, warm, np.empty(len(points)), np.empty(len(points), dtype=np.int64)


def chunk_count(count: int, per_thread: int = 4) -> int:
    """How many pieces a parallel pass over ``count`` points is cut into: one below
    :data:`PARALLEL_MIN` (no thread is woken), otherwise ``per_thread`` per thread (several for
    queries, whose cost varies from point to point; measured on the bunny at 1k-100k points, 1 to
    64 pieces per thread give the same query time)."""
    if count < PARALLEL_MIN:
        return 1
    return min(count, per_thread * numba.get_num_threads())


class CompiledTree:
    """KD-tree over a target cloud (numba), for exact nearest-neighbour queries.

    Parameters
    ----------
    target : (M, 3) float64 array, M >= 1
        Target points (target frame); copied in tree order.
    """

    def __init__(self, target: np.ndarray, leaf_size: int = LEAF_SIZE):
        if numba is None:  # pragma: no cover
            raise RuntimeError("CompiledTree needs numba: pip install numba")
        target = np.ascontiguousarray(target, dtype=np.float64)
        if target.ndim != 2 or target.shape[1] != 3 or len(target) == 0:
            raise ValueError(f"CompiledTree needs an (M, 3) array with M >= 1 points, got shape {target.shape}")
        self.points, self.order, self.starts, self.ends, self.lefts, self.boxes = _build(target, leaf_size)
        self.rank = np.empty(len(target), dtype=np.int64)
        self.rank[self.order] = np.arange(len(target))

    def query(self, points: np.ndarray, transform: np.ndarray | None = None,
              warm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(distances, indices)`` of the nearest target point of each of ``points`` (mapped by the
        4x4 ``transform`` first, if given; cloud units, indices into the target as given).
        ``warm`` (optional, (N,) target indices or -1) seeds each search; it changes only the speed."""
        points, rotation, translation, warm, distances, indices = query_arguments(points, transform, warm)
        run_parallel(_query, points, rotation, translation, warm, self.rank, self.points,
               self.order, self.starts, self.ends, self.lefts, self.boxes, distances, indices,
               chunk_count(len(points)))
        return distances, indices
