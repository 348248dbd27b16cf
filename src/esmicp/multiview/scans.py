"""``register_scans()``: many scans into one model, with no initial poses.

0. An exact duplicate of a scan (the same points, in any order) is not registered: it takes its
   twin's pose and verdict, and confirms nothing. Each scan is registered in its centroid frame
   (its points minus their centroid), and its poses mapped back to the frame it came in: every
   translation the merge measures is a displacement at the scan's own points, so a rigid motion
   of every scan (data in map coordinates 1e6 m away, a turn) changes no verdict, and the poses
   only by that motion (but the free-space premise, step 5, which is about the frames' origins).
1. Pairwise, O(N) pairs: with the capture order (``sequence=True``), each scan with its next
   ``sequence_neighbours`` scans, refined locally from the identity (the pairs it leaves
   untrusted searched globally where the walk needs them: where the trusted ones leave a scan on
   no cycle through the reference); without, each scan with its
   ``partners`` most similar scans: a cheap shape descriptor proposes each scan's nearest few,
   the fraction of their surface features (FPFH) that match each other mutually ranks them
   (:func:`esmicp.multiview.pairs.matching_distances`),
   searched globally by :func:`esmicp.register`. Every pair is then refined locally on denser
   subsets and judged there.
   The jobs run on a thread pool, a process pool or a Dask cluster (:func:`esmicp.register_many`).
2. Pose graph over the *usable* edges only: those whose pairwise result is trusted
   (:attr:`esmicp.RegistrationResult.trusted`). A consensus spanning tree gives initial poses, a
   robust least-squares refines them (each edge whitened by its 6x6 information matrix when the
   result carries one, else weighted by its confidence), and edges that disagree with the poses are
   rejected as cycle inconsistent.
3. With a sequence, loop closures: pairs of placed scans the graph's poses predict to overlap
   (:class:`esmicp.multiview.pairs.PredictedOverlap`), those the graph joins by the longest path
   first (the drift a closure corrects grows with the path it bypasses), at most
   ``loop_searches_per_scan`` per posed scan over the merge (the fields named here are
   :class:`esmicp.config.MergeConfig`'s); sought again after a round of more pairs (below) poses
   scans not posed before (the far side of a break in the walk), so that its loops tie it before
   the joint refinement and the free-space check judge its poses. Then, where a posed scan is not yet confirmed and the
   graph rejected a trusted edge as cycle inconsistent, those edges are judged once more against
   the poses a joint refinement over the kept edges gives (step 4; the pose graph weighs the
   pairwise estimates alone, whose small errors can add up around a long cycle), and kept when
   they agree within the same bounds, and the graph keeps them in every later solve (unless a
   free-space conflict cuts them). Then, with or without, more pairs only where a scan is
   not yet confirmed (not on a cycle of agreeing edges): across each edge on no cycle, the pair the
   poses predict to overlap most; for each piece of scans not placed, the pairs its pose as a
   whole proposes (the piece fused and searched against the placed scans fused), else those most
   like its scans; then the graph is solved again, until ``stalled_rounds`` rounds in a row place
   or confirm no scan. These pairs are chosen from poses but searched globally, never refined
   from those poses: a refinement started at a wrong pose can settle next to it and confirm it
   (``docs/design.md``, "Measured design choices"), and a wrong proposal only costs the searches
   it asked for.
4. Joint refinement: all placed scans against each other (multi-view point-to-plane over the
   kept edges, a few rounds with a shrinking correspondence distance; each pair queries the points
   of its overlap and counts with the inverse of its own residual variance, so a pair whose
   surfaces agree less pulls less).
5. A free-space check (:mod:`esmicp.trust.free_space`) between scans that are range images
   from their origins (depth frames, LiDAR scans in their sensor frames), as declared
   (``range_images``) or as each scan's own points show
   (:func:`esmicp.trust.free_space.range_image_test`; never from the poses being judged): placed
   scans whose extents overlap must not put surfaces where the other saw empty space. A conflict disproves
   an edge between them, and the scans the likeliest wrong edges join to the reference are
   doubtful. This catches wrong edges that agree with each other around every cycle (repeated
   structure). The first time a conflict cuts edges, they are vetoed and steps 2-5 run again:
   the scans they placed lose their pose and are searched again.
6. A verdict per scan (:mod:`esmicp.multiview.verdict`): ``"placed"``, ``"doubtful"`` or
   ``"unplaced"`` with its reasons; a doubtful or unplaced scan is never silently merged.

:func:`register_scans` reads as these steps, each a function of its own below (``_prepare``,
``_first_pairs``, the pose graph's ``_Graph.solve``, ``_Loops``, ``_more_pairs``,
``_joint_refinement``, ``_free_space_check``, ``_verdict``), and each records what it did
(:class:`esmicp.result.Stage`) in :attr:`MultiRegistrationResult.stages`.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from ..batch import register_many
from ..config import MergeConfig, RegistrationConfig
from ..core.compiled_tree import CompiledTree
from ..core.features import estimate_normals, voxel_grid
from ..core.procrustes import skew
from ..errors import InvalidInputError
from ..result import Stage
from ..trust import free_space
from ..types import as_points
from . import pairs as candidates
from . import pose_graph
from .refine import refine
from .verdict import cut_off, scan_verdicts

logger = logging.getLogger(__name__)

#: Kinds of :attr:`Edge.kind`: how the pairwise registration started.
GLOBAL, LOCAL = "global", "local"


@dataclass(frozen=True)
class Edge:
    """One pairwise registration: ``T_i_j`` maps scan j's points into scan i's frame (scan i was the
    target).

    ``confidence``, ``ambiguous`` and ``trusted`` are the pairwise result's
    (:class:`esmicp.RegistrationResult`); only trusted edges are usable. ``kept``: the final pose
    graph uses it. ``reason``: ``"kept"``, ``"untrusted (...)"``, ``"cycle inconsistent (...)"``,
    ``"not connected to the reference"`` or ``"failed: ..."``. ``overlap`` is the smaller of the
    fitness both ways (for information). ``kind``: ``"global"`` (a global search) or ``"local"``
    (refined from a predicted pose). ``inlier_distance`` in cloud units; ``information`` the
    result's 6x6 information matrix when it has one (rotation vector then translation, left
    perturbation of ``T_i_j`` in frame i).
    """

    i: int
    j: int
    T_i_j: np.ndarray
    overlap: float
    fitness: float
    reverse_fitness: float
    ambiguous: bool
    kept: bool
    reason: str
    confidence: float | None = None
    trusted: bool = False
    kind: str = GLOBAL
    inlier_distance: float = float("nan")
    information: np.ndarray | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        return {
            "i": self.i, "j": self.j, "T_i_j": self.T_i_j.tolist(), "overlap": self.overlap,
            "fitness": self.fitness, "reverse_fitness": self.reverse_fitness,
            "ambiguous": self.ambiguous, "kept": self.kept, "reason": self.reason,
            "confidence": self.confidence, "trusted": self.trusted, "kind": self.kind,
            "inlier_distance": self.inlier_distance,
        }


@dataclass(frozen=True)
class MultiRegistrationResult:
    """The poses of many scans and a verdict per scan.

    ``poses[k]`` is ``T_world_scan`` of input scan k (world = the reference scan's frame); rows of
    unplaced scans are NaN, doubtful scans have their (unconfirmed) pose.

    Per scan k: ``status[k]`` is ``"placed"`` (confirmed, see :mod:`esmicp.multiview.verdict`),
    ``"doubtful"`` (posed, but contradicted) or ``"unplaced"``; ``reasons[k]`` says why;
    ``scan_confidence[k]`` (0-1, below the trust bar when doubtful, None when unplaced);
    ``edges_kept[k]`` kept edges touching it; ``residual[k]`` its RMS point-to-plane residual
    (cloud units) in the last step of the joint refinement (None without one). ``placed[k]`` is
    ``status[k] == "placed"``; ``unplaced`` and ``doubtful`` list those scans' indices.
    ``pairs_registered``: pairwise registrations run (global and local). ``free_space_check``,
    what the free-space check did: ``"applied"`` (to every placed scan); ``"applied to K of N
    placed scans; the others are not range images, e.g. scan k: <why>"`` (only pairs of two range
    images are judged); ``"not range images: ..."`` (fewer than two placed scans are range images
    seen from their origins, as their points show: not applied); ``"declared off"``
    (``range_images=False``); ``"too few edges"`` (nothing placed to judge). ``stages``: what each
    stage of the merge did, in order (:class:`esmicp.result.Stage`, see :func:`register_scans`);
    empty for a result built by hand.
    """

    poses: np.ndarray
    reference: int
    placed: tuple[bool, ...]
    unplaced: tuple[int, ...]
    edges: tuple[Edge, ...]
    runtime_s: float
    refinement_rmse: float | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)
    status: tuple[str, ...] = ()
    scan_confidence: tuple[float | None, ...] = ()
    reasons: tuple[tuple[str, ...], ...] = ()
    edges_kept: tuple[int, ...] = ()
    residual: tuple[float | None, ...] = ()
    pairs_registered: int = 0
    free_space_check: str = "too few edges"
    stages: tuple[Stage, ...] = field(default=(), repr=False)

    def __repr__(self) -> str:
        """One line: how many scans are placed, doubtful and unplaced, the reference, the edges
        kept and the work, e.g. ``MultiRegistrationResult(scans=10, placed=9, doubtful=1,
        unplaced=0, reference=0, edges kept=14 of 27, pairs_registered=62, 32.5 s)`` (the arrays
        and per-scan reasons stay in the fields)."""
        placed = sum(1 for s in self.status if s == "placed")
        return (f"{type(self).__name__}(scans={len(self.status)}, placed={placed}, doubtful={len(self.doubtful)}, "
                f"unplaced={len(self.unplaced)}, reference={self.reference}, edges kept={len(self.kept_edges)} of "
                f"{len(self.edges)}, pairs_registered={self.pairs_registered}, {self.runtime_s:.1f} s)")

    @property
    def doubtful(self) -> tuple[int, ...]:
        """Indices of the doubtful scans (posed, but contradicted)."""
        return tuple(k for k, s in enumerate(self.status) if s == "doubtful")

    @property
    def all_placed(self) -> bool:
        """True when every scan is placed (none doubtful or unplaced)."""
        return all(self.placed)

    @property
    def kept_edges(self) -> tuple[Edge, ...]:
        return tuple(e for e in self.edges if e.kept)

    @property
    def rejected_edges(self) -> tuple[Edge, ...]:
        return tuple(e for e in self.edges if not e.kept)

    def merged(self, clouds, *, voxel: float | None = None, include_doubtful: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(points in the world frame, scan index per point) of the placed scans (and of the
        doubtful ones with ``include_doubtful``); with ``voxel``, one point (the centroid) per
        occupied voxel of that size, labelled by its first scan."""
        parts, labels = [], []
        for k, cloud in enumerate(clouds):
            if self.placed[k] or (include_doubtful and self.status[k] == "doubtful"):
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
            "doubtful": list(self.doubtful),
            "scans": [
                {"index": k, "status": self.status[k], "confidence": self.scan_confidence[k],
                 "edges_kept": self.edges_kept[k], "residual": self.residual[k], "reasons": list(self.reasons[k])}
                for k in range(len(self.status))
            ],
            "edges": [e.to_dict() for e in self.edges], "runtime_s": self.runtime_s,
            "pairs_registered": self.pairs_registered, "free_space_check": self.free_space_check,
            "refinement_rmse": self.refinement_rmse, "notes": list(self.notes),
            "stages": [stage.to_dict() for stage in self.stages],
        }


def _subsample(points: np.ndarray, count: int, draw: int = 0) -> np.ndarray:
    """``count`` points of ``points`` (all of them when it has no more), in their input order.

    The subset depends on the scan's shape alone: a rigid motion of the scan, or another place in
    the input, gives the same subset (the points are ranked by their distance from the centroid,
    and the ranks drawn by a generator seeded by the point count and ``draw``), so that the merge's
    verdicts do not depend on where the scans lie or in which order they come. Another ``draw``
    gives another subset of the same scan."""
    if len(points) <= count:
        return points
    centred = points - points.mean(axis=0)
    rank = np.argsort(np.einsum("ij,ij->i", centred, centred), kind="stable")
    seed = len(points) if draw == 0 else (len(points), draw)
    chosen = np.random.default_rng(seed).choice(len(points), count, replace=False)
    return points[np.sort(rank[chosen])]


def _shape_key(points: np.ndarray) -> tuple[int, float]:
    """A key of a scan's shape that a rigid motion leaves unchanged: its point count and RMS
    distance from its centroid (the larger scan of a pair is the target, whatever the input order
    and wherever the scans lie)."""
    centred = points - points.mean(axis=0)
    return len(points), float(np.sqrt(np.mean(np.einsum("ij,ij->i", centred, centred))))


def _shift(offset: np.ndarray) -> np.ndarray:
    """The 4x4 translation by ``offset``."""
    T = np.eye(4)
    T[:3, 3] = offset
    return T


def _information_moved(information: np.ndarray | None, offset: np.ndarray) -> np.ndarray | None:
    """An edge's 6x6 information matrix (left perturbation of ``T_i_j`` in frame i, rotation then
    translation) for frame i moved by ``offset`` (the new frame's coordinates are the old ones plus
    ``offset``): a perturbation ``(w, v)`` becomes ``(w, v + offset x w)``."""
    if information is None:
        return None
    A_inv = np.eye(6)
    A_inv[3:, :3] = -skew(np.asarray(offset, dtype=float))
    return A_inv.T @ np.asarray(information, dtype=float) @ A_inv


def _exact_twins(scans: list[np.ndarray], reference: int) -> list[int]:
    """For every scan, the scan it is an exact duplicate of (the same points, in any order): the
    reference or else the first of its twins; itself when it has none.

    Scans are grouped by an order-free hash of their points' bits (a sum over the points, so the
    same points in another order give the same hash), then compared point by point."""
    groups: dict[tuple, list[int]] = {}
    for k in [reference] + [k for k in range(len(scans)) if k != reference]:
        bits = np.ascontiguousarray(scans[k], dtype=np.float64).view(np.uint64)
        with np.errstate(over="ignore"):
            mixed = bits * np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9], dtype=np.uint64)
            row = (mixed[:, 0] ^ (mixed[:, 1] >> np.uint64(17)) ^ (mixed[:, 2] << np.uint64(11))) if len(bits) else mixed[:, 0]
            digest = int(row.sum(dtype=np.uint64))
        groups.setdefault((scans[k].shape, digest), []).append(k)
    twin = list(range(len(scans)))
    for members in groups.values():
        if len(members) < 2:
            continue
        rows = {k: scans[k][np.lexsort(scans[k].T[::-1])] for k in members}
        for position, k in enumerate(members):
            for first in members[:position]:
                if twin[first] == first and np.array_equal(rows[first], rows[k]):
                    twin[k] = first
                    break
    return twin


def _with_twins(result: "MultiRegistrationResult", unique: list[int], twin: list[int]) -> "MultiRegistrationResult":
    """``result``, a merge of the scans ``unique`` (one of each group of exact duplicates), for
    every scan: a duplicate gets its twin's pose and verdict, and says so; edges name scans by
    their input index."""
    slot = {k: m for m, k in enumerate(unique)}
    of = [slot[twin[k]] for k in range(len(twin))]
    status = tuple(result.status[m] for m in of)
    reasons = tuple(result.reasons[m] if twin[k] == k else
                    (f"an exact duplicate of scan {twin[k]} (the same points): given its pose and verdict, and not "
                     f"counted as confirming it",) + tuple(result.reasons[m]) for k, m in enumerate(of))
    notes = tuple(f"scan {k}: {status[k]}: {'; '.join(reasons[k])}" for k in range(len(twin)) if status[k] != "placed")
    return replace(
        result, poses=result.poses[of], reference=unique[result.reference], placed=tuple(result.placed[m] for m in of),
        unplaced=tuple(k for k in range(len(twin)) if status[k] == "unplaced"),
        edges=tuple(replace(e, i=unique[e.i], j=unique[e.j]) for e in result.edges), notes=notes, status=status,
        scan_confidence=tuple(result.scan_confidence[m] for m in of), reasons=reasons,
        edges_kept=tuple(result.edges_kept[m] for m in of), residual=tuple(result.residual[m] for m in of))


class _Plan:
    """The stages of one merge as they run: the ``progress(stage, done, total)`` reports (each
    stage opens at ``done == 0`` with its total, and closes at ``done == total`` before the next
    opens), and the record of what each stage did (:class:`esmicp.result.Stage`)."""

    def __init__(self, progress):
        self.progress = progress
        self.stage, self.total, self.done = None, 0, 0
        self.records: list[Stage] = []

    def record(self, name: str, started: float, *, points: int | None = None, **decided) -> None:
        """Record the stage ``name``, begun at ``started`` (``time.perf_counter()``), and what it decided."""
        self.records.append(Stage(name, time.perf_counter() - started, points=points, decided=decided))

    def open(self, stage: str, total: int) -> None:
        self.close()
        self.stage, self.total, self.done = stage, total, 0
        if self.progress is not None:
            self.progress(stage, 0, total)

    def advance(self, done: int) -> None:
        if self.stage is not None and done > self.done:
            self.done = min(done, self.total)
            if self.progress is not None:
                self.progress(self.stage, self.done, self.total)

    def close(self) -> None:
        if self.stage is not None:
            self.advance(self.total)
            self.stage = None


class _Pairwise:
    """The edges of one merge: runs pairwise registrations and keeps every edge tried (one per
    pair of scans; a later registration of the same pair replaces it only when it ranks higher by
    :func:`_standing`: a trusted result before an untrusted one, then the more confident).

    A pair is searched globally on the sparse subsets (``small``), or refined there from a given
    start, then refined locally on the dense subsets (``dense``) from the pose found, and judged
    there. A pair whose global search was not trusted is searched once more, on another draw of
    the sparse subsets, when it is asked for again (:meth:`run`): a search's outcome depends on
    the points drawn, and a second draw is a second, independent try. The overlap confidence of a
    registration is only meaningful at a density where the clouds' noise is finer than their
    spacing: right pairs of sparse subsets can score as low as wrong ones (``docs/design.md``,
    "Measured design choices")."""

    def __init__(self, centred, small, dense, keys, sequence, run_options, stages: _Plan, config: MergeConfig,
                 tree: Callable[[int], CompiledTree] | None = None):
        self.centred, self.small, self.dense, self.keys = centred, small, dense, keys
        # scan -> a compiled KD-tree over its dense subset (made once per scan when the caller shares them)
        self.tree = tree if tree is not None else (lambda k: CompiledTree(self.dense[k]))
        self.sequence, self.run_options, self.stages, self.config = sequence, run_options, stages, config
        self.edges: dict[tuple[int, int], Edge] = {}
        self.done = 0  # registrations run, for progress and the result
        self.tried: set[tuple[int, int]] = set()
        self.redrawn: set[tuple[int, int]] = set()  # pairs searched on a second draw too
        self.second: dict[int, np.ndarray] = {}  # scan -> its second draw of the sparse subset, once asked for

    def settled(self) -> set[tuple[int, int]]:
        """Pairs not worth searching again: trusted, or searched on both draws, or refined from a
        start. A pair searched once globally and not trusted may be searched on a second draw."""
        once = {key for key, edge in self.edges.items() if edge.kind == GLOBAL and not edge.trusted}
        return (self.tried - once) | self.redrawn

    def search_config(self) -> RegistrationConfig:
        """The registrations' config on the sparse subsets (the global pair searches, and the
        refinements from a given start): the merge's :attr:`~esmicp.config.MergeConfig.registration`,
        with at most :attr:`~esmicp.config.MergeConfig.pair_scan_searches` scan-strategy searches
        when its search config sets no bound itself, and the second try of a refinement from a
        given start as :attr:`~esmicp.config.MergeConfig.sparse_second_try` says."""
        registration = self.config.registration
        search = registration.search
        if search.scan_searches is None:
            search = replace(search, scan_searches=self.config.pair_scan_searches)
        return replace(registration, search=search,
                       refine=replace(registration.refine, second_try=self.config.sparse_second_try))

    def orient(self, a: int, b: int) -> tuple[int, int]:
        """(target, source): in a sequence the earlier scan is the target; otherwise the larger
        scan (:func:`_shape_key`: more points, then the larger extent), so that the same two scans
        give the same edge wherever they stand and however they lie."""
        if self.sequence:
            return (min(a, b), max(a, b))
        return (a, b) if (self.keys[a], -a) >= (self.keys[b], -b) else (b, a)

    def _register(self, jobs, inits, offset, config=None, **extra):
        """``jobs``: ``(source, target)`` clouds, each pair's source j onto its target i (``T_i_j``);
        ``extra`` register options unless the caller gave them; ``config``, when given, replaces the
        caller's (it is made from it: :meth:`search_config`)."""
        def report(done, _):
            self.stages.advance(offset + done)

        # the merge judges free space itself, on the scans in their own frames (step 5), not per pair
        options = {"range_images": False, **extra, **self.run_options}
        if config is not None:
            options["config"] = config
        outcomes = register_many(jobs, progress=report, inits=inits, **options)
        self.done += len(jobs)
        return outcomes

    def place_pieces(self, jobs, stage: str) -> list:
        """Global searches of ``jobs`` (``(source cloud, target cloud)``: a piece's fused scans onto
        the placed scans'); one progress ``stage``, counted among the registrations run."""
        self.stages.open(stage, len(jobs))
        outcomes = register_many(jobs, progress=lambda done, _: self.stages.advance(done),
                                 **{"range_images": False, **self.run_options})
        self.stages.close()
        self.done += len(jobs)
        return outcomes

    def run(self, requests, stage: str = "pairs", **asked) -> list[Edge]:
        """Register ``requests`` (``(a, b, T_a_b or None)``: None for a global search) and record
        their edges; returns the new edges. A pair searched globally before, and not trusted, is
        searched on the second draw of the sparse subsets. One progress ``stage`` of two
        registrations a pair (the search, the check; a pair whose search failed has its check
        counted as done), recorded with what it found and ``asked`` (why the pairs were asked for)."""
        started, before = time.perf_counter(), self.done
        if not requests:
            self._record(stage, started, before, [], {}, asked)
            return []
        once = self.tried - self.settled()
        sparse = {}
        for a, b, T_a_b in requests:
            again = T_a_b is None and (min(a, b), max(a, b)) in once
            for k in (a, b):
                if again and k not in self.second:
                    self.second[k] = _subsample(self.centred[k], len(self.small[k]), draw=1)
            sparse[(min(a, b), max(a, b))] = again
        oriented, inits = [], []
        for a, b, T_a_b in requests:
            i, j = self.orient(a, b)
            T = T_a_b if T_a_b is None or (i, j) == (a, b) else np.linalg.inv(T_a_b)
            oriented.append((i, j))
            inits.append(T)
        self.stages.open(stage, 2 * len(requests))
        # on the sparse subsets: a global search, or a local refinement from the given start; only
        # its pose and convergence are used (the check below is judged), so it is not judged
        subsets = [self.second if sparse[(min(i, j), max(i, j))] else self.small for i, j in oriented]
        found = self._register([(c[j], c[i]) for c, (i, j) in zip(subsets, oriented)], inits, 0,
                               config=self.search_config(), judge=False)
        outcomes = {n: outcome for n, outcome in enumerate(found) if not hasattr(outcome, "transformation")}
        # the check on the dense subsets starts at a converged pose: capped
        group = [n for n in range(len(requests)) if n not in outcomes]
        checked = self._register([(self.dense[oriented[n][1]], self.dense[oriented[n][0]]) for n in group],
                                 [found[n].transformation for n in group], 2 * len(requests) - len(group),
                                 max_iterations=self.config.check_iterations,
                                 tolerance=self.config.check_tolerance)
        self.stages.close()
        for n, check in zip(group, checked):
            if hasattr(check, "transformation"):
                # the check's cap is this function's own budget, not a run cut short: the pair has
                # converged when the run that found its pose did, and its iterations are both runs'
                check = replace(check, converged=found[n].converged,
                                num_iterations=found[n].num_iterations + check.num_iterations)
            outcomes[n] = check
        new = []
        for n, (i, j) in enumerate(oriented):
            edge = self._edge(i, j, outcomes[n], LOCAL if inits[n] is not None else GLOBAL)
            key = (min(i, j), max(i, j))
            if sparse[key]:
                self.redrawn.add(key)
            self.tried.add(key)
            old = self.edges.get(key)
            if old is None or _standing(edge) > _standing(old):
                self.edges[key] = edge
            new.append(edge)
        self._record(stage, started, before, new, sparse, asked)
        return new

    def _record(self, stage: str, started: float, before: int, new: list[Edge], sparse: dict, asked: dict) -> None:
        """Record a stage of pairs: ``new`` its edges, ``sparse`` which pairs were searched on the
        second draw, ``asked`` why they were asked for."""
        self.stages.record(stage, started, **asked, pairs=len(new), searched=sum(e.kind == GLOBAL for e in new),
                           refined=sum(e.kind == LOCAL for e in new), registrations=self.done - before,
                           trusted=sum(e.trusted for e in new), failed=sum(e.reason.startswith("failed") for e in new),
                           redrawn=sum(sparse.values()))

    def _edge(self, i: int, j: int, outcome, kind: str) -> Edge:
        if not hasattr(outcome, "transformation"):
            return Edge(i, j, np.full((4, 4), np.nan), 0.0, 0.0, 0.0, False, False, f"failed: {outcome}", kind=kind)
        T = outcome.transformation
        inverse = np.linalg.inv(T)
        moved = self.dense[i] @ inverse[:3, :3].T + inverse[:3, 3]
        d, _ = self.tree(j).query(moved, workers=1)
        reverse = float(np.mean(d < outcome.inlier_distance))
        confidence = getattr(outcome, "confidence", None)
        doubts = outcome.doubts()
        trusted = not doubts
        reason = "trusted" if trusted else f"untrusted ({'; '.join(doubts)})"
        return Edge(i, j, T, min(outcome.fitness, reverse), outcome.fitness, reverse, bool(outcome.ambiguous),
                    False, reason, confidence=confidence, trusted=trusted, kind=kind,
                    inlier_distance=float(outcome.inlier_distance),
                    information=getattr(outcome, "information", None))


def _standing(edge: Edge) -> tuple[bool, float]:
    """How two registrations of one pair rank, the higher kept: a trusted result before an
    untrusted one, whatever their confidences (a refinement stopped by its iteration cap can
    score the full overlap confidence, 1.0, and still be untrusted), then the more confident
    (a failed registration, which has no confidence, last)."""
    return edge.trusted, -1.0 if edge.confidence is None else edge.confidence


def _solve(edges: list[Edge], reference: int, config: MergeConfig, vetoed: dict | None = None,
           admitted: set | frozenset = frozenset()):
    """(poses of the scans joined to ``reference``, every edge with ``kept``/``reason`` set): the
    pose graph over the trusted edges (consensus tree, robust optimisation, cycle check, again),
    except the ``vetoed`` pairs (``(min, max) -> reason``: cut by a free-space conflict); the
    ``admitted`` pairs (``(min, max)``: kept by the surfaces, :func:`_rejudged`) are never rejected
    as cycle inconsistent."""
    vetoed = vetoed or {}
    max_edge_error_deg, direct = config.max_edge_error_deg, config.direct_solve_max_poses
    max_shift, gain = config.max_edge_shift_inliers, config.first_check_gain

    def start(e):
        pair = (min(e.i, e.j), max(e.i, e.j))
        if e.trusted and pair in vetoed:
            return replace(e, kept=False, reason=vetoed[pair])
        return replace(e, kept=e.trusted, reason=e.reason if not e.trusted else "kept")

    edges = [start(e) for e in edges]
    usable = [e for e in edges if e.kept]
    if not usable:
        return {reference: np.eye(4)}, edges

    def graph(of):
        return [(e.i, e.j, e.T_i_j, e.confidence, e.information) for e in of]

    def tree_edges(of):
        return [(e.i, e.j, e.T_i_j, e.confidence) for e in of]

    scale = float(np.median([e.inlier_distance for e in usable]))
    poses = pose_graph.consensus_tree(tree_edges(usable), reference, max_angle_deg=gain * max_edge_error_deg,
                                      max_shift=lambda m: gain * max_shift * usable[m].inlier_distance)

    def check(edges, poses, angle_deg, spacings):
        out = []
        for e in edges:
            if e.kept and e.i in poses and e.j in poses and (min(e.i, e.j), max(e.i, e.j)) not in admitted:
                angle, shift = pose_graph.edge_error(poses[e.i], poses[e.j], e.T_i_j)
                if angle > angle_deg or shift > spacings * e.inlier_distance:
                    e = replace(e, kept=False, reason=f"cycle inconsistent ({angle:.2f} deg, {shift:.3g} off the graph)")
            out.append(e)
        return out

    def placed(edges, poses):
        return [e for e in edges if e.kept and e.i in poses and e.j in poses]

    # Edges the consensus tree contradicts are rejected; the rest are optimised robustly and
    # checked again at the final tolerance.
    edges = check(edges, poses, gain * max_edge_error_deg, gain * max_shift)
    poses = pose_graph.optimise(poses, graph(placed(edges, poses)), reference, translation_scale=scale,
                                direct_solve_max_poses=direct)
    edges = check(edges, poses, max_edge_error_deg, max_shift)
    kept = placed(edges, poses)
    poses = {k: T for k, T in pose_graph.consensus_tree(tree_edges(kept), reference, max_angle_deg=max_edge_error_deg,
                                                        max_shift=lambda m: float("inf")).items() if k in poses}
    poses = pose_graph.optimise(poses, graph(placed(edges, poses)), reference, translation_scale=scale,
                                direct_solve_max_poses=direct)
    edges = [e if not e.kept or (e.i in poses and e.j in poses) else replace(e, kept=False, reason="not connected to the reference")
             for e in edges]
    return poses, edges


def _free_space_conflicts(work: "_Scans", poses, edges, range_images, premise,
                          config: MergeConfig) -> tuple[dict, dict, str]:
    """(scans a free-space conflict cuts off from the reference, and the edges it cuts, as
    :func:`cut_off` gives them; what the check did, :attr:`MultiRegistrationResult.free_space_check`).

    ``poses`` are in the scans' centroid frames (``work``'s); ``work.centres[k]`` is scan k's
    centroid in its own frame, where its sensor is when it is a range image. ``range_images``:
    True or False as declared, None to test each posed scan (:func:`free_space.range_image_test`,
    on the subset the check uses, in the scan's own frame; the tests are kept in ``premise``, scan
    -> test, across calls). Only pairs of two range images are judged."""
    n, reference, small, centres = work.n, work.reference, work.small, work.centres
    if range_images is False:
        return {}, {}, "declared off"
    kept = [e for e in edges if e.kept and e.i in poses and e.j in poses]
    if not kept:
        return {}, {}, "too few edges"
    policy = config.registration.trust
    tolerance = policy.free_space_tolerance_inliers * float(np.median([e.inlier_distance for e in kept]))
    posed = sorted(poses)
    # on threads: the KD-tree builds and queries release the GIL
    with ThreadPoolExecutor() as pool:
        # each scan in its own frame (the sensor at the origin), and its pose from there
        points = work.own_frame(posed, policy, pool)
        if range_images is None:
            todo = [k for k in posed if k not in premise]
            premise.update(zip(todo, pool.map(lambda k: free_space.range_image_test(points[k], policy), todo)))
            seen = [k for k in posed if premise[k].range_image]
        else:
            seen = posed
        if len(seen) < 2:
            first = next(k for k in posed if not premise[k].range_image)
            others = len(posed) - len(seen)
            return {}, {}, (f"not range images: {others} of {len(posed)} placed scans are not, e.g. scan {first}: "
                            f"{premise[first].reason}")
        world = {k: poses[k] @ _shift(-centres[k]) for k in seen}
        views = work.range_views(seen, policy, pool)

        def fractions(pairs):
            return dict(zip(pairs, pool.map(
                lambda pair: free_space.pair_free_space(views, points, world, *pair, tolerance, policy), pairs)))

        on_kept = fractions(sorted({(min(e.i, e.j), max(e.i, e.j)) for e in kept if e.i in world and e.j in world}))
        near = candidates.near_pairs(seen, candidates.world_extents({k: poses[k] for k in seen}, small), set(on_kept),
                                     config.visibility_partners)
        measured = {**on_kept, **fractions(near)}
    conflicts = [(a, b, f) for (a, b), f in sorted(measured.items()) if f is not None and f > policy.max_free_space]
    cut, removed = cut_off(n, reference, [(e.i, e.j, e.confidence) for e in kept], conflicts, trusted=policy.trusted)
    if len(seen) == len(posed):
        return cut, removed, "applied"
    first = next(k for k in posed if k not in seen)
    return cut, removed, (f"applied to {len(seen)} of {len(posed)} placed scans; the others are not range images, "
                          f"e.g. scan {first}: {premise[first].reason}")


def _veto_reasons(removed: dict) -> dict:
    """``pair -> edge reason`` of the edges a free-space conflict cut."""
    return {pair: f"free-space conflict (scans {a} and {b} at these poses: {100 * f:.0f}% of one scan's surface "
                  f"where the other saw empty space)" for pair, (a, b, f) in removed.items()}


def _unconfirmed(n, reference, poses, edges) -> list[int]:
    """Scans that are not on a cycle of kept edges (and not the reference): where more pairs help."""
    verdicts = scan_verdicts(n, reference, set(poses), edges)
    return [k for k, v in enumerate(verdicts) if k != reference and not (v.status == "placed" and v.reasons[0].startswith("confirmed"))]


def _predicted_overlap(poses, small, edges, config: MergeConfig) -> candidates.PredictedOverlap:
    """What ``poses`` predict pairs of posed scans share, on the sparse subsets, within
    ``config.predict_radius_inliers`` median inlier distances of the kept edges."""
    distances = [e.inlier_distance for e in edges if e.kept and np.isfinite(e.inlier_distance)]
    scale = float(np.median(distances)) if distances else float("inf")
    return candidates.PredictedOverlap(poses, small, config.predict_radius_inliers * scale,
                                      points=config.predict_points)


def _closing(reference, poses, edges, small, unconfirmed, tried, config: MergeConfig,
             unlike: Callable[[], np.ndarray]) -> list[tuple[int, int]]:
    """Pairs to search for the posed scans in ``unconfirmed``: across each edge on no cycle of the
    kept graph (:func:`candidates.hanging_parts`), and for each scan contradicted in the
    reference's 2-edge-connected core, the pairs the poses predict to overlap most
    (:func:`candidates.closing_pairs`); across an edge on no cycle where the poses predict no
    such pair, the most similar pairs (``unlike()``: the scans' dissimilarities,
    :func:`candidates.similar_crossing_pairs`)."""
    if not unconfirmed:
        return []
    kept = [(e.i, e.j) for e in edges if e.kept and e.i in poses and e.j in poses]
    bridged = candidates.hanging_parts(reference, kept)
    hanging = set().union(*bridged)
    parts = bridged + [{k} for k in unconfirmed if k not in hanging]  # in the core, but contradicted
    out = candidates.closing_pairs(parts, candidates.world_extents(poses, small),
                                   _predicted_overlap(poses, small, edges, config), tried,
                                   min_overlap=config.min_predicted_overlap, per_part=config.closing_pairs,
                                   partners=config.predict_partners)
    if any(not any((i in part) != (j in part) for i, j in out) for part in bridged):
        out += candidates.similar_crossing_pairs(bridged, unlike(), poses, tried, out, per_part=config.closing_pairs)
    return out


class _Pieces:
    """Pairs that may join pieces of unplaced scans to the placed ones.

    The poses cannot say which scans of a piece (scans joined to each other by trusted edges, or a
    single scan) overlap which placed scans, but the piece as a whole can be placed: its scans
    fused at their poses within the piece, searched globally against the placed scans fused at
    theirs (one registration per piece each time the placed scans change). That pose predicts the
    pairs across (:class:`candidates.PredictedOverlap`), and only those pairs are searched, each
    globally: the piece's pose chooses the pairs and is never an edge or a start, so a wrong one
    only costs the searches it proposed. A piece whose pose predicts no pair, or whose proposed
    pairs placed nothing, gets the placed scans most like its own by the surface matching instead
    (:func:`candidates.bridging_pairs`, ``partners * min(len(piece), partners)`` pairs the first
    time, ``bridging_growth`` times more each time after: the pairs that join it may rank low)."""

    def __init__(self, pairwise: "_Pairwise", small, config: MergeConfig):
        self.pairwise, self.small, self.config = pairwise, small, config
        self.piece_points, self.partners = config.piece_points, config.partners
        self.placed_at: dict[frozenset, frozenset] = {}  # piece -> the placed scans it was last searched against
        self.blind: dict[frozenset, int] = {}  # piece -> rounds it was paired by similarity alone
        self.unlike = None  # the scans' dissimilarities (:func:`_unlike`), once asked for

    def dissimilarities(self) -> np.ndarray:
        """The scans' ``(N, N)`` dissimilarities (:func:`_unlike`), made once when first asked for."""
        if self.unlike is None:
            self.unlike = _unlike(self.small, self.config)
        return self.unlike

    def _fused(self, poses: dict) -> np.ndarray:
        points = np.concatenate([self.small[k] @ T[:3, :3].T + T[:3, 3] for k, T in sorted(poses.items())])
        return _subsample(points, self.piece_points)

    def _within(self, piece, vetoed) -> dict:
        """The piece's own poses (its first scan's frame) from its trusted edges."""
        if len(piece) == 1:
            return {piece[0]: np.eye(4)}
        inside = set(piece)
        own = [e for e in self.pairwise.edges.values() if e.i in inside and e.j in inside]
        return _solve(own, piece[0], self.config, vetoed)[0]

    def pairs(self, pieces, poses, edges, vetoed, stage: str) -> list[tuple[int, int]]:
        """Pairs that may join ``pieces`` (lists of unplaced scans) to the scans placed at
        ``poses``; the pieces not searched against these placed scans yet are placed as a whole
        first, one registration each: the progress ``stage``, recorded when it runs."""
        started = time.perf_counter()
        placed = frozenset(poses)
        fresh = [piece for piece in pieces if self.placed_at.get(frozenset(piece)) != placed]
        proposed: dict[int, np.ndarray] = {}
        if fresh:
            within = [self._within(piece, vetoed) for piece in fresh]
            target = self._fused(poses)
            found = self.pairwise.place_pieces([(self._fused(own), target) for own in within], stage)
            for piece, own, outcome in zip(fresh, within, found):
                self.placed_at[frozenset(piece)] = placed
                T = getattr(outcome, "transformation", None)
                if T is not None and np.isfinite(T).all():
                    proposed.update({k: T @ P for k, P in own.items()})
        everything = {**poses, **proposed}
        overlap = _predicted_overlap(everything, self.small, edges, self.config)
        extents = candidates.world_extents(everything, self.small)
        tried = self.pairwise.tried
        out, blind = [], []
        for piece in pieces:
            near = candidates.nearest_posed(
                [k for k in piece if k in proposed], extents,
                lambda i, j: j in poses and (min(i, j), max(i, j)) not in tried, self.config.predict_partners)
            scored = sorted(((overlap(i, j), i, j) for i, others in near.items() for j in others), reverse=True)
            per_scan = -(-self.partners // len(piece))
            used: dict[int, int] = {}
            chosen = []
            for value, i, j in scored:
                if value < self.config.min_predicted_overlap or len(chosen) >= self.partners:
                    break
                if used.get(i, 0) < per_scan and used.get(j, 0) < 1:
                    chosen.append((min(i, j), max(i, j)))
                    used[i], used[j] = used.get(i, 0) + 1, 1
            out.extend(chosen)
            if not chosen:  # no pose for the piece, or its proposals were searched last round
                blind.append(piece)
        by_pose = len(out)
        if blind:
            asked = set(out)
            # a piece left apart by its earlier pairs gets more of them each time: the pairs that join it may rank low
            widen = [self.config.bridging_growth ** self.blind.get(frozenset(piece), 0) for piece in blind]
            for piece in blind:
                self.blind[frozenset(piece)] = self.blind.get(frozenset(piece), 0) + 1
            out.extend(p for p in candidates.bridging_pairs(self.dissimilarities(), poses, blind, tried, self.partners,
                                                            widen) if p not in asked)
        if fresh:
            posed = sum(1 for piece in fresh if piece[0] in proposed)
            self.pairwise.stages.record(stage, started, pieces=len(pieces), searched=len(fresh), posed=posed,
                                        pairs_by_pose=by_pose, pairs_by_likeness=len(out) - by_pose)
        return out


def _unlike(small, config: MergeConfig) -> np.ndarray:
    """The scans' ``(N, N)`` dissimilarities, most similar first (:func:`candidates.matching_distances`
    on the sparse subsets, with ``config``'s ``match_*`` values)."""
    return candidates.matching_distances(small, candidates=config.match_candidates,
                                         radius_spacings=config.match_radius_spacings,
                                         normal_neighbours=config.match_normal_neighbours, count=config.match_points)


def _apart(n, poses, edges) -> tuple[str, ...]:
    """One note per piece of two or more unplaced scans joined to each other by trusted edges but
    not to the reference: which scans stand apart together, and how many pairs across were tried."""
    unplaced = [k for k in range(n) if k not in poses]
    joined = [(e.i, e.j) for e in edges if e.trusted and not e.reason.startswith(("cycle", "free-space"))]
    out = []
    for piece in candidates.pieces(unplaced, joined):
        if len(piece) < 2:
            continue
        inside = set(piece)
        across = [e for e in edges if (e.i in inside) != (e.j in inside) and (e.i in poses or e.j in poses)]
        out.append(f"scans {_ranges(piece)} ({len(piece)} scans) are joined to each other but not to the placed "
                   f"scans: {len(across)} pair(s) across were searched, none trusted and agreeing")
    return tuple(out)


def _ranges(scans: list[int]) -> str:
    """``[0, 1, 2, 5, 7, 8]`` -> ``"0-2, 5, 7-8"``."""
    out, first = [], None
    for n, k in enumerate(scans):
        if first is None:
            first = k
        if n + 1 == len(scans) or scans[n + 1] != k + 1:
            out.append(f"{first}-{k}" if k > first else f"{k}")
            first = None
    return ", ".join(out)


def register_scans(
    clouds,
    *,
    reference: int = 0,
    sequence: bool = False,
    pair_points: int | None = None,
    refine_points: int | None = None,
    partners: int | None = None,
    sequence_neighbours: int | None = None,
    max_edge_error_deg: float | None = None,
    refine_rounds: int | None = None,
    range_images: bool | None = None,
    threads: int | None = None,
    processes: int | None = None,
    client=None,
    progress: Callable[[str, int, int], None] | None = None,
    config: MergeConfig | dict | None = None,
    **register_kwargs,
) -> MultiRegistrationResult:
    """Register N scans into one frame, with no initial poses; say plainly which scans are placed.

    Parameters
    ----------
    clouds : sequence of (N_k, 3) array-likes
        The scans, each in its own frame. Never modified.
    reference : int
        The scan whose frame is the world (``poses[reference]`` is the identity).
    sequence : bool
        The input order is the capture order, consecutive scans close in pose (a walk, an object
        turned in small steps): each scan is registered with its next ``sequence_neighbours`` scans
        (locally from the identity, globally when that is not trusted), then loop closures are
        sought among placed scans that overlap in the world. Without it the order means nothing.
    pair_points, refine_points : int, optional
        Points per scan (a content-seeded random subset) for the pairwise global searches, and for
        the local refinement that checks each pair (and judges it: its confidence) and the joint
        refinement; at least 3 (:data:`esmicp.types.MIN_POINTS`, what a registration needs).
        These keywords and the five below are fields of ``config`` too: each one given (not None)
        wins over ``config``'s field; None (the default) takes ``config``'s (by default
        :class:`~esmicp.config.MergeConfig`'s: 1500 and 8000 points, ``partners=2``,
        ``sequence_neighbours=2``, ``max_edge_error_deg=2.0``, ``refine_rounds=6``).
    partners : int, optional
        Without ``sequence``: each scan is first registered with its ``partners`` most similar scans
        (their surface features matched). Then, each round, each piece of scans not placed (scans
        joined to each other, or one scan) gets up to ``partners`` pairs with the placed scans:
        those its pose as a whole predicts to overlap, else those most like its scans, each scan in
        at most ``partners``. (Scans placed but not yet confirmed get one pair across each edge on
        no cycle, whatever ``partners``.)
    sequence_neighbours : int, optional
        With ``sequence``: each scan with the next this many scans (2 gives triangles, so every
        scan can be confirmed around a cycle).
    max_edge_error_deg : float, optional
        After the robust pose graph, a trusted edge disagreeing with the poses by more than this
        rotation (or by more than 3x its inlier distance in translation) is rejected as cycle
        inconsistent.
    refine_rounds : int, optional
        Correspondence distances of the joint refinement (each used for two Gauss-Newton steps;
        0: none).
    range_images : bool or None
        Whether every scan is a range image seen from its own origin (a depth-camera frame or a
        LiDAR scan in its sensor frame), the premise of the free-space check: True or False as
        you know it; None (default) to judge each scan from its own points
        (:func:`esmicp.trust.free_space.range_image_test`). Only pairs of two range images are
        checked; :attr:`MultiRegistrationResult.free_space_check` says what was done.
    threads, processes, client
        Where the pairwise registrations run, as in :func:`esmicp.register_many`: by default a
        thread pool on every core (works from any script, no ``__main__`` guard needed); or a
        spawned process pool of ``processes``; or a Dask ``client``. Each registration runs its
        kernels on one thread (``workers=1``) when several run at once, unless ``workers`` is given.
    progress : callable, optional
        ``progress(stage, done, total)``, called in this thread as the merge goes through its
        stages, one after the other: ``"pairs"`` (with ``sequence``, then ``"pairs (global
        retry)"`` and ``"pairs (loop closures)"``, the latter again after a round that poses scans
        not posed before), ``"more pairs (round r)"`` each time the graph
        asks for more (preceded by ``"piece pairs (round r)"`` when pieces of unplaced scans are
        placed as a whole to propose their pairs, one registration per piece), ``"pose graph"``
        whenever the graph is solved (``"joint refinement (cycle check)"`` once before the first
        round of more pairs when the graph rejected a trusted edge as cycle inconsistent and a
        posed scan is unconfirmed), ``"joint refinement"`` and ``"free-space check"``. Each
        stage opens with ``done == 0`` and its ``total``, which stays fixed; ``done`` never
        decreases, and the stage closes with ``done == total`` before the next opens. A pairs
        stage counts registrations, two per pair (the search and its check); the other stages
        count 1 when done. The pose graph, refinement and check stages recur
        (after every round of pairs; once more when a free-space conflict vetoes edges).
    config : esmicp.config.MergeConfig or dict, optional
        The merge's tuned values (a dict is read by :meth:`~esmicp.core.config.Config.from_dict`);
        None: the measured defaults. The keywords above that are also its fields win over it, so
        ``register_scans(clouds, partners=3)`` and ``register_scans(clouds,
        config=MergeConfig(partners=3))`` are the same merge.
    **register_kwargs
        Passed to every pairwise :func:`esmicp.register` call (its ``config`` is
        ``config.registration``).

    Returns
    -------
    MultiRegistrationResult
        Poses, a verdict per scan (``status``, ``scan_confidence``, ``reasons``, ``edges_kept``,
        ``residual``), every edge tried, and what each stage did (``stages``, in order, each a
        :class:`esmicp.result.Stage` whose ``decided`` holds its counts): ``"prepare"`` (scans,
        exact ``duplicates``, the subsets' points), ``"rank pairs"`` (without ``sequence``: the first
        ``pairs`` chosen by likeness), each stage of pairs (as ``progress`` names it: the ``pairs``
        registered, ``searched`` globally or ``refined`` from a start, ``registrations`` run,
        ``trusted``, ``failed``, ``redrawn`` on a second draw; a round of more pairs also the
        ``unconfirmed`` posed scans and ``unplaced`` scans it was asked for, a stage of loop closures the
        scans ``posed`` when they were sought; a stage of piece pairs
        the ``pieces``, those ``searched`` and ``posed`` as a whole, and the pairs they proposed),
        ``"pose graph"`` each time it is solved (``edges``, ``trusted``, ``kept``, ``vetoed``,
        ``cycle_inconsistent``, ``not_connected``, scans ``posed``), ``"joint refinement (cycle
        check)"`` and ``"joint refinement"`` (scans, edges, rounds, ``rmse``), ``"free-space
        check"`` (what it did, ``edges_cut``, ``scans_cut_off``) and ``"verdict"`` (scans
        ``placed``, ``doubtful``, ``unplaced``, ``edges_kept``).

    Notes
    -----
    Work: without ``sequence``, ``N * match_candidates`` matchings of surface features at most (a
    few milliseconds each) to rank the pairs, then about ``N * partners * 0.7`` global searches (the
    union of every scan's ``partners`` most similar), each followed by a local check on the dense
    subsets; then in each round one per edge on no cycle, and per piece of unplaced scans one
    registration of the piece as a whole and up to ``partners`` pairs
    (``partners * min(len(piece), partners)`` when its pose proposes none), until
    ``stalled_rounds`` rounds in a row place or confirm no scan. With ``sequence``, about
    ``N * sequence_neighbours`` local refinements (a global search for those they leave untrusted
    where the walk needs them), at most ``N * loop_searches_per_scan`` loop closures, then the
    same rounds.

    Memory, for 1,000 scans of 20,000 points (the input clouds, 480 MB as float64, stay the caller's): per
    scan, the sparse subset (``pair_points`` x 24 bytes: 36 KB) and the dense one (``refine_points`` x 24
    bytes: 192 KB), its normals (192 KB) and, from its first edge to the end of the merge, a
    compiled KD-tree over it (about 320 KB): about 0.75 MB a scan, 0.75 GB for 1,000 at the defaults (linear in
    ``refine_points``). Per kept edge, the refinement's last neighbours (2 x ``query_points`` x 8 bytes: 16 KB;
    about 0.05 GB for 3,000 edges); the pose graph's sparse Jacobian (72 numbers per edge and residual block, a
    few MB for 5,000 edges) and the refinement's block-sparse normal matrix (two 6x6 blocks per kept edge). The
    free-space check holds, per posed scan, from its first call to the end of the merge, a 4,000-point subset
    and a KD-tree of its directions (about 0.25 MB; 0.25 GB for 1,000 scans). Choosing pairs from poses holds,
    per posed scan asked about, its sparse subset in the world frame and a KD-tree over it (about 0.1 MB;
    0.1 GB for 1,000 scans, while the pairs are chosen). Ranking the first pairs holds, per scan,
    its ``match_points`` surface features and a KD-tree over them (about 0.25 MB; 0.25 GB for
    1,000 scans, while they are ranked). The N x N arrays are the scans' dissimilarities (8 MB for
    1,000 scans) and, with ``sequence``, the graph's path lengths while the
    loop closures are chosen (8 MB, and as much again for each update). Each
    registration running at once holds its own pair's working set besides. Measured
    (``benchmarks/merge_scale.py``: 1,000 scans of 8,000 points, 2,997 edges): peak memory 1.15
    GB; consensus tree, pose graph and joint refinement 1.7 s, 6 s and 136 s on 2 cores.
    """
    started = time.perf_counter()
    scans, reference, config, range_images = _checked(
        clouds, reference, config, range_images, progress, pair_points=pair_points, refine_points=refine_points,
        partners=partners, sequence_neighbours=sequence_neighbours, max_edge_error_deg=max_edge_error_deg,
        refine_rounds=refine_rounds)
    sequence, plan = bool(sequence), _Plan(progress)
    work = _prepare(scans, reference, config, plan, started)
    pairwise = _Pairwise(work.centred, work.small, work.dense, work.keys, sequence,
                         {"threads": threads, "processes": processes, "client": client,
                          "config": config.registration, **register_kwargs}, plan, config, work.tree)
    pieces = _Pieces(pairwise, work.small, config)
    graph = _Graph(pairwise, work.reference, config, plan)
    _first_pairs(work, pairwise, pieces, sequence, config, plan)
    poses, edges = graph.solve()
    loops = _Loops(work, pairwise, graph, config) if sequence and work.n > config.sequence_neighbours + 1 else None
    if loops is not None:
        poses, edges = loops(poses, edges)
    premise: dict[int, free_space.RangeImageTest] = {}  # posed scans' range-image tests, made once
    rounds = 1  # rounds of pairs, for the stages' names
    for attempt in range(2):
        poses, edges, rounds = _more_pairs(work, pairwise, pieces, graph, poses, edges, rounds, config, loops)
        poses, rmse, residual = _joint_refinement(work, poses, edges, config, plan)
        # on the refined poses (the graph's alone drift along a walk and conflict falsely): the
        # edges a conflict disproves are cut once, and the scans they placed searched again
        check = _free_space_check(work, poses, edges, range_images, premise, config, plan)
        if not check.removed or attempt == 1:
            break
        graph.veto(check.removed)
        poses, edges = graph.solve()
    result = _verdict(work, poses, edges, rmse, residual, check, pairwise.done, plan)
    for note in result.notes:
        logger.warning("register_scans: %s", note)
    return replace(result, runtime_s=time.perf_counter() - started)


def _checked(clouds, reference, config, range_images, progress, **given) -> tuple:
    """``(scans, reference, config, range_images)``: :func:`register_scans`'s arguments checked,
    ``given`` (its keywords that are :class:`~esmicp.config.MergeConfig` fields, None when not
    given) laid over ``config``.

    Raises
    ------
    InvalidInputError
        An argument is not what :func:`register_scans` takes, naming it.
    """
    try:
        scans = [as_points(c, f"clouds[{k}]") for k, c in enumerate(clouds)]
    except TypeError:
        raise InvalidInputError("clouds: expected a sequence of (N, 3) point arrays") from None
    n = len(scans)
    if n < 1:
        raise InvalidInputError("clouds: expected at least one scan")
    if isinstance(reference, bool) or not isinstance(reference, (int, np.integer)) or not 0 <= reference < n:
        raise InvalidInputError(f"reference: expected a scan index in [0, {n}), got {reference!r}")
    config = replace(MergeConfig.of(config), **{name: MergeConfig.checked(name, value, name)
                                                 for name, value in given.items() if value is not None})
    if range_images is not None and not isinstance(range_images, (bool, np.bool_)):
        raise InvalidInputError(f"range_images: expected True, False or None, got {range_images!r}")
    if progress is not None and not callable(progress):
        raise InvalidInputError(f"progress: expected a callable(stage, done, total), got {type(progress).__name__}")
    return scans, int(reference), config, None if range_images is None else bool(range_images)


@dataclass(frozen=True)
class _Scans:
    """The scans one merge registers: one of each group of exact duplicates, each in its centroid
    frame, with its subsets.

    ``twin[k]``: the input scan that input scan k duplicates (itself when none); ``unique``: the
    input indices of the scans merged, in order; the other fields are per merged scan, by position
    in ``unique``: ``reference`` (the reference's position), ``centres`` (centroids in the frames
    given), ``centred`` (the points minus their centroid), ``small`` and ``dense`` (the sparse and
    dense subsets, :func:`_subsample`), ``keys`` (:func:`_shape_key`)."""

    twin: list[int]
    unique: list[int]
    reference: int
    centres: list[np.ndarray]
    centred: list[np.ndarray]
    small: list[np.ndarray]
    dense: list[np.ndarray]
    keys: list[tuple[int, float]]
    made: dict = field(default_factory=dict, repr=False, compare=False)  # (what, scan) -> made once, see below

    @property
    def n(self) -> int:
        """How many scans are merged."""
        return len(self.unique)

    def fine(self, scans, neighbours: int) -> tuple[dict, dict, dict]:
        """For each of ``scans``, in its centroid frame: a compiled KD-tree over its dense subset,
        that subset's normals (from its ``neighbours`` nearest points) and its median point spacing
        (distance to the nearest other point, cloud units), as three dicts scan -> value. Each is
        made once per merge and scan: the joint refinement asks again after a free-space conflict."""
        for k in scans:
            if ("fine", k) not in self.made:
                tree = self.tree(k)
                normals = estimate_normals(self.dense[k], k=neighbours, tree=tree, workers=None)
                spacing = float(np.median(tree.query_k(self.dense[k], 2)[0][:, 1]))
                self.made["fine", k] = (neighbours, tree, normals, spacing)
        made = {k: self.made["fine", k] for k in scans}
        if any(m[0] != neighbours for m in made.values()):
            raise ValueError("one merge asks for its normals from one number of neighbours")
        return ({k: m[1] for k, m in made.items()}, {k: m[2] for k, m in made.items()},
                {k: m[3] for k, m in made.items()})

    def tree(self, k: int) -> CompiledTree:
        """A compiled KD-tree over scan k's dense subset, in its centroid frame; made once per merge
        and scan (each edge's reverse fitness and the joint refinement query it)."""
        if ("tree", k) not in self.made:
            self.made["tree", k] = CompiledTree(self.dense[k])
        return self.made["tree", k]

    def own_frame(self, scans, policy, pool) -> dict:
        """Scan -> its ``policy.free_space_points`` subset of its dense subset, in its own frame
        (its sensor at the origin when it is a range image), for each of ``scans``; made once per
        merge and scan on ``pool``'s threads (the free-space check asks again after a conflict).
        One merge has one ``policy``."""
        todo = [k for k in scans if ("own frame", k) not in self.made]
        for k, p in zip(todo, pool.map(lambda k: _subsample(self.dense[k], policy.free_space_points) + self.centres[k],
                                       todo)):
            self.made["own frame", k] = p
        return {k: self.made["own frame", k] for k in scans}

    def range_views(self, scans, policy, pool) -> dict:
        """Scan -> the :class:`free_space.RangeView` of its :meth:`own_frame` subset, for each of
        ``scans``; made once per merge and scan, as :meth:`own_frame`."""
        points = self.own_frame(scans, policy, pool)
        todo = [k for k in scans if ("range view", k) not in self.made]
        for k, v in zip(todo, pool.map(lambda k: free_space.RangeView(points[k], policy), todo)):
            self.made["range view", k] = v
        return {k: self.made["range view", k] for k in scans}


def _prepare(scans: list[np.ndarray], reference: int, config: MergeConfig, plan: _Plan, started: float) -> _Scans:
    """The stage ``"prepare"``: the exact duplicates set aside (an exact duplicate confirms nothing:
    the merge runs on one scan of each group of twins), the others moved to their centroid frames
    and subsampled.

    Each scan is registered in its centroid frame (its points minus their centroid): every
    translation the merge measures (an edge's disagreement with the poses, the pose graph's
    residuals, the joint refinement's steps) is then a displacement at the scan's own points,
    whatever the origin of the frame it was given in; the poses are mapped back at the end."""
    twin = _exact_twins(scans, reference)
    unique = [k for k in range(len(scans)) if twin[k] == k]
    centres = [scans[k].mean(axis=0) if len(scans[k]) else np.zeros(3) for k in unique]
    centred = [scans[k] - c for k, c in zip(unique, centres)]
    small = [_subsample(s, config.pair_points) for s in centred]
    dense = [_subsample(s, config.refine_points) for s in centred]
    work = _Scans(twin, unique, unique.index(reference), centres, centred, small, dense,
                  [_shape_key(s) for s in centred])
    plan.record("prepare", started, points=sum(len(s) for s in scans), scans=len(scans),
                duplicates=len(scans) - len(unique), pair_points=sum(len(s) for s in small),
                refine_points=sum(len(s) for s in dense))
    return work


class _Graph:
    """The pose graph of one merge, solved over the edges tried so far (:func:`_solve`) less those a
    free-space conflict vetoed: the stage ``"pose graph"`` each time."""

    def __init__(self, pairwise: _Pairwise, reference: int, config: MergeConfig, plan: _Plan):
        self.pairwise, self.reference, self.config, self.plan = pairwise, reference, config, plan
        self.vetoed: dict[tuple[int, int], str] = {}  # edges cut by a free-space conflict -> why
        self.admitted: set[tuple[int, int]] = set()  # edges the surfaces kept after the graph rejected them

    def solve(self) -> tuple[dict, list[Edge]]:
        """(poses of the scans joined to the reference, every edge with ``kept``/``reason`` set)."""
        self.plan.open("pose graph", 1)
        started = time.perf_counter()
        poses, edges = _solve(list(self.pairwise.edges.values()), self.reference, self.config, self.vetoed,
                              self.admitted)
        self.plan.close()
        self.plan.record("pose graph", started, edges=len(edges), trusted=sum(e.trusted for e in edges),
                         kept=sum(e.kept for e in edges), vetoed=sum(e.reason.startswith("free-space") for e in edges),
                         cycle_inconsistent=sum(e.reason.startswith("cycle") for e in edges),
                         not_connected=sum(e.reason == "not connected to the reference" for e in edges),
                         posed=len(poses))
        return poses, edges

    def admit(self, before: list[Edge], after: list[Edge]) -> None:
        """Remember the edges :func:`_rejudged` kept (``before`` the graph's edges, ``after`` its
        answer, edge for edge): every later solve keeps them unless a free-space conflict cuts them."""
        self.admitted.update((min(a.i, a.j), max(a.i, a.j)) for b, a in zip(before, after) if a.kept and not b.kept)

    def veto(self, removed: dict) -> None:
        """Cut the edges a free-space conflict disproved (``removed``, as :func:`cut_off` gives them)."""
        self.vetoed.update(_veto_reasons(removed))


def _first_pairs(work: _Scans, pairwise: _Pairwise, pieces: _Pieces, sequence: bool, config: MergeConfig,
                 plan: _Plan) -> None:
    """The first pairs, registered: with ``sequence``, each scan with its next
    ``config.sequence_neighbours`` refined from the identity, then the untrusted ones the walk needs
    searched globally (``"pairs (global retry)"``); without, each scan with its ``config.partners``
    most similar scans (the stage ``"rank pairs"``), searched globally."""
    n = work.n
    if sequence:
        # from the identity in the frames given: a shift between the centroid frames
        pairwise.run([(i, j, _shift(work.centres[j] - work.centres[i]))
                      for i, j in candidates.sequence_pairs(n, config.sequence_neighbours)])
        # a pair the identity start did not bring to trust is searched globally where the walk
        # needs it: where the trusted pairs leave one of its scans off every cycle through the reference
        core = candidates.two_edge_core(work.reference, [(e.i, e.j) for e in pairwise.edges.values() if e.trusted])
        retry = [(e.i, e.j, None) for e in pairwise.edges.values() if not e.trusted and not {e.i, e.j} <= core]
        pairwise.run(retry, "pairs (global retry)")
    elif n > 1:
        started = time.perf_counter()
        ranked = candidates.ranked_partners(pieces.dissimilarities())
        first = {(min(i, j), max(i, j)) for i in range(n) for j in ranked[i][:config.partners]}
        plan.record("rank pairs", started, scans=n, pairs=len(first))
        pairwise.run([(i, j, None) for i, j in sorted(first)])


class _Loops:
    """With a sequence, the loop closures (``"pairs (loop closures)"``, the graph solved again):
    pairs of posed scans the graph's poses predict to overlap, searched globally, those the graph
    joins by the longest path first (:func:`candidates.loop_pairs`), at most
    ``config.loop_searches_per_scan`` per posed scan over the whole merge.

    Sought once the first pairs are solved, over the scans posed then, and again each time a
    round of more pairs poses scans that were not (a walk whose first pairs break where frames
    are missing or the view jumps: the far side is joined later, by the pairs its piece proposes),
    within what is left of the budget, where the new scans' loops are the longest bypasses: the
    loops that tie the far side to the near one are searched before the joint refinement and the
    free-space check judge the poses, rather than left to a single bridge."""

    def __init__(self, work: _Scans, pairwise: "_Pairwise", graph: "_Graph", config: MergeConfig):
        self.work, self.pairwise, self.graph, self.config = work, pairwise, graph, config
        self.searched = 0  # loop closures searched so far
        self.posed: frozenset[int] | None = None  # the scans posed when loops were last sought

    def __call__(self, poses: dict, edges: list[Edge]) -> tuple[dict, list[Edge]]:
        """(poses, edges), the graph solved again when loops were sought: the first call always,
        a later one when scans are posed that were not at the last and a search is left."""
        first = self.posed is None
        if not first and set(poses) <= self.posed:
            return poses, edges
        self.posed = frozenset(poses) | (self.posed or frozenset())
        work, config = self.work, self.config
        budget = int(np.ceil(config.loop_searches_per_scan * len(poses))) - self.searched
        loops = []
        if budget > 0:
            extents = candidates.world_extents(poses, work.small)
            kept = [(e.i, e.j) for e in edges if e.kept and e.i in poses and e.j in poses]
            loops = candidates.loop_pairs(kept, extents, _predicted_overlap(poses, work.small, edges, config),
                                          self.pairwise.tried, min_overlap=config.min_predicted_overlap,
                                          min_hops=config.loop_min_hops, budget=budget,
                                          partners=config.predict_partners)
        if not first and not loops:
            return poses, edges
        self.searched += len(loops)
        self.pairwise.run([(i, j, None) for i, j in loops], "pairs (loop closures)", posed=len(poses))
        return self.graph.solve()


def _more_pairs(work: _Scans, pairwise: _Pairwise, pieces: _Pieces, graph: _Graph, poses: dict, edges: list[Edge],
                rounds: int, config: MergeConfig, loops: _Loops | None = None) -> tuple[dict, list[Edge], int]:
    """Rounds of more pairs only where a scan is not yet confirmed (``"more pairs (round r)"``, the
    graph solved after each), until ``config.stalled_rounds`` rounds in a row place or confirm no
    scan or no pair is left to ask for: (poses, edges, the rounds of pairs run so far). Before the
    first round, when a posed scan is unconfirmed and the graph rejected a trusted edge between
    posed scans as cycle inconsistent, those edges are judged again against the surfaces, once
    (:func:`_rejudged`). With ``loops`` (a sequence), a round that poses scans not posed before
    has their loop closures sought after it (:class:`_Loops`)."""
    n, reference = work.n, work.reference
    stalled, best = 0, -1  # rounds in a row that placed or confirmed no scan; the most placed and confirmed
    first = True
    while n > 1 and stalled < config.stalled_rounds:
        unconfirmed = _unconfirmed(n, reference, poses, edges)
        if first and any(k in poses for k in unconfirmed) and any(_cycle_rejected(e, poses) for e in edges):
            # the graph's poses may have pinned what the pairwise estimates' small errors add up to
            # around a long cycle on one right edge: the surfaces judge it again, once, before pairs are asked for
            rejudged = _rejudged(work, poses, edges, config, graph.plan)
            graph.admit(edges, rejudged)
            edges = rejudged
            unconfirmed = _unconfirmed(n, reference, poses, edges)
        first = False
        settled = len(poses) + n - len(unconfirmed)
        stalled, best = (0, settled) if settled > best else (stalled + 1, best)
        if stalled >= config.stalled_rounds:
            break
        posed = [k for k in unconfirmed if k in poses]
        wanted = _closing(reference, poses, edges, work.small, posed, pairwise.settled(), config,
                          pieces.dissimilarities)
        unplaced = [k for k in unconfirmed if k not in poses]
        if unplaced:  # not placed at all: each piece of them placed as a whole proposes its pairs
            joined = [(e.i, e.j) for e in edges if e.trusted and not e.reason.startswith(("cycle", "free-space"))]
            asked = set(wanted)
            wanted.extend(p for p in pieces.pairs(candidates.pieces(unplaced, joined), poses, edges, graph.vetoed,
                                                  f"piece pairs (round {rounds + 1})") if p not in asked)
        if not wanted:
            break
        rounds += 1
        pairwise.run([(i, j, None) for i, j in wanted], f"more pairs (round {rounds})", unconfirmed=len(posed),
                     unplaced=len(unplaced))
        poses, edges = graph.solve()
        if loops is not None:
            poses, edges = loops(poses, edges)
    return poses, edges, rounds


def _joint_refinement(work: _Scans, poses: dict, edges: list[Edge], config: MergeConfig,
                      plan: _Plan, stage: str = "joint refinement") -> tuple[dict, float | None, dict]:
    """The stage ``"joint refinement"`` (or ``stage``; :func:`refine`, when an edge is kept and
    ``config.refine_rounds`` > 0): (poses, the last step's RMS residual or None, scan -> its
    residual). ``poses`` itself is left as it was."""
    kept_pairs = [(e.i, e.j) for e in edges if e.kept and e.i in poses and e.j in poses]
    if not kept_pairs or config.refine_rounds <= 0:
        return poses, None, {}
    poses = dict(poses)
    plan.open(stage, 1)
    started = time.perf_counter()
    fine = {k: work.dense[k] for k in poses}
    # one compiled KD-tree per scan gives its normals, its point spacing and the refinement's queries
    trees, fine_normals, spacings = work.fine(fine, config.refine_normal_neighbours)
    scale = float(np.median([e.inlier_distance for e in edges if e.kept]))
    fine_spacing = float(np.median([spacings[k] for k in fine]))
    reach = np.geomspace(config.refine_reach_inliers * scale, max(config.refine_floor_spacings * fine_spacing, 1e-12),
                         config.refine_rounds)
    poses, rmse, residual = refine(poses, fine, fine_normals, kept_pairs, work.reference, reach,
                                   query_points=config.query_points, rounds_per_distance=config.refine_steps,
                                   huber_ratio=config.refine_huber_ratio, min_pairs=config.refine_min_pairs,
                                   trees=trees)
    plan.close()
    plan.record(stage, started, points=sum(len(f) for f in fine.values()), scans=len(fine),
                edges=len(kept_pairs), rounds=config.refine_rounds, rmse=rmse)
    return poses, rmse, residual


def _cycle_rejected(edge: Edge, poses: dict) -> bool:
    """A trusted edge between two posed scans that the pose graph rejected as cycle inconsistent."""
    return edge.trusted and edge.reason.startswith("cycle inconsistent") and edge.i in poses and edge.j in poses


def _rejudged(work: _Scans, poses: dict, edges: list[Edge], config: MergeConfig, plan: _Plan) -> list[Edge]:
    """``edges``, each trusted edge the graph rejected as cycle inconsistent kept again when it
    agrees within the graph's own bounds (``max_edge_error_deg``, ``max_edge_shift_inliers``
    inlier distances) with the poses a joint refinement of the graph's ``poses`` over the kept
    edges gives (the stage ``"joint refinement (cycle check)"``; the refined poses judge only,
    the merge goes on from the graph's).

    The pose graph weighs the pairwise estimates alone: their small errors, when they lean the
    same way, add up around a long cycle (a ring of scans of an object turned a step at a time
    closes several degrees off when each pair is a few tenths of a degree off), and the robust
    loss pins the sum on one right edge. The refined poses come from the surfaces of the kept edges, never from the
    rejected edge, so a wrong edge stays rejected. With no refinement (``refine_rounds`` 0) the
    edges stay as the graph left them."""
    refined, _, _ = _joint_refinement(work, poses, edges, config, plan, stage="joint refinement (cycle check)")
    if refined is poses:
        return edges
    out = []
    for e in edges:
        if _cycle_rejected(e, refined):
            angle, shift = pose_graph.edge_error(refined[e.i], refined[e.j], e.T_i_j)
            if angle <= config.max_edge_error_deg and shift <= config.max_edge_shift_inliers * e.inlier_distance:
                e = replace(e, kept=True, reason="kept")
        out.append(e)
    return out


@dataclass(frozen=True)
class _Check:
    """What the free-space check found: ``conflicted`` and ``removed`` as :func:`cut_off` gives them
    (the scans a conflict cuts off from the reference, the edges it cuts), and ``checked``
    (:attr:`MultiRegistrationResult.free_space_check`)."""

    conflicted: dict
    removed: dict
    checked: str


def _free_space_check(work: _Scans, poses: dict, edges: list[Edge], range_images: bool | None, premise: dict,
                      config: MergeConfig, plan: _Plan) -> _Check:
    """The stage ``"free-space check"`` (:func:`_free_space_conflicts`)."""
    plan.open("free-space check", 1)
    started = time.perf_counter()
    check = _Check(*_free_space_conflicts(work, poses, edges, range_images, premise, config))
    plan.close()
    plan.record("free-space check", started, check=check.checked, edges_cut=len(check.removed),
                scans_cut_off=len(check.conflicted))
    return check


def _verdict(work: _Scans, poses: dict, edges: list[Edge], rmse: float | None, residual: dict, check: _Check,
             registered: int, plan: _Plan) -> MultiRegistrationResult:
    """The stage ``"verdict"``: a verdict per scan (:func:`scan_verdicts`), the poses and edges
    mapped back to the frames given, and every exact duplicate given its twin's pose and verdict;
    the result, with every stage recorded."""
    started = time.perf_counter()
    n, reference, centres = work.n, work.reference, work.centres
    verdicts = scan_verdicts(n, reference, set(poses), edges, check.conflicted)
    # back to the frames given: T_world_k = C_reference T'_world_k C_k^-1, T_i_j = C_i T'_i_j C_j^-1
    all_poses = np.full((n, 4, 4), np.nan)
    for k, T in poses.items():
        all_poses[k] = _shift(centres[reference]) @ T @ _shift(-centres[k])
    all_poses[reference] = np.eye(4)
    edges = [replace(e, T_i_j=_shift(centres[e.i]) @ e.T_i_j @ _shift(-centres[e.j]),
                     information=_information_moved(e.information, centres[e.i])) for e in edges]
    status = tuple(v.status for v in verdicts)
    notes = _apart(n, poses, edges) + tuple(f"scan {k}: {v.status}: {'; '.join(v.reasons)}"
                                            for k, v in enumerate(verdicts) if v.status != "placed")
    result = MultiRegistrationResult(
        all_poses, reference, tuple(s == "placed" for s in status),
        tuple(k for k in range(n) if status[k] == "unplaced"), tuple(edges), 0.0,
        rmse, notes, status=status, scan_confidence=tuple(v.confidence for v in verdicts),
        reasons=tuple(v.reasons for v in verdicts), edges_kept=tuple(v.edges_kept for v in verdicts),
        residual=tuple(residual.get(k) for k in range(n)), pairs_registered=registered,
        free_space_check=check.checked,
    )
    if work.n < len(work.twin):
        result = _with_twins(result, work.unique, work.twin)
    plan.record("verdict", started, placed=result.status.count("placed"), doubtful=result.status.count("doubtful"),
                unplaced=result.status.count("unplaced"), edges_kept=len(result.kept_edges))
    return replace(result, stages=tuple(plan.records))
