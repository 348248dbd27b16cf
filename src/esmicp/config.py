"""The configuration tree: every tuned value of a registration and of a merge, in frozen,
documented objects.

* :class:`RegistrationConfig` (``register(..., config=...)``): the global search's values
  (:class:`~esmicp.globalreg.config.SearchConfig`), the local refinement's
  (:class:`RefineConfig`) and the trust policy (:class:`~esmicp.trust.policy.TrustPolicy`: the
  bars a result must pass to be trusted).
* :class:`MergeConfig` (``register_scans(..., config=...)``): the merge's values (how many points,
  which pairs, how long a check runs, how far the joint refinement goes) and the
  :class:`RegistrationConfig` of its pairwise registrations, whose trust policy also judges the
  merge's scans.

Each is frozen, checked when made (an invalid value raises :class:`~esmicp.errors.InvalidInputError`
naming the field) and round-trips through a JSON-ready dict
(:meth:`~esmicp.core.config.Config.to_dict`, :meth:`~esmicp.core.config.Config.from_dict`, which
refuses unknown keys). The defaults are the measured values.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from .core.config import Config, NeighbourIndexConfig, count, flag, fraction, number, part
from .errors import InvalidInputError
from .globalreg.config import SearchConfig, as_config
from .methods.config import EsmConfig, LoopConfig, PlaneConfig
from .trust.policy import TrustPolicy
from .types import MIN_POINTS


@dataclass(frozen=True)
class RefineConfig(Config):
    """Tuned values of a registration's local refinement and evaluation (:func:`esmicp.register`).

    Attributes
    ----------
    strided_points : int
        A source of more than twice this many points is refined on this many evenly strided
        points (count; not with ``esm-paper``, whose pairs are by index): where every point would
        take the pose from there lies well inside the pose's own standard deviation.
    strided_tolerance : float
        After a global search, the strided stages stop at this tolerance when the caller's is
        finer (radians; times the target's bounding-box diagonal for a translation): the
        subsample's optimum is not the whole source's, and the strided ``esm`` creeps on in no
        steady direction; stopping there moves the pose by a fraction of its own standard
        deviation.
    looser_from_points : int
        After a global search, a source too small for the strided stages is refined at
        ``whole_tolerance``, from this many points on (count); smaller sources (objects
        under heavy outliers, which may still be sliding there) keep the caller's tolerance.
    whole_tolerance : float
        ... that tolerance, when the caller's is finer (radians; times the target's bounding-box
        diagonal for a translation): a global pose is already close, and the last iterations
        creep on by less than the pose's own standard deviation.
    plane_iterations : int
        After a global search, ``esm`` on the strided points is preceded by at most this many
        ``esm-plane`` iterations (count; 0: none): the plane residual pulls back a pose slid along
        a road or a corridor, where ``esm``'s Gaussian weight is nil.
    plane_points : int
        ... on this many of the strided points, evenly strided again (count): fewer points cost
        less per iteration, too few take more iterations.
    plane_confidence_drop : float
        The ``esm-plane`` stage is undone when it lowers the overlap confidence by more than this
        (confidence units, 0-1).
    inlier_distance_spacings : float
        The default inlier distance of ``fitness`` and ``inlier_rmse``, in target point spacings
        (gain).
    evaluated_points : int
        ``fitness``, ``inlier_rmse`` and the pose covariance's pairs are measured on at most this
        many evenly strided source points (count; every point when ``return_correspondences`` asks
        for the pairs, and with ``esm-paper``, whose pairs are by index). A fraction measured on
        ``n`` such points has a standard error of at most ``0.5 / sqrt(n)`` (0.0025 at 40,000);
        each pair of the covariance stands for the source points strided over.
    second_try : bool
        From a given start, ``esm`` with the automatic sigma runs a second time, with a tighter
        coarse sigma, when the first run ends below the trust bar, and keeps the more confident
        run (:func:`esmicp.register`'s ``init``). False: the first run only.
    index_aligned_fraction : float
        An ``esm-paper`` result whose source points lie nearest to the target point of their own
        index for less than this fraction of them (0-1) warns that the clouds are not
        index-aligned (:class:`~esmicp.errors.IndexAlignmentWarning`).
    esm : EsmConfig
        ``esm``'s automatic sigma and ``esm-paper``'s sigma
        (:class:`esmicp.methods.config.EsmConfig`).
    plane : PlaneConfig
        ``esm-plane``'s values (:class:`esmicp.methods.config.PlaneConfig`).
    loop : LoopConfig
        The local loop's values (:class:`esmicp.methods.config.LoopConfig`).
    index : NeighbourIndexConfig
        When the target's nearest-neighbour index answers through its voxel hash and its
        neighbour graph (:class:`esmicp.core.config.NeighbourIndexConfig`; speed only): the index
        :func:`esmicp.register` builds, which its global search shares (and the indices the search
        builds for itself take).

    References
    ----------
    Each field's value, the data it was chosen on and confirmed on, and the page with the figures:
    ``docs/design.md``, "Tuned values" (``strided_*``, ``whole_tolerance`` and ``plane_*``:
    ``docs/speed.md``, "Real scan pairs", and ``docs/scans-refinement.md``; ``plane_confidence_drop``:
    ``docs/scans-partial-overlap.md``).
    """

    strided_points: int = count(20_000)
    strided_tolerance: float = number(1e-5, least=0.0)
    looser_from_points: int = count(10_000, least=0)
    whole_tolerance: float = number(3e-5, least=0.0)
    plane_iterations: int = count(30, least=0)
    plane_points: int = count(2_500)
    plane_confidence_drop: float = number(0.25, least=0.0)
    inlier_distance_spacings: float = number(3.0, above=0.0)
    evaluated_points: int = count(40_000, least=3)
    index_aligned_fraction: float = fraction(0.5)
    second_try: bool = flag(True)
    esm: EsmConfig = part(EsmConfig)
    plane: PlaneConfig = part(PlaneConfig)
    loop: LoopConfig = part(LoopConfig)
    index: NeighbourIndexConfig = part(NeighbourIndexConfig)


@dataclass(frozen=True)
class RegistrationConfig(Config):
    """Tuned values of one registration (:func:`esmicp.register`).

    Attributes
    ----------
    search : SearchConfig
        The global search's values, and the ranges the overlap confidence maps its measures from
        (:class:`esmicp.globalreg.config.SearchConfig`).
    refine : RefineConfig
        The local refinement's and the evaluation's values (:class:`RefineConfig`).
    trust : TrustPolicy
        The bars a result must pass to be trusted, and the values of the measures behind them
        (:class:`esmicp.trust.policy.TrustPolicy`).
    coincident_warning_fraction : float
        From this fraction (0-1) of a cloud's points being exact copies of other points on,
        :func:`esmicp.register` warns (:class:`~esmicp.errors.CoincidentPointsWarning`).
    """

    search: SearchConfig = part(SearchConfig)
    refine: RefineConfig = part(RefineConfig)
    trust: TrustPolicy = part(TrustPolicy)
    coincident_warning_fraction: float = fraction(0.1)

    @classmethod
    def of(cls, value, name: str = "config") -> "RegistrationConfig":
        """``value`` as a :class:`RegistrationConfig`: None gives the defaults; an instance is kept;
        a :class:`SearchConfig` gives its search values and the defaults of the rest; a dict whose
        keys are among the fields of this class (``search``, ``refine``, ``trust``, ...) is read by
        :meth:`from_dict`, any other dict as a :class:`SearchConfig`'s fields. Anything else
        raises :class:`InvalidInputError`."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, SearchConfig):
            return cls(search=value)
        if isinstance(value, dict):
            if value and set(value) <= {field.name for field in fields(cls)}:
                return cls.from_dict(value)
            return cls(search=as_config(value))
        raise InvalidInputError(f"{name}: expected a RegistrationConfig, a SearchConfig or a dict, "
                                f"got {type(value).__name__}")


@dataclass(frozen=True)
class MergeConfig(Config):
    """Tuned values of :func:`esmicp.register_scans`.

    Lengths are gains times a length the data give: the median inlier distance of the kept
    edges (the registrations' :attr:`~esmicp.RegistrationResult.inlier_distance`, the scans'
    noise and spacing at the subsets' resolution), or the median point spacing of the dense
    subsets.

    Attributes
    ----------
    pair_points : int
        Points per scan (a content-seeded random subset) for the pairwise global searches (count).
    refine_points : int
        Points per scan for the local check of each pair and the joint refinement (count).
    partners : int
        Without ``sequence``: the most similar scans each scan is first registered with, and the
        pairs a round asks for per piece of unplaced scans (count).
    match_candidates : int
        Without ``sequence``: each scan's nearest scans by the shape descriptor whose surface
        features are matched to rank its partners
        (:func:`esmicp.multiview.pairs.matching_distances`; count).
    match_radius_spacings : float
        The FPFH neighbourhood of those features, in median point spacings of the sparse subset
        (gain).
    match_normal_neighbours : int
        Nearest points of the normals under those features (count).
    match_points : int
        Features per scan (evenly strided over the sparse subset) matched between two scans
        (count).
    sequence_neighbours : int
        With ``sequence``: the next scans each scan is registered with (count; 2 gives triangles).
    max_edge_error_deg : float
        A trusted edge disagreeing with the solved poses by more than this rotation (degrees; or
        by more than ``max_edge_shift_inliers`` in translation) is rejected as cycle inconsistent.
    max_edge_shift_inliers : float
        ... the translation bar, in the edge's own inlier distances (gain).
    first_check_gain : float
        Before the robust optimisation, the consensus tree and the first cycle check allow this
        many times ``max_edge_error_deg`` and ``max_edge_shift_inliers`` (gain): the unoptimised
        tree's poses carry the error of every edge on their path.
    refine_rounds : int
        Correspondence distances of the joint refinement, each used for ``refine_steps``
        Gauss-Newton steps (count; 0: no joint refinement).
    stalled_rounds : int
        Rounds in a row that place or confirm no scan after which the merge stops asking for
        more pairs (count).
    pair_scan_searches : int
        Scan-strategy searches at most in each global search of a pair on the sparse subsets
        (count; :attr:`~esmicp.globalreg.config.SearchConfig.scan_searches`, unless
        ``registration.search`` sets its own): an untrusted pair gets its second search on another
        draw of the subsets when the graph needs it.
    closing_pairs : int
        Pairs searched a round across each edge on no cycle of the kept graph (count).
    bridging_growth : float
        A piece of unplaced scans paired with the placed scans most like its own (its pose found
        no pairs) gets this many times the pairs of its previous such round (ratio, at least 1;
        ``partners * min(len(piece), partners)`` the first time): the pairs that join it may
        rank low, and the search stays bounded by ``stalled_rounds``.
    piece_points : int
        Points (a content-seeded random subset, at most) of each fused cloud in the global search
        that places a piece of unplaced scans as a whole: the piece's scans fused at their poses
        within it, and the placed scans fused at theirs (count).
    predict_radius_inliers : float
        What the poses predict two posed scans share is measured within this many median inlier
        distances of the kept edges (gain).
    min_predicted_overlap : float
        Below this predicted overlap (fraction of points, 0-1) a pair is not searched to close a
        cycle or a loop.
    predict_points : int
        Points of a scan (evenly strided, at most) whose distances to another posed scan predict
        the pair's overlap (count).
    predict_partners : int
        Posed scans nearest in the world whose overlap with a scan is predicted when pairs are
        sought for it (count).
    loop_min_hops : int
        With ``sequence``: a loop closure is searched only where the graph joins the two scans by
        a path of at least this many edges (count).
    loop_searches_per_scan : float
        With ``sequence``: loop closures searched, at most, per posed scan over the whole merge
        (ratio; rounded up over the scans posed when they are sought: after the first pairs, and
        again after a round of more pairs that poses scans not posed before).
    check_iterations : int
        Iterations of the local check of a pair on the dense subsets, unless ``max_iterations``
        is passed to :func:`esmicp.register_scans` (count).
    check_tolerance : float
        The local check stops once an increment rotates less than this (radians; translates less
        than this times the target's bounding-box diagonal); measured for the merge's checks
        (``docs/merge.md``), finer than :attr:`RefineConfig.strided_tolerance`, where
        :func:`esmicp.register`'s own refinement stops after a global search.
    sparse_second_try : bool
        Whether a pair refined from a given start on the sparse subsets (with ``sequence``, the
        first pairs) runs its second, tighter coarse sigma when it ends below the trust bar
        (:attr:`RefineConfig.second_try`). Off: the overlap confidence that asks for it is not
        meaningful at the sparse subsets' density (right pairs score as low as wrong ones there),
        and the check on the dense subsets, which starts where that refinement ends, runs its own
        second try when it ends below the bar.
    refine_normal_neighbours : int
        Nearest points of each normal of the dense subsets, whose planes the joint refinement's
        residuals measure (count).
    refine_steps : int
        Gauss-Newton steps of the joint refinement at each correspondence distance (count).
    refine_huber_ratio : float
        The joint refinement weighs a residual by Huber's rule beyond the correspondence distance
        divided by this (ratio).
    refine_min_pairs : int
        A direction of an edge with fewer correspondences than this within the distance adds
        nothing to a step of the joint refinement (count).
    refine_reach_inliers : float
        The joint refinement's first correspondence distance, in median inlier distances of the
        kept edges (gain).
    refine_floor_spacings : float
        The joint refinement's last correspondence distance, in median point spacings of the
        dense subsets (gain; the distances in between shrink geometrically).
    query_points : int
        Points of a scan each direction of an edge queries in a step of the joint refinement
        (count; evenly strided).
    direct_solve_max_poses : int
        Up to this many free poses, each step of the pose graph's optimiser is a sparse direct
        solve; beyond, preconditioned conjugate gradients (count).
    visibility_partners : int
        Placed scans each scan is checked against for free-space conflicts, its nearest in the
        world whose extents overlap its own, besides the scans it shares a kept edge with (count).
    registration : RegistrationConfig
        The pairwise registrations' values; its trust policy also judges the merge (the free-space
        check between placed scans, the trust of its edges).

    References
    ----------
    ``stalled_rounds``, ``pair_scan_searches``, ``refine_floor_spacings``, ``query_points``,
    ``check_iterations``, ``check_tolerance``, ``sparse_second_try``, ``loop_searches_per_scan``,
    ``piece_points`` and the ``match_*`` fields were each chosen on one set of scans and confirmed on another:
    ``docs/design.md``, "Tuned values". ``bridging_growth`` is a bound on the search, not a tuned
    optimum.
    The measurements: ``docs/merge.md``, "Tuned values".
    """

    pair_points: int = count(1500, least=MIN_POINTS)
    refine_points: int = count(8000, least=MIN_POINTS)
    partners: int = count(2)
    match_candidates: int = count(8, least=0)
    match_radius_spacings: float = number(10.0, above=0.0)
    match_normal_neighbours: int = count(20, least=3)
    match_points: int = count(500)
    sequence_neighbours: int = count(2)
    max_edge_error_deg: float = number(2.0, above=0.0, most=180.0)
    max_edge_shift_inliers: float = number(3.0, above=0.0)
    first_check_gain: float = number(2.0, least=1.0)
    refine_rounds: int = count(6, least=0)
    stalled_rounds: int = count(3)
    pair_scan_searches: int = count(1)
    closing_pairs: int = count(1)
    piece_points: int = count(3000, least=MIN_POINTS)
    bridging_growth: float = number(2.0, least=1.0)
    predict_radius_inliers: float = number(3.0, above=0.0)
    min_predicted_overlap: float = fraction(0.3)
    predict_points: int = count(300)
    predict_partners: int = count(16)
    loop_min_hops: int = count(6)
    loop_searches_per_scan: float = number(0.125, least=0.0)
    check_iterations: int = count(30)
    check_tolerance: float = number(3e-6, least=0.0)
    sparse_second_try: bool = flag(False)
    refine_normal_neighbours: int = count(12, least=3)
    refine_steps: int = count(2)
    refine_huber_ratio: float = number(3.0, above=0.0)
    refine_min_pairs: int = count(10)
    refine_reach_inliers: float = number(3.0, above=0.0)
    refine_floor_spacings: float = number(2.0, above=0.0)
    query_points: int = count(1000)
    direct_solve_max_poses: int = count(200, least=0)
    visibility_partners: int = count(8, least=0)
    registration: RegistrationConfig = part(RegistrationConfig)

    @classmethod
    def of(cls, value, name: str = "config") -> "MergeConfig":
        """``value`` as a :class:`MergeConfig` (None: the defaults; a dict: :meth:`from_dict`);
        anything else raises :class:`InvalidInputError`, which points a registration's config to
        the field ``registration``."""
        if isinstance(value, (RegistrationConfig, SearchConfig)):
            raise InvalidInputError(f"{name}: expected a MergeConfig or a dict, got {type(value).__name__}; the "
                                    f"pairwise registrations' values go in MergeConfig(registration=...)")
        return super().of(value, name)
