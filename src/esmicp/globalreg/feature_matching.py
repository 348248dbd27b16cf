"""Global pose hypotheses from FPFH correspondences, without any initial guess.

Pipeline of :func:`feature_hypotheses` (all lengths scale with the ``voxel`` argument):

1. Voxel-downsample each cloud (the keypoints), and drop isolated keypoints, with their points:
   fewer occupied voxels within ``2 voxel`` than 0.3 x the cloud's 75th percentile
   (:func:`~esmicp.core.features.dense_point_mask`). This removes scattered outliers, which
   otherwise corrupt the normals and histograms of the clean points near them.
2. PCA normals at the keypoints from the remaining dense points (at most 60 within ``4 voxel``),
   oriented away from the centroid; FPFH within ``7 voxel`` (:mod:`esmicp.core.features`).
3. Mutual nearest neighbours in feature space (:func:`match_features`).
4. A robust estimator over the correspondences, ``method``:

   ``"ransac"`` (default)
       RANSAC over 3-correspondence samples, drawn in batches (256, then doubling up to
       ``batch``). A sample survives only if its three side lengths agree between source and
       target to within 10 % (a rigid motion preserves lengths) and its smallest side is at least
       ``2 voxel``; all survivors are solved at once by a batched Kabsch fit
       (``numpy.linalg.svd`` on ``(B, 3, 3)``) and scored at once by counting the correspondences
       each maps to within ``inlier_distance``. Batches are drawn until the RANSAC stopping rule
       is met (``confidence`` that an all-inlier sample was drawn, given the best inlier fraction
       so far) and ``min_trials`` samples were drawn, or ``max_trials`` samples were drawn.
   ``"clique"``
       Pairwise-consistency graph (the idea of TEASER++ / KISS-Matcher, re-derived here):
       correspondences ``i`` and ``j`` are adjacent when
       ``| |s_i - s_j| - |t_i - t_j| | <= 2 inlier_distance``. Greedy cliques grown from the
       best-connected unused correspondences are solved by Kabsch.

5. The best candidates by inlier count are made distinct (rotations more than 10 degrees apart or
   translations more than 2 voxels apart), each is refit by Kabsch on its own inlier
   correspondences (twice), and the survivors are ranked by the *overlap* of the keypoint clouds
   they produce (fraction of source keypoints within ``inlier_distance`` of a target keypoint),
   which tells the true pose from a wrong one better than the count of correspondences does.

The default radii (normals 4, FPFH 7, filter 2 voxels:
:class:`~esmicp.globalreg.config.FeatureMatchingConfig`) are wider than Open3D's usual 2 and 5
voxels because they measured better on the outlier protocols (``docs/measured-global.md``, "Why
these choices").

Transforms are ``T_target_source``: ``target ~= source @ R.T + t``. Randomness comes only from
the ``rng`` argument, so a seed gives identical hypotheses.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from typing import TYPE_CHECKING

import numpy as np

from .. import _kernels
from ..core.compiled_tree import CompiledTree, threads
from ..core.features import dense_point_mask, estimate_normals, fpfh, voxel_grid
from ..core.procrustes import batched_weighted_procrustes, to_matrix
from ..errors import InvalidInputError
from ..types import as_count, as_generator, as_points, as_positive, as_real
from .config import DEFAULT, SearchConfig

if TYPE_CHECKING:  # SciPy is imported where it is used: `register` on a clean pair never needs it
    from scipy.spatial import cKDTree

#: Feature-space problems up to this many (source x target) pairs use brute force, not a KD-tree
#: (count; both exact, only the speed differs).
_BRUTE_FORCE_PAIRS = 4_000_000

#: Largest number of (candidate x correspondence) residuals evaluated at once (count; bounds the
#: memory of the scoring).
_SCORE_CHUNK = 2_000_000

#: Ways of turning matched features into hypotheses (``method`` of :func:`feature_hypotheses`).
MATCHING_METHODS = ("ransac", "clique")

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
    overlap : float
        Fraction of the source keypoints (the downsampled, filtered source) that it maps within
        ``inlier_distance`` of a target keypoint, in ``[0, 1]``. Hypotheses are ranked by it.
    """

    transformation: np.ndarray
    inlier_count: int
    inlier_fraction: float
    overlap: float


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
            # argmin, not a <= comparison: float32 rounding can tie two source rows for one target
            # row, and a mutual match must stay one-to-one.
            is_mutual = squared.argmin(axis=0)[forward] == rows
        return forward, distance, second_distance, is_mutual
    from scipy.spatial import cKDTree

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
    min_matches: int | None = None,
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
    min_matches : int, optional
        See ``mutual``; default
        :attr:`~esmicp.globalreg.config.FeatureMatchingConfig.min_mutual_matches`.

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
    min_matches = DEFAULT.features.min_mutual_matches if min_matches is None else min_matches
    if mutual and (selected & is_mutual).sum() >= min_matches:
        selected &= is_mutual
    rows = np.flatnonzero(selected)
    rows = rows[np.argsort(distance[rows], kind="stable")]
    return np.stack([rows, forward[rows]], axis=1).astype(np.intp)


# --------------------------------------------------------------------------------------------
# Batched rigid fits and scoring


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


def _inlier_counts(rotations: np.ndarray, translations: np.ndarray, source: np.ndarray, target: np.ndarray,
                   distance: float, workers: int | None = None) -> np.ndarray:
    """``(S,)``: how many pairs ``source[k] <-> target[k]`` each pose ``(rotations[c],
    translations[c])`` maps within ``distance`` (cloud units) of each other: ``_inlier_mask``'s
    row sums, counted in one compiled pass (RANSAC and the scan strategy's pruning score hundreds
    to thousands of poses at a time). ``workers``: threads (None: every core)."""
    counts = np.empty(len(rotations), dtype=np.int64)
    _kernels.pair_inlier_counts(np.ascontiguousarray(rotations, dtype=np.float64).reshape(-1, 9),
                                np.ascontiguousarray(translations, dtype=np.float64),
                                np.ascontiguousarray(source, dtype=np.float64),
                                np.ascontiguousarray(target, dtype=np.float64), float(distance), counts,
                                threads(workers))
    return counts


def _rotation_gaps_deg(rotations: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Geodesic angles (degrees) between each of ``(C, 3, 3)`` rotations and one reference."""
    cosine = 0.5 * (np.einsum("cij,ij->c", rotations, reference) - 1.0)
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def _distinct_order(rotations, translations, scores, max_count, min_translation, min_rotation_deg) -> np.ndarray:
    """Indices of at most ``max_count`` mutually distinct candidates (rotations more than
    ``min_rotation_deg`` degrees apart or translations more than ``min_translation`` apart), best
    score first."""
    remaining = np.argsort(-scores, kind="stable")
    chosen = []
    while len(remaining) and len(chosen) < max_count:
        best = remaining[0]
        chosen.append(best)
        rest = remaining[1:]
        far = (_rotation_gaps_deg(rotations[rest], rotations[best]) > min_rotation_deg) | (
            np.linalg.norm(translations[rest] - translations[best], axis=1) > min_translation
        )
        remaining = rest[far]
    return np.asarray(chosen, dtype=np.intp)


def _refit(rotations, translations, source, target, threshold, rounds: int = 2, workers: int | None = None):
    """Refit every candidate by Kabsch on its own inliers, ``rounds`` times.

    Candidates with fewer than 3 inliers are left as they are. Returns the refit rotations,
    translations and final inlier counts. ``workers``: threads of the compiled count.
    """
    for _ in range(rounds):
        mask = _inlier_mask(rotations, translations, source, target, threshold)
        counts = mask.sum(axis=1)
        enough = counts >= 3
        if not enough.any():
            return rotations, translations, counts
        rotations, translations = rotations.copy(), translations.copy()
        fitted_r, fitted_t = batched_weighted_procrustes(source, target, mask[enough].astype(np.float64))
        rotations[enough], translations[enough] = fitted_r, fitted_t
    counts = _inlier_counts(rotations, translations, source, target, threshold, workers)
    return rotations, translations, counts


# --------------------------------------------------------------------------------------------
# Robust estimators over correspondences


def _edge_lengths(points: np.ndarray) -> np.ndarray:
    """``(B, 3)`` side lengths of ``(B, 3, 3)`` triangles: |p0 p1|, |p1 p2|, |p2 p0|."""
    return np.linalg.norm(points - np.roll(points, -1, axis=1), axis=2)


def _ransac(
    source, target, threshold, rng, *, max_trials, min_trials, batch, confidence, min_edge, keep, min_translation,
    workers=None, config: SearchConfig = DEFAULT,
):
    """Batched RANSAC on paired points.

    Returns ``(rotations, translations, counts)`` of at most ``keep`` mutually distinct candidates
    (see :func:`_distinct_order`), each the best-scoring of its neighbourhood of poses.
    ``workers``: threads of the compiled inlier count; ``config``: the edge tolerance of a sample
    (``config.features.edge_tolerance``), the first batch's size (``config.features.first_batch``)
    and the distinct rotation
    (``config.verification.distinct_rotation_deg``).
    """
    count = len(source)
    pool_r = np.zeros((0, 3, 3))
    pool_t = np.zeros((0, 3))
    pool_c = np.zeros(0, dtype=np.intp)
    trials, needed, best = 0, max(max_trials, 1), 0
    size = min(batch, config.features.first_batch)
    while trials < min(needed, max_trials):
        # Batches grow from small to ``batch``: an easy problem stops after the first one.
        size = min(size, max_trials - trials)
        trials += size
        sample = rng.integers(0, count, size=(size, 3))
        src, tgt = source[sample], target[sample]
        src_edges, tgt_edges = _edge_lengths(src), _edge_lengths(tgt)
        tolerance = config.features.edge_tolerance
        ok = (np.abs(src_edges - tgt_edges) <= tolerance * np.maximum(src_edges, tgt_edges)).all(axis=1)
        ok &= src_edges.min(axis=1) >= min_edge
        if not ok.any():
            size = min(2 * size, batch)
            continue
        rotations, translations = batched_weighted_procrustes(src[ok], tgt[ok])
        counts = _inlier_counts(rotations, translations, source, target, threshold, workers)
        pool_r = np.concatenate([pool_r, rotations])
        pool_t = np.concatenate([pool_t, translations])
        pool_c = np.concatenate([pool_c, counts])
        # Keep the best candidate of each of the ``keep`` best distinct poses seen so far.
        top = _distinct_order(pool_r, pool_t, pool_c, keep, min_translation, config.verification.distinct_rotation_deg)
        pool_r, pool_t, pool_c = pool_r[top], pool_t[top], pool_c[top]
        best = max(best, int(counts.max()))
        fraction = best / count
        if fraction >= 1.0:
            needed = min_trials
        elif fraction**3 > 0:
            needed = max(min_trials, int(np.ceil(np.log1p(-confidence) / np.log1p(-(fraction**3)))))
        size = min(2 * size, batch)
    return pool_r, pool_t, pool_c


def _cliques(source, target, threshold, *, max_cliques, min_edge, workers=None):
    """Greedy cliques of the pairwise length-consistency graph; returns Kabsch fits of each.

    Correspondences ``i`` and ``j`` are adjacent when their source and target distances agree to
    within ``2 threshold`` (and both exceed ``min_edge``). Each clique starts at the unused
    correspondence of highest degree and repeatedly adds the candidate adjacent to the most
    remaining candidates (degrees within the candidate set are updated incrementally, so growing
    one clique costs O(K^2) in all). ``workers``: threads of the compiled inlier count.
    """
    count = len(source)
    source_d = np.linalg.norm(source[:, None] - source[None], axis=2)
    target_d = np.linalg.norm(target[:, None] - target[None], axis=2)
    graph = np.abs(source_d - target_d) <= 2.0 * threshold
    graph &= np.minimum(source_d, target_d) >= min_edge
    weights = graph.astype(np.float32)
    degree = graph.sum(axis=1)
    used = np.zeros(count, dtype=bool)
    rotations, translations = [], []
    for _ in range(max_cliques):
        free = np.flatnonzero(~used & (degree >= 2))
        if len(free) == 0:
            break
        seed = free[np.argmax(degree[free])]
        members = [seed]
        candidates = graph[seed].copy()
        local = weights @ candidates.astype(np.float32)  # neighbours of every node among candidates
        while candidates.any():
            pool = np.flatnonzero(candidates)
            pick = pool[np.argmax(local[pool])]
            members.append(pick)
            removed = candidates & ~graph[pick]
            removed[pick] = True
            candidates &= ~removed
            local -= weights[:, removed].sum(axis=1)
        members = np.asarray(members)
        used[members] = True
        if len(members) < 3:
            continue
        r, t = batched_weighted_procrustes(source[members][None], target[members][None])
        rotations.append(r[0])
        translations.append(t[0])
    if not rotations:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.intp)
    rotations, translations = np.stack(rotations), np.stack(translations)
    counts = _inlier_counts(rotations, translations, source, target, threshold, workers)
    return rotations, translations, counts


def _overlap(rotations, translations, source, target_tree, threshold) -> np.ndarray:
    """``(C,)`` fraction of ``source`` points that each candidate maps within ``threshold`` of a
    point of ``target_tree``."""
    moved = np.einsum("cij,nj->cni", rotations, source) + translations[:, None, :]
    distances, _ = target_tree.query(moved.reshape(-1, 3), distance_upper_bound=threshold)
    return (distances.reshape(len(rotations), len(source)) <= threshold).mean(axis=1)


# --------------------------------------------------------------------------------------------
# The public entry point




def _keypoints(
    points: np.ndarray, voxel: float, normal_radius: float, feature_radius: float, filter_radius: float | None,
    *, normals_from_keypoints: bool = False, grid: tuple[np.ndarray, np.ndarray] | None = None, neighbours: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Downsampled points and their FPFH. ``grid``: :func:`~esmicp.core.features.voxel_grid`
    of ``points`` at ``voxel``, when the caller has it already.

    Isolated voxels (few occupied voxels within ``filter_radius``: scattered outliers) are dropped
    with their points before normals are estimated; so are keypoints without FPFH neighbours.
    Normals are PCA normals of the (dense) remaining points around each keypoint, or with
    ``normals_from_keypoints`` of the keypoints themselves (the ``neighbours`` nearest
    within ``normal_radius``): the voxel's scale rather than the sensor's, less noisy on depth
    scans, and no tree over the dense cloud.
    """
    down, owner = voxel_grid(points, voxel) if grid is None else grid
    tree = CompiledTree(down)  # one tree over the keypoints: their filter, normals and FPFH
    if filter_radius is not None:
        keep = dense_point_mask(down, filter_radius, tree=tree)
        if not keep.all():
            down = down[keep]
            tree = CompiledTree(down)
            if not normals_from_keypoints:  # the dense points serve only the dense normals
                points = points[keep[owner]]
    if normals_from_keypoints:
        normals = estimate_normals(down, k=neighbours, radius=normal_radius, tree=tree)
    else:
        normals = estimate_normals(points, k=neighbours, radius=normal_radius, at=down)
    features = fpfh(down, normals, feature_radius, tree=tree)
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
    workers: int | None = None,
    normals_from_keypoints: bool = False,
    config: SearchConfig = DEFAULT,
) -> list[Hypothesis]:
    """Candidate poses ``T_target_source`` from FPFH feature correspondences, best first.

    See the module docstring for the pipeline.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) arrays
        The clouds, in the same units, in any relative pose.
    voxel : float
        Downsampling voxel edge (cloud units); sets the scale of everything else
        (:attr:`~esmicp.globalreg.config.FeatureMatchingConfig.voxel_diagonals` of the target's
        bounding-box diagonal in the global search).
    rng : numpy.random.Generator or int
        The only source of randomness (an int is a seed for ``numpy.random.default_rng``).
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
        Robust estimator.
    confidence : float
        RANSAC stopping rule: probability, in ``(0, 1)``, that an all-inlier sample was drawn.
    batch : int
        Largest RANSAC batch (samples drawn and checked at once).
    normal_radius, feature_radius : float, optional
        Neighbourhood radii (cloud units) of the normals and of FPFH. Default ``4 voxel`` and
        ``7 voxel``.
    filter_radius : float, optional
        Radius (cloud units) of the isolated-keypoint filter; default ``2 voxel``; 0 disables it.
    workers : int, optional
        Threads: 1 computes the two clouds' features one after the other; otherwise (None: every
        core) on two threads.
    config : SearchConfig
        The default radii, the normals' neighbours, the matching's and the distinct poses' values
        (``config.features``, :class:`~esmicp.globalreg.config.FeatureMatchingConfig`).

    Returns
    -------
    list of Hypothesis
        At most ``max_hypotheses`` distinct hypotheses, each refit on its own inliers, ordered by
        decreasing ``overlap`` (then ``inlier_count``). Empty when fewer than 3 correspondences
        are found or no sample passes the checks.
    """
    source = as_points(source, "source")
    target = as_points(target, "target")
    voxel = as_positive(voxel, "voxel")
    threshold = 1.5 * voxel if inlier_distance is None else as_positive(inlier_distance, "inlier_distance")
    if method not in MATCHING_METHODS:
        raise InvalidInputError(f"method: expected one of {', '.join(MATCHING_METHODS)}, got {method!r}")
    if rng is None:
        raise InvalidInputError("rng: a numpy Generator or an integer seed is required (results must be reproducible)")
    confidence = as_real(confidence, "confidence")
    if not 0.0 < confidence < 1.0:
        raise InvalidInputError(f"confidence: must be in (0, 1), got {confidence!r}")
    rng = as_generator(rng)
    max_hypotheses = as_count(max_hypotheses, "max_hypotheses", 1)
    max_trials = as_count(max_trials, "max_trials", 0)
    min_trials = as_count(min_trials, "min_trials", 0)
    batch = as_count(batch, "batch", 1)

    settings = config.features
    if normal_radius is None:
        normal_radius = settings.normal_radius_voxels * voxel
    normal_radius = as_positive(normal_radius, "normal_radius")
    if feature_radius is None:
        feature_radius = settings.fpfh_radius_voxels * voxel
    feature_radius = as_positive(feature_radius, "feature_radius")
    if filter_radius is None:
        filter_radius = settings.filter_radius_voxels * voxel
    elif as_real(filter_radius, "filter_radius") == 0:
        filter_radius = None
    else:
        filter_radius = as_positive(filter_radius, "filter_radius")
    # The two clouds' features are independent: compute them on two threads (numpy and scipy
    # release the GIL in their loops; measured 1.8x faster on 2 cores, same result).
    pool = ThreadPoolExecutor(max_workers=1 if workers == 1 else 2)
    try:
        source_job = pool.submit(_keypoints, source, voxel, normal_radius, feature_radius, filter_radius,
                                 normals_from_keypoints=normals_from_keypoints, neighbours=settings.normal_neighbours)
        target_job = pool.submit(_keypoints, target, voxel, normal_radius, feature_radius, filter_radius,
                                 normals_from_keypoints=normals_from_keypoints, neighbours=settings.normal_neighbours)
        (source_points, source_features), (target_points, target_features) = source_job.result(), target_job.result()
    except BaseException:
        # Ctrl-C (or an error) while waiting: do not wait for the other cloud's features to be
        # finished (measured: a KeyboardInterrupt 1.5 s late on 1M points); they end on their own.
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    matches = match_features(source_features, target_features, min_matches=settings.min_mutual_matches)
    if len(matches) < 3:
        return []
    paired_source = source_points[matches[:, 0]]
    paired_target = target_points[matches[:, 1]]
    min_edge = 2.0 * voxel
    min_translation = settings.distinct_translation_voxels * voxel
    distinct_deg = config.verification.distinct_rotation_deg
    if method == "ransac":
        rotations, translations, counts = _ransac(
            paired_source,
            paired_target,
            threshold,
            rng,
            max_trials=max_trials,
            min_trials=min_trials,
            batch=batch,
            confidence=confidence,
            min_edge=min_edge,
            keep=4 * max_hypotheses,
            min_translation=min_translation,
            workers=workers,
            config=config,
        )
    else:
        rotations, translations, counts = _cliques(
            paired_source, paired_target, threshold, max_cliques=4 * max_hypotheses, min_edge=min_edge,
            workers=workers,
        )
    if len(counts) == 0:
        return []
    pool = _distinct_order(rotations, translations, counts, 4 * max_hypotheses, min_translation, distinct_deg)
    rotations, translations, counts = _refit(
        rotations[pool], translations[pool], paired_source, paired_target, threshold, workers=workers
    )
    final = _distinct_order(rotations, translations, counts, max_hypotheses, min_translation, distinct_deg)
    rotations, translations, counts = rotations[final], translations[final], counts[final]
    # Rank by geometric overlap of the keypoint clouds: it tells the true pose from a wrong one
    # with many consistent (but wrong) correspondences better than the count does.
    from scipy.spatial import cKDTree

    overlap = _overlap(rotations, translations, source_points, cKDTree(target_points), threshold)
    order = np.lexsort((-counts, -overlap))
    hypotheses = []
    for index in order:
        matrix = to_matrix(rotations[index], translations[index])
        matrix.setflags(write=False)
        hypotheses.append(
            Hypothesis(
                transformation=matrix,
                inlier_count=int(counts[index]),
                inlier_fraction=float(counts[index]) / len(matches),
                overlap=float(overlap[index]),
            )
        )
    return hypotheses
