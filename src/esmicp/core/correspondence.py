"""Nearest-neighbour correspondences against a target cloud.

A :class:`NearestNeighbors` index is built once per target and queried every iteration (and, later,
by every hypothesis of a global search). :meth:`NearestNeighbors.query` answers any query exactly
with a compiled KD-tree (:mod:`esmicp.core.compiled_tree`, C++ built at install time); :meth:`NearestNeighbors.query_near` gives the same exact answers faster when
most query points lie near the target (local registration): warm-started with last iteration's
neighbours, through a voxel hash (:mod:`esmicp.core.voxel_hash`) that hands the points it cannot
answer to the compiled tree in the same compiled loop. Both are built on first use.
"""

from __future__ import annotations

import numpy as np

from .. import _kernels
from . import compiled_tree, voxel_hash
from .config import NeighbourIndexConfig
from .procrustes import axis_bounds


def coincident_points(points: np.ndarray) -> tuple[int, int, int, np.ndarray]:
    """``(repeats, most_index, most_count, first)`` of ``(N, 3)`` points, in one O(N) pass (a hash
    of exact coordinates): how many points equal an earlier one, the index of the most repeated
    point and its number of occurrences, and a boolean mask of the first occurrence of each
    distinct point."""
    first = np.empty(len(points), dtype=np.uint8)
    repeats, most, most_count = _kernels.coincident(np.ascontiguousarray(points, dtype=np.float64), first)
    return int(repeats), int(most), int(most_count), first.view(bool)


class NearestNeighbors:
    """KD-tree over a target cloud; queries run on ``workers`` threads.

    Parameters
    ----------
    target : (M, 3) float64 array
        The cloud to search in (target frame). Kept by reference: do not mutate it afterwards.
    workers : int or None
        Threads of every compiled call made through this index (queries, and the steps of the
        local loop that uses it); None uses every core.
    config : NeighbourIndexConfig or None
        When the voxel hash and the neighbour graph answer (speed only; None: the defaults).
    """

    def __init__(self, target: np.ndarray, *, workers: int | None = None,
                 config: NeighbourIndexConfig | None = None):
        self.points = target
        self.workers = workers
        self.config = NeighbourIndexConfig() if config is None else config
        self._compiled: compiled_tree.CompiledTree | None = None
        self._spacing: float | None = None
        self._near: voxel_hash.VoxelHash | None = None
        self._hash_misses = 0.0  # fraction of the last near query's points beyond one hash cell
        self._index: "_kernels.Index | None" = None  # the compiled index of :meth:`step`
        self._coincident: tuple[int, int, int, np.ndarray] | None = None
        self._index_hashed = False
        self._index_graphed = False
        self._step_rmse = np.inf  # RMS distance of the last step's pairs
        self._axis_bounds: tuple[np.ndarray, np.ndarray] | None = None

    def exact_tree(self) -> "compiled_tree.CompiledTree":
        """The compiled KD-tree of the target (built on first use)."""
        if self._compiled is None:
            self._compiled = compiled_tree.CompiledTree(self.points, workers=self.workers)
        return self._compiled

    def __len__(self) -> int:
        return len(self.points)

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The target's per-axis ``(low, high)`` (computed once)."""
        if self._axis_bounds is None:
            self._axis_bounds = axis_bounds(self.points)
        return self._axis_bounds

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(distances, indices)`` of each point's nearest target point.

        ``distances`` are Euclidean, in the clouds' units; ``indices`` index ``self.points``.
        """
        return self.exact_tree().query(points, workers=self.workers)

    def query_near(
        self, points: np.ndarray, warm: np.ndarray | None = None, transform: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Exactly what :meth:`query` returns (up to ties), faster for points near the target.

        ``transform`` (optional 4x4 ``T_target_source``): query ``points`` as mapped by it (no
        mapped copy is made). ``warm`` (optional, (N,) target indices, e.g. last iteration's
        ``indices``) seeds each search with that candidate's distance; any valid index is correct,
        only the speed changes. From ``config.near_query_min`` points on, a voxel hash answers the
        points whose neighbour is within a few spacings, the compiled tree the rest.
        """
        tree = self.exact_tree()
        near = self._near_index() if len(points) >= self.config.near_query_min else None
        if near is None:
            return tree.query(points, transform=transform, warm=warm, workers=self.workers)
        use_hash = self._hash_misses <= self.config.hash_miss_limit
        distances, indices, misses = near.query(points, tree, transform=transform, warm=warm, use_hash=use_hash,
                                                workers=self.workers)
        self._hash_misses = misses / len(points)
        return distances, indices

    def step(self, source: np.ndarray, transformation: np.ndarray, indices: np.ndarray, distances: np.ndarray,
             out: np.ndarray, *, warm: bool, weighting: np.ndarray, objective_sigma: float,
             reject_below: float = -np.inf) -> np.ndarray:
        """One local iteration in one compiled call: the nearest target point of each source point
        as placed by ``transformation`` (exactly what :meth:`query_near` returns, written into
        ``indices`` and ``distances``; ``warm``: ``indices`` holds last iteration's neighbours), the
        weights, the pair moments, the Kabsch increment and the composed pose, into ``out``.

        ``source`` (N, 3) and ``transformation`` (4, 4) are C-contiguous float64; ``indices`` (N,)
        int64 and ``distances`` (N,) float64 are filled in place. ``weighting`` is
        ``(fixed sigma or 0, sigma floor, factor on the median distance, 1 in the fine phase, 1 for
        Gaussian weights / 0 for weights of 1)``; ``objective_sigma`` > 0 asks for the mean
        Gaussian similarity at that sigma too; when that is below ``reject_below`` (the trial of an
        accelerated pose that fits worse than the pose it came from) the call stops after the
        queries, and ``out`` holds only the RMS distance, the objective, the misses and the flag.
        ``out`` (``_kernels.STEP_OUT``): sigma, RMS distance, objective, misses, effective pairs,
        increment angle and translation norm, increment rotation (9) and translation (3), the
        composed pose (16), its motion (angle, translation norm), sum of weights, sum of squared
        weights, 1.0 if the call stopped below ``reject_below`` (else 0.0), the number of queries
        the graph walk answered.

        Near convergence (the last step's RMS distance within ``config.graph_rms_spacings``
        target spacings) each warm-started query first walks a neighbour graph of the target
        from its last neighbour, and takes the point the walk certifies as the exact nearest
        (every nearer point would be in that point's list); the others go to the hash and the
        tree as before. The graph is built then, once per target (or by :meth:`prepare_step`).
        """
        config = self.config
        near = len(source) >= config.near_query_min
        index = self._compiled_index(near)
        use_hash = bool(near and self._index_hashed and self._hash_misses <= config.hash_miss_limit)
        use_graph = bool(warm and use_hash and self._step_rmse <= config.graph_rms_spacings * self.spacing())
        if use_graph:
            self._step_graph()  # built once, when the warm starts first come near the target
        index.step(source, transformation, indices, distances, warm, use_hash, use_graph, weighting, objective_sigma,
                   reject_below, out, compiled_tree.threads(self.workers))
        self._step_rmse = float(out[1])
        if near and self._index_hashed:
            self._hash_misses = float(out[3]) / len(source)
        return out

    def prepare_step(self, count: int) -> None:
        """Build now what :meth:`step` uses for ``count`` source points (the compiled index, the
        voxel hash, the neighbour graph), which it otherwise builds on first use (the graph at
        the first warm-started step near the target): benchmarks time the builds apart."""
        self._compiled_index(count >= self.config.near_query_min)
        self._step_graph()

    def _step_graph(self) -> None:
        """The target's neighbour graph (``config.graph_neighbours`` each, from the voxel hash) in
        the compiled index; none without the hash (fewer than ``config.near_query_min`` queries)."""
        neighbours = self.config.graph_neighbours
        if neighbours and self._index_hashed and not self._index_graphed:
            self._index.build_graph(min(neighbours, len(self.points)), compiled_tree.threads(self.workers))
            self._index_graphed = True

    def _compiled_index(self, hashed: bool) -> "_kernels.Index":
        if self._index is None:
            tree = self.exact_tree()
            self._target_c = np.ascontiguousarray(self.points, dtype=np.float64)
            self._index = _kernels.Index(self._target_c, tree.points, tree.order, tree.rank, tree.starts, tree.ends,
                                         tree.lefts, tree.boxes)
        if hashed and not self._index_hashed:
            near = self._near_index()
            if near is not None:
                self._index.set_hash(near.sorted_points, near.sorted_index, near.rank, near.cell_starts,
                                     near.table_keys, near.table_cells, near.low, near.cell, near.dims)
                self._index_hashed = True
        return self._index

    def spatial_order(self, points: np.ndarray) -> np.ndarray:
        """A permutation of ``points`` (target frame) that sorts them by voxel-hash cell.

        Queries in this order touch the target's memory coherently, which roughly halves the CPU
        time of :meth:`query_near` on large targets (``docs/design.md``, "Measured design choices").
        """
        near = self._near_index()
        cell = near.cell if near is not None else max(self.config.near_cell_spacings * self.spacing(), 1e-12)
        low = self._bounds()[0]
        ijk = np.floor((points - low) / cell).astype(np.int64)
        ijk_low, ijk_high = axis_bounds(ijk)
        ijk -= ijk_low
        dims = ijk_high - ijk_low + 1
        return np.argsort(ijk[:, 0] + dims[0] * (ijk[:, 1] + dims[1] * ijk[:, 2]), kind="stable")

    def _near_index(self) -> "voxel_hash.VoxelHash | None":
        if self._near is None:
            spacing = self.spacing() if self._spacing is None else self._spacing
            low, high = self._bounds()
            diagonal = float(np.linalg.norm(high - low))
            cell = max(self.config.near_cell_spacings * spacing, 1e-6 * diagonal)
            if cell > 0:
                self._near = voxel_hash.VoxelHash(self.points, cell)
        return self._near

    def coincident(self) -> tuple[int, int, int, np.ndarray]:
        """:func:`coincident_points` of the target (computed once)."""
        if self._coincident is None:
            self._coincident = coincident_points(self.points)
        return self._coincident

    def spacing(self, max_samples: int = 5000) -> float:
        """Median distance from a target point to its nearest *distinct* target point (cloud units).

        Uses an evenly strided subset of at most ``max_samples`` points, so the value is
        deterministic and cheap on large clouds. Duplicated points are looked past (the nearest
        neighbour among the distinct target points), so a cloud full of coincident points costs no
        more than one without. Returns 0.0 only if no sampled point has a distinct neighbour.
        Computed once for the default argument, by the compiled tree: the second nearest point of
        each sampled point, itself being the first (SciPy's k-nearest query gave the same value
        at several times the cost: ``docs/speed.md``, "First call").
        """
        default = max_samples == 5000
        if default and self._spacing is not None:
            return self._spacing
        count = len(self.points)
        sample = self.points[np.linspace(0, count - 1, min(count, max_samples)).astype(np.intp)]
        repeats, _, _, first = self.coincident()
        tree = self.exact_tree() if not repeats else compiled_tree.CompiledTree(self.points[first], workers=self.workers)
        if len(tree.points) < 2:
            return self._keep_spacing(0.0, default)
        distances = tree.query_k(sample, 2, workers=self.workers)[0][:, 1]
        positive = distances[np.isfinite(distances) & (distances > 0)]
        return self._keep_spacing(float(np.median(positive)) if len(positive) else 0.0, default)

    def _keep_spacing(self, value: float, default: bool) -> float:
        if default:
            self._spacing = value
        return value
