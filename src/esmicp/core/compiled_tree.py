"""A compiled KD-tree (C++, :mod:`esmicp._kernels`): exact nearest neighbours, warm-started, on all cores.

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

import numpy as np

from .. import _kernels
from .procrustes import axis_bounds

#: Points per leaf, at most (count): a speed and memory trade of the tree's layout, every answer
#: exact whatever its value.
LEAF_SIZE = 8

#: Most neighbours :meth:`CompiledTree.query_k` returns per query (the kernels' bound, as are the
#: search stack's depth ``_kernels.STACK``: median splits give depth log2(M / LEAF_SIZE) + 1, 27
#: for 1e9 points).
K_MAX = _kernels.GRAPH_K_MAX


def available() -> bool:
    """True: the compiled kernels are built with the package (kept for callers that ask)."""
    return True


def threads(workers: int | None = None) -> int:
    """Threads for a kernel call: ``workers`` (a whole number >= 1), or 0 ("every core", as the
    kernels read it) for None. The number is always an argument, never a module setting."""
    return 0 if workers is None else int(workers)


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
    warm = np.full(len(points), -1, dtype=np.int64) if warm is None else np.ascontiguousarray(warm, dtype=np.int64)
    return points, rotation, translation, warm, np.empty(len(points)), np.empty(len(points), dtype=np.int64)


class CompiledTree:
    """KD-tree over a target cloud (compiled), for exact nearest-neighbour queries.

    Parameters
    ----------
    target : (M, 3) float64 array, M >= 1
        Target points (target frame); copied in tree order.
    workers : int or None
        Threads of the build (default: the calling thread alone; None: every core); the tree is the
        same whatever their number.
    """

    def __init__(self, target: np.ndarray, leaf_size: int = LEAF_SIZE, workers: int | None = 1):
        given = target
        target = np.ascontiguousarray(target, dtype=np.float64)
        # The caller's array when the tree was built from it or a view of it (no copy is kept alive).
        self._given = given if target is given or target.base is given else None
        if target.ndim != 2 or target.shape[1] != 3 or len(target) == 0:
            raise ValueError(f"CompiledTree needs an (M, 3) array with M >= 1 points, got shape {target.shape}")
        count = len(target)
        capacity = 1
        while capacity * leaf_size < count:
            capacity *= 2
        capacity = 2 * capacity + 1
        points = np.empty((count, 3))
        order = np.empty(count, dtype=np.int64)
        starts = np.empty(capacity, dtype=np.int64)
        ends = np.empty(capacity, dtype=np.int64)
        lefts = np.empty(capacity, dtype=np.int64)
        boxes = np.empty((capacity, 6))
        nodes = _kernels.build_tree(target, int(leaf_size), points, order, starts, ends, lefts, boxes,
                                     threads(workers))
        self.points, self.order = points, order
        self.starts, self.ends = starts[:nodes].copy(), ends[:nodes].copy()
        self.lefts, self.boxes = lefts[:nodes].copy(), boxes[:nodes].copy()
        self.rank = np.empty(len(target), dtype=np.int64)
        self.rank[self.order] = np.arange(len(target))

    def is_over(self, points: np.ndarray) -> bool:
        """True when this tree's points are ``points`` ((M, 3), in that order): the very array the
        tree was built from (which must not have changed since), or one equal to it."""
        if points is self._given:
            return True
        return len(self.points) == len(points) and np.array_equal(self.points[self.rank], points)

    def query(self, points: np.ndarray, transform: np.ndarray | None = None,
              warm: np.ndarray | None = None, workers: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(distances, indices)`` of the nearest target point of each of ``points`` (mapped by the
        4x4 ``transform`` first, if given; cloud units, indices into the target as given).
        ``warm`` (optional, (N,) target indices or -1) seeds each search; it changes only the speed."""
        points, rotation, translation, warm, distances, indices = query_arguments(points, transform, warm)
        _kernels.tree_query(points, rotation, translation, warm, self.rank, self.points,
                            self.order, self.starts, self.ends, self.lefts, self.boxes, distances, indices,
                            threads(workers))
        return distances, indices

    def query_k(self, points: np.ndarray, k: int, workers: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(distances, indices)``, each ``(N, k)``, of the ``k`` nearest target points of each of
        ``points``, nearest first (cloud units; indices into the target as given; a non-finite query
        gets infinite distances and index ``M``). ``1 <= k <= min(M, K_MAX)``."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        distances = np.empty((len(points), k))
        indices = np.empty((len(points), k), dtype=np.int64)
        _kernels.tree_knn(points, self.points, self.order, self.starts, self.ends, self.lefts, self.boxes,
                          distances, indices, threads(workers))
        return distances, indices


def k_nearest(points: np.ndarray, queries: np.ndarray, k: int, workers: int | None = None, *,
              tree_below: int = 50_000, cell_gain: float = 2.0, doublings: int = 2) -> np.ndarray:
    """``(Q, k)`` indices of the ``k`` nearest of ``points`` to each of ``queries``, nearest first:
    ``CompiledTree(points).query_k(queries, k)[1]`` (up to the order of points at equal distances),
    without building a tree over a large cloud for a few queries. Each query is answered from the
    points in the 27 voxels around its own (compiled; exact where the k-th lies within one voxel),
    the voxel doubled for those that it does not answer, and a tree answers the rest.

    The keywords trade speed only; the distances found are exact whatever their values.
    ``tree_below`` (count): clouds of at most this many points are answered by a tree, which costs
    little there, while a cloud's sparse parts make the cells large. ``cell_gain`` (gain): the first
    cell edge in the cloud's spacing (guessed from its bounding box) times ``sqrt(k)``: the k
    nearest of a query on a surface lie within about ``sqrt(k / pi)`` spacings. ``doublings``
    (count): times the cell is doubled for the queries it did not answer before a tree takes them."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
    if len(points) <= tree_below or not np.isfinite(queries).all():
        return CompiledTree(points, workers=workers).query_k(queries, k, workers=workers)[1]
    low, high = axis_bounds(points)
    faces = np.sort(high - low)[1:]
    spacing = float(np.sqrt(faces[0] * faces[1] / len(points)))
    cell = cell_gain * spacing * float(np.sqrt(k))
    indices = np.empty((len(queries), k), dtype=np.int64)
    pending = np.arange(len(queries))
    for _ in range(doublings + 1):
        if not len(pending) or not cell > 0:
            break
        found = np.empty((len(pending), k), dtype=np.int64)
        exact = np.empty(len(pending), dtype=np.uint8)
        _kernels.knn_in_cells(points, np.ascontiguousarray(queries[pending]), low, float(cell), found, exact,
                              threads(workers))
        answered = exact.view(bool)
        indices[pending[answered]] = found[answered]
        pending = pending[~answered]
        cell *= 2.0
    if len(pending):
        indices[pending] = CompiledTree(points, workers=workers).query_k(queries[pending], k, workers=workers)[1]
    return indices
