"""Global pose hypotheses from FPFH correspondences, without any initial guess.

Pipeline of :func:`feature_hypotheses`: voxel-downsample both clouds, estimate normals, compute
FPFH (:mod:`esmicp.init.features`), match the features (:func:`match_features`), then find rigid
transforms that many correspondences agree with, robustly:

``"ransac"``
    RANSAC over 3-correspondence samples, drawn in batches of thousands. A sample survives only
    if the three pairwise distances agree between source and target to within 10 % (a rigid
    motion preserves lengths) and its triangle is not too small; every survivor is solved at once
    by a batched Kabsch fit (``numpy.linalg.svd`` on ``(B, 3, 3)``) and scored by counting, for
    all correspondences at once, those it maps to within ``inlier_distance``. Batches are drawn
    until the standard RANSAC stopping rule is met (``confidence`` that an all-inlier sample was
    drawn, given the best inlier fraction so far) or ``max_trials`` samples were drawn.
``"clique"``
    Pairwise-consistency graph (as in TEASER++ / KISS-Matcher, re-derived here): correspondences
    ``i`` and ``j`` are consistent when ``| |s_i - s_j| - |t_i - t_j| | <= 2 inlier_distance``.
    Greedy cliques grown from the best-connected correspondences are solved by Kabsch.

Either way each candidate is refit by Kabsch on its own inliers, and the best *distinct*
candidates are returned (distinct: rotations more than 10 degrees apart or translations more than
2 voxels apart). Transforms are ``T_target_source``: ``target ~= source @ R.T + t``.
Randomness comes only from the ``rng`` argument, so a seed gives identical hypotheses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..core.procrustes import to_matrix
from ..errors import InvalidInputError
from ..types import as_points, as_positive
from .features import dense_point_mask, estimate_normals, fpfh, voxel_downsample

#: Below this many mutual matches, :func:`match_features` falls back to one-way matches.
MIN_MUTUAL_MATCHES = 30

#: Relative tolerance of the edge-length consistency check on RANSAC samples.
EDGE_TOLERANCE = 0.1

#: Two hypotheses are distinct when their rotations differ by more than this (degrees) ...
DISTINCT_ROTATION_DEG = 10.0
#: ... or their translations by more than this many voxels.
DISTINCT_TRANSLATION_VOXELS = 2.0

#: Feature-space problems up to this many (source x target) pairs use brute force, not a KD-tree.
_BRUTE_FORCE_PAIRS = 4_000_000

#: Largest number of (candidate x correspondence) residuals evaluated at once.
_SCORE_CHUNK = 2_000_000

#: Size of the first RANSAC batch (later ones double, up to the ``batch`` argument).
_FIRST_BATCH = 256

#: Candidates kept between RANSAC batches (best inlier counts).
_POOL = 256

METHODS = ("ransac", "clique")

#: Neighbours (at most) of a normal's PCA.
_NORMAL_NEIGHBOURS = 60

#: Default radii, in voxels: normals (PCA), FPFH, and the isolated-point filter.
NORMAL_RADIUS_VOXELS = 4.0
FEATURE_RADIUS_VOXELS = 7.0
FILTER_RADIUS_VOXELS = 2.0


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """A candidate pose from :func:`feature_hypotheses`.

    Attributes
    ----------
    transformation : (4, 4) read-only float64 array
        ``T_target_source`` (``target ~= source @ R.T + t``), in the clouds' units.
    inlier_count : int
        Feature correspondences it maps to within ``inlier_distance`` of their target point.
    inlier_fraction : float
        ``inlier_count`` divided by the number of correspondences, in ``[0, 1]``.
    """

    transformation: np.ndarray
    inlier_count: int
    inlier_fraction: float


# --------------------------------------------------------------------------------------------
# Feature matching


def _matches(source: np.ndarray, target: np.ndarray, *, second: bool, mutual: bool):
    """Nearest target row of every source row (Euclidean), and what the filters need.

    Returns ``(forward, distance, second_distance, is_mutual)``: the index of each source row's
    nearest target row and its distance, the distance to the second-nearest (None unless
    ``second``), and whether the source row is in turn the target row's nearest source row (None
    unless ``mutual``). Small problems use one float32 Gram matrix (BLAS) for both directions;
    larger ones KD-trees.
    """
    if len(source) * len(target) <= _BRUTE_FORCE_PAIRS:
        source32, target32 = source.astype(np.float32), target.astype(np.float32)
        squared = source32 @ target32.T
        squared *= -2.0
        squared += np.einsum("ij,ij->i", target32, target32)[None, :]
        squared += np.einsum("ij,ij->i", source32, source32)[:, None]
        forward = squared.argmin(axis=1)
        rows = np.arange(len(source))
        best = squared[rows, forward]
        distance = np.sqrt(np.maximum(best, 0.0)).astype(np.float64)
        second_distance = is_mutual = None
        if second:
            squared[rows, forward] = np.inf
            second_distance = np.sqrt(np.maximum(squared.min(axis=1), 0.0)).astype(np.float64)
            squared[rows, forward] = best
        if mutual:
            is_mutual = best <= squared.min(axis=0)[forward]
        return forward, distance, second_distance, is_mutual
    distances, indices = cKDTree(target).query(source, k=2 if second else 1)
    distances, indices = distances.reshape(len(source), -1), indices.reshape(len(source), -1)
    forward = indices[:, 0]
    is_mutual = None
    if mutual:
        _, backward = cKDTree(source).query(target, k=1)
        is_mutual = backward[forward] == np.arange(len(source))
    return forward, distances[:, 0], (distances[:, 1] if second else None), is_mutual


def match_features(
    source_features,
    target_features,
    *,
    mutual: bool = True,
    ratio: float | None = None,
    min_matches: int = MIN_MUTUAL_MATCHES,
) -> np.ndarray:
    """Nearest-neighbour correspondences in feature space.

    Each source feature is matched to its nearest target feature (Euclidean distance; by brute
    force in float32 for small sets, with KD-trees otherwise).

    Parameters
    ----------
    source_features, target_features : (N, D), (M, D) arrays
    mutual : bool
        Keep only matches that are also the source's nearest from the target's side. If fewer than
        ``min_matches`` survive, the one-way matches are returned instead (all of them that pass
        the ratio test).
    ratio : float, optional
        Lowe's ratio test: keep a match only if its distance is below ``ratio`` times the distance
        to the second-nearest target feature.
    min_matches : int
        See ``mutual``.

    Returns
    -------
    (K, 2) intp array
        Rows ``(source index, target index)``, ordered by increasing feature distance.
    """
    source_features = np.asarray(source_features, dtype=np.float64)
    target_features = np.asarray(target_features, dtype=np.float64)
    if source_features.ndim != 2 or target_features.ndim != 2 or source_features.shape[1] != target_features.shape[1]:
        raise InvalidInputError(
            f"features: expected (N, D) and (M, D) arrays, got {source_features.shape} and {target_features.shape}"
        )
    if len(source_features) == 0 or len(target_features) == 0:
        return np.zeros((0, 2), dtype=np.intp)
    use_ratio = ratio is not None and len(target_features) >= 2
    forward, distance, second_distance, is_mutual = _matches(
        source_features, target_features, second=use_ratio, mutual=mutual
    )
    selected = np.ones(len(source_features), dtype=bool)
    if use_ratio:
        selected &= distance < float(ratio) * second_distance
    if mutual and (selected & is_mutual).sum() >= min_matches:
        selected &= is_mutual
    rows = np.flatnonzero(selected)
    rows = rows[np.argsort(distance[rows], kind="stable")]
    return np.stack([rows, forward[rows]], axis=1).astype(np.intp)


# --------------------------------------------------------------------------------------------
# Batched rigid fits and scoring


def _kabsch(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Batched least-squares rigid fits of paired points.

    ``source``, ``target``: ``(B, n, 3)`` paired points, or ``(n, 3)`` shared by every fit when
    ``weights`` ``(B, n)`` (non-negative, each row with a positive sum) select the pairs of each
    fit. Returns rotations ``(B, 3, 3)`` and translations ``(B, 3)`` with
    ``target ~= source @ R.T + t``.
    """
    if weights is None:
        source_centroid = source.mean(axis=1)
        target_centroid = target.mean(axis=1)
        cross = np.einsum("bni,bnj->bij", source - source_centroid[:, None], target - target_centroid[:, None])
    else:
        total = weights.sum(axis=1)
        source_centroid = (weights @ source) / total[:, None]
        target_centroid = (weights @ target) / total[:, None]
        # sum_k w_k s_k t_k^T - total * s_bar t_bar^T, with s and t first centred on their plain
        # means for accuracy.
        source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
        outer = ((source - source_mean)[:, :, None] * (target - target_mean)[:, None, :]).reshape(len(source), 9)
        cross = (weights @ outer).reshape(-1, 3, 3)
        cross -= total[:, None, None] * (
            (source_centroid - source_mean)[:, :, None] * (target_centroid - target_mean)[:, None, :]
        )
    u, _, vt = np.linalg.svd(cross)
    # R = V diag(1, 1, d) U^T with d = det(V U^T), the reflection fix.
    v = np.swapaxes(vt, 1, 2)
    d = np.sign(np.linalg.det(v @ np.swapaxes(u, 1, 2)))
    d[d == 0] = 1.0
    v[:, :, 2] *= d[:, None]
    rotations = v @ np.swapaxes(u, 1, 2)
    translations = target_centroid - np.einsum("bij,bj->bi", rotations, source_centroid)
    return rotations, translations


def _inlier_mask(rotations, translations, source, target, threshold) -> np.ndarray:
    """``(C, K)`` bool: correspondence ``k`` maps within ``threshold`` under candidate ``c``."""
    count, pairs = len(rotations), len(source)
    mask = np.empty((count, pairs), dtype=bool)
    step = max(1, _SCORE_CHUNK // max(3 * pairs, 1))
    limit = threshold * threshold
    for start in range(0, count, step):
        stop = min(start + step, count)
        chunk = stop - start
        # One matrix product maps every source point by every rotation of the chunk:
        # stacked[j, 3c + i] = R_c[i, j], so (source @ stacked)[k, 3c + i] = (R_c s_k)_i.
        stacked = rotations[start:stop].transpose(2, 0, 1).reshape(3, 3 * chunk)
        residual = (source @ stacked).reshape(pairs, chunk, 3)
        residual += translations[None, start:stop, :]
        residual -= target[:, None, :]
        np.square(residual, out=residual)
        mask[start:stop] = (residual.sum(axis=2) <= limit).T
    return mask


def _rotation_gaps_deg(rotations: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Geodesic angles (degrees) between each of ``(C, 3, 3)`` rotations and one reference."""
    cosine = 0.5 * (np.einsum("cij,ij->c", rotations, reference) - 1.0)
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def _distinct_order(rotations, translations, scores, max_count, min_translation) -> np.ndarray:
    """Indices of at most ``max_count`` mutually distinct candidates, best score first."""
    remaining = np.argsort(-scores, kind="stable")
    chosen = []
    while len(remaining) and len(chosen) < max_count:
        best = remaining[0]
        chosen.append(best)
        rest = remaining[1:]
        far = (_rotation_gaps_deg(rotations[rest], rotations[best]) > DISTINCT_ROTATION_DEG) | (
            np.linalg.norm(translations[rest] - translations[best], axis=1) > min_translation
        )
        remaining = rest[far]
    return np.asarray(chosen, dtype=np.intp)


def _refit(rotations, translations, source, target, threshold, rounds: int = 2):
    """Refit every candidate by Kabsch on its own inliers, ``rounds`` times.

    Candidates with fewer than 3 inliers are left as they are. Returns the refit rotations,
    translations and final inlier counts.
    """
    for _ in range(rounds):
        mask = _inlier_mask(rotations, translations, source, target, threshold)
        counts = mask.sum(axis=1)
        enough = counts >= 3
        if not enough.any():
            return rotations, translations, counts
        rotations, translations = rotations.copy(), translations.copy()
        fitted_r, fitted_t = _kabsch(source, target, mask[enough].astype(np.float64))
        rotations[enough], translations[enough] = fitted_r, fitted_t
    counts = _inlier_mask(rotations, translations, source, target, threshold).sum(axis=1)
    return rotations, translations, counts


# --------------------------------------------------------------------------------------------
# Robust estimators over correspondences


def _edge_lengths(points: np.ndarray) -> np.ndarray:
    """``(B, 3)`` side lengths of ``(B, 3, 3)`` triangles: |p0 p1|, |p1 p2|, |p2 p0|."""
    return np.linalg.norm(points - np.roll(points, -1, axis=1), axis=2)


def _ransac(source, target, threshold, rng, *, max_trials, min_trials, batch, confidence, min_edge):
    """Batched RANSAC on paired points; returns candidate ``(rotations, translations, counts)``."""
    count = len(source)
    pool_r = np.zeros((0, 3, 3))
    pool_t = np.zeros((0, 3))
    pool_c = np.zeros(0, dtype=np.intp)
    trials, needed, best = 0, max(max_trials, 1), 0
    size = min(batch, _FIRST_BATCH)
    while trials < min(needed, max_trials):
        # Batches grow from small to ``batch``: an easy problem stops after the first one.
        size = min(size, max_trials - trials)
        trials += size
        sample = rng.integers(0, count, size=(size, 3))
        src, tgt = source[sample], target[sample]
        src_edges, tgt_edges = _edge_lengths(src), _edge_lengths(tgt)
        ok = (np.abs(src_edges - tgt_edges) <= EDGE_TOLERANCE * np.maximum(src_edges, tgt_edges)).all(axis=1)
        ok &= src_edges.min(axis=1) >= min_edge
        if not ok.any():
            size = min(2 * size, batch)
            continue
        rotations, translations = _kabsch(src[ok], tgt[ok])
        counts = _inlier_mask(rotations, translations, source, target, threshold).sum(axis=1)
        pool_r = np.concatenate([pool_r, rotations])
        pool_t = np.concatenate([pool_t, translations])
        pool_c = np.concatenate([pool_c, counts])
        if len(pool_c) > _POOL:
            top = np.argsort(-pool_c, kind="stable")[:_POOL]
            pool_r, pool_t, pool_c = pool_r[top], pool_t[top], pool_c[top]
        best = max(best, int(counts.max()))
        fraction = best / count
        if fraction >= 1.0:
            needed = min_trials
        elif fraction**3 > 0:
            needed = max(min_trials, int(np.ceil(np.log1p(-confidence) / np.log1p(-(fraction**3)))))
        size = min(2 * size, batch)
    return pool_r, pool_t, pool_c


def _cliques(source, target, threshold, *, max_cliques, min_edge):
    """Greedy cliques of the pairwise length-consistency graph; returns Kabsch fits of each."""
    count = len(source)
    source_d = np.linalg.norm(source[:, None] - source[None], axis=2)
    target_d = np.linalg.norm(target[:, None] - target[None], axis=2)
    graph = np.abs(source_d - target_d) <= 2.0 * threshold
    graph &= np.minimum(source_d, target_d) >= min_edge
    degree = graph.sum(axis=1)
    used = np.zeros(count, dtype=bool)
    rotations, translations = [], []
    for _ in range(max_cliques):
        free = np.flatnonzero(~used & (degree >= 2))
        if len(free) == 0:
            break
        seed = free[np.argmax(degree[free])]
        members = [seed]
        candidates = np.flatnonzero(graph[seed])
        while len(candidates):
            local = graph[np.ix_(candidates, candidates)].sum(axis=1)
            pick = candidates[np.argmax(local)]
            members.append(pick)
            candidates = candidates[graph[pick, candidates]]
        members = np.asarray(members)
        used[members] = True
        if len(members) < 3:
            continue
        r, t = _kabsch(source[members][None], target[members][None])
        rotations.append(r[0])
        translations.append(t[0])
    if not rotations:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.intp)
    rotations, translations = np.stack(rotations), np.stack(translations)
    counts = _inlier_mask(rotations, translations, source, target, threshold).sum(axis=1)
    return rotations, translations, counts


# --------------------------------------------------------------------------------------------
# The public entry point


def _keypoints(points: np.ndarray, voxel: float, normal_radius: float, feature_radius: float, filter_radius: float | None):
    """Downsampled points and their FPFH (rows of isolated points removed)."""
    if filter_radius is not None:
        points = points[dense_point_mask(points, filter_radius)]
    down = voxel_downsample(points, voxel)
    normals = estimate_normals(points, k=_NORMAL_NEIGHBOURS, radius=normal_radius, at=down)
    features = fpfh(down, normals, feature_radius)
    described = features.any(axis=1)
    return down[described], features[described]


def feature_hypotheses(
    source,
    target,
    *,
    voxel: float,
    rng,
    max_hypotheses: int = 8,
    max_trials: int = 20_000,
    min_trials: int = 1_000,
    inlier_distance: float | None = None,
    method: str = "ransac",
    confidence: float = 0.999,
    batch: int = 2_000,
    normal_radius: float | None = None,
    feature_radius: float | None = None,
    filter_radius: float | None = None,
) -> list[Hypothesis]:
    """Candidate poses ``T_target_source`` from FPFH feature correspondences, best first.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) arrays
        The clouds, in the same units, in any relative pose.
    voxel : float
        Downsampling voxel edge (cloud units); sets the scale of everything: normals use
        neighbours within ``2 voxel`` (at most 30), FPFH within ``5 voxel``. About 1/40 of the
        object's bounding-box diagonal is a good start.
    rng : numpy.random.Generator or int
        The only source of randomness (a seed is turned into ``default_rng(seed)``).
    max_hypotheses : int
        Return at most this many distinct hypotheses.
    max_trials, min_trials : int
        RANSAC budget (``method="ransac"``): at most ``max_trials`` 3-point samples; at least
        ``min_trials`` (unless ``max_trials`` is smaller) even when the stopping rule is met
        early, so that runners-up (alternative poses) are explored too.
    inlier_distance : float, optional
        A correspondence is an inlier of a pose when the pose maps its source point within this
        distance (cloud units) of its target point. Default ``1.5 voxel``.
    method : {"ransac", "clique"}
        Robust estimator (see the module docstring).
    confidence : float
        RANSAC stops early once an all-inlier sample has been drawn with this probability.
    batch : int
        RANSAC samples drawn and checked at once.

    Returns
    -------
    list of Hypothesis
        Distinct hypotheses (rotations > 10 degrees or translations > 2 voxels apart), ordered by
        decreasing ``inlier_count``; each is refit by Kabsch on its own inlier correspondences.
        Empty when fewer than 3 correspondences are found or no sample passes the checks.
    """
    source = as_points(source, "source")
    target = as_points(target, "target")
    voxel = as_positive(voxel, "voxel")
    threshold = 1.5 * voxel if inlier_distance is None else as_positive(inlier_distance, "inlier_distance")
    if method not in METHODS:
        raise InvalidInputError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    if rng is None:
        raise InvalidInputError("rng: a numpy Generator or an integer seed is required (results must be reproducible)")
    rng = np.random.default_rng(rng)
    max_hypotheses = int(max_hypotheses)
    if max_hypotheses < 1:
        raise InvalidInputError(f"max_hypotheses: must be >= 1, got {max_hypotheses}")

    normal_radius = NORMAL_RADIUS_VOXELS * voxel if normal_radius is None else as_positive(normal_radius, "normal_radius")
    feature_radius = FEATURE_RADIUS_VOXELS * voxel if feature_radius is None else as_positive(feature_radius, "feature_radius")
    filter_radius = FILTER_RADIUS_VOXELS * voxel if filter_radius is None else (filter_radius or None)
    source_points, source_features = _keypoints(source, voxel, normal_radius, feature_radius, filter_radius)
    target_points, target_features = _keypoints(target, voxel, normal_radius, feature_radius, filter_radius)
    matches = match_features(source_features, target_features)
    if len(matches) < 3:
        return []
    paired_source = source_points[matches[:, 0]]
    paired_target = target_points[matches[:, 1]]
    min_edge = 2.0 * voxel
    if method == "ransac":
        rotations, translations, counts = _ransac(
            paired_source,
            paired_target,
            threshold,
            rng,
            max_trials=int(max_trials),
            min_trials=int(min_trials),
            batch=int(batch),
            confidence=float(confidence),
            min_edge=min_edge,
        )
    else:
        rotations, translations, counts = _cliques(
            paired_source, paired_target, threshold, max_cliques=4 * max_hypotheses, min_edge=min_edge
        )
    if len(counts) == 0:
        return []
    min_translation = DISTINCT_TRANSLATION_VOXELS * voxel
    pool = _distinct_order(rotations, translations, counts, 4 * max_hypotheses, min_translation)
    rotations, translations, counts = _refit(
        rotations[pool], translations[pool], paired_source, paired_target, threshold
    )
    final = _distinct_order(rotations, translations, counts, max_hypotheses, min_translation)
    hypotheses = []
    for index in final:
        matrix = to_matrix(rotations[index], translations[index])
        matrix.setflags(write=False)
        hypotheses.append(
            Hypothesis(
                transformation=matrix,
                inlier_count=int(counts[index]),
                inlier_fraction=float(counts[index]) / len(matches),
            )
        )
    return hypotheses
