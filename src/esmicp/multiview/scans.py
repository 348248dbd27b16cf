"""``register_scans()``: many scans into one model, with no initial poses and no scan order.

1. Pairwise: every candidate pair (all pairs up to ``max_all_pairs`` scans, else each scan's most
   similar scans by a cheap shape descriptor) is registered globally by :func:`esmicp.register`,
   on all cores or a Dask cluster (the path of :func:`esmicp.register_many`). Each edge gets a
   confidence: its overlap both ways (the smaller of the two fitness values) and the global
   search's ``ambiguous`` flag.
2. Pose graph: a maximum spanning tree of the confident edges gives initial poses; a robust
   (Cauchy) least-squares over all confident edges refines them; edges whose error stays large
   (cycle inconsistent) are rejected and the graph is solved again without them.
3. Joint refinement: all placed scans against each other (multi-view point-to-plane over the kept
   edges, a few rounds with a shrinking correspondence distance).

Scans that no kept edge connects to the reference are reported in ``unplaced``, never forced in.
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..batch import register_many
from ..errors import InvalidInputError
from ..globalreg.features import voxel_grid
from ..types import as_points
from . import pose_graph

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Edge:
    """One pairwise registration: ``T_i_j`` maps scan j's points into scan i's frame."""

    i: int
    j: int
    T_i_j: np.ndarray
    overlap: float  # min(fitness j->i, fitness i->j)
    fitness: float
    reverse_fitness: float
    ambiguous: bool
    kept: bool
    reason: str  # "kept", "low overlap", "cycle inconsistent (... deg, ...)", "failed: ..."

    def to_dict(self) -> dict:
        return {
            "i": self.i, "j": self.j, "T_i_j": self.T_i_j.tolist(), "overlap": self.overlap,
            "fitness": self.fitness, "reverse_fitness": self.reverse_fitness,
            "ambiguous": self.ambiguous, "kept": self.kept, "reason": self.reason,
        }


@dataclass(frozen=True)
class MultiRegistrationResult:
    """``poses[k]`` is ``T_world_scan`` of input scan k (world = the reference scan's frame);
    rows of unplaced scans are NaN."""

    poses: np.ndarray
    reference: int
    placed: tuple[bool, ...]
    unplaced: tuple[int, ...]
    edges: tuple[Edge, ...]
    runtime_s: float
    refinement_rmse: float | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def kept_edges(self) -> tuple[Edge, ...]:
        return tuple(e for e in self.edges if e.kept)

    @property
    def rejected_edges(self) -> tuple[Edge, ...]:
        return tuple(e for e in self.edges if not e.kept)

    def merged(self, clouds, *, voxel: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(points in the world frame, scan index per point) of the placed scans; with ``voxel``,
        one point (the centroid) per occupied voxel of that size, labelled by its first scan."""
        parts, labels = [], []
        for k, cloud in enumerate(clouds):
            if self.placed[k]:
                points = as_points(cloud, f"clouds[{k}]")
                parts.append(points @ self.poses[k][:3, :3].T + self.poses[k][:3, 3])
                labels.append(np.full(len(points), k))
        points, label = np.concatenate(parts), np.concatenate(labels)
        if voxel is None:
            return points, label
        if not voxel > 0:
            raise InvalidInputError(f"voxel: expected a positive size, got {voxel!r}")
        centroids, owner = voxel_grid(points, voxel)
        _, first = np.unique(owner, return_index=True)  # each voxel's first point
        return centroids, label[first]

    def to_dict(self) -> dict:
        return {
            "poses": [p.tolist() if np.isfinite(p).all() else None for p in self.poses],
            "reference": self.reference, "placed": list(self.placed), "unplaced": list(self.unplaced),
            "edges": [e.to_dict() for e in self.edges], "runtime_s": self.runtime_s,
            "refinement_rmse": self.refinement_rmse, "notes": list(self.notes),
        }


def _subsample(points: np.ndarray, count: int) -> np.ndarray:
    if len(points) <= count:
        return points
    # Seeded by the content, so a scan gets the same subset wherever it stands in the input.
    generator = np.random.default_rng(zlib.crc32(np.ascontiguousarray(points).tobytes()))
    return points[np.sort(generator.choice(len(points), count, replace=False))]


def _descriptor(points: np.ndarray) -> np.ndarray:
    centred = points - points.mean(axis=0)
    eigen = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(centred.T)), 0.0))
    radii = np.linalg.norm(centred, axis=1)
    histogram = np.histogram(radii / (radii.max() + 1e-300), bins=8, range=(0, 1))[0] / len(points)
    return np.concatenate([eigen / (eigen.sum() + 1e-300), histogram])


def candidate_pairs(clouds: Sequence[np.ndarray], *, max_all_pairs: int = 30, neighbours: int = 6) -> list[tuple[int, int]]:
    """All pairs for up to ``max_all_pairs`` scans; beyond, each scan with its ``neighbours`` most
    similar scans by extent and radial-distribution descriptor (a cheap overlap cue)."""
    n = len(clouds)
    if n <= max_all_pairs:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    descriptors = np.array([_descriptor(c) for c in clouds])
    _, near = cKDTree(descriptors).query(descriptors, k=min(neighbours + 1, n))
    return sorted({(min(i, int(j)), max(i, int(j))) for i, row in enumerate(near) for j in row if int(j) != i})


def _normals(points: np.ndarray, k: int = 12) -> np.ndarray:
    _, idx = cKDTree(points).query(points, k=min(k, len(points)))
    neighbourhoods = points[idx] - points[idx].mean(axis=1, keepdims=True)
    covariances = np.einsum("nki,nkj->nij", neighbourhoods, neighbourhoods)
    return np.linalg.eigh(covariances)[1][:, :, 0]


def _refine(poses, clouds, normals, edges, reference, distances, rounds_per_distance=2):
    """Multi-view point-to-plane: all placed poses jointly, over the kept edges (Gauss-Newton with
    Huber weights, the reference held fixed)."""
    free = [k for k in sorted(poses) if k != reference]
    slot = {k: n for n, k in enumerate(free)}
    rmse = None
    for cutoff in distances:
        for _ in range(rounds_per_distance):
            world = {k: clouds[k] @ poses[k][:3, :3].T + poses[k][:3, 3] for k in poses}
            world_n = {k: normals[k] @ poses[k][:3, :3].T for k in poses}
            trees = {k: cKDTree(world[k]) for k in poses}
            H = np.zeros((6 * len(free), 6 * len(free)))
            g = np.zeros(6 * len(free))
            squares, count = 0.0, 0
            for i, j in edges:
                for a_scan, b_scan in ((i, j), (j, i)):
                    d, idx = trees[a_scan].query(world[b_scan], distance_upper_bound=cutoff)
                    ok = np.isfinite(d)
                    if ok.sum() < 10:
                        continue
                    b = world[b_scan][ok]
                    a = world[a_scan][idx[ok]]
                    n = world_n[a_scan][idx[ok]]
                    r = np.einsum("ij,ij->i", n, a - b)
                    huber = cutoff / 3
                    w = np.where(np.abs(r) <= huber, 1.0, huber / np.maximum(np.abs(r), 1e-300))
                    J = np.hstack([np.cross(b, n), n])  # d r / d xi of scan a; scan b: -J
                    squares += float(np.sum(r * r)); count += len(r)
                    blocks = [(a_scan, 1.0), (b_scan, -1.0)]
                    for p, sp in blocks:
                        if p == reference:
                            continue
                        gp = slice(6 * slot[p], 6 * slot[p] + 6)
                        g[gp] += sp * (J * (w * r)[:, None]).sum(axis=0)
                        for q, sq in blocks:
                            if q == reference:
                                continue
                            gq = slice(6 * slot[q], 6 * slot[q] + 6)
                            H[gp, gq] += sp * sq * (J * w[:, None]).T @ J
            if not free or count == 0:
                return poses, rmse
            rmse = float(np.sqrt(squares / count))
            step = np.linalg.solve(H + 1e-9 * np.trace(H) / len(H) * np.eye(len(H)), -g)
            for k in free:
                poses[k] = pose_graph.pose_from_vector(step[6 * slot[k]: 6 * slot[k] + 6]) @ poses[k]
    return poses, rmse


def register_scans(
    clouds,
    *,
    reference: int = 0,
    pair_points: int = 1500,
    refine_points: int = 8000,
    min_overlap: float = 0.3,
    max_edge_error_deg: float = 2.0,
    max_all_pairs: int = 30,
    refine_rounds: int = 6,
    processes: int | None = None,
    client=None,
    progress: Callable[[int, int], None] | None = None,
    **register_kwargs,
) -> MultiRegistrationResult:
    """Register N scans into one frame, with no initial poses and no order assumed.

    Parameters
    ----------
    clouds : sequence of (N_k, 3) array-likes
        The scans, each in its own frame. Never modified.
    reference : int
        The scan whose frame is the world (``poses[reference]`` is the identity).
    pair_points, refine_points : int
        Points per scan (a content-seeded random subset) for the pairwise global registrations and
        for the joint refinement.
    min_overlap : float
        Edges whose overlap both ways (min of the two fitness values) is below this are rejected.
    max_edge_error_deg : float
        After the robust pose graph, an edge disagreeing with the poses by more than this rotation
        (or by more than 3x its inlier distance in translation) is rejected as cycle inconsistent.
    max_all_pairs : int
        Up to this many scans every pair is a candidate; beyond, see :func:`candidate_pairs`.
    refine_rounds : int
        Correspondence distances of the joint refinement (each used for two Gauss-Newton steps).
    processes, client
        Where the pairwise registrations run, as in :func:`esmicp.register_many` (each on one
        thread, ``workers=1``, when several run at once, unless ``workers`` is given).
    progress : callable, optional
        ``progress(done, total)`` after every pairwise registration.
    **register_kwargs
        Passed to every pairwise :func:`esmicp.register` call.
    """
    import time

    start = time.perf_counter()
    try:
        scans = [as_points(c, f"clouds[{k}]") for k, c in enumerate(clouds)]
    except TypeError:
        raise InvalidInputError("clouds: expected a sequence of (N, 3) point arrays") from None
    n = len(scans)
    if n < 1:
        raise InvalidInputError("clouds: expected at least one scan")
    if isinstance(reference, bool) or not isinstance(reference, (int, np.integer)) or not 0 <= reference < n:
        raise InvalidInputError(f"reference: expected a scan index in [0, {n}), got {reference!r}")
    reference = int(reference)
    small = [_subsample(s, pair_points) for s in scans]
    keys = [zlib.crc32(np.ascontiguousarray(s).tobytes()) for s in scans]
    pairs = candidate_pairs(small, max_all_pairs=max_all_pairs)
    # Orient every pair by content (the target is the scan with the smaller key), so the same two
    # scans give the same registration whatever their input positions.
    oriented = [(i, j) if (keys[i], i) <= (keys[j], j) else (j, i) for i, j in pairs]
    jobs = [(small[j], small[i]) for i, j in oriented]  # source j onto target i: T_i_j
    outcomes = register_many(jobs, processes=processes, client=client, progress=progress, **register_kwargs)

    edges: list[Edge] = []
    for (i, j), outcome in zip(oriented, outcomes):
        if not hasattr(outcome, "transformation"):
            edges.append(Edge(i, j, np.full((4, 4), np.nan), 0.0, 0.0, 0.0, False, False, f"failed: {outcome}"))
            continue
        T = outcome.transformation
        inverse = np.linalg.inv(T)
        moved = small[i] @ inverse[:3, :3].T + inverse[:3, 3]
        d, _ = cKDTree(small[j]).query(moved, distance_upper_bound=outcome.inlier_distance)
        reverse = float(np.isfinite(d).mean())
        overlap = min(outcome.fitness, reverse)
        ok = overlap >= min_overlap
        edges.append(Edge(i, j, T, overlap, outcome.fitness, reverse, outcome.ambiguous, ok,
                          "kept" if ok else f"low overlap ({overlap:.2f} < {min_overlap})"))
    inlier = {id(e): o.inlier_distance for e, o in zip(edges, outcomes) if hasattr(o, "inlier_distance")}

    def weight(e):
        return e.overlap * (0.5 if e.ambiguous else 1.0)

    confident = [e for e in edges if e.kept]
    graph = [(e.i, e.j, e.T_i_j, weight(e)) for e in confident]
    scale = float(np.median([inlier[id(e)] for e in confident])) if graph else 1.0
    poses = pose_graph.consensus_tree(graph, reference, max_angle_deg=2 * max_edge_error_deg,
                                      max_shift=lambda m: 6 * inlier[id(confident[m])])

    def check(edges, poses, angle_deg, spacings):
        out = []
        for e in edges:
            if e.kept and e.i in poses and e.j in poses:
                angle, shift = pose_graph.edge_error(poses[e.i], poses[e.j], e.T_i_j)
                if angle > angle_deg or shift > spacings * inlier[id(e)]:
                    e = Edge(e.i, e.j, e.T_i_j, e.overlap, e.fitness, e.reverse_fitness, e.ambiguous, False,
                             f"cycle inconsistent ({angle:.2f} deg, {shift:.3g} off the graph)")
            out.append(e)
        return out

    # Edges the consensus tree contradicts are rejected; the rest are optimised robustly and
    # checked again at the final tolerance.
    edges = check(edges, poses, 2 * max_edge_error_deg, 6)
    graph = [(e.i, e.j, e.T_i_j, weight(e)) for e in edges if e.kept and e.i in poses and e.j in poses]
    poses = pose_graph.optimise(poses, graph, reference, translation_scale=scale)
    edges = check(edges, poses, max_edge_error_deg, 3)
    graph = [(e.i, e.j, e.T_i_j, weight(e)) for e in edges if e.kept and e.i in poses and e.j in poses]
    poses = {k: T for k, T in pose_graph.consensus_tree(graph, reference, max_angle_deg=max_edge_error_deg,
                                                        max_shift=lambda m: float("inf")).items()
             if k in poses}
    poses = pose_graph.optimise(poses, graph, reference, translation_scale=scale)

    rmse = None
    kept_pairs = [(e.i, e.j) for e in edges if e.kept and e.i in poses and e.j in poses]
    if kept_pairs and refine_rounds > 0:
        fine = {k: _subsample(scans[k], refine_points) for k in poses}
        normals = {k: _normals(fine[k]) for k in fine}
        fine_spacing = float(np.median([np.median(cKDTree(f).query(f, k=2)[0][:, 1]) for f in fine.values()]))
        distances = np.geomspace(3.0 * scale, max(3.0 * fine_spacing, 1e-12), refine_rounds)
        poses, rmse = _refine(poses, fine, normals, kept_pairs, reference, distances)

    all_poses = np.full((n, 4, 4), np.nan)
    for k, T in poses.items():
        all_poses[k] = T
    all_poses[reference] = np.eye(4)
    placed = tuple(k in poses for k in range(n))
    unplaced = tuple(k for k in range(n) if not placed[k])
    notes = tuple(f"scan {k}: no kept edge connects it to the reference scan {reference}" for k in unplaced)
    for note in notes:
        logger.warning("register_scans: %s", note)
    return MultiRegistrationResult(all_poses, reference, placed, unplaced, tuple(edges),
                                   time.perf_counter() - start, rmse, notes)
