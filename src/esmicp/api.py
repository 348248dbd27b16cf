"""``register()``: one registration as its stages: validate and prepare (a working frame, the
target's index), start (a global search unless a pose is given), refine, evaluate, judge
(:func:`esmicp.trust.judge.judge`); each records what it did in ``result.stages``."""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass

import numpy as np

from .core.correspondence import NearestNeighbors
from .core.procrustes import bounding_box_diagonal
from .core.correspondence import coincident_points
from .core.keypoints import Keypoints
from .core.sampling import evenly_strided
from .config import RefineConfig, RegistrationConfig
from .errors import CoincidentPointsWarning, IndexAlignmentWarning, InvalidInputError
from .globalreg.config import SearchConfig
from .globalreg.search import STRATEGIES, GlobalEstimate, global_estimate
from .interrupts import keeps_keyboard_interrupt
from .methods import METHODS, ConvergenceCriteria, PlaneEstimator, make_estimator
from .methods.esm import EsmEstimator
from .methods.guard import guarded_refine
from .methods.local import STOPPED_BY_CALLBACK, Callback, Observer, RefinementOutcome
from .result import Correspondences, RegistrationResult, Stage
from .trust.confidence import overlap_confidence
from .trust.judge import SensorClouds, Verdict, judge
from .trust.policy import TrustPolicy
from .types import as_count, as_generator, as_points, as_positive, as_real, as_transform, as_workers, check_not_degenerate
from .types import InitName, MethodName, PointsLike, TransformLike, check_geometry
from .working_frame import WorkingFrame

#: ``init`` strings meaning "no global search: start from the identity".
IDENTITY_NAMES = ("identity", "none")

#: Every ``init`` string :func:`register` accepts (anything else must be a 4x4 matrix); the values
#: of :data:`esmicp.types.InitName`.
INIT_NAMES = ("global", *STRATEGIES, *IDENTITY_NAMES)

#: Seed of the global search when ``rng`` is None (results are reproducible by default).
DEFAULT_SEED = 0

@dataclass(frozen=True, eq=False)
class _Request:
    """The validated arguments of one :func:`register` call."""

    source: np.ndarray
    target: np.ndarray
    method: str
    init_name: str
    initial: np.ndarray | None  # None: a global search finds the start
    sigma: float | None
    criteria: ConvergenceCriteria
    rng: np.random.Generator
    inlier_distance: float | None
    workers: int | None  # threads of every compiled kernel (None: every core)
    config: SearchConfig  # the global search's tuned values
    refine: RefineConfig  # the refinement's and the evaluation's
    trust: TrustPolicy  # the bars the result is judged by
    coincident_warning: float  # RegistrationConfig.coincident_warning_fraction
    range_images: bool | None = None  # both clouds are range images in their sensor frames (None: as their points show)
    judge: bool = True  # False: the pose without its covariance, mirror test and free-space test (never trusted)


@keeps_keyboard_interrupt
def register(
    source: PointsLike,
    target: PointsLike,
    *,
    method: MethodName = "esm",
    init: InitName | TransformLike | None = None,
    sigma: float | None = None,
    max_iterations: int = 100,
    tolerance: float = 1e-8,
    rng: int | np.random.Generator | None = None,
    callback: Callback | None = None,
    record_history: bool = False,
    inlier_distance: float | None = None,
    workers: int | None = None,
    return_correspondences: bool = False,
    config: RegistrationConfig | SearchConfig | dict | None = None,
    range_images: bool | None = None,
    judge: bool = True,
) -> RegistrationResult:
    """Rigidly register ``source`` onto ``target``.

    Parameters
    ----------
    source : (N, 3) array-like, or a cloud object (``open3d.geometry.PointCloud``, ``open3d.t.geometry.PointCloud``)
        Points to move (source frame). Never modified.
    target : (M, 3) array-like, or a cloud object with ``points``
        Points to align to (target frame). N and M may differ. Never modified.
    method : {"esm", "esm-paper", "icp", "esm-plane"}
        ``esm``: Gaussian-weighted Procrustes on nearest-neighbour pairs (any sizes, any order).
        ``esm-paper``: the paper's symmetric-matrix formulation; needs index-aligned clouds of
        equal size (source point k and target point k the same physical point).
        ``icp``: point-to-point ICP.
        ``esm-plane``: the Gaussian weights on point-to-plane residuals (target normals), sigma
        from the overlap (:mod:`esmicp.methods.plane`): for partially overlapping scans.
    init : None, str or (4, 4) array-like
        Where to start. None or ``"global"`` (the default): find the pose globally, from any
        rotation and translation, with the best measured strategy (``"auto"``: both strategies
        below, every candidate verified the same way). ``"rotation-search"`` or ``"features"``:
        global with that strategy only (see :mod:`esmicp.globalreg.search`). ``"scan"``: global
        for partially overlapping scans (RGB-D fragments, LiDAR): FPFH correspondences pruned by
        second-order compatibility, verified on the overlap (:mod:`esmicp.globalreg.scan`). ``"identity"`` (or
        ``"none"``): pure local refinement from the identity. A 4x4 ``T_target_source``: pure local
        refinement from there. (From a given start, ``esm`` with the automatic sigma runs a second
        time with a tighter coarse sigma when the first run ends below the trust bar, and keeps
        the more confident run, unless ``config.refine.second_try`` is False.)
    sigma : float, optional
        Kernel width in the clouds' units. None: ``esm`` and ``esm-plane`` choose it from the data
        each iteration (see :mod:`esmicp.methods.esm`, :mod:`esmicp.methods.plane`), ``esm-paper``
        uses the paper's 1.0. Ignored by ``icp``.
    max_iterations : int
        Upper bound on iterations (>= 1).
    tolerance : float
        Convergence tolerance: stop once an increment rotates less than ``tolerance`` radians and
        translates less than ``tolerance`` times the target's bounding-box diagonal, or once the
        RMS correspondence distance changes by less than ``tolerance`` relative to itself. After a
        global search, the refinement of a source of more than ``config.refine.looser_from_points``
        (10,000) points stops at ``config.refine.whole_tolerance`` (3e-5) when ``tolerance`` is
        finer, and at ``config.refine.strided_tolerance`` (1e-5) on a source of more than twice
        ``config.refine.strided_points`` (20,000) points, which is refined on that many evenly
        strided points. A given ``init`` and smaller sources keep ``tolerance``.
    rng : None, int or numpy.random.Generator
        Randomness of the global search (its subsamples). None uses a fixed seed, so the same input
        gives the same result; local refinement itself is deterministic.
    callback : callable, optional
        Called with an :class:`~esmicp.methods.local.IterationState` after every iteration of the
        local refinement (after the global search, if any); returning True stops the run. It
        observes and never changes the run: the pose is the one without a callback. When a
        second run from the same start is tried (see ``init``), it sees that run too, counted
        from iteration 1 again.
    record_history : bool
        Keep an :class:`~esmicp.result.IterationRecord` per iteration of the run whose pose is
        returned in ``result.history`` (every point at each iteration's pose; the pose is the
        one without a history).
    inlier_distance : float, optional
        Distance (cloud units) within which a source point counts as an inlier for ``fitness`` and
        ``inlier_rmse``. Default: 3 x the target's median point spacing.
    workers : int, optional
        Threads of the compiled kernels (nearest neighbours, moments), in the global search and
        the refinement alike. None (the default) uses every core; pass 1 when registering many
        pairs in parallel processes (as :func:`esmicp.register_many` does). The result is the same
        for every value (the kernels sum in a fixed order).
    return_correspondences : bool
        Also return the final pose's point pairs in ``result.correspondences``
        (:class:`~esmicp.result.Correspondences`: source and target indices, weights, distances
        of the pairs within ``inlier_distance``, Open3D's ``correspondence_set``); they hold
        four arrays per pair, and on a source of more than ``config.refine.evaluated_points``
        (40,000) points every source point is then evaluated (else a strided subset is: see
        :class:`esmicp.config.RefineConfig`).
    config : esmicp.config.RegistrationConfig, esmicp.globalreg.config.SearchConfig or dict, optional
        The tuned values: the global search's (and the overlap confidence's ranges), the local
        refinement's (:class:`esmicp.config.RefineConfig`) and the trust policy the result is
        judged by (:class:`esmicp.trust.policy.TrustPolicy`, kept in
        ``result.policy``). A SearchConfig (or a dict of its fields) sets the search's values with
        the default policy; a dict with the keys ``search`` and / or ``trust`` is a
        RegistrationConfig's. None: the measured defaults.
    range_images : bool or None
        True: both clouds are range images in their sensor frames: every point as its sensor saw
        it, the sensor at the origin (depth-camera frames, LiDAR scans as recorded). The final pose
        is then also checked against the space each sensor saw empty
        (:func:`esmicp.trust.free_space.free_space_fraction`, in ``result.free_space``): a pose
        that puts more than the policy's ``max_free_space_pair`` (8%) of either cloud there is not
        trusted, however sharply the clouds coincide (a repeated structure
        matched in the wrong place, a pair that shares no surface). The pose itself is the same.
        None (the default): as each cloud's own points show
        (:func:`esmicp.trust.free_space.range_image_test`, never from the pose being judged): the
        check runs when both clouds prove range images and nothing else already casts doubt on
        the pose. False: no such check (clouds in another frame, such as meshes, fused fragments
        or maps, would fail it).
    judge : bool
        True (the default): the pose is judged (``result.verdict``). False: the pose and its overlap
        confidence only, without the covariance, the mirror test or the free-space test, for a
        caller that judges the pose by other means (the merge's first pass on sparse subsets, whose
        poses its check on denser ones judges). Such a result is never trusted (its doubt "not
        judged") and has no covariance.

    Returns
    -------
    RegistrationResult
        With the judgement of the pose (``result.verdict``, :func:`esmicp.trust.judge.judge`) and
        what each stage did (``result.stages``, :class:`esmicp.result.Stage`).

    Raises
    ------
    InvalidInputError
        On malformed or degenerate clouds (or beyond float64 geometry, see
        :func:`esmicp.types.check_geometry`), an unknown method, a malformed or non-rigid ``init``,
        or non-positive ``sigma``, ``max_iterations``, ``inlier_distance`` or ``workers``.
    """
    started = time.perf_counter()
    stages: list[Stage] = []
    request = _validate(source, target, method, init, sigma, max_iterations, tolerance, rng, inlier_distance, workers,
                        config, range_images, judge)
    clouds = _prepare(request, started, stages)
    initial, init_name, estimate, keypoints = _start(request, clouds, stages)
    observer = None
    if callback is not None or record_history:
        observer = Observer(clouds.source, clouds.index, clouds.frame.callback(callback), record_history)
    outcome, confidence = _refine_from(initial, request, clouds, keypoints, estimate, observer, stages)
    fitness, inlier_rmse, inlier_distance, pairs = _evaluate(clouds, outcome, request, stages,
                                                             every_point=return_correspondences)
    correspondences = None
    if return_correspondences:
        estimator = _estimator(method, request, clouds.index, clouds.diagonal)
        correspondences = _correspondences(pairs, estimator, outcome.sigma)
    verdict = _judge(outcome, confidence, request, clouds, keypoints, estimate, pairs, inlier_distance, stages)
    outcome = clouds.frame.outcome(outcome)
    message = outcome.message if verdict.free_space_words is None else f"{outcome.message}; {verdict.free_space_words}"
    return RegistrationResult(
        transformation=outcome.transformation,
        converged=outcome.converged,
        num_iterations=outcome.num_iterations,
        fitness=fitness,
        inlier_rmse=inlier_rmse,
        inlier_distance=inlier_distance,
        runtime_s=time.perf_counter() - started,
        method=method,
        sigma=outcome.sigma,
        message=message,
        history=outcome.history,
        init=init_name,
        **_search_summary(estimate, clouds.frame),
        confidence=verdict.confidence,
        correspondences=correspondences,
        covariance=None if verdict.uncertainty is None else verdict.uncertainty.covariance,  # None: not judged
        information=None if verdict.uncertainty is None else verdict.uncertainty.information,
        degenerate_directions=verdict.degenerate_directions,
        free_space=verdict.free_space,
        policy=request.trust,
        verdict=verdict,
        stages=tuple(stages),
    )


@dataclass(frozen=True, eq=False)
class _Clouds:
    """The two clouds in the working frame ``frame``, the target's nearest-neighbour index and
    bounding-box diagonal (cloud units)."""

    frame: WorkingFrame
    source: np.ndarray
    target: np.ndarray
    index: NearestNeighbors
    diagonal: float

    def pose_out(self, transformation: np.ndarray) -> np.ndarray:
        """A copy of ``transformation`` (working frame) in the clouds' own frames."""
        return np.array(self.frame.transform_out(transformation), dtype=np.float64)


def _prepare(request: _Request, started: float, stages: list) -> _Clouds:
    """Stage 1 (after :func:`_validate`): the working frame, the target's index, and a warning for
    either cloud made largely of copies; the stage ``prepare``, timed from ``started``."""
    frame = WorkingFrame.for_target(request.target)
    source_points, target_points = frame.points(request.source), frame.points(request.target)
    target_index = NearestNeighbors(target_points, workers=request.workers, config=request.refine.index)
    _warn_if_coincident(request.source, "source", coincident_points(request.source), request.coincident_warning)
    _warn_if_coincident(request.target, "target", target_index.coincident(), request.coincident_warning)
    clouds = _Clouds(frame, source_points, target_points, target_index, bounding_box_diagonal(target_points))
    stages.append(Stage("prepare", time.perf_counter() - started, points=len(source_points),
                        decided={"method": request.method, "target_points": len(target_points),
                                 "shifted": frame.origin is not None}))
    return clouds


def _start(request: _Request, clouds: _Clouds, stages: list) -> tuple[np.ndarray, str, GlobalEstimate | None, Keypoints]:
    """Stage 2: the starting pose (working frame), its name, the global estimate if one was made,
    and the keypoints the overlap confidence is measured on (the search's, else new ones)."""
    started = time.perf_counter()
    estimate = None
    if request.initial is not None:
        initial, name = clouds.frame.transform_in(request.initial), request.init_name
    else:
        estimate = global_estimate(
            clouds.source, clouds.target, strategy=request.init_name, rng=request.rng, target_index=clouds.index,
            target_spacing=clouds.index.spacing(), workers=request.workers, config=request.config,
            policy=request.trust,
        )
        initial, name = estimate.transformation, f"global:{estimate.strategies[0]}"
    keypoints = getattr(estimate, "keypoints", None)
    if keypoints is None:
        keypoints = Keypoints.of(clouds.source, clouds.target, clouds.index.spacing(), request.config.keypoints,
                                 request.config.scan.keypoint.min_voxel_spacings)
    decided = {"init": name}
    if estimate is not None:
        decided.update(candidates=estimate.candidates, confidence=estimate.confidence,
                       ambiguous=bool(estimate.ambiguous), runner_up_ratio=estimate.runner_up_ratio)
    stages.append(Stage("start", time.perf_counter() - started, pose=clouds.pose_out(initial), decided=decided))
    return initial, name, estimate, keypoints


def _search_summary(estimate: GlobalEstimate | None, frame: WorkingFrame) -> dict:
    """The result's fields of the global search (its defaults without one)."""
    if estimate is None:
        return {"ambiguous": False, "runner_up_ratio": None, "global_candidates": 0, "runner_up": None}
    runner_up = estimate.runner_up
    return {"ambiguous": bool(estimate.ambiguous), "runner_up_ratio": estimate.runner_up_ratio,
            "global_candidates": estimate.candidates,
            "runner_up": None if runner_up is None else frame.transform_out(np.array(runner_up, dtype=np.float64))}


def _refine_from(initial: np.ndarray, request: _Request, clouds: _Clouds, keypoints: Keypoints,
                 estimate: GlobalEstimate | None, observer: Observer | None, stages: list):
    """Stage 3: ``(outcome, confidence)``: the refinement from ``initial`` (working frame) and the
    overlap confidence of its pose on ``keypoints``; from a given start, ``esm`` with the automatic
    sigma tries a second run when the first ends below the trust bar (:func:`_second_try`; unless
    ``refine.second_try`` is False).
    ``observer`` (the callback and the history, working frame) watches every run and changes none."""
    # After a global search (which ends at the finest sigma) the pose is already close: start in
    # the fine phase, so that a coarse sigma cannot pull partial overlaps apart again.
    estimator = _estimator(request.method, request, clouds.index, clouds.diagonal, start_fine=estimate is not None)
    start_distances = None
    if estimate is None and isinstance(estimator, EsmEstimator):
        # A given start: its coarse sigma comes from the overlap's residuals (partial overlaps).
        start_distances = clouds.index.query_near(clouds.source, transform=initial)[0]
        estimator.start_from(start_distances)
    outcome = _refine(clouds, estimator, initial, request, keypoints, estimate, observer, stages)
    confidence = _confidence(outcome.transformation, keypoints, request)
    if start_distances is not None and request.sigma is None and request.refine.second_try \
            and confidence < request.trust.trusted and not (observer is not None and observer.stopped):
        outcome, confidence = _second_try(clouds, initial, request, keypoints, start_distances, outcome, confidence,
                                          observer, stages)
    if observer is not None:
        outcome = dataclasses.replace(outcome, history=observer.recorded())
    return outcome, confidence


def _confidence(transformation: np.ndarray, keypoints: Keypoints, request: _Request) -> float:
    """The overlap confidence of ``transformation`` (working frame) on ``keypoints``, by the request's
    ranges and policy."""
    return overlap_confidence(transformation, keypoints, request.workers, config=request.config, policy=request.trust)


def _refine(clouds: _Clouds, estimator, initial, request: _Request, keypoints: Keypoints,
            estimate: GlobalEstimate | None, observer: Observer | None, stages: list, name: str = "refine"):
    """``estimator`` from ``initial`` (working frame): on a large source the strided run
    (:func:`_refine_strided`), else the whole source at once (after a global
    search, from ``refine.looser_from_points`` points on, at ``refine.whole_tolerance`` when the request's
    tolerance is finer); the stage ``name``. ``observer`` (the callback and the history, working
    frame) watches every stage and changes none."""
    source = clouds.source
    if len(source) > 2 * request.refine.strided_points and estimator.order_invariant:
        # (``esm-paper`` pairs source point k with target point k: a strided subset has no pairs.)
        return _refine_strided(clouds, estimator, initial, request, keypoints, estimate, observer, stages, name)
    started = time.perf_counter()
    criteria = request.criteria
    if estimate is not None and len(source) > request.refine.looser_from_points:
        criteria = dataclasses.replace(criteria, tolerance=max(criteria.tolerance, request.refine.whole_tolerance))
    outcome = guarded_refine(
        source, clouds.index, estimator, init=initial, criteria=criteria, scale=clouds.diagonal,
        coarse_points=request.refine.esm.coarse_points, observer=observer, loop=request.refine.loop,
    )
    stages.append(_refine_stage(name, started, clouds, outcome, len(source), outcome.num_iterations, criteria))
    return outcome


def _refine_stage(name: str, started: float, clouds: _Clouds, outcome, points: int, iterations: int,
                  criteria: ConvergenceCriteria):
    """The record of a refinement stage begun at ``started`` that ran ``iterations`` on ``points``
    source points with ``criteria`` and ended at ``outcome``."""
    return Stage(name, time.perf_counter() - started, pose=clouds.pose_out(outcome.transformation), points=points,
                 iterations=iterations, decided={"converged": bool(outcome.converged), "sigma": outcome.sigma,
                                                 "tolerance": criteria.tolerance,
                                                 "max_iterations": criteria.max_iterations})


def _second_try(clouds: _Clouds, initial, request: _Request, keypoints: Keypoints, start_distances: np.ndarray,
                outcome, confidence: float, observer: Observer | None, stages: list):
    """``(outcome, confidence)``: of ``outcome`` (an ``esm`` run from a given start, overlap
    confidence ``confidence`` below the trust bar) and a second run from the same start whose coarse
    sigma comes from the start's ``refine.esm.tight_start_quantile`` distance quantile, the more confident
    (the first on a tie); the message says what the second try gave, and the stage ``second try``
    which run was kept.

    Why: the first run's coarse sigma assumes a quarter of the source overlaps. Where less does
    (scans cut to 15-50%), that sigma pulls a good start apart; the tight one keeps it, but
    narrows the reach from a poor start on a whole object, so it only comes second, and only
    where the first run is not trusted (``docs/scans-start-drift.md``). ``observer`` watches the second run as a new run;
    its history ends as that of the run kept."""
    first_confidence = confidence
    tight = _estimator(request.method, request, clouds.index, clouds.diagonal)
    tight.start_from(start_distances, request.refine.esm.tight_start_quantile)
    first_history = None if observer is None else observer.new_run()
    second = _refine(clouds, tight, initial, request, keypoints, None, observer, stages, "second try")
    second_confidence = _confidence(second.transformation, keypoints, request)
    tried = stages.pop()
    if observer is not None and observer.stopped:
        kept, outcome, confidence = "second", second, second_confidence
    elif second_confidence > confidence:
        quantile = request.refine.esm.tight_start_quantile
        note = (f"; a second try with a tighter coarse sigma (the start's {quantile:.0%} distance "
                f"quantile) raised the overlap confidence {confidence:.2f} -> {second_confidence:.2f}")
        kept, outcome = "second", dataclasses.replace(second, message=second.message + note)
        confidence = second_confidence
    else:
        note = (f"; a second try with a tighter coarse sigma ended at overlap confidence {second_confidence:.2f}: "
                f"this run kept")
        if observer is not None and observer.history is not None:
            observer.history = list(first_history or ())
        kept, outcome = "first", dataclasses.replace(outcome, message=outcome.message + note)
    decided = {**tried.decided, "first_confidence": first_confidence, "confidence": second_confidence, "kept": kept}
    stages.append(dataclasses.replace(tried, pose=clouds.pose_out(outcome.transformation), decided=decided))
    return outcome, confidence


def _refine_strided(clouds: _Clouds, estimator, initial, request: _Request, keypoints: Keypoints,
                    estimate: GlobalEstimate | None, observer: Observer | None, stages: list, name: str):
    """:func:`_refine` on a large source: ``estimator`` on ``refine.strided_points`` evenly strided source
    points (where every point would take the pose from there lies well inside its standard
    deviation). The outcome's iterations count every stage; ``refine`` is ``request.refine``.

    After a global search (``estimate``, whose ``confidence`` is that of ``initial`` on
    ``keypoints`` when it judged it), ``esm`` is preceded by at most ``refine.plane_iterations`` of
    ``esm-plane`` on ``refine.plane_points`` of the strided points (the stage ``plane``), undone when they lower the
    overlap confidence on ``keypoints`` by more than ``refine.plane_confidence_drop``, and the
    strided stages stop at ``refine.strided_tolerance`` when the request's tolerance is finer: a
    global pose is already close.
    From a given start (``estimate`` None) the strided run keeps the request's tolerance, since a
    start can lie further off and a slow slide toward the optimum must run to its end. ``observer``
    watches every stage (a stage its callback stopped is the last)."""
    source = clouds.source
    strided = source[np.linspace(0, len(source) - 1, request.refine.strided_points).astype(np.intp)]
    plane_iterations, plane_note = 0, ""
    if estimate is not None:
        request = dataclasses.replace(request, criteria=_at_strided_tolerance(request.criteria, request.refine))
    if estimate is not None and request.method == "esm":
        count = min(request.refine.plane_points, len(strided))
        planed = strided[np.linspace(0, len(strided) - 1, count).astype(np.intp)]
        initial, plane_iterations, plane_note = _plane_start(planed, clouds, initial, request, keypoints,
                                                             estimate.confidence, observer, stages)
        if observer is not None and observer.stopped:
            return RefinementOutcome(initial, False, plane_iterations, None, plane_note + STOPPED_BY_CALLBACK, None)
        request = dataclasses.replace(request, criteria=dataclasses.replace(
            request.criteria, max_iterations=request.criteria.max_iterations - plane_iterations))
    started = time.perf_counter()
    coarse = guarded_refine(strided, clouds.index, estimator, init=initial, criteria=request.criteria,
                            scale=clouds.diagonal, observer=observer, loop=request.refine.loop)
    stages.append(_refine_stage(name, started, clouds, coarse, len(strided), coarse.num_iterations, request.criteria))
    if coarse.num_iterations == 0:
        return coarse  # no start to refine (the guard's message says why)
    return dataclasses.replace(coarse, message=f"{plane_note}{coarse.message} on {len(strided):,} strided source points",
                               num_iterations=plane_iterations + coarse.num_iterations)


def _at_strided_tolerance(criteria: ConvergenceCriteria, refine: RefineConfig) -> ConvergenceCriteria:
    """``criteria`` stopping at ``refine.strided_tolerance`` when its own tolerance is finer: a
    refinement from a global pose, whose last iterations creep in no steady direction."""
    return dataclasses.replace(criteria, tolerance=max(criteria.tolerance, refine.strided_tolerance))


def _estimator(method: str, request: _Request, target_index, diagonal: float, start_fine: bool = False):
    """``make_estimator`` for this request; ``esm-plane`` takes its normals' neighbours from the
    target index's own KD-tree, on the request's threads."""
    estimator = make_estimator(method, request.sigma, target_index.spacing(), diagonal, start_fine=start_fine,
                               esm=request.refine.esm, plane=request.refine.plane)
    if isinstance(estimator, PlaneEstimator):
        estimator.use_target_tree(target_index.exact_tree(), request.workers)
    return estimator


def _plane_start(points, clouds: _Clouds, initial, request: _Request, keypoints: Keypoints,
                 initial_confidence: float | None, observer: Observer | None, stages: list) -> tuple[np.ndarray, int, str]:
    """``(pose, iterations, note)`` of at most ``refine.plane_iterations`` ``esm-plane`` iterations
    on ``points`` (``refine.plane_points`` strided source points) from ``initial``, leaving ``esm`` at least
    one iteration of ``max_iterations``; the note begins the result's message, the stage ``plane``
    records them. ``initial`` when the budget leaves none, the guard
    refused the start, or the iterations lowered the overlap confidence on ``keypoints`` by more
    than ``refine.plane_confidence_drop`` (they still count against the budget and the note says
    so); ``refine`` is ``request.refine``."""
    started = time.perf_counter()
    budget = min(request.refine.plane_iterations, request.criteria.max_iterations - 1)
    if budget <= 0:
        return initial, 0, ""
    planar = _estimator("esm-plane", request, clouds.index, clouds.diagonal)
    criteria = dataclasses.replace(request.criteria, max_iterations=budget)
    plane = guarded_refine(points, clouds.index, planar, init=initial, criteria=criteria, scale=clouds.diagonal,
                           observer=observer, loop=request.refine.loop)
    if plane.num_iterations == 0:
        return initial, 0, ""
    if observer is not None and observer.stopped:
        stages.append(Stage("plane", time.perf_counter() - started, pose=clouds.pose_out(plane.transformation),
                            points=len(points), iterations=plane.num_iterations, decided={"undone": False}))
        return plane.transformation, plane.num_iterations, ""
    before = initial_confidence
    if before is None:
        before = _confidence(initial, keypoints, request)
    after = _confidence(plane.transformation, keypoints, request)
    undone = after < before - request.refine.plane_confidence_drop
    pose = initial if undone else plane.transformation
    stages.append(Stage("plane", time.perf_counter() - started, pose=clouds.pose_out(pose), points=len(points),
                        iterations=plane.num_iterations,
                        decided={"undone": bool(undone), "confidence_before": before, "confidence_after": after}))
    if undone:
        return initial, plane.num_iterations, (
            f"{plane.num_iterations} esm-plane iteration(s) on {len(points):,} points undone (overlap confidence "
            f"{before:.2f} -> {after:.2f}), then ")
    note = f"{plane.num_iterations} esm-plane iteration(s) on {len(points):,} points, then "
    return plane.transformation, plane.num_iterations, note


def _evaluate(clouds: _Clouds, outcome, request: _Request, stages: list, every_point: bool = False):
    """Stage 4: ``(fitness, inlier_rmse, inlier_distance, (distances, indices, inliers, sample))`` of
    the final pose of ``outcome`` (working frame), in Open3D's meaning, on at most
    ``refine.evaluated_points`` evenly strided source points (``sample``: their indices, None for
    every point, as with ``every_point`` and ``esm-paper``), with each one's nearest target distance
    and index (and, for ``esm-paper``, a warning when the clouds were not index-aligned). The
    refinement's last neighbours of the source points, if it has them, are where the queries start
    (the same answers, sooner)."""
    started = time.perf_counter()
    source, target_index, warm = clouds.source, clouds.index, outcome.neighbours
    if warm is not None and len(warm) != len(source):
        warm = None  # another source's (the strided subsample's)
    sample = None
    if not every_point and request.method != "esm-paper" and len(source) > request.refine.evaluated_points:
        sample = evenly_strided(len(source), request.refine.evaluated_points)
        source = source[sample]
        warm = None if warm is None else warm[sample]
    inlier_distance = request.inlier_distance
    if inlier_distance is None:
        spacing = target_index.spacing()
        inlier_distance = (request.refine.inlier_distance_spacings * spacing if spacing > 0
                           else 1e-6 * bounding_box_diagonal(target_index.points))
    distances, indices = target_index.query_near(source, warm=warm, transform=outcome.transformation)
    inliers = distances <= inlier_distance
    fitness = float(inliers.mean())
    inlier_rmse = float(np.sqrt(np.mean(np.square(distances[inliers])))) if inliers.any() else 0.0
    if request.method == "esm-paper" and len(source) == len(target_index.points):
        _warn_if_not_index_aligned(indices, request.refine.index_aligned_fraction)
    stages.append(Stage("evaluate", time.perf_counter() - started, points=len(source),
                        decided={"fitness": fitness, "inlier_rmse": inlier_rmse,
                                 "inlier_distance": float(inlier_distance)}))
    return fitness, inlier_rmse, float(inlier_distance), (distances, indices, inliers, sample)


def _judge(outcome, confidence: float, request: _Request, clouds: _Clouds, keypoints: Keypoints,
           estimate: GlobalEstimate | None, pairs, inlier_distance: float, stages: list) -> Verdict:
    """Stage 5: the verdict on the final pose of ``outcome`` (working frame), whose overlap
    confidence the refinement measured (:func:`esmicp.trust.judge.judge`); with range images, the
    free-space test too. Unless the request asks for no judgement: then the verdict on the
    convergence, the confidence and the search alone, with the doubt "not judged". ``keypoints``:
    :func:`_start`'s; when not the search's, they are the whole clouds' keypoints the judge reads
    the clouds' scatter from, and it reads it from them rather than making them again (and from
    the search's :attr:`~esmicp.globalreg.search.GlobalEstimate.whole_keypoints` when it made them);
    the search's reading of that scatter, when it made one, is not made again
    (:attr:`~esmicp.globalreg.search.GlobalEstimate.scattered`)."""
    started = time.perf_counter()
    if not request.judge:
        return Verdict.of(converged=outcome.converged, num_iterations=outcome.num_iterations, confidence=confidence,
                          ambiguous=bool(estimate is not None and estimate.ambiguous),
                          runner_up_ratio=None if estimate is None else estimate.runner_up_ratio,
                          policy=request.trust, judged=False,
                          unsupported=None if estimate is None else estimate.unsupported)
    sensors = None
    if request.range_images is not False:
        sensors = SensorClouds(request.source, request.target, inlier_distance, request.range_images)
    verdict = judge(outcome.transformation, source=clouds.source, target_index=clouds.index, keypoints=keypoints,
                    pairs=pairs[:2], sample=pairs[3], sigma=None if request.method == "icp" else outcome.sigma,  # ICP: unit weights
                    converged=outcome.converged, num_iterations=outcome.num_iterations, config=request.config,
                    policy=request.trust, ambiguous=bool(estimate is not None and estimate.ambiguous),
                    runner_up_ratio=None if estimate is None else estimate.runner_up_ratio, confidence=confidence,
                    origin=clouds.frame.origin, sensors=sensors, workers=request.workers,
                    unsupported=None if estimate is None else estimate.unsupported,
                    made=keypoints if estimate is None or estimate.keypoints is None else estimate.whole_keypoints,
                    scatter=None if estimate is None else estimate.scattered)
    stages.append(Stage("judge", time.perf_counter() - started, pose=clouds.pose_out(outcome.transformation),
                        decided={"confidence": verdict.confidence, "trusted": verdict.trusted,
                                 "doubts": tuple(doubt.kind for doubt in verdict.doubts),
                                 "degenerate_directions": len(verdict.degenerate_directions),
                                 "free_space": verdict.free_space}))
    return verdict

def _validate(source, target, method, init, sigma, max_iterations, tolerance, rng, inlier_distance, workers,
              config=None, range_images=None, judge=True) -> _Request:
    """Stage 1: every argument checked (one clear :class:`InvalidInputError` otherwise)."""
    source_points = as_points(source, "source")
    target_points = as_points(target, "target")
    check_geometry({"source": source_points, "target": target_points})  # first: it blames the numbers
    for points, name in ((source_points, "source"), (target_points, "target")):
        check_not_degenerate(points, name)
    if method not in METHODS:
        raise InvalidInputError(f"method: unknown method {method!r}; choose one of {', '.join(METHODS)}")
    init_name, initial = _resolve_init(init)
    if initial is not None:
        _check_start_representable(initial, source_points)
    registration = RegistrationConfig.of(config)
    request = _Request(
        source_points, target_points, method, init_name, initial,
        sigma=None if sigma is None else as_positive(sigma, "sigma"),
        criteria=ConvergenceCriteria(as_count(max_iterations, "max_iterations"), _as_tolerance(tolerance)),
        rng=as_generator(rng, default_seed=DEFAULT_SEED),
        inlier_distance=None if inlier_distance is None else as_positive(inlier_distance, "inlier_distance"),
        workers=as_workers(workers),
        config=registration.search,
        refine=registration.refine,
        trust=registration.trust,
        coincident_warning=registration.coincident_warning_fraction,
        range_images=None if range_images is None else _as_flag(range_images, "range_images"),
        judge=_as_flag(judge, "judge"),
    )
    if method == "esm-paper" and len(source_points) != len(target_points):
        warnings.warn(
            f"esm-paper needs index-aligned clouds of equal size, got {len(source_points)} source "
            f"and {len(target_points)} target points; its result is not meaningful here: use method='esm'",
            IndexAlignmentWarning,
            stacklevel=3,
        )
    return request


def _correspondences(pairs, estimator, sigma: float | None) -> Correspondences:
    """The inlier pairs of :func:`_evaluate` (``(distances, indices, inliers, None)``: every source
    point's) with the weight
    ``estimator`` gives each at ``sigma`` (1 where it weighs none)."""
    distances, indices, inliers, _ = pairs
    weights = estimator.pair_weights(distances, sigma)
    weights = np.ones(len(distances)) if weights is None else np.clip(weights, 0.0, 1.0)
    chosen = np.flatnonzero(inliers)
    return Correspondences(chosen.astype(np.int64), indices[chosen].astype(np.int64),
                           weights[chosen].astype(np.float64), distances[chosen].astype(np.float64))


def _warn_if_coincident(points: np.ndarray, name: str, coincident, fraction: float) -> None:
    """Warn when at least ``fraction`` of ``points`` are exact copies of
    other points (``coincident``: :func:`~esmicp.core.correspondence.coincident_points` of them)."""
    repeats, most, most_count, _ = coincident
    if repeats < fraction * len(points):
        return
    location = points[most]
    where = ", ".join(f"{value:.6g}" for value in location)
    advice = "deduplicate it (e.g. numpy.unique(points, axis=0))"
    if not location.any():
        advice += (
            " and drop the (0, 0, 0) points: depth sensors store invalid pixels there "
            "(e.g. points[(points != 0).any(axis=1)])"
        )
    warnings.warn(
        f"{name}: {repeats:,} of its {len(points):,} points ({100.0 * repeats / len(points):.1f}%) are copies of "
        f"other points (the most repeated: {most_count:,} at ({where})); copies add no information, and many "
        f"at one place pull the fit toward it: {advice}",
        CoincidentPointsWarning,
        stacklevel=5,  # the caller of register (through _prepare and the interrupt wrapper)
    )


def _check_start_representable(initial: np.ndarray, source_points: np.ndarray) -> None:
    """Refuse a start that moves the source beyond float64 geometry (a translation of 1e200 used to
    overflow in silence and end ``converged=True`` at a wrong pose)."""
    from .types import MAX_COORDINATE

    reach = float(np.abs(initial[:3, 3]).max()) + float(np.abs(source_points).max()) * 3 ** 0.5
    if not reach <= MAX_COORDINATE:
        raise InvalidInputError(
            f"init: its translation ({float(np.abs(initial[:3, 3]).max()):.3g}) moves the source beyond the "
            f"{MAX_COORDINATE:g} that float64 squared distances allow; is it in the clouds' units?"
        )


def _warn_if_not_index_aligned(indices: np.ndarray, fraction: float) -> None:
    """Warn when fewer than ``fraction`` of the source points lie nearest to the target point of
    their own index (:attr:`esmicp.config.RefineConfig.index_aligned_fraction`)."""
    own = float(np.mean(indices == np.arange(len(indices))))
    if own < fraction:
        warnings.warn(
            f"esm-paper assumes index-aligned clouds (source point k = target point k), but after "
            f"registration only {100 * own:.1f}% of source points lie nearest to the target point of "
            f"their own index; the clouds are probably not index-aligned and the result is likely "
            f"wrong: use method='esm'",
            IndexAlignmentWarning,
            stacklevel=4,
        )


def _resolve_init(init) -> tuple[str, np.ndarray | None]:
    """``(name, T)`` for a given ``init``; ``T`` is None when a global search must find it."""
    if init is None:
        return "auto", None
    if isinstance(init, str):
        name = "auto" if init == "global" else init
        if name in STRATEGIES:
            return name, None
        if name in IDENTITY_NAMES:
            return "identity", np.eye(4)
        raise InvalidInputError(
            f"init: unknown strategy {init!r}; choose one of {', '.join(INIT_NAMES)}, or give a 4x4 matrix"
        )
    return "given", as_transform(init, "init")


def _as_flag(value, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise InvalidInputError(f"{name}: expected True or False, got {value!r}")
    return bool(value)


def _as_tolerance(value) -> float:
    number = as_real(value, "tolerance")
    if not np.isfinite(number) or number < 0:
        raise InvalidInputError(f"tolerance: expected a finite number >= 0, got {value!r}")
    return number
