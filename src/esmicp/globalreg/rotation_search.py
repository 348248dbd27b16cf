"""Global initialisation by multi-hypothesis rotation search, refined by batched ESM.

Rigid registration from an arbitrary pose has many local optima, but ESM (like ICP) converges from
any start within a few tens of degrees of the truth. So we start from many rotations spread
evenly over SO(3) (a super-Fibonacci spiral), each with the centroids aligned, run a short ESM
refinement of ALL of them on subsampled clouds (one compiled call, the hypotheses spread over the
threads, each one's nearest-neighbour queries warm-started), and keep the ones whose clouds then
overlap best under a fixed-width Gaussian score.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import _kernels
from ..core import compiled_tree
from ..core.correspondence import NearestNeighbors
from ..core.nearest_grid import NearestGrid
from ..core.procrustes import to_matrix

#: Constants of the super-Fibonacci spiral (Alexa, "Super-Fibonacci Spirals", CVPR 2022).
_PHI = np.sqrt(2.0)
_PSI = 1.533751168755204288118041


def so3_grid(count: int) -> np.ndarray:
    """``count`` rotations spread near-uniformly over SO(3), as ``(count, 3, 3)`` matrices.

    Deterministic (a super-Fibonacci spiral of unit quaternions). Measured over 20,000 random
    rotations, the distance to the nearest grid rotation is at most 58 degrees (mean 30) for 64
    rotations, 52 (mean 26) for 96, and 44 (mean 24) for 128.
    """
    s = np.arange(count) + 0.5
    r = np.sqrt(s / count)
    big_r = np.sqrt(1.0 - s / count)
    alpha = 2.0 * np.pi * s / _PHI
    beta = 2.0 * np.pi * s / _PSI
    w, x, y, z = r * np.sin(alpha), r * np.cos(alpha), big_r * np.sin(beta), big_r * np.cos(beta)
    return quaternions_to_matrices(np.column_stack([w, x, y, z]))


def quaternions_to_matrices(quaternions: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(K, 4)`` as ``(w, x, y, z)`` to rotation matrices ``(K, 3, 3)``."""
    w, x, y, z = (quaternions / np.linalg.norm(quaternions, axis=1, keepdims=True)).T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


@dataclass(frozen=True)
class Hypotheses:
    """Poses ``T_target_source`` ``(K, 4, 4)`` with their scores (higher is better, in [0, 1])."""

    transformations: np.ndarray
    scores: np.ndarray


#: Neighbours per target point in a :class:`NeighbourGraph` (count). A design value for speed
#: only: every answer is the exact nearest neighbour whatever its value (uncertified queries go
#: to the tree); the share of queries it certifies against the cost of its build is measured in
#: ``docs/speed.md``.
GRAPH_NEIGHBOURS = 12


@dataclass(frozen=True)
class NeighbourGraph:
    """The ``k`` nearest target points of every target point, itself among them (``neighbours``,
    ``(M, k)`` target indices), and the squared distance to the k-th (``radii``, ``(M,)``, cloud
    units squared). Every target point strictly nearer than that to a point is in its list, so a
    query whose warm-start neighbour ``p`` has no nearer point in its list, and lies within half
    of ``p``'s radius, has ``p`` as its exact nearest neighbour: :func:`batched_esm` answers most
    of its queries so, without the tree."""

    neighbours: np.ndarray
    radii: np.ndarray

    @classmethod
    def of(cls, index: NearestNeighbors, k: int = GRAPH_NEIGHBOURS) -> "NeighbourGraph":
        """The graph of ``index``'s target, ``k`` (at most the target's size) neighbours each."""
        tree = index.exact_tree()
        count = min(int(k), len(tree.points))
        neighbours, radii = np.empty((len(tree.points), count), dtype=np.int64), np.empty(len(tree.points))
        _kernels.neighbour_graph(tree.points, tree.order, tree.starts, tree.ends, tree.lefts, tree.boxes, neighbours,
                                 radii, compiled_tree.threads(index.workers))
        return cls(neighbours, radii)

    @classmethod
    def none(cls) -> "NeighbourGraph":
        """No graph: :func:`batched_esm` then answers every query by the tree, from its warm start
        (the same neighbours; cheaper than building the graph of a large target for few queries)."""
        return cls(np.empty((0, GRAPH_NEIGHBOURS), dtype=np.int64), np.empty(0))

    @property
    def empty(self) -> bool:
        return len(self.radii) == 0


def batched_esm(
    source: np.ndarray,
    target: NearestNeighbors | NearestGrid,
    rotations: np.ndarray,
    translations: np.ndarray,
    *,
    iterations: int,
    sigma_floor: float,
    sigma_factor: float = 3.0,
    fine_iterations: int = 0,
    workers: int | None = None,
    graph: NeighbourGraph | None = None,
    seeds: NearestGrid | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run ``iterations`` ESM steps for K hypotheses at once, in one compiled call.

    ``rotations`` ``(K, 3, 3)`` and ``translations`` ``(K, 3)`` are the starting ``T_target_source``;
    ``source`` ``(n, 3)`` is in the source frame, ``target`` an exact index or the global search's
    lookup grid. With an exact index, each hypothesis' queries start from its previous neighbours
    and are answered through ``graph`` (:class:`NeighbourGraph` of ``target``, built here if not
    given; :meth:`NeighbourGraph.none`: no graph) where it certifies them, by the tree otherwise:
    exact either way. ``seeds`` (optional,
    the lookup grid over the same target points) starts each first query from its cell's point
    instead of from scratch (only the speed changes). Each hypothesis
    anneals its own sigma as ``max(sigma_floor, sigma_factor * median distance)`` (cloud units);
    the last ``fine_iterations`` of the ``iterations`` use ``sigma_floor`` itself (the fine phase
    of :mod:`esmicp.methods.esm`, which keeps outliers from biasing the pose). Every step weighs
    the pairs by ``exp(-(d^2 - min d^2) / (2 sigma^2))`` and moves the pose by their weighted
    Kabsch fit. Hypotheses run one per piece on ``workers`` threads (None: every core); the result
    does not depend on the number. Returns the final rotations, translations and the final
    correspondence distances ``(K, n)``.
    """
    count = len(rotations)
    source = np.ascontiguousarray(source, dtype=np.float64)
    rotations = np.array(rotations, dtype=np.float64).reshape(count, 9)
    translations = np.array(translations, dtype=np.float64).reshape(count, 3)
    distances = np.empty((count, len(source)))
    if count == 0:
        return rotations.reshape(0, 3, 3), translations, distances
    schedule = (int(iterations), float(sigma_floor), float(sigma_factor), int(fine_iterations))
    points = np.ascontiguousarray(target.points, dtype=np.float64)
    threads = compiled_tree.threads(workers)
    if isinstance(target, NearestGrid):
        _kernels.batched_esm_grid(source, rotations, translations, *schedule, distances, points, target.lookup,
                                  target.low, target.cell, target.shape.astype(np.int64), threads)
    else:
        tree = target.exact_tree()
        graph = NeighbourGraph.of(target) if graph is None else graph
        if seeds is None:
            seeding = (np.empty(0, dtype=np.int64), np.zeros(3), 1.0, np.zeros(3, dtype=np.int64))
        elif seeds.points is not target.points:
            raise ValueError("batched_esm: the seeds' grid must be over the same target points as the index")
        else:
            seeding = (seeds.lookup, seeds.low, seeds.cell, seeds.shape.astype(np.int64))
        _kernels.batched_esm_tree(source, rotations, translations, *schedule, distances, points, tree.rank,
                                  tree.points, tree.order, tree.starts, tree.ends, tree.lefts, tree.boxes,
                                  graph.neighbours, graph.radii, *seeding, threads)
    return rotations.reshape(count, 3, 3), translations, distances


def gaussian_overlap_score(distances: np.ndarray, width: float) -> np.ndarray:
    """Mean Gaussian similarity ``exp(-d^2 / (2 width^2))`` per row: the soft fraction of source
    points lying on the target (1 = every point exactly on it)."""
    return np.exp(-np.square(distances) / (2.0 * width * width)).mean(axis=-1)


def rotation_search(
    source: np.ndarray,
    target: NearestNeighbors | NearestGrid,
    *,
    rotations: int = 96,
    iterations: int = 12,
    score_width: float,
    sigma_floor: float,
    source_centroid: np.ndarray | None = None,
    target_centroid: np.ndarray | None = None,
    workers: int | None = None,
) -> Hypotheses:
    """Score ``rotations`` starting rotations (a :func:`so3_grid`) after a short batched ESM.

    ``source`` should be a subsample (a few hundred points); ``target`` an index over a (possibly
    subsampled) target. Each start aligns ``source_centroid`` with ``target_centroid`` (defaults:
    the clouds' means). Returns every hypothesis with its :func:`gaussian_overlap_score` of width
    ``score_width`` (cloud units), best first. ``workers``: threads of :func:`batched_esm`.
    """
    if source_centroid is None:
        source_centroid = source.mean(axis=0)
    if target_centroid is None:
        target_centroid = target.points.mean(axis=0)
    starts = so3_grid(rotations)
    translations = target_centroid - starts @ source_centroid
    final_rotations, final_translations, distances = batched_esm(
        source, target, starts, translations, iterations=iterations, sigma_floor=sigma_floor, workers=workers
    )
    scores = gaussian_overlap_score(distances, score_width)
    order = np.argsort(-scores, kind="stable")
    transformations = np.stack([to_matrix(final_rotations[k], final_translations[k]) for k in order])
    return Hypotheses(transformations, scores[order])
