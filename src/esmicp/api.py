"""``register()``: one registration as its stages: validate, move to a working frame, start (a
global search unless a pose is given), refine, evaluate."""

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
from .config import RefineConfig, RegistrationConfig
from .errors import CoincidentPointsWarning, IndexAlignmentWarning, InvalidInputError
from .globalreg.config import SearchConfig
from .globalreg.search import STRATEGIES, GlobalEstimate, global_estimate
from .interrupts import keeps_keyboard_interrupt
from .methods import METHODS, ConvergenceCriteria, PlaneEstimator, make_estimator
from .methods.esm import COARSE_POINTS, TIGHT_START_QUANTILE, EsmEstimator
from .methods.guard import guarded_refine
from .methods.local import STOPPED_BY_CALLBACK, Callback, Observer, RefinementOutcome
from .result import Correspondences, RegistrationResult
from .trust import uncertainty
from .trust.confidence import overlap_confidence
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
    range_images: bool = False,
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
        the more confident run.)
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
        (10,000) points stops at ``config.refine.strided_tolerance`` (1e-5) when ``tolerance`` is
        finer. A given ``init`` and smaller sources keep ``tolerance``. (A source of more than twice
        ``config.refine.strided_points`` (20,000) points is refined on that many evenly strided
        points.)
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
        of the pairs within ``inlier_distance``, Open3D's ``correspondence_set``); they cost
        nothing more to find, but hold four arrays per pair.
    config : esmicp.config.RegistrationConfig, esmicp.globalreg.config.SearchConfig or dict, optional
        The tuned values: the global search's (and the overlap confidence's ranges), the local
        refinement's (:class:`esmicp.config.RefineConfig`) and the trust policy the result is
        judged by (:class:`esmicp.trust.policy.TrustPolicy`, kept in
        ``result.policy``). A SearchConfig (or a dict of its fields) sets the search's values with
        the default policy; a dict with the keys ``search`` and / or ``trust`` is a
        RegistrationConfig's. None: the measured defaults.
    range_images : bool
        Both clouds are range images in their sensor frames: every point as its sensor saw it,
        the sensor at the origin (depth-camera frames, LiDAR scans as recorded). The final pose
        is then also checked against the space each sensor saw empty
        (:func:`esmicp.trust.free_space.free_space_fraction`, in ``result.free_space``): a pose
        that puts more than the policy's ``max_free_space_pair`` (8%) of either cloud there is not
        trusted, however sharply the clouds coincide (a repeated structure
        matched in the wrong place, a pair that shares no surface). The pose itself is the same.
        False (the default): no such check (clouds in another frame, such as meshes, fused
        fragments or maps, would fail it).

    Returns
    -------
    RegistrationResult

    Raises
    ------
    InvalidInputError
        On malformed or degenerate clouds (or beyond float64 geometry, see
        :func:`esmicp.types.check_geometry`), an unknown method, a malformed or non-rigid ``init``,
        or non-positive ``sigma``, ``max_iterations``, ``inlier_distance`` or ``workers``.
    """
    started = time.perf_counter()
    request = _validate(source, target, method, init, sigma, max_iterations, tolerance, rng, inlier_distance, workers,
                        config)
    if not isinstance(range_images, (bool, np.bool_)):
        raise InvalidInputError(f"range_images: expected True or False, got {range_images!r}")
    frame = WorkingFrame.for_target(request.target)
    source_points, target_points = frame.points(request.source), frame.points(request.target)
    target_index = NearestNeighbors(target_points, workers=request.workers)
    _warn_if_coincident(request.source, "source", coincident_points(request.source), request.coincident_warning)
    _warn_if_coincident(request.target, "target", target_index.coincident(), request.coincident_warning)
    diagonal = bounding_box_diagonal(target_points)
    initial, init_name, estimate = _start(request, source_points, target_points, target_index, frame)
    keypoints = getattr(estimate, "keypoints", None)
    if keypoints is None:
        keypoints = Keypoints.of(source_points, target_points, target_index.spacing(), request.config.keypoints)
    # After a global search (which ends at the finest sigma) the pose is already close: start in
    # the fine phase, so that a coarse sigma cannot pull partial overlaps apart again.
    estimator = _estimator(method, request, target_index, diagonal, start_fine=estimate is not None)
    start_distances = None
    if estimate is None and isinstance(estimator, EsmEstimator):
        # A given start: its coarse sigma comes from the overlap's residuals (partial overlaps).
        start_distances = target_index.query_near(source_points, transform=initial)[0]
        estimator.start_from(start_distances)
    observer = None
    if callback is not None or record_history:
        observer = Observer(source_points, target_index, frame.callback(callback), record_history)
    outcome = _refine(source_points, target_index, estimator, initial, request, diagonal, keypoints, estimate,
                      observer)
    confidence = overlap_confidence(outcome.transformation, keypoints, request.workers, config=request.config,
                                    policy=request.trust)
    if start_distances is not None and request.sigma is None and confidence < request.trust.trusted \
            and not (observer is not None and observer.stopped):
        outcome, confidence = _second_try(source_points, target_index, initial, request, diagonal, keypoints,
                                          start_distances, outcome, confidence, observer=observer)
    if observer is not None:
        outcome = dataclasses.replace(outcome, history=observer.recorded())
    fitness, inlier_rmse, inlier_distance, pairs = _evaluate(source_points, target_index, outcome.transformation,
                                                             request, outcome.neighbours)
    correspondences = None
    if return_correspondences:
        correspondences = _correspondences(pairs, _estimator(method, request, target_index, diagonal), outcome.sigma)
    weights_sigma = None if method == "icp" else outcome.sigma  # ICP: unit weights
    pose = uncertainty.from_registration(source_points, target_index, outcome.transformation, weights_sigma,
                                         origin=frame.origin, workers=request.workers, pairs=pairs[:2],
                                         policy=request.trust)
    outcome = frame.outcome(outcome)
    free_space = None
    if range_images:
        from .trust.free_space import pair_verdict

        free_space = _free_space(request, outcome.transformation, inlier_distance)
        outcome = dataclasses.replace(outcome, message=f"{outcome.message}; {pair_verdict(free_space, request.trust)[1]}")
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
        message=outcome.message,
        history=outcome.history,
        init=init_name,
        ambiguous=bool(estimate is not None and estimate.ambiguous),
        runner_up_ratio=None if estimate is None else estimate.runner_up_ratio,
        global_candidates=0 if estimate is None else estimate.candidates,
        runner_up=None if estimate is None or estimate.runner_up is None else frame.transform_out(
            np.array(estimate.runner_up, dtype=np.float64)),
        confidence=confidence,
        correspondences=correspondences,
        covariance=pose.covariance,
        information=pose.information,
        degenerate_directions=pose.degenerate_directions,
        free_space=free_space,
        policy=request.trust,
    )


def _free_space(request: _Request, transformation: np.ndarray, inlier_distance: float) -> float | None:
    """The free-space test of the pair at ``transformation`` (``T_target_source``, the clouds' own
    frames), at the policy's ``free_space_tolerance_inliers`` inlier distances."""
    from .trust import free_space  # here: it loads SciPy

    policy = request.trust
    return free_space.free_space_fraction(request.target, request.source, transformation,
                                          policy.free_space_tolerance_inliers * inlier_distance, policy)


def _validate(source, target, method, init, sigma, max_iterations, tolerance, rng, inlier_distance, workers,
              config=None) -> _Request:
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
    )
    if method == "esm-paper" and len(source_points) != len(target_points):
        warnings.warn(
            f"esm-paper needs index-aligned clouds of equal size, got {len(source_points)} source "
            f"and {len(target_points)} target points; its result is not meaningful here: use method='esm'",
            IndexAlignmentWarning,
            stacklevel=3,
        )
    return request


def _start(request: _Request, source, target, target_index, frame) -> tuple[np.ndarray, str, GlobalEstimate | None]:
    """Stage 3: the starting pose (working frame), its name, and the global estimate if one was made."""
    if request.initial is not None:
        return frame.transform_in(request.initial), request.init_name, None
    estimate = global_estimate(
        source, target, strategy=request.init_name, rng=request.rng, target_index=target_index,
        target_spacing=target_index.spacing(), workers=request.workers, config=request.config,
        policy=request.trust,
    )
    return estimate.transformation, f"global:{estimate.strategies[0]}", estimate


def _refine(source, target_index, estimator, initial, request: _Request, diagonal: float, keypoints: Keypoints,
            estimate: GlobalEstimate | None, observer: Observer | None = None):
    """Stage 4: ``estimator`` from ``initial`` (working frame): on a large source the strided run
    (:func:`_refine_strided`), else the whole source at once (after a global
    search, from ``refine.looser_from_points`` points on, at ``refine.strided_tolerance`` when the request's
    tolerance is finer). ``observer`` (the callback and the history, working frame) watches every
    stage and changes none."""
    if len(source) > 2 * request.refine.strided_points and estimator.order_invariant:
        # (``esm-paper`` pairs source point k with target point k: a strided subset has no pairs.)
        return _refine_strided(source, target_index, estimator, initial, request, diagonal, keypoints, estimate,
                               observer)
    criteria = request.criteria
    if estimate is not None and len(source) > request.refine.looser_from_points:
        criteria = _at_strided_tolerance(criteria, request.refine)
    return guarded_refine(
        source, target_index, estimator, init=initial, criteria=criteria, scale=diagonal,
        coarse_points=COARSE_POINTS, observer=observer,
    )


def _second_try(source, target_index, initial, request: _Request, diagonal: float, keypoints: Keypoints,
                start_distances: np.ndarray, outcome, confidence: float, observer: Observer | None = None):
    """``(outcome, confidence)``: of ``outcome`` (an ``esm`` run from a given start, overlap
    confidence ``confidence`` below the trust bar) and a second run from the same start whose coarse
    sigma comes from the start's ``TIGHT_START_QUANTILE`` distance quantile, the more confident
    (the first on a tie); the message says what the second try gave.

    Why: the first run's coarse sigma assumes a quarter of the source overlaps. Where less does
    (scans cut to 15-50%), that sigma pulls a good start apart; the tight one keeps it, but
    narrows the reach from a poor start on a whole object, so it only comes second, and only
    where the first run is not trusted (measured on the ModelNet40 halves and whole objects:
    ``docs/scans-start-drift.md``). ``observer`` watches the second run as a new run;
    its history ends as that of the run kept."""
    tight = _estimator(request.method, request, target_index, diagonal)
    tight.start_from(start_distances, TIGHT_START_QUANTILE)
    first_history = None if observer is None else observer.new_run()
    second = _refine(source, target_index, tight, initial, request, diagonal, keypoints, None, observer)
    second_confidence = overlap_confidence(second.transformation, keypoints, request.workers, config=request.config,
                                           policy=request.trust)
    if observer is not None and observer.stopped:
        return second, second_confidence
    if second_confidence > confidence:
        note = (f"; a second try with a tighter coarse sigma (the start's {TIGHT_START_QUANTILE:.0%} distance "
                f"quantile) raised the overlap confidence {confidence:.2f} -> {second_confidence:.2f}")
        return dataclasses.replace(second, message=second.message + note), second_confidence
    note = (f"; a second try with a tighter coarse sigma ended at overlap confidence {second_confidence:.2f}: "
            f"this run kept")
    if observer is not None and observer.history is not None:
        observer.history = list(first_history or ())
    return dataclasses.replace(outcome, message=outcome.message + note), confidence


def _refine_strided(source, target_index, estimator, initial, request: _Request, diagonal: float,
                    keypoints: Keypoints, estimate: GlobalEstimate | None = None,
                    observer: Observer | None = None):
    """Stage 4 on a large source: ``estimator`` on ``refine.strided_points`` evenly strided source
    points (where every point would take the pose from there lies well inside its standard
    deviation). The outcome's iterations count every stage; ``refine`` is ``request.refine``.

    After a global search (``estimate``, whose ``confidence`` is that of ``initial`` on
    ``keypoints`` when it judged it), ``esm`` is preceded by at most ``refine.plane_iterations`` of
    ``esm-plane`` on ``refine.plane_points`` of the strided points, undone when they lower the
    overlap confidence on ``keypoints`` by more than ``refine.plane_confidence_drop``, and the
    strided stages stop at ``refine.strided_tolerance`` when the request's tolerance is finer: a
    global pose is already close.
    From a given start (``estimate`` None) the strided run keeps the request's tolerance, since a
    start can lie further off and a slow slide toward the optimum must run to its end. ``observer``
    watches every stage (a stage its callback stopped is the last)."""
    strided = source[np.linspace(0, len(source) - 1, request.refine.strided_points).astype(np.intp)]
    plane_iterations, plane_note = 0, ""
    if estimate is not None:
        request = dataclasses.replace(request, criteria=_at_strided_tolerance(request.criteria, request.refine))
    if estimate is not None and request.method == "esm":
        count = min(request.refine.plane_points, len(strided))
        planed = strided[np.linspace(0, len(strided) - 1, count).astype(np.intp)]
        initial, plane_iterations, plane_note = _plane_start(planed, target_index, initial, request, diagonal,
                                                             keypoints, estimate.confidence, observer)
        if observer is not None and observer.stopped:
            return RefinementOutcome(initial, False, plane_iterations, None, plane_note + STOPPED_BY_CALLBACK, None)
        request = dataclasses.replace(request, criteria=dataclasses.replace(
            request.criteria, max_iterations=request.criteria.max_iterations - plane_iterations))
    coarse = guarded_refine(strided, target_index, estimator, init=initial, criteria=request.criteria, scale=diagonal,
                            observer=observer)
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
    estimator = make_estimator(method, request.sigma, target_index.spacing(), diagonal, start_fine=start_fine)
    if isinstance(estimator, PlaneEstimator):
        estimator.use_target_tree(target_index.exact_tree(), request.workers)
    return estimator


def _plane_start(points, target_index, initial, request: _Request, diagonal: float,
                 keypoints: Keypoints, initial_confidence: float | None = None,
                 observer: Observer | None = None) -> tuple[np.ndarray, int, str]:
    """``(pose, iterations, note)`` of at most ``refine.plane_iterations`` ``esm-plane`` iterations
    on ``points`` (``refine.plane_points`` strided source points) from ``initial``, leaving ``esm`` at least
    one iteration of ``max_iterations``; the note begins the result's message. ``initial`` when the budget leaves none, the guard
    refused the start, or the iterations lowered the overlap confidence on ``keypoints`` by more
    than ``refine.plane_confidence_drop`` (they still count against the budget and the note says
    so); ``refine`` is ``request.refine``."""
    budget = min(request.refine.plane_iterations, request.criteria.max_iterations - 1)
    if budget <= 0:
        return initial, 0, ""
    planar = _estimator("esm-plane", request, target_index, diagonal)
    criteria = dataclasses.replace(request.criteria, max_iterations=budget)
    plane = guarded_refine(points, target_index, planar, init=initial, criteria=criteria, scale=diagonal,
                           observer=observer)
    if plane.num_iterations == 0:
        return initial, 0, ""
    if observer is not None and observer.stopped:
        return plane.transformation, plane.num_iterations, ""
    before = initial_confidence
    if before is None:
        before = overlap_confidence(initial, keypoints, request.workers, config=request.config,
                                        policy=request.trust)
    after = overlap_confidence(plane.transformation, keypoints, request.workers, config=request.config,
                               policy=request.trust)
    if after < before - request.refine.plane_confidence_drop:
        return initial, plane.num_iterations, (
            f"{plane.num_iterations} esm-plane iteration(s) on {len(points):,} points undone (overlap confidence "
            f"{before:.2f} -> {after:.2f}), then ")
    note = f"{plane.num_iterations} esm-plane iteration(s) on {len(points):,} points, then "
    return plane.transformation, plane.num_iterations, note


def _evaluate(source, target_index, transformation, request: _Request, warm=None):
    """Stage 5: ``(fitness, inlier_rmse, inlier_distance, (distances, indices, inliers))`` of the
    final pose, in Open3D's meaning, with each source point's nearest target distance and index
    (and, for ``esm-paper``, a warning when the clouds were not index-aligned). ``warm``: the
    refinement's last neighbours of the source points, if it has them (the queries start there:
    the same answers, sooner)."""
    inlier_distance = request.inlier_distance
    if inlier_distance is None:
        spacing = target_index.spacing()
        inlier_distance = (request.refine.inlier_distance_spacings * spacing if spacing > 0
                           else 1e-6 * bounding_box_diagonal(target_index.points))
    if warm is not None and len(warm) != len(source):
        warm = None  # another source's (the strided subsample's)
    distances, indices = target_index.query_near(source, warm=warm, transform=transformation)
    inliers = distances <= inlier_distance
    fitness = float(inliers.mean())
    inlier_rmse = float(np.sqrt(np.mean(np.square(distances[inliers])))) if inliers.any() else 0.0
    if request.method == "esm-paper" and len(source) == len(target_index.points):
        _warn_if_not_index_aligned(indices, request.refine.index_aligned_fraction)
    return fitness, inlier_rmse, float(inlier_distance), (distances, indices, inliers)


def _correspondences(pairs, estimator, sigma: float | None) -> Correspondences:
    """The inlier pairs of :func:`_evaluate` (``(distances, indices, inliers)``) with the weight
    ``estimator`` gives each at ``sigma`` (1 where it weighs none)."""
    distances, indices, inliers = pairs
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
        stacklevel=4,  # the caller of register (through its interrupt wrapper)
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


def _as_tolerance(value) -> float:
    number = as_real(value, "tolerance")
    if not np.isfinite(number) or number < 0:
        raise InvalidInputError(f"tolerance: expected a finite number >= 0, got {value!r}")
    return number
