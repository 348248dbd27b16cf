"""Which pairs of scans :func:`esmicp.register_scans` registers: O(N) candidates from what the data says.

* With the capture order (``sequence=True``): each scan with its next few scans
  (:func:`sequence_pairs`).
* Without: each scan with the scans most similar to it: a cheap shape descriptor
  (:func:`descriptor_distances`) proposes each scan's nearest few, and the fraction of their
  local surface features that match each other mutually ranks those (:func:`matching_distances`,
  :func:`ranked_partners`).
* Once poses exist, what they predict two scans share (:class:`PredictedOverlap`) chooses the
  pairs worth a global search: loop closures where they bypass the longest stretch of the graph
  (:func:`loop_pairs`), and pairs that put an edge on no cycle on one (:func:`closing_pairs`).
  The prediction only chooses which pairs are searched; the search itself starts from nowhere,
  so its result is evidence independent of the poses that proposed it.
* Scans not joined to the reference: each piece of them (:func:`pieces`) with the placed scans
  most like it (:func:`bridging_pairs`).
* Scans whose placed extents overlap in the world frame (:func:`near_pairs`), for the free-space
  check.

Pairs are unordered ``(i, j)`` with ``i < j``; the caller decides which is the target.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Iterable, Sequence

import numpy as np

def descriptor(points: np.ndarray) -> np.ndarray:
    """A pose-invariant shape summary of one scan (27 numbers): the square roots of its covariance
    eigenvalues, normalised to sum 1; the histogram (8 bins) of its points' distances from the
    centroid, relative to the largest; and the histogram (16 bins) of the distances between 4,000
    random pairs of its points, relative to their median (the D2 shape distribution). Similar views
    of one surface have nearby descriptors (dimensionless; how often the nearest are true
    neighbours: ``docs/design.md``, "Measured design choices")."""
    centred = points - points.mean(axis=0)
    eigen = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(centred.T)), 0.0))
    radii = np.linalg.norm(centred, axis=1)
    histogram = np.histogram(radii / (radii.max() + 1e-300), bins=8, range=(0, 1))[0] / len(points)
    generator = np.random.default_rng(0)  # fixed: a scan's descriptor depends on the scan alone
    first, second = generator.integers(len(points), size=(2, 4000))
    distances = np.linalg.norm(points[first] - points[second], axis=1)
    shape = np.histogram(distances / (np.median(distances) + 1e-300), bins=16, range=(0, 4))[0] / 4000
    return np.concatenate([eigen / (eigen.sum() + 1e-300), histogram, shape])


def descriptor_distances(clouds: Sequence[np.ndarray]) -> np.ndarray:
    """``(N, N)`` Euclidean distances between the scans' :func:`descriptor` vectors (8 MB for
    1,000 scans): small for similar views."""
    from scipy.spatial.distance import cdist

    descriptors = np.array([descriptor(c) for c in clouds])
    return cdist(descriptors, descriptors)


def surface_features(points: np.ndarray, *, radius_spacings: float, normal_neighbours: int, count: int) -> np.ndarray:
    """The FPFH features (:func:`esmicp.core.features.fpfh`) of ``count`` evenly strided points of
    one scan (at most), over a neighbourhood of ``radius_spacings`` times its median point spacing,
    normals from its ``normal_neighbours`` nearest points: ``(count, 33)``, invariant to a rigid
    motion of the scan."""
    from ..core.compiled_tree import CompiledTree
    from ..core.features import estimate_normals, fpfh
    from ..core.sampling import evenly_strided

    if len(points) < 3:
        return np.zeros((0, 33))
    tree = CompiledTree(points)  # one KD-tree gives the spacing, the normals and the features
    spacing = float(np.median(tree.query_k(points, 2, workers=1)[0][:, 1]))
    if not spacing > 0:
        return np.zeros((0, 33))
    features = fpfh(points, estimate_normals(points, k=normal_neighbours, tree=tree), radius_spacings * spacing,
                    tree=tree)
    return features[evenly_strided(len(points), count)]


def mutual_matches(a: np.ndarray, b: np.ndarray, tree_a=None, tree_b=None) -> float:
    """The fraction (0-1, of the smaller set) of the features ``a`` and ``b`` (rows) that are each
    other's nearest neighbour in feature space. Two views of one surface share features where
    they overlap, so the fraction grows with the overlap; it does not need their poses."""
    from scipy.spatial import cKDTree

    if len(a) == 0 or len(b) == 0:
        return 0.0
    tree_a = cKDTree(a) if tree_a is None else tree_a
    tree_b = cKDTree(b) if tree_b is None else tree_b
    _, a_to_b = tree_b.query(a)
    _, b_to_a = tree_a.query(b)
    return float(np.sum(b_to_a[a_to_b] == np.arange(len(a)))) / min(len(a), len(b))


def matching_distances(clouds: Sequence[np.ndarray], *, candidates: int, radius_spacings: float,
                       normal_neighbours: int, count: int) -> np.ndarray:
    """``(N, N)`` dissimilarities of the scans (0 on the diagonal; small for scans worth
    registering first): among each scan's ``candidates`` nearest by :func:`descriptor_distances`,
    one minus the fraction of their surface features that match mutually (:func:`surface_features`,
    :func:`mutual_matches`; 0-1), plus a ten-millionth of their descriptor distance (ties, such as
    two pairs with no match at all, are broken by the descriptor, not by the scans' input order);
    every other pair one plus its descriptor distance, so that it ranks after every matched pair.
    O(N * candidates) feature matchings. How often a scan's most similar overlap it:
    ``docs/design.md``, "Measured design choices"."""
    from scipy.spatial import cKDTree

    coarse = descriptor_distances(clouds)
    n = len(clouds)
    out = 1.0 + coarse
    np.fill_diagonal(out, 0.0)
    if n < 2 or candidates < 1:
        return out
    pairs = {(min(i, int(j)), max(i, int(j))) for i in range(n)
             for j in [j for j in np.argsort(coarse[i], kind="stable") if j != i][:candidates]}
    pairs = sorted(pairs)
    # on threads: the compiled kernels and the KD-tree queries release the GIL
    with ThreadPoolExecutor() as pool:
        features = list(pool.map(lambda c: surface_features(c, radius_spacings=radius_spacings,
                                                            normal_neighbours=normal_neighbours, count=count), clouds))
        trees = list(pool.map(cKDTree, features))
        matched = list(pool.map(lambda pair: mutual_matches(features[pair[0]], features[pair[1]], trees[pair[0]],
                                                            trees[pair[1]]), pairs))
    for (i, j), fraction in zip(pairs, matched):
        out[i, j] = out[j, i] = 1.0 - fraction + 1e-7 * coarse[i, j]
    return out


def ranked_partners(distances: np.ndarray) -> list[list[int]]:
    """For every scan, every other scan, most similar first (``distances`` from
    :func:`matching_distances`; ties by index)."""
    return [[int(j) for j in np.argsort(row, kind="stable") if j != i] for i, row in enumerate(distances)]


def bridging_pairs(distances: np.ndarray, placed: Iterable[int], pieces: Iterable[Sequence[int]], tried: set,
                   per_scan: int, widen: Sequence[float] | None = None) -> list[tuple[int, int]]:
    """Untried pairs of one scan of a piece not placed (``pieces``: each a list of scans joined
    to each other, not to the placed ones) and one placed scan, most similar first (``distances``
    from :func:`matching_distances`), each scan in at most ``per_scan`` of them and each piece
    in at most ``per_scan * min(len(piece), per_scan)``; ``widen[n]`` (at least 1) multiplies
    both caps for the scans of piece n (a piece whose first pairs found nothing: the pairs that
    join it may rank low).

    Only such a pair can place a piece: one between two unplaced scans joins them to each other,
    not to the reference. One trusted pair places a whole piece, so a piece of many scans that
    shares no surface with the placed ones costs as many searches a round as one of ``per_scan``
    scans, not one per scan. The cap holds on both sides, so the pairs are spread over the scans
    whichever side is the larger (a few unplaced scans among many placed, or a reference whose
    few placed scans face all the others)."""
    placed = sorted(placed)
    pieces_given = list(pieces)
    pieces = [sorted(piece) for piece in pieces_given if len(piece)]
    if not placed or not pieces or per_scan < 1:
        return []
    widen = [1.0] * len(pieces) if widen is None else [max(1.0, float(w)) for w, piece in zip(widen, pieces_given)
                                                        if len(piece)]
    unplaced = [k for piece in pieces for k in piece]
    piece_of = {k: n for n, piece in enumerate(pieces) for k in piece}
    block = distances[np.ix_(unplaced, placed)]
    rows, columns = np.unravel_index(np.argsort(block, axis=None, kind="stable"), block.shape)
    used: dict[int, int] = {}
    per_piece: dict[int, int] = {}
    out: list[tuple[int, int]] = []
    for row, column in zip(rows, columns):
        i, j = unplaced[row], placed[column]
        piece = piece_of[i]
        pair = (min(i, j), max(i, j))
        scan_cap = per_scan * widen[piece]
        if (pair in tried or used.get(i, 0) >= scan_cap or used.get(j, 0) >= scan_cap
                or per_piece.get(piece, 0) >= scan_cap * min(len(pieces[piece]), per_scan)):
            continue
        out.append(pair)
        used[i], used[j] = used.get(i, 0) + 1, used.get(j, 0) + 1
        per_piece[piece] = per_piece.get(piece, 0) + 1
    return out


def sequence_pairs(n: int, neighbours: int) -> list[tuple[int, int]]:
    """``(i, i + k)`` for ``k = 1..neighbours``: scans captured one after the other."""
    return [(i, i + k) for k in range(1, neighbours + 1) for i in range(n - k)]


def world_extents(poses: dict[int, np.ndarray], clouds: Sequence[np.ndarray]) -> dict[int, tuple[np.ndarray, float]]:
    """``k -> (centre in the world frame, RMS radius)`` of every posed scan (cloud units)."""
    out = {}
    for k, T in poses.items():
        centre = clouds[k].mean(axis=0)
        radius = float(np.sqrt(np.mean(np.sum((clouds[k] - centre) ** 2, axis=1))))
        out[k] = (T[:3, :3] @ centre + T[:3, 3], radius)
    return out


def near_pairs(scans: Iterable[int], extents: dict[int, tuple[np.ndarray, float]], tried: set, per_scan: int,
               *, min_gap: int = 0) -> list[tuple[int, int]]:
    """Untried pairs of each scan in ``scans`` with up to ``per_scan`` posed scans whose placed
    extents overlap its own (centres closer than the sum of the RMS radii), nearest first.
    ``min_gap``: skip partners fewer than this many positions away (their pairs are asked for
    already in a sequence)."""
    keys = sorted(extents)
    if not keys:
        return []
    centres = np.array([extents[k][0] for k in keys])
    radii = np.array([extents[k][1] for k in keys])
    out: list[tuple[int, int]] = []
    for i in scans:
        if i not in extents:
            continue
        centre, radius = extents[i]
        distance = np.linalg.norm(centres - centre, axis=1)
        chosen = 0
        for slot in np.argsort(distance, kind="stable"):
            j = keys[slot]
            pair = (min(i, j), max(i, j))
            if j == i or abs(j - i) < min_gap or pair in tried or pair in out:
                continue
            if distance[slot] >= radius + radii[slot]:
                break
            out.append(pair)
            chosen += 1
            if chosen >= per_scan:
                break
    return out


class PredictedOverlap:
    """What the poses predict two posed scans share: the fraction of one scan's points (at most
    ``points``, evenly strided) lying within ``radius`` (cloud units) of the other's where
    ``poses`` (``T_world_scan``) put them, the smaller of the two ways (0-1).

    Only ranks candidate pairs (a rank, not a measurement, needs few points): a wrong pose
    predicts the wrong pairs, which then cost a global search each and are judged by it. One
    KD-tree per scan asked about, built once."""

    def __init__(self, poses: dict[int, np.ndarray], clouds: Sequence[np.ndarray], radius: float, *, points: int):
        self.poses, self.clouds, self.radius, self.points = poses, clouds, float(radius), points
        self._trees: dict = {}
        self._queried: dict[int, np.ndarray] = {}
        self._known: dict[tuple[int, int], float] = {}

    def _world(self, k: int) -> np.ndarray:
        T = self.poses[k]
        return self.clouds[k] @ T[:3, :3].T + T[:3, 3]

    def _tree(self, k: int):
        if k not in self._trees:
            from scipy.spatial import cKDTree

            world = self._world(k)
            self._trees[k] = cKDTree(world)
            stride = max(1, len(world) // self.points)
            self._queried[k] = world[::stride]
        return self._trees[k]

    def _fraction(self, a: int, b: int) -> float:
        self._tree(a)
        distances, _ = self._tree(b).query(self._queried[a], distance_upper_bound=self.radius)
        return float(np.isfinite(distances).mean())

    def __call__(self, a: int, b: int) -> float:
        key = (min(a, b), max(a, b))
        if key not in self._known:
            self._known[key] = min(self._fraction(a, b), self._fraction(b, a))
        return self._known[key]


def nearest_posed(scans: Iterable[int], extents: dict[int, tuple[np.ndarray, float]], allowed,
                  count: int) -> dict[int, list[int]]:
    """For each of ``scans``, up to ``count`` posed scans for which ``allowed(scan, other)`` holds
    and whose extents overlap its own, nearest centre first."""
    keys = sorted(extents)
    if not keys:
        return {}
    centres = np.array([extents[k][0] for k in keys])
    radii = np.array([extents[k][1] for k in keys])
    out: dict[int, list[int]] = {}
    for i in scans:
        if i not in extents:
            continue
        centre, radius = extents[i]
        distance = np.linalg.norm(centres - centre, axis=1)
        chosen = out.setdefault(i, [])
        for slot in np.argsort(distance, kind="stable"):
            if distance[slot] >= radius + radii[slot]:
                break
            j = keys[slot]
            if j != i and allowed(i, j):
                chosen.append(j)
                if len(chosen) >= count:
                    break
    return out


def loop_pairs(edges: Iterable[tuple[int, int]], extents: dict[int, tuple[np.ndarray, float]],
               overlap, tried: set, *, min_overlap: float, min_hops: int, budget: int,
               partners: int) -> list[tuple[int, int]]:
    """Loop-closure candidates among the posed scans (``extents``): untried pairs the poses
    predict to share at least ``min_overlap`` (``overlap(a, b)``, e.g. :class:`PredictedOverlap`),
    chosen one after the other where the graph of ``edges`` (and of the pairs chosen before) joins
    the two scans by the longest path (in edges), as long as that is at least ``min_hops``; at
    most ``budget``. Each scan's overlap is predicted with its ``partners`` nearest posed scans
    (:func:`nearest_posed`): O(N) predictions.

    A loop closure corrects the drift that accumulates along the path it bypasses, so the longest
    bypass comes first, and once a pair is chosen the pairs next to it are short bypasses: the
    closures spread over the loops of a walk instead of piling up where frames overlap most."""
    posed = sorted(extents)
    if budget < 1 or len(posed) < 2:
        return []
    slot = {k: n for n, k in enumerate(posed)}
    hops = _hops(len(posed), [(slot[a], slot[b]) for a, b in edges if a in slot and b in slot])

    def allowed(i, j):
        return i < j and (i, j) not in tried and hops[slot[i], slot[j]] >= min_hops

    near = nearest_posed(posed, extents, lambda i, j: allowed(min(i, j), max(i, j)), partners)
    candidates = sorted({(min(i, j), max(i, j)) for i, others in near.items() for j in others})
    candidates = [(i, j) for i, j in candidates if overlap(i, j) >= min_overlap]
    out: list[tuple[int, int]] = []
    while candidates and len(out) < budget:
        best = max(candidates, key=lambda p: (hops[slot[p[0]], slot[p[1]]], overlap(*p), -p[0], -p[1]))
        a, b = slot[best[0]], slot[best[1]]
        if hops[a, b] < min_hops:
            break
        out.append(best)
        candidates.remove(best)
        # the chosen pair is an edge now: every path may take it
        hops = np.minimum(hops, np.minimum(hops[:, a, None] + 1 + hops[None, b, :], hops[:, b, None] + 1 + hops[None, a, :]))
    return out


def _hops(count: int, edges: list[tuple[int, int]]) -> np.ndarray:
    """``(count, count)`` lengths (in edges) of the shortest paths; a large number where none."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import shortest_path

    if not edges:
        out = np.full((count, count), float(count + 1))
        np.fill_diagonal(out, 0.0)
        return out
    rows, cols = np.array(edges).T
    graph = csr_matrix((np.ones(len(edges)), (rows, cols)), shape=(count, count))
    out = shortest_path(graph, directed=False, unweighted=True)
    out[~np.isfinite(out)] = count + 1
    return out


def two_edge_core(reference: int, pairs: Iterable[tuple[int, int]]) -> set[int]:
    """The scans joined to ``reference`` by two paths of ``pairs`` with no pair in common (its
    2-edge-connected component; ``{reference}`` alone when it has none)."""
    from .verdict import bridges

    pairs = [(min(a, b), max(a, b)) for a, b in pairs]
    cut = bridges(pairs)
    adjacency: dict[int, list[int]] = {}
    for a, b in pairs:
        if (a, b) not in cut:
            adjacency.setdefault(a, []).append(b)
            adjacency.setdefault(b, []).append(a)
    seen, stack = {reference}, [reference]
    while stack:
        for other in adjacency.get(stack.pop(), []):
            if other not in seen:
                seen.add(other)
                stack.append(other)
    return seen


def hanging_parts(reference: int, kept: Iterable[tuple[int, int]]) -> list[set[int]]:
    """For every edge on no cycle of the graph ``kept`` (a bridge), the scans it alone joins to
    ``reference``: one set per bridge, smallest first (a part hanging from another comes first)."""
    from .verdict import bridges

    kept = [(min(a, b), max(a, b)) for a, b in kept]
    adjacency: dict[int, list[int]] = {}
    for a, b in kept:
        adjacency.setdefault(a, []).append(b)
        adjacency.setdefault(b, []).append(a)
    parts = []
    for cut in sorted(bridges(kept)):
        seen, stack = {reference}, [reference]
        while stack:
            node = stack.pop()
            for other in adjacency.get(node, []):
                if other not in seen and (min(node, other), max(node, other)) != cut:
                    seen.add(other)
                    stack.append(other)
        part = {k for k in adjacency if k not in seen}
        if part:
            parts.append(part)
    return sorted(parts, key=lambda part: (len(part), min(part)))


def closing_pairs(parts: list[set[int]], extents: dict[int, tuple[np.ndarray, float]], overlap, tried: set, *,
                  min_overlap: float, per_part: int, partners: int) -> list[tuple[int, int]]:
    """Pairs that would put bridges on a cycle: for each set of ``parts`` (scans joined to the rest
    of the posed scans, ``extents``, by one edge only; smallest first) not yet crossed by a pair
    chosen before, up to ``per_part`` untried pairs of one of its scans and a posed scan outside it,
    the largest predicted overlap first (``overlap(a, b)``, at least ``min_overlap``), among each
    scan's ``partners`` nearest posed scans (:func:`nearest_posed`).

    A scan hanging on one edge is confirmed by any second path to the reference, so one pair across
    each cut is what is needed, not one per scan: a pair chosen for a part also crosses every cut
    between its two scans, and the parts it crosses get none of their own."""
    out: list[tuple[int, int]] = []
    for part in parts:
        if any((i in part) != (j in part) for i, j in out):
            continue
        near = nearest_posed(sorted(part), extents, lambda i, j: j not in part
                              and (min(i, j), max(i, j)) not in tried, partners)
        scored = sorted({(min(i, j), max(i, j)) for i, others in near.items() for j in others},
                        key=lambda p: (-overlap(*p), p))
        out.extend([p for p in scored if overlap(*p) >= min_overlap and p not in out][:per_part])
    return out


def similar_crossing_pairs(parts: list[set[int]], distances: np.ndarray, posed: Iterable[int], tried: set,
                           chosen: Iterable[tuple[int, int]], *, per_part: int) -> list[tuple[int, int]]:
    """For each set of ``parts`` (smallest first) that no pair of ``chosen`` or of those picked
    before crosses, up to ``per_part`` untried pairs of one of its scans and a posed scan outside
    it, the most similar first (``distances`` from :func:`matching_distances`): the pairs that may
    put a bridge on a cycle when the poses predict no overlap across it (a view seen from a
    direction no placed scan comes near)."""
    posed = sorted(posed)
    out: list[tuple[int, int]] = []
    taken = list(chosen)
    for part in parts:
        if any((i in part) != (j in part) for i, j in taken + out):
            continue
        inside, outside = sorted(part), [k for k in posed if k not in part]
        if not inside or not outside:
            continue
        block = distances[np.ix_(inside, outside)]
        picked = []
        for slot in np.argsort(block, axis=None, kind="stable"):
            i, j = inside[slot // len(outside)], outside[slot % len(outside)]
            pair = (min(i, j), max(i, j))
            if pair not in tried and pair not in out and pair not in picked:
                picked.append(pair)
                if len(picked) >= per_part:
                    break
        out.extend(picked)
    return out


def pieces(scans: Iterable[int], joined: Iterable[tuple[int, int]]) -> list[list[int]]:
    """The connected pieces of ``scans`` under the pairs ``joined`` (pairs with a scan outside
    ``scans`` are ignored), each sorted, in order of their first scan."""
    scans = sorted(set(scans))
    parent = {k: k for k in scans}

    def root(k):
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for a, b in joined:
        if a in parent and b in parent:
            parent[root(a)] = root(b)
    out: dict[int, list[int]] = {}
    for k in scans:
        out.setdefault(root(k), []).append(k)
    return sorted(out.values())
