"""Global registration: a pose ``T_target_source`` from anywhere, with the evidence to judge it.

The default search (``"auto"``, :func:`global_estimate`) is one pipeline; the tuned values it
names are fields of :class:`~esmicp.globalreg.config.SearchConfig` (``config.<field>``).

**Generators** (each returns rigid ``(4, 4)`` poses ``T_target_source``):

- the *rotation search* (:func:`_rotation_candidates`), for whole objects:
  ``config.rotation.rotations`` starting rotations spread over SO(3), centroids aligned, refined
  together by a short batched ESM on ``config.rotation.points`` source points
  (:func:`~esmicp.globalreg.rotation_search.rotation_search`);
- *correspondences pruned by consistency* (:func:`_scan`, :mod:`esmicp.globalreg.scan`), for
  partially overlapping scans: FPFH matches kept by second-order spatial compatibility, each
  pose checked on the overlap both ways; and the *feature hypotheses* of
  :mod:`esmicp.globalreg.feature_matching` (:func:`_feature_candidates`);
- the *twins* of a pose (:func:`_twins`): turned by 180 degrees about each principal axis of the
  target, which a near-symmetric object under heavy noise otherwise ends on.

**Verifier** (:func:`_verify`, then :func:`_decide`): every candidate is refined by batched ESM at
the data's resolution and scored by the soft fraction (0-1) of source points lying on the target
(Gaussian of width ``config.verification.score_width_spacings`` target spacings), in successive-halving rounds.
When the runner-up scores at least ``config.decide_ratio`` of the best, the contenders are
re-scored on up to the full clouds, both ways (source on target and target on source).

**Decision**: the best verified pose, unless one of the scan strategy's poses is confident on the
overlap (:func:`~esmicp.trust.confidence.overlap_confidence` at least ``config.confident``) and
overlaps more (:func:`_scan_leads`), or the chosen pose is not confident there and a scan pose is
clearly more (:func:`_sharper_on_the_overlap`, ``config.sharper_than_chosen``): the verifier
counts how much of the source lies on the target, which a cut object's flip can satisfy better
than the truth. The result is *ambiguous* when a clearly different pose (rotation more than
:attr:`~esmicp.globalreg.config.VerificationConfig.distinct_rotation_deg` away) scores at least
``config.ambiguity_ratio``
of the returned one, or more (the returned pose then won on sharpness);
:attr:`GlobalEstimate.runner_up_ratio` is the lower of the two scores over the higher. A scan
pose that wins keeps its place, but it and its runner-ups are scored by the verifier too
(:func:`_on_the_verifier_scale`), so that every result's scores, ``ambiguous`` and
``runner_up_ratio`` are on the verifier's one scale, whichever generator won.

**One exit, for cost**: the rotation search's pose is final before the scan strategy runs when
it scores ``config.confident_score`` (after a few more ESM iterations, :func:`_settle`, when it
scored just short of it: ``config.settle_from``), unambiguously, and is confident on the overlap
or covers the target (``config.full_cover``). When either cloud carries scattered points
(:func:`~esmicp.trust.judge.scattered_keypoints`, read from the clouds alone), the score cannot
reach the bar (the scattered points never lie on the other cloud): the unambiguous pose is then
final when it is confident on the overlap, which measures such a cloud on its surface, and stays
unambiguous once its twins (:func:`_twins`) are verified beside it. Most whole
objects end there; closing the exit (``confident_score`` above 1 closes both ways) costs 1.5 times
the time on the development objects and halves, for the same successes (``docs/measured-global.md``,
"Exits for cost").

``init="rotation-search"`` / ``"features"`` / ``"scan"`` run one generator alone, through the same
verifier (the scan strategy through its own verification on the overlap).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from ..core.correspondence import NearestNeighbors
from ..core.nearest_grid import NearestGrid
from ..core.procrustes import apply, batched_rotation_angle, bounding_box_diagonal, rigid_inverse, to_matrix
from .config import DEFAULT, SearchConfig
from ..trust.policy import DEFAULT_POLICY, TrustPolicy
from .rotation_search import NeighbourGraph, batched_esm, gaussian_overlap_score, rotation_search

if TYPE_CHECKING:  # for the annotations only: the functions below import scan where they use it
    from ..core.keypoints import Keypoints

#: Names accepted as ``init=`` strategies for global registration.
STRATEGIES = ("auto", "rotation-search", "features", "scan")

@dataclass(frozen=True)
class GlobalEstimate:
    """The verified poses, best first, each distinct from those before it.

    ``transformations`` ``(K, 4, 4)`` and ``scores`` ``(K,)`` (soft fraction, 0-1, of the
    verification source points lying on the target) hold the best pose and every distinct pose
    scoring at least ``ambiguity_ratio`` of it, plus the best distinct runner-up below that, if any.
    ``strategies`` names where each came from; ``candidates`` counts the poses verified;
    ``unsupported``: why the scan strategy stopped before its searches at other voxels, in words
    (:attr:`esmicp.globalreg.scan.ScanEstimate.unsupported`: a doubt on the result), or None.
    ``whole_keypoints``: the whole clouds' :class:`~esmicp.core.keypoints.Keypoints` (``Keypoints.of``
    at the config's voxel, the ones the judge reads the clouds' scatter from) when the search
    made them, else None. ``scattered``: the search's reading of the clouds' scatter
    (:func:`~esmicp.trust.judge.scattered_keypoints` with its config, policy and workers: True
    when a cloud carries scattered points, ``whole_keypoints`` then the keypoints it returned),
    None when it did not read it.
    """

    transformations: np.ndarray
    scores: np.ndarray
    strategies: tuple[str, ...]
    candidates: int
    keypoints: object = None  # the scan strategy's :class:`~esmicp.core.keypoints.Keypoints`, for confidence
    confidence: float | None = None  # overlap confidence of transformations[0] on keypoints, when already judged
    ambiguity_ratio: float = DEFAULT.ambiguity_ratio  # the config's, for :attr:`ambiguous`
    unsupported: str | None = None
    whole_keypoints: object = None  # the whole clouds' :class:`~esmicp.core.keypoints.Keypoints`, when made
    scattered: bool | None = None  # the clouds' scatter as the search read it, when it did

    @property
    def transformation(self) -> np.ndarray:
        return self.transformations[0]

    @property
    def score(self) -> float:
        return float(self.scores[0])

    @property
    def runner_up_score(self) -> float | None:
        return float(self.scores[1]) if len(self.scores) > 1 else None

    @property
    def runner_up(self) -> np.ndarray | None:
        """The distinct runner-up ``T_target_source`` (as verified, in the search's frame), or None."""
        return self.transformations[1] if len(self.transformations) > 1 else None

    @property
    def ambiguous(self) -> bool:
        """True when the distinct runner-up scores at least ``ambiguity_ratio`` of the returned
        pose's score, or more than it (the returned pose then won on a tie-break the score does not
        see: it is sharper on the overlap, or better constrained along a slide)."""
        return len(self.scores) > 1 and self.scores[1] >= self.ambiguity_ratio * self.scores[0]

    @property
    def runner_up_ratio(self) -> float | None:
        """The lower of the two scores (the returned pose's and the distinct runner-up's) over the
        higher, 0-1 (1: they score alike; 1 also when both are 0); None without a runner-up."""
        if len(self.scores) < 2:
            return None
        low, high = sorted((float(self.scores[0]), float(self.scores[1])))
        return low / high if high > 0 else 1.0


def _subsample(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    if len(points) <= count:
        return points
    return points[rng.choice(len(points), size=count, replace=False)]


def _distinct(transformations: np.ndarray, order: np.ndarray, limit: int, min_rotation_deg: float) -> list[int]:
    """Indices (in ``order``) of up to ``limit`` poses, each distinct from those before it (its
    rotation more than ``min_rotation_deg`` degrees from theirs)."""
    order = [int(index) for index in order]
    if not order:
        return []
    rotations = transformations[order, :3, :3]
    count = len(order)
    # R_a^T R_b for every pair from one (3K, 3) x (3, 3K) product
    # (cheaper than K^2 separate 3x3 products: docs/speed.md).
    columns = np.swapaxes(rotations, 1, 2).reshape(3 * count, 3)
    relative = (columns @ columns.T).reshape(count, 3, count, 3).transpose(0, 2, 1, 3)  # [a, b] = R_a^T R_b
    angles = np.degrees(batched_rotation_angle(relative))
    kept: list[int] = []
    for position in range(len(order)):
        if (angles[position, kept] > min_rotation_deg).all():
            kept.append(position)
            if len(kept) == limit:
                break
    return [order[position] for position in kept]


@dataclass
class _Workspace:
    """What every stage of one global search shares."""

    source: np.ndarray
    target: np.ndarray
    rng: np.random.Generator
    full_index: NearestNeighbors
    index: NearestNeighbors  # over ``target`` or a subsample of it
    spacing: float
    width: float
    config: SearchConfig = DEFAULT
    policy: TrustPolicy = DEFAULT_POLICY  # the overlap confidence's values
    graphs: dict[int, NeighbourGraph] = field(default_factory=dict)  # by id() of ``index`` / ``full_index``
    grid: NearestGrid | None = None  # the rotation search's lookup grid over ``index``, once built
    _keypoints: "Keypoints | None" = field(default=None, repr=False)  # once built (:meth:`keypoints`)
    _source_index: NearestNeighbors | None = field(default=None, repr=False)  # once built (:meth:`source_index`)
    _scatter: bool | None = field(default=None, repr=False)  # once read (:func:`_scattered`)

    def keypoints(self) -> "Keypoints":
        """The pair's :class:`~esmicp.core.keypoints.Keypoints` (the ones ``register`` judges its
        confidence on), built once."""
        from ..core.keypoints import Keypoints

        if self._keypoints is None:
            self._keypoints = Keypoints.of(self.source, self.target, self.full_index.spacing(), self.config.keypoints,
                                           self.config.scan.keypoint.min_voxel_spacings)
        return self._keypoints

    def source_index(self) -> NearestNeighbors:
        """A :class:`NearestNeighbors` over the source (for target points placed on it), built once,
        with the target index's workers and values."""
        if self._source_index is None:
            self._source_index = NearestNeighbors(self.source, workers=self.full_index.workers,
                                                  config=self.full_index.config)
        return self._source_index

    def seeds(self, index: NearestNeighbors) -> NearestGrid | None:
        """The lookup grid when it covers ``index``'s points (the first queries of a batched ESM
        on ``index`` then start from its answers), else None."""
        return self.grid if self.grid is not None and self.grid.points is index.points else None

    def graph(self, index: NearestNeighbors, queries: int) -> NeighbourGraph:
        """The :class:`NeighbourGraph` of ``index`` (one of the two above), built once, for a batched
        ESM of ``queries`` nearest-neighbour queries; :meth:`NeighbourGraph.none` when it has not
        been built and would serve fewer than ``config.verification.graph_queries_per_point``
        queries per target point (the tree answers them sooner than the graph is built: the same
        neighbours)."""
        if id(index) not in self.graphs:
            if queries < self.config.verification.graph_queries_per_point * len(index.points):
                return NeighbourGraph.none()
            self.graphs[id(index)] = NeighbourGraph.of(index)
        return self.graphs[id(index)]


def global_estimate(
    source: np.ndarray,
    target: np.ndarray,
    *,
    strategy: str = "auto",
    rng: np.random.Generator,
    target_index: NearestNeighbors | None = None,
    target_spacing: float | None = None,
    workers: int | None = None,
    config: SearchConfig = DEFAULT,
    policy: TrustPolicy = DEFAULT_POLICY,
) -> GlobalEstimate:
    """Find ``T_target_source`` from any initial pose (the stages: the module docstring).

    ``source`` and ``target`` are validated ``(N, 3)`` / ``(M, 3)`` float64 arrays; ``rng`` drives
    every random subsample, so a seeded generator makes the result reproducible. ``target_index``
    (a :class:`NearestNeighbors` over ``target``) is reused when given, and so is
    ``target_spacing`` (its :meth:`~NearestNeighbors.spacing`, cloud units). ``workers``: threads
    of the compiled kernels (None: every core; a given ``target_index`` keeps its own, and the
    indices the search builds take its workers and its values, ``target_index.config``).
    ``strategy``: one of :data:`STRATEGIES`; ``config``: the tuned values; ``policy``: the overlap
    confidence's values (:class:`~esmicp.trust.policy.TrustPolicy`).
    """
    full_index = target_index if target_index is not None else NearestNeighbors(target, workers=workers)
    if strategy == "scan":
        return _scan(source, target, full_index, target_spacing, config=config, policy=policy)
    work = _workspace(source, target, rng, full_index, target_spacing, config, policy)
    if strategy == "rotation-search":
        return _decide(work, _verify(work, _rotation_candidates(work), "rotation-search"))
    if strategy == "features":
        found = _feature_candidates(work)
        if found:
            return _decide(work, _verify(work, found, "features"))
        # Too few feature matches to propose anything: the rotation search rather than a failure.
        return global_estimate(source, target, strategy="rotation-search", rng=rng, target_index=full_index,
                               target_spacing=target_spacing, workers=full_index.workers, config=config,
                               policy=policy)
    return replace(_auto(work, target_spacing), whole_keypoints=work._keypoints, scattered=work._scatter)


def _auto(work: _Workspace, target_spacing: float | None) -> GlobalEstimate:
    """The default search: generators, one verification, one decision (module docstring)."""
    config, policy, workers = work.config, work.policy, work.full_index.workers
    # 1. Whole objects: the rotation search's poses, verified.
    rotation = _verify(work, _rotation_candidates(work), "rotation-search")
    searched = rotation.candidates
    # The one exit, for cost: a confident rotation-search pose (most whole objects) is final here;
    # one just short of the score (``config.settle_from``) is settled by a few more iterations first.
    scored = None  # that pose, when its score alone is confident
    final: GlobalEstimate | None
    if rotation.score >= config.settle_from * config.confident_score and not rotation.ambiguous:
        if rotation.score >= config.confident_score:
            final = scored = _on_the_overlap(work, _decide(work, rotation))
        else:
            final = _settle(work, rotation)
        confident = final is not None and final.confidence is not None and final.confidence >= config.confident
        if final is not None and (confident or _covers_the_target(work, final.transformation)):
            return final
    if scored is None and not rotation.ambiguous and config.confident_score <= 1.0 and _scattered(work):
        # A cloud carrying scattered points: its score cannot reach the bar (they never lie on the
        # other cloud); the pose is final when it is confident on the overlap, measured on the
        # surface, and stays unambiguous against its twins (a box's flip is as confident there).
        if _confidence(work, rotation.transformation) >= config.confident:
            twins = _twins(work.index.points, rotation.transformation, config.verification.twin_angles_deg)
            checked = _decide(work, _verify(work, twins, "rotation-search", carried=rotation))
            if not checked.ambiguous:
                final = _on_the_overlap(work, replace(checked, candidates=searched + len(twins)))
                if final.confidence >= config.confident:
                    return final
    # 2. Partial overlaps: correspondences pruned by consistency (the scan strategy); a pose
    # confident on its score alone is only checked by its first search, and a pair carrying
    # scattered points by ``config.verification.scattered_scan_searches``.
    searches = config.scan_searches if scored is None else 1
    if searches != 1 and _scattered(work):
        most = config.verification.scattered_scan_searches
        searches = min(searches or most, most)
    scanned = _scan(work.source, work.target, work.full_index, target_spacing, searches=searches, config=config,
                    policy=policy, scattered=lambda: _scattered(work))
    return replace(_after_the_scan(work, rotation, scored, scanned, searched), unsupported=scanned.unsupported)


def _after_the_scan(work: _Workspace, rotation: GlobalEstimate, scored: GlobalEstimate | None,
                    scanned: GlobalEstimate, searched: int) -> GlobalEstimate:
    """Steps 2-4 of :func:`_auto` after the scan strategy's searches (``scanned``): the decision
    between its poses, the rotation search's (``rotation``; ``scored`` when its score alone was
    confident) and, unless the scan strategy leads, the feature strategy's. ``searched``: the
    candidates counted before."""
    config, policy, workers = work.config, work.policy, work.full_index.workers
    if _scan_leads(scanned, rotation.transformation, margin=config.scan_margin, workers=workers, config=config,
                   policy=policy):
        return _on_the_verifier_scale(work, replace(scanned, candidates=searched + scanned.candidates))
    if scored is not None:
        return _sharper_or_chosen(work, replace(scored, candidates=searched + scanned.candidates), scanned)
    # 3. Everything else verified together: the twins of the rotation search's pose, the scan
    # strategy's unconfident poses and the feature hypotheses, with the rotation search's
    # verified contenders carried into the last round.
    twins = _twins(work.index.points, rotation.transformation, config.verification.twin_angles_deg)
    scan_poses = _unconfident_scan_poses(scanned, config)
    found = _feature_candidates(work)
    origins = ["rotation-search"] * len(twins) + ["scan"] * len(scan_poses) + ["features"] * len(found)
    chosen = _decide(work, _verify(work, twins + scan_poses + found, origins, carried=rotation))
    # Each pose counted once: the scan strategy's in ``scanned.candidates``.
    chosen = replace(chosen, candidates=searched + len(twins) + len(found) + scanned.candidates)
    # 4. The decision: the best verified pose, unless the scan strategy's is confident and
    # overlaps more, or this one is not confident on the overlap and a scan pose is clearly more.
    if _scan_leads(scanned, chosen.transformation, workers=workers, config=config, policy=policy):
        return _on_the_verifier_scale(work, replace(scanned, candidates=chosen.candidates))
    return _sharper_or_chosen(work, replace(chosen, keypoints=scanned.keypoints), scanned)


def _sharper_or_chosen(work: _Workspace, chosen: GlobalEstimate, scanned: GlobalEstimate) -> GlobalEstimate:
    """:func:`_sharper_on_the_overlap`, its result on the verifier's scale: a scan pose that
    replaced ``chosen`` comes with overlap scores on keypoints (:func:`_on_the_verifier_scale`)."""
    result = _sharper_on_the_overlap(chosen, scanned, work.full_index.workers, work.config, work.policy)
    replaced = not np.array_equal(result.transformation, chosen.transformation)
    return _on_the_verifier_scale(work, result) if replaced else result


def _workspace(source, target, rng, full_index: NearestNeighbors, target_spacing: float | None,
               config: SearchConfig, policy: TrustPolicy = DEFAULT_POLICY) -> _Workspace:
    """The :class:`_Workspace` of one search: the target indexed (a subsample of
    ``config.rotation.target_points`` drawn from ``rng`` when larger), its spacing and the score width."""
    if len(target) <= config.rotation.target_points:
        index = full_index
    else:
        index = NearestNeighbors(_subsample(target, config.rotation.target_points, rng), workers=full_index.workers,
                                 config=full_index.config)
    spacing = target_spacing if target_spacing is not None and index is full_index else index.spacing()
    width = config.verification.score_width_spacings * spacing if spacing > 0 else 1e-6 * bounding_box_diagonal(target)
    return _Workspace(source, target, rng, full_index, index, spacing, width, config, policy)


def _on_the_overlap(work: _Workspace, estimate: GlobalEstimate) -> GlobalEstimate:
    """``estimate`` with the pair's keypoints and the overlap confidence of its best pose
    (:func:`~esmicp.trust.confidence.overlap_confidence`). ``"auto"`` takes the rotation search's
    pose, confident on its score, at once only when this is at least
    ``config.confident`` (the search's own bar; ``register``'s result is
    trusted from :attr:`~esmicp.trust.policy.TrustPolicy.trusted`) or the pose covers the whole target
    (:func:`_covers_the_target`); otherwise the scan strategy's first search checks it
    (:func:`global_estimate`).

    Why: the rotation search's score counts the source points lying on the target, which a cut
    object's wrong pose can satisfy better than the truth (a piano half flipped end to end lies on
    the other half's surface), while the overlap confidence asks the overlap to coincide both ways:
    on cut objects such wrong poses become right and none is lost. One search only, and not when
    the pose covers the whole target: a clean pose of an object under outliers can fall short of
    the trust bar on the overlap (its outliers are keypoints too), and every search costs time (``docs/scans-partial-overlap.md``)."""
    from ..trust.confidence import overlap_confidence

    keypoints = work.keypoints()
    confidence = overlap_confidence(estimate.transformation, keypoints, work.full_index.workers, config=work.config,
                                    policy=work.policy)
    return replace(estimate, keypoints=keypoints, confidence=confidence)


def _confidence(work: _Workspace, transformation: np.ndarray) -> float:
    """The overlap confidence of ``transformation`` on the pair's keypoints
    (:func:`~esmicp.trust.confidence.overlap_confidence`, as :func:`_on_the_overlap` measures it)."""
    from ..trust.confidence import overlap_confidence

    return overlap_confidence(transformation, work.keypoints(), work.full_index.workers, config=work.config,
                              policy=work.policy)


def _scattered(work: _Workspace) -> bool:
    """True when either cloud carries scattered points, read from the clouds alone before any pose
    (:func:`~esmicp.trust.judge.scattered_keypoints`, the judge's reading; the pair's keypoints are
    then those :meth:`_Workspace.keypoints` builds, kept for it)."""
    from ..trust.judge import scattered_keypoints

    if work._scatter is None:
        found = scattered_keypoints(work.source, work.full_index, work.config, work.policy, work.full_index.workers,
                                    made=work._keypoints)
        if found is not None and work._keypoints is None:
            work._keypoints = found
        work._scatter = found is not None
    return work._scatter


def _covers_the_target(work: _Workspace, transformation: np.ndarray) -> bool:
    """True when at least ``config.full_cover`` of up to ``config.verification.cover_points``
    evenly strided target points lie within two score widths of the source placed by ``transformation``."""
    count = min(work.config.verification.cover_points, len(work.target))
    target = work.target[np.linspace(0, len(work.target) - 1, count).astype(np.intp)]
    distances, _ = work.source_index().query(apply(rigid_inverse(transformation), target))
    return bool(np.mean(distances <= 2.0 * work.width) >= work.config.full_cover)


def _settle(work: _Workspace, estimate: GlobalEstimate) -> GlobalEstimate | None:
    """``estimate`` with its best pose settled (``config.verification.settle_iterations`` more ESM
    iterations on ``config.verification.settle_points`` strided source points), the pair's
    keypoints and the settled pose's overlap confidence, when the settled pose scores
    ``config.confident_score``; else None. The
    source points are strided, not drawn: the generator's later draws stay those of a search
    without this step."""
    from ..trust.confidence import overlap_confidence

    count = min(work.config.verification.settle_points, len(work.source))
    stride = np.linspace(0, len(work.source) - 1, count).astype(np.intp)
    settled, scores = _batched_verification(work, work.index, work.source[stride], estimate.transformations[:1],
                                            work.config.verification.settle_iterations, work.width)
    if scores[0] < work.config.confident_score:
        return None
    keypoints = work.keypoints()
    confidence = overlap_confidence(settled[0], keypoints, work.full_index.workers, config=work.config,
                                    policy=work.policy)
    return replace(estimate, transformations=np.concatenate([settled, estimate.transformations[1:]]),
                   scores=np.concatenate([scores, estimate.scores[1:]]), keypoints=keypoints, confidence=confidence)


def _scan(source, target, full_index: NearestNeighbors, target_spacing: float | None,
          searches: int | None = None, config: SearchConfig = DEFAULT,
          policy: TrustPolicy = DEFAULT_POLICY, scattered=None) -> GlobalEstimate:
    """The ``"scan"`` strategy (:mod:`esmicp.globalreg.scan`): its poses and overlap scores, from at
    most ``searches`` of its searches (None: until one is confident). ``scattered``: a callable
    telling whether either cloud carries scattered points (None: read here when asked)."""
    from .scan import scan_estimate_until_confident

    from ..trust.judge import scattered_keypoints

    if scattered is None:
        def scattered():
            return scattered_keypoints(source, full_index, config, policy, full_index.workers) is not None

    spacing = full_index.spacing() if target_spacing is None else target_spacing
    found = scan_estimate_until_confident(
        source, target, spacing=spacing, workers=full_index.workers, searches=searches, config=config, policy=policy,
        scattered=scattered)
    return GlobalEstimate(
        found.transformations, found.scores, ("scan",) * len(found.scores), candidates=len(found.scores),
        keypoints=found.keypoints, confidence=found.confidence, ambiguity_ratio=config.ambiguity_ratio,
        unsupported=found.unsupported,
    )


def _scan_leads(scanned: GlobalEstimate, other: np.ndarray, *, margin: float = 1.0,
                workers: int | None = None, config: SearchConfig = DEFAULT,
                policy: TrustPolicy = DEFAULT_POLICY) -> bool:
    """True when the scan strategy's best pose is confident on the overlap
    (:func:`~esmicp.trust.confidence.overlap_confidence`) and either its overlap score (keypoints of
    both clouds on the other cloud) is above ``margin`` times that of ``other``, or it overlaps at
    least ``config.sharper_score_ratio`` as much and is sharper by ``config.sharper_by``: a pose slid along a
    wall or a floor can overlap a little more, while only the true one makes the overlap coincide
    (``docs/scans-partial-overlap.md``). ``workers``: threads of the queries."""
    from ..trust.confidence import overlap_confidence
    from .scan import overlap_score

    keypoints, confidence = scanned.keypoints, scanned.confidence  # judged by the scan strategy itself
    if confidence < config.confident:
        return False
    mine = overlap_score(scanned.transformation, keypoints, workers, config=config)
    theirs = overlap_score(other, keypoints, workers, config=config)
    if mine > margin * theirs:
        return True
    return mine >= config.sharper_score_ratio * theirs and \
        confidence >= overlap_confidence(other, keypoints, workers, config=config, policy=policy) + config.sharper_by


def _sharper_on_the_overlap(chosen: GlobalEstimate, scanned: GlobalEstimate,
                            workers: int | None = None, config: SearchConfig = DEFAULT,
                            policy: TrustPolicy = DEFAULT_POLICY) -> GlobalEstimate:
    """``chosen`` (its keypoints set) with the overlap confidence of its best pose on its keypoints,
    unless that is below ``config.confident`` and one of the scan strategy's
    poses is more confident by ``config.sharper_than_chosen``: then the most confident of those, with
    the chosen pose as its runner-up when the two are distinct (rotations more than
    ``config.verification.distinct_rotation_deg`` apart), each scored by its overlap score on the
    keypoints. The chosen pose usually overlaps more, so such a result is usually flagged ambiguous, and its
    ``runner_up_score`` can exceed its score.

    Why: the verification scores how much of the source lies on the target, and a cut object's
    flip or turn about a near-symmetry axis often lies on more of the other part than the truth,
    whose cut-away part hangs free; the scan strategy often has the truth among its poses, ranked
    below by the same overlap but sharper where the clouds do coincide: on cut objects a right pose
    had often been weighed where the chosen one was wrong (``docs/scans-partial-overlap.md``)."""
    from ..trust.confidence import overlap_confidence
    from .scan import overlap_score

    keypoints = chosen.keypoints
    confidence = chosen.confidence
    if confidence is None:
        confidence = overlap_confidence(chosen.transformation, keypoints, workers, config=config, policy=policy)
    chosen = replace(chosen, confidence=confidence)
    poses = scanned.transformations[scanned.scores > 0]  # a search that found nothing sends nothing
    if confidence >= config.confident or not len(poses):
        return chosen
    # The scan strategy judged its best pose already, on these keypoints when they are its own.
    known = scanned.confidence if keypoints is scanned.keypoints and scanned.scores[0] > 0 else None
    confidences = [known if k == 0 and known is not None
                   else overlap_confidence(pose, keypoints, workers, config=config, policy=policy)
                   for k, pose in enumerate(poses)]
    best = int(np.argmax(confidences))
    if confidences[best] < confidence + config.sharper_than_chosen:
        return chosen
    pair = np.stack([poses[best], chosen.transformation])
    # the same pose, sharpened: no runner-up
    pair = pair[_distinct(pair, np.arange(2), 2, config.verification.distinct_rotation_deg)]
    scores = np.array([overlap_score(pose, keypoints, workers, config=config) for pose in pair])
    strategies = ("scan",) + chosen.strategies[:1] * (len(pair) - 1)
    return GlobalEstimate(pair, scores, strategies, candidates=chosen.candidates, keypoints=keypoints,
                          confidence=confidences[best], ambiguity_ratio=config.ambiguity_ratio)


def _unconfident_scan_poses(scanned: GlobalEstimate, config: SearchConfig = DEFAULT) -> list[np.ndarray]:
    """The scan strategy's best ``config.scan_candidates`` poses when its best is not confident on the
    overlap, else none: a confident one keeps the way to win it had (:func:`_scan_leads`), and its
    runner-ups get no chance to beat it in a verification that scores differently (sending them
    whatever the confidence gave the same results on the crops and the object protocols measured:
    ``docs/scans-partial-overlap.md``). A search that found nothing
    (:meth:`~esmicp.globalreg.scan.ScanEstimate.nothing`: the identity, score 0) sends nothing.
    They are counted once, in ``scanned.candidates``."""
    if scanned.confidence >= config.confident:
        return []
    return list(scanned.transformations[scanned.scores > 0][:config.scan_candidates])


def _rotation_candidates(work: _Workspace) -> list[np.ndarray]:
    target = work.index.points
    diagonal = bounding_box_diagonal(target)
    settings = work.config.rotation
    grid = work.grid = NearestGrid(target, settings.grid_cell_diagonals * diagonal,
                                   margin=settings.grid_margin_diagonals * diagonal)
    found = rotation_search(
        _subsample(work.source, settings.points, work.rng), grid,
        rotations=settings.rotations, iterations=settings.iterations, score_width=work.width, sigma_floor=work.width,
        workers=work.full_index.workers,
    )
    return [found.transformations[k] for k in _distinct(found.transformations, np.arange(len(found.scores)),
                                                         work.config.verification.candidates,
                                                         work.config.verification.distinct_rotation_deg)]


def _feature_candidates(work: _Workspace) -> list[np.ndarray]:
    """The feature strategy's hypotheses, with normals from the dense points and from the
    keypoints (each kind finds poses the other misses: ``docs/measured-global.md``)."""
    from .feature_matching import feature_hypotheses

    hypotheses = [
        hypothesis
        for normals_from_keypoints in (False, True)
        for hypothesis in feature_hypotheses(
            work.source, work.target, voxel=_feature_voxel(work.target, work.config), rng=work.rng,
            workers=work.full_index.workers, normals_from_keypoints=normals_from_keypoints, config=work.config,
        )
    ]
    return [hypothesis.transformation for hypothesis in hypotheses]


def _batched_verification(work, index, source_points, transformations, iterations, width, sigma=None):
    rotations, translations, distances = batched_esm(
        source_points, index, transformations[:, :3, :3], transformations[:, :3, 3],
        iterations=iterations, sigma_floor=width if sigma is None else sigma, fine_iterations=iterations,
        workers=index.workers, graph=work.graph(index, len(transformations) * len(source_points) * iterations),
        seeds=work.seeds(index),
    )
    refined = np.stack([to_matrix(rotation, translation) for rotation, translation in zip(rotations, translations)])
    return refined, gaussian_overlap_score(distances, width)


def _verify(
    work: _Workspace,
    candidates: list[np.ndarray],
    origins: list[str] | str,
    *,
    carried: GlobalEstimate | None = None,
) -> GlobalEstimate:
    """The verifier: successive halving over ``candidates`` (``config.verification.rounds``: batched ESM on
    a source subsample, each pose scored by the soft fraction of those points on the target);
    ``origins`` names each candidate's generator (one name for all). ``carried`` poses (with their
    scores and origins), verified before by the same rounds, join the survivors after the last
    round. Returns the contenders (:func:`_contenders`), best first."""
    verified = np.stack(candidates)
    origins_array = np.array([origins] * len(candidates) if isinstance(origins, str) else origins)
    for points, iterations, keep in work.config.verification.rounds:
        verified, scores = _batched_verification(
            work, work.index, _subsample(work.source, points, work.rng), verified, iterations, work.width
        )
        survivors = _distinct(verified, np.argsort(-scores, kind="stable"), keep,
                              work.config.verification.distinct_rotation_deg)
        verified, scores, origins_array = verified[survivors], scores[survivors], origins_array[survivors]
    if carried is not None:
        verified = np.concatenate([verified, carried.transformations])
        scores = np.concatenate([scores, carried.scores])
        origins_array = np.concatenate([origins_array, np.array(carried.strategies)])
    kept = _contenders(verified, scores, work.config)
    return GlobalEstimate(verified[kept], scores[kept], tuple(origins_array[kept]), candidates=len(candidates),
                          ambiguity_ratio=work.config.ambiguity_ratio)


def _decide(work: _Workspace, estimate: GlobalEstimate) -> GlobalEstimate:
    """Re-verify ``estimate``'s contenders on (up to) the full clouds when the runner-up scores at
    least ``config.decide_ratio`` of the best (:func:`_full_resolution_scores`). Returns the
    contenders re-ranked by it."""
    scores = estimate.scores
    if len(scores) < 2 or scores[1] < work.config.decide_ratio * scores[0]:
        return estimate
    refined, decided = _full_resolution_scores(work, estimate.transformations)
    order = _contenders(refined, decided, work.config)
    strategies = tuple(estimate.strategies[k] for k in order)
    return GlobalEstimate(refined[order], decided[order], strategies, candidates=estimate.candidates,
                          ambiguity_ratio=work.config.ambiguity_ratio)


def _full_resolution_scores(work: _Workspace, transformations: np.ndarray,
                            refine: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The verifier's full-resolution score of each pose, both ways: the mean of two Gaussian
    overlap scores (0-1), ``decide_points`` source points on the full target and ``decide_points``
    target points on the full placed source (``config.verification``). With ``refine``, each pose
    is first refined by ``decide_iterations`` ESM iterations at a sigma of ``decide_sigma_spacings`` target spacings
    on those source points; without, scored where it is. Returns the (refined) poses and their
    scores."""
    full_spacing = work.spacing if work.index is work.full_index else work.full_index.spacing()
    settings = work.config.verification
    full_width = settings.score_width_spacings * full_spacing if full_spacing > 0 else work.width
    source_points = _subsample(work.source, settings.decide_points, work.rng)
    if refine:
        sigma = settings.decide_sigma_spacings * full_spacing if full_spacing > 0 else None
        refined, forward = _batched_verification(work, work.full_index, source_points, transformations,
                                                 settings.decide_iterations, full_width, sigma=sigma)
    else:
        refined = np.asarray(transformations, dtype=np.float64)
        placed = np.matmul(source_points[None], refined[:, :3, :3].transpose(0, 2, 1)) + refined[:, None, :3, 3]
        distances, _ = work.full_index.query(placed.reshape(-1, 3))
        forward = gaussian_overlap_score(distances.reshape(len(refined), -1), full_width)
    # Coverage the other way: the target points (clean, unlike a noisy source) lying on the placed
    # source. A symmetric twin leaves the target's asymmetric details uncovered.
    target_points = _subsample(work.target, settings.decide_points, work.rng)
    source_index = work.source_index()
    # Target points in the source frame under each pose: rows (t - translation) @ R = R^T (t - translation).
    in_source = np.matmul(target_points[None] - refined[:, None, :3, 3], refined[:, :3, :3])
    backward, _ = source_index.query(in_source.reshape(-1, 3))
    return refined, 0.5 * (forward + gaussian_overlap_score(backward.reshape(len(refined), -1), full_width))


def _on_the_verifier_scale(work: _Workspace, estimate: GlobalEstimate) -> GlobalEstimate:
    """The scan strategy's result (its poses ranked by its own overlap count on keypoints) with
    every pose's score on the verifier's scale (:func:`_full_resolution_scores`, each scored where
    the scan strategy's ICP left it: refining them first builds a neighbour graph of the full
    target, and gave the same verdicts at up to 1.6 times a partial scan pair's registration time), so that
    ``ambiguous`` and ``runner_up_ratio`` read alike whichever generator won: the returned pose
    stays first (the decision stands; it may now score below its runner-up, which then makes the
    result ambiguous), the others follow by their new score, and the poses are not moved.

    Why: the keypoint count is coarser than the verifier's score; a box's 180-degree twin, as
    good a fit as the pose returned, counted 3% fewer keypoints and left a trusted result that
    is right only up to the box's symmetry."""
    if len(estimate.transformations) < 2:
        return estimate
    _, scores = _full_resolution_scores(work, estimate.transformations, refine=False)
    order = [0] + [1 + k for k in np.argsort(-scores[1:], kind="stable")]
    return replace(estimate, scores=scores[order], transformations=estimate.transformations[order],
                   strategies=tuple(estimate.strategies[k] for k in order))


def _contenders(transformations: np.ndarray, scores: np.ndarray, config: SearchConfig) -> list[int]:
    """Indices of the best pose, every distinct pose within ``config.ambiguity_ratio`` of it (at
    most ``config.verification.max_contenders`` in all), and the best distinct pose below that,
    best first."""
    ratio, most = config.ambiguity_ratio, config.verification.max_contenders
    order = np.argsort(-scores, kind="stable")
    distinct = _distinct(transformations, order, most + 1, config.verification.distinct_rotation_deg)
    close = sum(scores[index] >= ratio * scores[distinct[0]] for index in distinct)
    return distinct[: min(close + 1, most + 1)]




def _twins(target: np.ndarray, transformation: np.ndarray,
           angles_deg: tuple = DEFAULT.verification.twin_angles_deg) -> list[np.ndarray]:
    """``transformation`` composed on the left with turns by ``angles_deg`` (degrees;
    :attr:`~esmicp.globalreg.config.VerificationConfig.twin_angles_deg`) about the principal axes
    of ``target`` through its centroid (``len(angles_deg) * 3`` poses)."""
    from scipy.spatial.transform import Rotation

    centre = target.mean(axis=0)
    centred = target - centre
    _, axes = np.linalg.eigh(centred.T @ centred)
    twins = []
    for axis in axes.T:
        for angle in angles_deg:
            turn = Rotation.from_rotvec(np.radians(angle) * axis).as_matrix()
            twins.append(to_matrix(turn, centre - turn @ centre) @ transformation)
    return twins


def _feature_voxel(target: np.ndarray, config: SearchConfig = DEFAULT) -> float:
    """The feature strategy's voxel: ``config.features.voxel_diagonals`` of the target's
    bounding-box diagonal (cloud units)."""
    return config.features.voxel_diagonals * bounding_box_diagonal(target)
