"""Per-scan verdicts of :func:`esmicp.register_scans`: placed, doubtful or unplaced, and why.

The evidence is the pairwise edges (:class:`esmicp.multiview.Edge`). An edge is *usable* when its
pairwise result is trusted (:attr:`esmicp.RegistrationResult.trusted`: confidence at the trust bar,
not ambiguous, no degenerate direction); the pose graph keeps the usable edges that agree with the solved poses and
rejects the others as cycle inconsistent. A scan is then

* ``"placed"``: the reference scan; or posed and confirmed: joined to the reference by two paths
  of kept edges with no edge in common (its pose is checked around a cycle), with more kept
  edges than contradicting ones; or, in a merge of two scans, posed by their one trusted edge
  (no third scan could check it);
* ``"doubtful"``: posed, but usable edges contradict its pose, or it is joined to the reference
  only across a bridge (an edge on no cycle, which nothing checks: one wrong trusted edge would
  place it, and every scan beyond it, wrongly), or its pose puts surfaces where another placed
  scan saw empty space (:mod:`esmicp.trust.free_space`; :func:`cut_off` says which side of
  the conflict is cut off from the reference);
* ``"unplaced"``: no pose, with the reason (no usable edge at all: another object, no shared
  surface, too few points; or usable edges only to scans not joined to the reference).

``scan_confidence`` is the strongest kept edge's confidence for a placed scan (1.0 for the
reference); for a doubtful one, that minus the strongest contradicting edge's when contradicted,
else half of it (one unchecked edge counts as half a checked one), so that it falls below the
trust bar; 0 when a free-space conflict disproves it; None for an unplaced one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, maximum_flow

from .pairs import two_edge_core


@dataclass(frozen=True)
class ScanVerdict:
    """One scan's verdict: ``status`` ("placed" / "doubtful" / "unplaced"), ``confidence`` (0-1, None
    when unplaced), ``edges_kept`` (kept edges touching it), ``edges_contradicting`` (usable edges
    touching it rejected as cycle inconsistent) and ``reasons`` (plain sentences)."""

    status: str
    confidence: float | None
    edges_kept: int
    edges_contradicting: int
    reasons: tuple[str, ...]


def _best(edges, k):
    """The edge touching ``k`` with the highest confidence (None if none has one)."""
    scored = [e for e in edges if e.confidence is not None]
    return max(scored, key=lambda e: e.confidence, default=None)


def _describe(edge, k) -> str:
    other = edge.j if edge.i == k else edge.i
    flags = ", ambiguous" if edge.ambiguous else ""
    return f"scan {other}: confidence {edge.confidence:.2f}{flags}"


def bridges(edges: list[tuple[int, int]]) -> set[tuple[int, int]]:
    """The bridges of an undirected graph (edges on no cycle), as ``(min, max)`` pairs (Tarjan's
    low-link, iterative; parallel edges count as a cycle)."""
    adjacency: dict[int, list[tuple[int, int]]] = {}
    for n, (a, b) in enumerate(edges):
        adjacency.setdefault(a, []).append((b, n))
        adjacency.setdefault(b, []).append((a, n))
    order: dict[int, int] = {}
    low: dict[int, int] = {}
    out: set[tuple[int, int]] = set()
    for root in adjacency:
        if root in order:
            continue
        order[root] = low[root] = len(order)
        stack = [(root, -1, iter(adjacency[root]))]
        while stack:
            node, via, neighbours = stack[-1]
            advanced = False
            for other, n in neighbours:
                if n == via:
                    continue
                if other in order:
                    low[node] = min(low[node], order[other])
                else:
                    order[other] = low[other] = len(order)
                    stack.append((other, n, iter(adjacency[other])))
                    advanced = True
                    break
            if not advanced:
                stack.pop()
                if stack:
                    parent = stack[-1][0]
                    low[parent] = min(low[parent], low[node])
                    if low[node] > order[parent]:
                        out.add((min(parent, node), max(parent, node)))
    return out


def cut_off(n: int, reference: int, kept, conflicts, *,
            trusted: float) -> tuple[dict[int, tuple[int, float]], dict[tuple[int, int], tuple[int, int, float]]]:
    """The scans whose placement a free-space conflict disproves, each with its evidence.

    ``kept``: the kept edges as ``(i, j, confidence)``; ``conflicts``: pairs of placed scans that
    cannot both be right, as ``(a, b, free-space fraction)``. Some edge on every path between a
    conflicting pair is wrong. For each conflict in turn (worst first) whose scans are still joined,
    the minimum cut between them (edges weighted by the log-odds of their confidence: the likeliest
    set of wrong edges) is removed; the scans the cuts separate from the reference are returned, as
    ``scan -> (the scan it conflicts with, fraction)`` of the conflict that cut it off.
    ``trusted``: the trust bar (:attr:`esmicp.trust.policy.TrustPolicy.trusted`), the least
    confidence a kept edge is weighted by.
    """
    capacity: dict[tuple[int, int], int] = {}  # sparse: a few entries per scan, never n x n
    for i, j, confidence in kept:
        # the log-odds of the edge being right: the minimum cut is then the likeliest set of wrong
        # edges, if each is right with probability its confidence, independently
        p = min(max(confidence or 0.0, trusted), 0.999)
        weight = 1 + int(round(1000 * np.log(p / (1 - p))))
        for key in ((i, j), (j, i)):
            capacity[key] = capacity.get(key, 0) + weight

    def matrix(values):
        keys = list(values)
        rows, cols = (np.array([k[m] for k in keys], dtype=np.int32) for m in (0, 1))
        return csr_matrix((np.array([values[k] for k in keys], dtype=np.int32), (rows, cols)), shape=(n, n))

    def labels():
        return connected_components(matrix(capacity), directed=False)[1]

    cut: dict[int, tuple[int, float]] = {}
    removed: dict[tuple[int, int], tuple[int, int, float]] = {}
    for a, b, fraction in sorted(conflicts, key=lambda c: -c[2]):
        if not capacity or (label := labels())[a] != label[b]:
            continue
        flow = maximum_flow(matrix(capacity), a, b).flow.todok()
        neighbours: dict[int, list[int]] = {}
        for (i, j), c in capacity.items():
            if c - flow.get((i, j), 0) > 0:  # residual capacity left
                neighbours.setdefault(i, []).append(j)
        side, stack = {a}, [a]  # scans reachable from a in the residual graph: a's side of the cut
        while stack:
            for other in neighbours.get(stack.pop(), []):
                if other not in side:
                    side.add(other)
                    stack.append(other)
        for i, j in [key for key in capacity if key[0] in side and key[1] not in side]:
            removed[(min(i, j), max(i, j))] = (a, b, fraction)
            del capacity[(i, j)], capacity[(j, i)]
        label = labels() if capacity else np.arange(n)
        for k in range(n):
            if label[k] != label[reference] and k not in cut:
                cut[k] = (b if label[a] != label[reference] else a, fraction)
    return cut, removed


def scan_verdicts(n: int, reference: int, posed: set, edges, conflicted: dict | None = None) -> list[ScanVerdict]:
    """The verdict of every scan ``0..n-1``; ``posed`` are the scans the pose graph placed (joined to
    ``reference`` by kept edges), ``edges`` every :class:`~esmicp.multiview.Edge` tried."""
    touching: dict[int, list] = {k: [] for k in range(n)}
    for e in edges:
        touching[e.i].append(e)
        touching[e.j].append(e)
    kept_pairs = [(e.i, e.j) for e in edges if e.kept and e.i in posed and e.j in posed]
    core = two_edge_core(reference, kept_pairs)
    out = []
    for k in range(n):
        mine = touching[k]
        kept = [e for e in mine if e.kept and e.i in posed and e.j in posed]
        contradicting = [e for e in mine if e.trusted and not e.kept and e.reason.startswith("cycle")]
        best_kept = max((e.confidence for e in kept), default=0.0)
        if k == reference:
            status, confidence, reason = "placed", 1.0, "the reference: its frame is the world frame"
        elif k not in posed:
            status, confidence, reason = "unplaced", None, _why_unplaced(k, mine, reference)
        elif conflicted and k in conflicted:
            other, fraction = conflicted[k]
            status, confidence = "doubtful", 0.0
            reason = (f"its pose contradicts what scan {other} saw ({100 * fraction:.0f}% of one scan's surface "
                      f"lies in the space the other saw empty): an edge joining it to the reference is wrong")
        elif contradicting and (k not in core or len(contradicting) >= len(kept)):
            against = max(e.confidence for e in contradicting)
            status, confidence = "doubtful", max(0.0, best_kept - against)
            reason = f"{len(contradicting)} trusted edge(s) contradict its pose, {len(kept)} agree"
        elif k in core:
            status, confidence = "placed", best_kept
            reason = (f"confirmed: joined to the reference by two paths of trusted edges that agree ({len(kept)} kept"
                      + (f", {len(contradicting)} disagreeing rejected)" if contradicting else ")"))
        elif n == 2:
            status, confidence = "placed", best_kept
            reason = "the only pair: one trusted edge, nothing contradicts it (no third scan can check it)"
        else:
            # one unchecked trusted edge counts as half of a checked one: below the trust bar
            status, confidence = "doubtful", best_kept / 2
            reason = ("joined to the reference only across an edge on no cycle: no other pair checks that "
                      "edge, and one wrong trusted edge would place it wrongly")
        out.append(ScanVerdict(status, confidence, len(kept), len(contradicting), (reason,)))
    return out


def _why_unplaced(k: int, mine, reference: int) -> str:
    usable = [e for e in mine if e.trusted]
    if not mine:
        return "no pair with this scan was registered"
    if not usable:
        best = _best(mine, k)
        failed = sum(1 for e in mine if e.reason.startswith("failed"))
        detail = f"best {_describe(best, k)}" if best is not None else "every registration failed"
        note = f"; {failed} failed" if failed and best is not None else ""
        return (f"no trusted edge among {len(mine)} tried ({detail}{note}): another object, no surface "
                f"shared with the other scans, or too few points")
    if all(e.reason.startswith(("cycle", "free-space")) for e in usable):
        seen = any(e.reason.startswith("free-space") for e in usable)
        return (f"its {len(usable)} trusted edge(s) all disagree with the pose graph (cycle inconsistent"
                + (", or surfaces where other scans saw empty space)" if seen else ")"))
    return f"its trusted edges join it only to scans not connected to the reference scan {reference}"
