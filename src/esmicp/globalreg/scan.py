"""Global registration of partially overlapping scans: FPFH correspondences pruned by second-order
spatial compatibility, verified on the overlap.

The pipeline of :func:`scan_estimate` (every length is a multiple of one voxel the data chooses,
so a pair scaled by 1000 gives the same pose):

1. **Scale.** :func:`~esmicp.core.keypoints.keypoint_voxel`: the voxel edge at which the target has about
   ``SearchConfig.keypoints`` occupied voxels (found from the voxel counts, which scale as the inverse square of
   the edge on a surface), never below ``SearchConfig.scan.keypoint.min_voxel_spacings`` target
   point spacings.
2. **Keypoints and descriptors.** Voxel centroids of each cloud, isolated ones dropped; PCA
   normals from the keypoints (or from the dense points), FPFH within ``ScanStrategyConfig.fpfh_radius_keypoint_voxels``
   (:mod:`esmicp.globalreg.feature_matching`'s keypoints).
3. **Correspondences.** Each source keypoint's nearest target descriptor and each target
   keypoint's nearest source descriptor (the union: a partial overlap leaves too few mutual
   matches), ranked by Lowe's ratio, at most ``max_correspondences``.
4. **Pruning** (the idea of SC2-PCR, re-derived here). Two correspondences are compatible when
   a rigid motion could map both: their source and target lengths agree to within
   ``compatibility_voxels``. The second-order compatibility of a compatible pair counts the
   correspondences compatible with both; it separates inliers from the outliers that happen to be
   compatible with one, and survives 95-99% outliers. Seeds (the ``seeds`` correspondences of
   highest leading-eigenvector score of the compatibility matrix, spread apart in both clouds)
   each grow a group of their ``group_size`` most second-order-compatible partners; each group is
   solved by a Kabsch fit weighted by the leading eigenvector of its own second-order matrix.
5. **Hypotheses.** Each fit is scored by the correspondences it maps within the compatibility
   distance; the best distinct ones are refit on their inliers.
6. **Verification on the overlap** (:func:`overlap_counts`). ICP on the keypoints until each
   pose settles (:func:`_icp`, all poses in one batch), then the keypoints lying within
   ``SearchConfig.scan.keypoint.coincide_voxels`` of the other cloud, counted both ways (source on target and target on
   source): the overlap, not the whole source. When two distinct poses
   count alike (a corridor, a road), each is scored by the inliers whose target normal points
   along the displacement between the two poses: only that geometry constrains the slide.

:func:`scan_estimate_until_confident` runs the pipeline with each setting of
``NORMALS_FROM_KEYPOINTS`` in turn until the best pose is confident on the overlap, then at other
voxels (``ScanStrategyConfig.last_keypoints``).

The tuned values are :class:`~esmicp.globalreg.config.ScanStrategyConfig` (``SearchConfig.scan``),
named in ``code`` above. Transforms are ``T_target_source`` (``target ~= source @ R.T + t``).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from .. import _kernels
from ..core.compiled_tree import CompiledTree, threads
from ..core.features import estimate_normals, voxel_grid
from ..core.keypoints import Keypoints, keypoint_voxel
from ..core.procrustes import batched_weighted_procrustes, rigid_inverse, rotation_angle, to_matrix
from ..trust.confidence import overlap_confidence
from ..trust.policy import DEFAULT_POLICY, TrustPolicy
from .feature_matching import _keypoints, _inlier_counts, _inlier_mask, _distinct_order
from .config import DEFAULT, SearchConfig



#: The searches of :func:`scan_estimate_until_confident`, tried in order until one's best pose is
#: confident (``SearchConfig.confident``): ``normals_from_keypoints`` of :func:`scan_estimate` (normals from
#: the keypoints, then from the dense points). Each finds partial scan pairs that the other misses
#: (``docs/scans-partial-overlap.md``).
NORMALS_FROM_KEYPOINTS = (True, False)

@dataclass(frozen=True)
class ScanEstimate:
    """Verified poses, best first (each distinct from those before it), their overlap scores (the
    fraction of keypoints of both clouds lying on the other cloud, 0-1), and the keypoints;
    ``confidence``: :func:`~esmicp.trust.confidence.overlap_confidence` of the best pose on those
    keypoints, once :func:`scan_estimate_until_confident` has judged it (None before);
    ``unsupported``: why the searches stopped before the other voxels, in words, when they did
    (``VerificationConfig.support_confidence``), else None."""

    transformations: np.ndarray
    scores: np.ndarray
    keypoints: Keypoints
    correspondences: int
    inlier_counts: np.ndarray
    confidence: float | None = None
    unsupported: str | None = None

    @property
    def voxel(self) -> float:
        return self.keypoints.voxel

    @classmethod
    def nothing(cls, keypoints: Keypoints) -> "ScanEstimate":
        """A search that found no hypothesis: the identity, with overlap score 0 (callers that
        pool poses skip scores of 0)."""
        return cls(np.eye(4)[None], np.zeros(1), keypoints, 0, np.zeros(1, dtype=np.intp))


def overlap_score(transformation: np.ndarray, keypoints: Keypoints, workers: int | None = None, *,
                  config: SearchConfig = DEFAULT) -> float:
    """The fraction of both clouds' keypoints within ``config.scan.keypoint.coincide_voxels`` of the other cloud
    under ``transformation`` (the verification's score, :func:`rank_poses`). ``workers``: threads
    of the compiled tree's queries (None: every core)."""
    forward, backward = overlap_counts(
        transformation[None], keypoints.source, keypoints.target, keypoints.source_tree,
        keypoints.target_tree, config.scan.keypoint.coincide_voxels * keypoints.voxel, workers,
    )
    return float(forward[0] + backward[0]) / (len(keypoints.source) + len(keypoints.target))


def _correspondences(source_features: np.ndarray, target_features: np.ndarray, limit: int,
                     workers: int | None = None) -> np.ndarray:
    """``(K, 2)`` (source, target) keypoint indices: nearest descriptors both ways, best ratio first."""
    forward_i, forward_r, backward_i, backward_r = _nearest_both_ways(source_features, target_features, workers)
    pairs = np.concatenate([
        np.stack([np.arange(len(source_features)), forward_i], axis=1),
        np.stack([backward_i, np.arange(len(target_features))], axis=1),
    ])
    order = np.argsort(np.concatenate([forward_r, backward_r]), kind="stable")
    pairs = pairs[order]
    _, first = np.unique(pairs[:, 0] * (len(target_features) + 1) + pairs[:, 1], return_index=True)
    pairs = pairs[np.sort(first)]
    return pairs[:limit].astype(np.intp)


def _nearest_both_ways(source: np.ndarray, target: np.ndarray, workers: int | None = None):
    """Nearest target row of every source row and nearest source row of every target row
    (Euclidean, float32, in one compiled pass: each distance from its dot product, never a whole
    distance matrix in memory, and no BLAS, whose threads keep spinning after each product and
    take the cores from the rest), each with Lowe's ratio (nearest over second-nearest distance).
    Ties go to the first row or column."""
    source32 = np.ascontiguousarray(source, dtype=np.float32)
    target32 = np.ascontiguousarray(target, dtype=np.float32)
    forward_i = np.empty(len(source), dtype=np.intp)
    forward_best = np.empty(len(source), dtype=np.float32)
    forward_second = np.empty(len(source), dtype=np.float32)
    column_best = np.empty((2, len(target)), dtype=np.float32)
    column_index = np.empty(len(target), dtype=np.intp)
    _kernels.nearest_descriptors(source32, np.ascontiguousarray(target32.T), np.einsum("ij,ij->i", source32, source32),
                                 np.einsum("ij,ij->i", target32, target32), forward_i, forward_best, forward_second,
                                 column_best, column_index, threads(workers))
    forward_r = np.sqrt(forward_best / np.maximum(forward_second, 1e-30)).astype(np.float64)
    backward_r = np.sqrt(column_best[0] / np.maximum(column_best[1], 1e-30))
    return forward_i, forward_r, column_index, backward_r


#: Power-iteration steps (at most) of a leading eigenvector (count): a cap on the work, the
#: iteration ending sooner at :attr:`~esmicp.globalreg.config.ScanStrategyConfig.leading_tolerance`.
_LEADING_STEPS = 20


def _leading_vector(matrices: np.ndarray, tolerance: float, iterations: int = _LEADING_STEPS) -> np.ndarray:
    """Leading eigenvectors (non-negative) of symmetric non-negative ``(..., n, n)`` matrices, by
    power iteration (batched products of the small group matrices; the large compatibility matrix
    has its compiled kernel, ``_kernels.leading_vector``, whose threads are the kernels' own:
    BLAS's threads keep spinning after each product and take the cores from the rest): at most
    ``iterations`` steps, fewer once a step moves no entry by more than ``tolerance``
    (:attr:`~esmicp.globalreg.config.ScanStrategyConfig.leading_tolerance`)."""
    vector = np.full(matrices.shape[:-1], 1.0 / max(matrices.shape[-1], 1) ** 0.5, dtype=matrices.dtype)
    for _ in range(iterations):
        previous = vector
        vector = np.matmul(matrices, vector[..., None])[..., 0]
        norm = np.linalg.norm(vector, axis=-1, keepdims=True)
        vector = vector / np.where(norm > 0, norm, 1.0)
        if float(np.abs(vector - previous).max(initial=0.0)) <= tolerance:
            break
    return vector


def prune(source: np.ndarray, target: np.ndarray, tolerance: float, *, seeds: int | None = None,
          group_size: int | None = None, spread: float | None = None, workers: int | None = None,
          config: SearchConfig = DEFAULT) -> tuple[np.ndarray, np.ndarray]:
    """Pose fits of paired points ``source[k] <-> target[k]`` (most of them possibly wrong) by
    second-order spatial compatibility (see the module docstring, step 4).

    ``tolerance``: the length disagreement (cloud units) two inlier correspondences may have.
    ``spread`` (default ``2 tolerance``): a candidate seed within ``spread`` of a better seed in
    both clouds (its source point near that seed's source point and its target point near that
    seed's target point) is skipped. ``workers``: threads of the compiled kernels (None: every
    core). Returns rotations ``(S, 3, 3)`` and translations ``(S, 3)``, one per seed group of at
    least 3 members. ``seeds``, ``group_size``: default ``config.scan.seeds`` and
    ``config.scan.group_size``.
    """
    seeds = config.scan.seeds if seeds is None else seeds
    group_size = config.scan.group_size if group_size is None else group_size
    count = len(source)
    if count < 3:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    compatible = np.empty((count, count), dtype=np.float32)
    _kernels.compatibility(np.ascontiguousarray(source, dtype=np.float64),
                           np.ascontiguousarray(target, dtype=np.float64), float(tolerance), compatible,
                           threads(workers))
    score = np.empty(count, dtype=np.float32)
    _kernels.leading_vector(compatible, float(config.scan.leading_tolerance), _LEADING_STEPS, score, threads(workers))
    spread = 2.0 * tolerance if spread is None else spread
    order = np.argsort(-score, kind="stable")
    order = order[score[order] > 0].astype(np.int64)
    chosen = np.empty(min(seeds, len(order)), dtype=np.int64)
    chosen = chosen[:_kernels.spread_seeds(order, np.ascontiguousarray(source, dtype=np.float64),
                                           np.ascontiguousarray(target, dtype=np.float64), float(spread), seeds,
                                           chosen)]
    if not len(chosen):
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    # Second order: for each seed and each correspondence compatible with it, how many
    # correspondences are compatible with both; each seed's group is it and its partners of
    # highest second-order compatibility (compiled, from the rows as bitsets).
    size = min(group_size, count - 1)
    partners = np.empty((len(chosen), size), dtype=np.int64)
    counted = np.empty((len(chosen), size), dtype=np.uint8)
    _kernels.second_order_partners(compatible, chosen, partners, counted, threads(workers))
    groups = np.concatenate([chosen[:, None], partners], axis=1).astype(np.intp)
    valid = np.concatenate([np.ones((len(chosen), 1), bool), counted.astype(bool)], axis=1)
    # Each group's own second-order matrix (compiled, groups in parallel): its members' compatibility
    # times the count of members compatible with both.
    local_second = np.empty((len(groups), groups.shape[1] ** 2), dtype=np.float32)
    _kernels.group_second_order(compatible, np.ascontiguousarray(groups, dtype=np.int64),
                                np.ascontiguousarray(valid, dtype=np.uint8), local_second, threads(workers))
    local_second = local_second.reshape(len(groups), groups.shape[1], groups.shape[1])
    weights = _leading_vector(local_second.astype(np.float64), config.scan.leading_tolerance) * valid
    enough = (weights > 1e-9).sum(axis=1) >= 3
    if not enough.any():
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    groups, weights = groups[enough], weights[enough]
    return batched_weighted_procrustes(source[groups], target[groups], weights)


def overlap_counts(transformations: np.ndarray, source: np.ndarray, target: np.ndarray,
                   source_tree: CompiledTree, target_tree: CompiledTree, distance: float,
                   workers: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(C,)`` source points within ``distance`` of the target under each pose, and ``(C,)``
    target points within ``distance`` of the placed source (compiled trees over each cloud)."""
    forward = np.empty(len(transformations), dtype=np.intp)
    backward = np.empty(len(transformations), dtype=np.intp)
    for k, matrix in enumerate(transformations):
        d_forward, _ = target_tree.query(source, transform=matrix, workers=workers)
        d_backward, _ = source_tree.query(target, transform=rigid_inverse(matrix), workers=workers)
        forward[k] = int(np.count_nonzero(d_forward <= distance))
        backward[k] = int(np.count_nonzero(d_backward <= distance))
    return forward, backward


def _icp(poses, source, target_tree: CompiledTree, target, distance, steps, settled=0.0, workers=None):
    """Point-to-point ICP on keypoints for every pose of ``poses`` ``(B, 4, 4)`` at once (pairs
    within ``distance``, cloud units): up to ``steps`` steps, a pose stopping once a step moves none
    of its keypoints by more than ``settled``, or when fewer than 3 pairs are left. One compiled
    call, the poses in parallel, each query warm-started from the pose's last neighbours."""
    poses = np.array(poses, dtype=np.float64)
    rotations = np.ascontiguousarray(poses[:, :3, :3].reshape(-1, 9))
    translations = np.ascontiguousarray(poses[:, :3, 3])
    _kernels.trimmed_icp_tree(np.ascontiguousarray(source, dtype=np.float64), rotations, translations, int(steps),
                              float(distance), 0.0, 3, float(settled), True, np.empty(len(poses), dtype=np.int64),
                              np.ascontiguousarray(target, dtype=np.float64), target_tree.rank, target_tree.points,
                              target_tree.order, target_tree.starts, target_tree.ends, target_tree.lefts,
                              target_tree.boxes, threads(workers))
    poses[:, :3, :3], poses[:, :3, 3] = rotations.reshape(-1, 3, 3), translations
    return poses


def _slide_votes(first, second, source, target_tree: CompiledTree, target_normals, distance,
                 workers=None) -> tuple[float, float]:
    """Inliers of each pose weighted by how much their target normal points along the
    displacement between the two poses (at the source keypoints' centroid)."""
    centre = source.mean(axis=0)
    direction = (first[:3, :3] @ centre + first[:3, 3]) - (second[:3, :3] @ centre + second[:3, 3])
    length = np.linalg.norm(direction)
    if length == 0:
        return 0.0, 0.0
    direction /= length
    votes = []
    for matrix in (first, second):
        gaps, nearest = target_tree.query(source, transform=matrix, workers=workers)
        close = gaps <= distance
        votes.append(float(np.abs(target_normals[nearest[close]] @ direction).sum()))
    return votes[0], votes[1]


def scan_estimate(source: np.ndarray, target: np.ndarray, *, spacing: float, workers: int | None = None,
                  normals_from_keypoints: bool = True, voxel: float | None = None,
                  config: SearchConfig = DEFAULT) -> ScanEstimate:
    """Poses ``T_target_source`` of two partially overlapping scans, best first (the module
    docstring). ``spacing``: the target's median point spacing (cloud units);
    ``normals_from_keypoints``: the keypoints' normals from the keypoints themselves, else from the
    dense points (:func:`~esmicp.globalreg.feature_matching._keypoints`); ``voxel``: the keypoint
    voxel (cloud units; default :func:`~esmicp.core.keypoints.keypoint_voxel` of the target). Deterministic."""
    settings = config.scan
    if voxel is None:
        voxel = keypoint_voxel(target, spacing, config.keypoints, settings.keypoint.min_voxel_spacings)
    normal_radius = settings.keypoint.normal_radius_voxels * voxel
    feature_radius = settings.fpfh_radius_keypoint_voxels * voxel
    filter_radius = settings.filter_radius_voxels * voxel
    with ThreadPoolExecutor(max_workers=1 if workers == 1 else 2) as pool:
        grids = list(pool.map(lambda cloud: voxel_grid(cloud, voxel), (source, target)))
        if min(len(centroids) for centroids, _ in grids) < settings.min_keypoints:
            # Too few distinct places to describe (e.g. a few points repeated): no hypothesis.
            return ScanEstimate.nothing(Keypoints(grids[0][0], grids[1][0], voxel))
        jobs = [pool.submit(_keypoints, cloud, voxel, normal_radius, feature_radius, filter_radius,
                            normals_from_keypoints=normals_from_keypoints, grid=grid,
                            neighbours=settings.normal_neighbours)
                for cloud, grid in zip((source, target), grids)]
        (source_keys, source_features), (target_keys, target_features) = (job.result() for job in jobs)
    keypoints = Keypoints(source_keys, target_keys, voxel)  # its trees serve every score below and after
    empty = ScanEstimate.nothing(keypoints)
    if len(source_keys) < 3 or len(target_keys) < 3:
        return empty
    pairs = _correspondences(source_features, target_features, settings.max_correspondences, workers)
    paired_source, paired_target = source_keys[pairs[:, 0]], target_keys[pairs[:, 1]]
    tolerance = settings.compatibility_voxels * voxel
    rotations, translations = prune(paired_source, paired_target, tolerance,
                                    spread=settings.seed_spread_voxels * voxel, workers=workers, config=config)
    if len(rotations) == 0:
        return empty
    counts = _inlier_counts(rotations, translations, paired_source, paired_target, tolerance, workers)
    keep = _distinct_order(rotations, translations, counts, settings.hypotheses,
                           settings.distinct_voxels * voxel, config.verification.distinct_rotation_deg)
    rotations, translations = rotations[keep], translations[keep]
    # Refit each on its own inliers (twice).
    for _ in range(2):
        mask = _inlier_mask(rotations, translations, paired_source, paired_target, tolerance)
        enough = mask.sum(axis=1) >= 3
        if enough.any():
            rotations, translations = rotations.copy(), translations.copy()
            rotations[enough], translations[enough] = batched_weighted_procrustes(
                paired_source, paired_target, mask[enough].astype(float))
    counts = _inlier_counts(rotations, translations, paired_source, paired_target, tolerance, workers)

    stride = -(-len(source_keys) // settings.icp_points)
    poses = _icp(np.stack([to_matrix(r, t) for r, t in zip(rotations, translations)]), source_keys[::stride],
                 keypoints.target_tree, target_keys, settings.icp_voxels * voxel, settings.icp_steps,
                 settings.icp_settled_voxels * voxel, workers)
    order, scores = rank_poses(poses, source_keys, target_keys, voxel, target_tree=keypoints.target_tree,
                               source_tree=keypoints.source_tree, workers=workers, config=config)
    return ScanEstimate(poses[order], scores[order], keypoints, len(pairs), counts[order])


def scan_estimate_until_confident(source: np.ndarray, target: np.ndarray, *, spacing: float,
                                  workers: int | None = None, searches: int | None = None,
                                  config: SearchConfig = DEFAULT, policy: TrustPolicy = DEFAULT_POLICY,
                                  scattered: Callable[[], bool] | None = None) -> ScanEstimate:
    """:func:`scan_estimate` with each setting of ``NORMALS_FROM_KEYPOINTS`` in turn until one's
    best pose is confident (:func:`~esmicp.trust.confidence.overlap_confidence` at least
    ``config.confident``), then, while none is, at the voxel of each count of
    ``config.scan.last_keypoints`` in turn (skipped when its voxel was searched already): the estimate
    whose best pose is the most confident (the first on a tie). The first searches are each judged
    on their own keypoints; the last ones on those of the
    most confident before them, which they then carry: the confidence keeps the data's one scale,
    and :attr:`ScanEstimate.voxel` stays the standard keypoint voxel. ``searches``: stop after
    that many searches (None: no limit). ``policy``: the overlap confidence's values.

    The searches at other voxels are skipped when none at the standard voxel went above
    ``config.verification.support_confidence`` (by default: no pose made the clouds coincide at
    all; the estimate then says so, :attr:`ScanEstimate.unsupported`), unless ``scattered()``
    (asked only then) says either cloud carries scattered points: such a pair ends after two
    searches, not four. Every pair those searches brought to a right pose had been confident to
    some degree at the standard voxel.

    Why: at 10-25% overlap only a few hundred of the 5,000 keypoints lie in the overlap and often
    no true correspondence survives the pruning; normals at the keypoints' scale and at the dense
    points' give different descriptors, and so does every voxel: each search finds crops the
    others miss. A confident first search costs nothing more."""
    best: ScanEstimate | None = None
    done = 0

    def keep_if_better(found: ScanEstimate) -> bool:
        """Judge ``found`` on its keypoints, keep it if more confident; True once one is confident
        or ``searches`` have run."""
        nonlocal best, done
        found = replace(found, confidence=overlap_confidence(found.transformations[0], found.keypoints, workers,
                                                             config=config, policy=policy))
        if best is None or found.confidence > best.confidence:
            best = found
        done += 1
        return best.confidence >= config.confident or done == searches

    floor = config.scan.keypoint.min_voxel_spacings
    voxel = keypoint_voxel(target, spacing, config.keypoints, floor)  # the same for each standard search: found once
    for normals_from_keypoints in NORMALS_FROM_KEYPOINTS:
        if keep_if_better(scan_estimate(source, target, spacing=spacing, workers=workers,
                                        normals_from_keypoints=normals_from_keypoints, voxel=voxel,
                                        config=config)):
            return best
    others = []
    for count in config.scan.last_keypoints:
        other = keypoint_voxel(target, spacing, count, floor)
        if other != voxel and other not in others:  # not a repeat (a small cloud is at the floor for every count)
            others.append(other)
    bar = config.verification.support_confidence
    if others and best.confidence <= bar and not (scattered is not None and scattered()):
        return replace(best, unsupported=(
            f"no support: no pose of the searches at the standard voxel made the clouds coincide (overlap confidence "
            f"{best.confidence:.2f}, at most {bar:g}), so the searches at {len(others)} other voxel(s) were skipped"))
    for other in others:
        found = scan_estimate(source, target, spacing=spacing, workers=workers, voxel=other, config=config)
        if keep_if_better(replace(found, keypoints=best.keypoints)):
            break
    return best


def rank_poses(poses: np.ndarray, source: np.ndarray, target: np.ndarray, voxel: float, *,
               target_tree: CompiledTree | None = None, source_tree: CompiledTree | None = None,
               workers: int | None = None, config: SearchConfig = DEFAULT) -> tuple[np.ndarray, np.ndarray]:
    """Verification on the overlap (module docstring, step 6): the indices of the mutually
    distinct ``poses`` ``(C, 4, 4)``, best first, and every pose's overlap score (the fraction of
    ``source`` and ``target`` keypoints within ``config.scan.keypoint.coincide_voxels`` of the other cloud).

    A pose of about the same rotation as the leader (within
    ``config.verification.distinct_rotation_deg``) and a score of at least
    ``config.scan.tie_ratio`` of its score challenges it on the slide: both count their
    inliers weighted by ``|n . u|``, with ``n`` the target normal and ``u`` the direction between
    the two poses, and the higher count leads. On a corridor the slid pose can overlap *more*
    (it slides the source further along), while only the true one aligns the geometry across it.
    ``target_tree`` / ``source_tree``: compiled trees over ``target`` / ``source`` to reuse (built
    here when not given).
    """
    target_tree = CompiledTree(target) if target_tree is None else target_tree
    source_tree = CompiledTree(source) if source_tree is None else source_tree
    distance = config.scan.keypoint.coincide_voxels * voxel
    forward, backward = overlap_counts(poses, source, target, source_tree, target_tree, distance, workers)
    scores = (forward + backward) / float(len(source) + len(target))
    distinct_deg = config.verification.distinct_rotation_deg
    order = _distinct_poses(poses, list(np.argsort(-scores, kind="stable")), config.scan.contender_voxels * voxel,
                            distinct_deg)
    normals = None
    leader = 0
    for position in range(1, len(order)):
        challenger, best = order[position], order[leader]
        if scores[challenger] < config.scan.tie_ratio * scores[best]:
            break
        turn = np.degrees(rotation_angle(poses[challenger, :3, :3].T @ poses[best, :3, :3]))
        if turn > distinct_deg:
            continue
        if normals is None:
            normals = estimate_normals(target, k=config.scan.keypoint.slide_normal_neighbours,
                                       radius=config.scan.keypoint.normal_radius_voxels * voxel, tree=target_tree)
        best_votes, challenger_votes = _slide_votes(poses[best], poses[challenger], source, target_tree, normals,
                                                    distance, workers)
        if challenger_votes > best_votes:
            leader = position
    order.insert(0, order.pop(leader))
    return np.asarray(order, dtype=np.intp), scores


def _distinct_poses(poses: np.ndarray, order: list[int], min_translation: float, min_rotation_deg: float) -> list[int]:
    kept: list[int] = []
    for index in order:
        if all(
            np.degrees(rotation_angle(poses[index, :3, :3].T @ poses[other, :3, :3])) > min_rotation_deg
            or np.linalg.norm(poses[index, :3, 3] - poses[other, :3, 3]) > min_translation
            for other in kept
        ):
            kept.append(int(index))
    return kept
