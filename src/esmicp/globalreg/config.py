"""The tuned values of the global search, in one frozen, documented object.

:class:`SearchConfig` holds every value of the global search that was chosen by measurement (a
bar, a ratio, a count whose value trades accuracy for time). The other numbers of
:mod:`esmicp.globalreg` are fixed design values (a grid's resolution, a cap on the work of one
stage) or derived from these. ``register(..., config=SearchConfig(...))`` runs the search with
other values; the default is :data:`DEFAULT`.

Each value was chosen on a development set and confirmed on another: the data sets, the values
and the pages with the figures are in ``docs/design.md``, "Tuned values"
(``docs/measured-global.md`` holds most figures).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field

from ..core.config import Config, count, fraction, number, numbers_tuple, part, span
from ..errors import InvalidInputError


@dataclass(frozen=True)
class RotationSearchConfig(Config):
    """Values of the rotation search (:func:`esmicp.globalreg.rotation_search.rotation_search`:
    batched ESM from many starting rotations).

    Attributes
    ----------
    rotations : int
        Starting rotations, spread over SO(3) (count). More reach more starts within ESM's basin
        (64: at most 58 degrees from any rotation) at a linear cost.
    points : int
        Source points (a random subsample) refined from every starting rotation (count).
    iterations : int
        ESM iterations from each starting rotation (count).
    target_points : int
        Target points (a random subsample) indexed for the rotation search and the verification
        (count).
    grid_cell_diagonals : float
        Cell edge of the rotation search's nearest-neighbour grid
        (:class:`~esmicp.core.nearest_grid.NearestGrid`), in target bounding-box diagonals (gain).
    grid_margin_diagonals : float
        Margin of that grid around the target, in target bounding-box diagonals (gain).

    References
    ----------
    ``rotations``, ``points``, ``iterations``: the object protocols of ``docs/measured-global.md``.
    """

    rotations: int = count(64)
    points: int = count(200)
    iterations: int = count(10)
    target_points: int = count(3000)
    grid_cell_diagonals: float = number(1.0 / 40.0, above=0.0)
    grid_margin_diagonals: float = number(0.25, least=0.0)


@dataclass(frozen=True)
class VerificationConfig(Config):
    """Values of the verification that scores every candidate pose the same way and decides
    between them (:mod:`esmicp.globalreg.search`).

    Attributes
    ----------
    candidates : int
        Distinct rotation-search poses passed on to the verification (count).
    score_width_spacings : float
        Width of the verifier's Gaussian overlap score, and floor of its annealed sigma, in target
        point spacings (gain).
    rounds : tuple of (int, int, int)
        Rounds of successive halving: ``(source points, ESM iterations at the finest sigma,
        distinct poses kept)`` (counts). Every candidate runs the first round; the survivors the next.
    distinct_rotation_deg : float
        Two poses are distinct when their rotations differ by more than this (degrees): the
        runner-up of an ambiguous search, two feature hypotheses, two scan-strategy poses.
    max_contenders : int
        Poses (at most) returned as contenders for the full-resolution decision (count).
    decide_points : int
        Points (at most, of each cloud) of the full-resolution decision between contenders that
        scored alike on the subsample (count).
    decide_iterations : int
        ESM iterations of that decision (count).
    decide_sigma_spacings : float
        Fixed sigma of that decision, in target point spacings (gain; finer than the
        verification's, so that near-truth poses converge).
    settle_points : int
        Source points (evenly strided) refined when a rotation-search pose is settled (count).
    settle_iterations : int
        ESM iterations of that settling (count).
    cover_points : int
        Target points (evenly strided, at most) checked for the full cover of
        :attr:`SearchConfig.full_cover` (count).
    twin_angles_deg : tuple of float
        Twins of the rotation search's best pose join the candidates when ``"auto"`` is not
        confident: the pose turned by each of these angles (degrees) about each principal axis of
        the target, through the target's centroid. A near-symmetric object under heavy noise
        otherwise ends on a symmetric twin of the truth that neither strategy proposes.
    graph_queries_per_point : float
        A batched ESM of the verification or the decision builds the neighbour graph of its target
        (:class:`~esmicp.globalreg.rotation_search.NeighbourGraph`) only when it makes at least
        this many nearest-neighbour queries per target point (poses x source points x iterations
        over target points; ratio); fewer are answered by the tree alone, from their warm starts,
        with the same neighbours: only the time changes.
    support_confidence : float
        When the best pose of every scan-strategy search at the standard voxel has an overlap
        confidence of at most this (0-1; the default 0: no pose made the clouds coincide at all),
        the pair shows no support there: the searches at other voxels
        (:attr:`ScanStrategyConfig.last_keypoints`) are skipped and the result carries the doubt
        "no support" (never trusted). Not applied when either cloud carries scattered points
        (their keypoints' overlap confidence is blind to a right pose) or when no other voxel is
        left to search; negative: never.
    scattered_scan_searches : int
        At most this many searches of the scan strategy in one ``"auto"`` search (count) when
        either cloud carries scattered points (:func:`~esmicp.trust.judge.scattered_keypoints`,
        read from the clouds alone): its searches judge their poses on keypoints that keep the
        points scattered a few voxels off the surface, so none becomes confident and every search
        would run.

    References
    ----------
    ``rounds``, ``decide_*``, ``settle_*`` and ``twin_angles_deg``: the object protocols of
    ``docs/measured-global.md``; ``distinct_rotation_deg``: its symmetric shapes;
    ``graph_queries_per_point``: the break-even between the graph's build time per target point
    and the time it spares per query it answers (``docs/design.md``, "Tuned values"; the poses
    are the same either way); ``support_confidence``: the confidence's floor, not tuned: pairs the
    searches at other voxels brought to a right pose had reached 0.17-0.45 at the standard voxel,
    and no bar above the floor kept every one of them while stopping pairs that share nothing
    (``docs/design.md``, "Tuned values"); ``scattered_scan_searches``: whole objects
    under 60% outliers, one search as good as two on the development and the confirmation
    objects (``docs/measured-global.md``, "Clouds carrying scattered points").
    """

    candidates: int = count(16)
    score_width_spacings: float = number(2.0, above=0.0)
    rounds: tuple = numbers_tuple(((200, 6, 6), (400, 12, 4)))
    distinct_rotation_deg: float = number(10.0, least=0.0, most=180.0)
    max_contenders: int = count(3)
    decide_points: int = count(2000)
    decide_iterations: int = count(10)
    decide_sigma_spacings: float = number(1.0, above=0.0)
    settle_points: int = count(400)
    settle_iterations: int = count(12)
    cover_points: int = count(1000)
    twin_angles_deg: tuple = numbers_tuple((180.0,))
    graph_queries_per_point: float = number(1.0, least=0.0)
    support_confidence: float = number(0.0, least=-1.0, most=1.0)
    scattered_scan_searches: int = count(1)


@dataclass(frozen=True)
class KeypointConfig(Config):
    """The keypoints' values (:class:`esmicp.core.keypoints.Keypoints`: both clouds voxel-downsampled
    at one voxel the data choose), which the scan strategy and the overlap confidence
    (:func:`esmicp.trust.confidence.overlap_confidence`) share. Lengths are gains times the keypoint
    voxel, or the target's median point spacing.

    Attributes
    ----------
    min_voxel_spacings : float
        The keypoint voxel is at least this many target point spacings (gain).
    coincide_voxels : float
        A keypoint coincides with the other cloud within this many keypoint voxels of one of its
        keypoints (gain): the verification's overlap score and the overlap confidence's sharpness
        count those.
    normal_radius_voxels : float
        Radius of a keypoint normal's PCA, in keypoint voxels (gain): the keypoints' FPFH and the
        target normals of the slide votes (:func:`~esmicp.globalreg.scan.rank_poses`).
    slide_normal_neighbours : int
        Neighbours (at most) of each target normal of the slide votes (count).
    """

    min_voxel_spacings: float = number(1.5, above=0.0)
    coincide_voxels: float = number(1.0, above=0.0)
    normal_radius_voxels: float = number(3.0, above=0.0)
    slide_normal_neighbours: int = count(20, least=3)


@dataclass(frozen=True)
class ScanStrategyConfig(Config):
    """Values of the scan strategy (:mod:`esmicp.globalreg.scan`: FPFH correspondences of voxel
    keypoints pruned by second-order spatial compatibility, verified on the overlap). Lengths are
    gains times the keypoint voxel (:attr:`SearchConfig.keypoints`).

    Attributes
    ----------
    last_keypoints : tuple of int
        When no standard search is confident, searches at other voxels, in turn while none is:
        where the target has about each of these many occupied voxels (counts). A finer voxel puts
        more keypoints in a small overlap, a coarser one gives descriptors of a larger part of the
        scene.
    fpfh_radius_keypoint_voxels : float
        FPFH radius of the keypoints, in keypoint voxels (gain).
    filter_radius_voxels : float
        Radius of the isolated-keypoint filter, in keypoint voxels (gain).
    normal_neighbours : int
        Neighbours (at most) of a keypoint normal's PCA (count).
    min_keypoints : int
        Below this many occupied voxels in either cloud the strategy proposes nothing (count).
    max_correspondences : int
        Correspondences kept for pruning, best Lowe ratio first (count).
    compatibility_voxels : float
        Two correspondences are compatible when their lengths agree to within this many keypoint
        voxels (gain).
    seeds : int
        Seed correspondences of the pruning (count): many, spread in both clouds, since at a small
        overlap the few true correspondences rank far down the leading eigenvector.
    seed_spread_voxels : float
        A seed is skipped when both its keypoints lie within this many keypoint voxels of a better
        seed's (gain).
    group_size : int
        Size of the group each seed grows (count).
    leading_tolerance : float
        The power iteration of the compatibility matrix's leading eigenvector stops once a step
        moves no entry by more than this (unit-norm vector entries).
    hypotheses : int
        Distinct hypotheses verified on the overlap (count).
    distinct_voxels : float
        Two hypotheses are distinct when their translations differ by more than this many
        keypoint voxels (gain; or their rotations by
        :attr:`VerificationConfig.distinct_rotation_deg`).
    contender_voxels : float
        Two verified poses are different ones (contenders, which make a result ambiguous) from
        this many keypoint voxels apart on (gain; closer ones end in the same place after
        refinement).
    icp_steps : int
        ICP steps on the keypoints before verification, at most (count).
    icp_voxels : float
        ICP pairs lie within this many keypoint voxels (gain).
    icp_settled_voxels : float
        A pose's ICP stops once a step moves its keypoints by less than this many keypoint voxels
        (gain).
    icp_points : int
        The ICP runs on at most this many source keypoints, evenly strided (count).
    tie_ratio : float
        A pose of about the leader's rotation scoring at least this fraction of its overlap score
        challenges it on the slide-constraining inliers (0-1).
    keypoint : KeypointConfig
        The keypoints' own values (:class:`KeypointConfig`): the voxel's floor, when two
        coincide, their normals.

    References
    ----------
    ``last_keypoints``, ``seeds``, ``seed_spread_voxels`` and ``icp_steps``: scan crops at
    15-25% overlap (``docs/scans-partial-overlap.md``; ``docs/design.md``, "Tuned values").
    """

    last_keypoints: tuple = numbers_tuple((10000, 2500))
    fpfh_radius_keypoint_voxels: float = number(6.0, above=0.0)
    filter_radius_voxels: float = number(2.0, above=0.0)
    normal_neighbours: int = count(60, least=3)
    min_keypoints: int = count(10)
    max_correspondences: int = count(2500)
    compatibility_voxels: float = number(1.5, above=0.0)
    seeds: int = count(512)
    seed_spread_voxels: float = number(3.0, least=0.0)
    group_size: int = count(30)
    leading_tolerance: float = number(1e-6, above=0.0)
    hypotheses: int = count(6)
    distinct_voxels: float = number(3.0, least=0.0)
    contender_voxels: float = number(6.0, least=0.0)
    icp_steps: int = count(30, least=0)
    icp_voxels: float = number(2.0, above=0.0)
    icp_settled_voxels: float = number(0.05, least=0.0)
    icp_points: int = count(1500)
    tie_ratio: float = fraction(0.5)
    keypoint: KeypointConfig = part(KeypointConfig)


@dataclass(frozen=True)
class FeatureMatchingConfig(Config):
    """Values of the feature strategy (:func:`esmicp.globalreg.feature_matching.feature_hypotheses`:
    FPFH correspondences, RANSAC or cliques). Lengths are gains times the feature voxel.

    Attributes
    ----------
    voxel_diagonals : float
        The feature voxel, in target bounding-box diagonals (gain).
    normal_radius_voxels : float
        Radius of the PCA normals, in feature voxels (gain).
    fpfh_radius_voxels : float
        FPFH radius, in feature voxels (gain).
    filter_radius_voxels : float
        Radius of the isolated-point filter, in feature voxels (gain).
    normal_neighbours : int
        Neighbours (at most) of a normal's PCA (count).
    min_mutual_matches : int
        Below this many mutual matches, the matching falls back to one-way matches (count).
    edge_tolerance : float
        Relative tolerance of the edge-length consistency check on RANSAC samples (ratio).
    first_batch : int
        Samples of the first RANSAC batch (count; later ones double, up to ``feature_hypotheses``'s
        ``batch``): an easy problem stops after it.
    distinct_translation_voxels : float
        Two hypotheses are distinct when their translations differ by more than this many feature
        voxels (gain; or their rotations by :attr:`VerificationConfig.distinct_rotation_deg`).

    References
    ----------
    The object protocols of ``docs/measured-global.md``.
    """

    voxel_diagonals: float = number(1.0 / 40.0, above=0.0)
    normal_radius_voxels: float = number(4.0, above=0.0)
    fpfh_radius_voxels: float = number(7.0, above=0.0)
    filter_radius_voxels: float = number(2.0, above=0.0)
    normal_neighbours: int = count(60, least=3)
    min_mutual_matches: int = count(30)
    edge_tolerance: float = number(0.1, least=0.0)
    first_batch: int = count(256)
    distinct_translation_voxels: float = number(2.0, least=0.0)


@dataclass(frozen=True)
class SearchConfig(Config):
    """Tuned values of the global search (:func:`esmicp.globalreg.search.global_estimate`).

    Attributes
    ----------
    ambiguity_ratio : float
        A clearly different pose (rotation more than
        :attr:`VerificationConfig.distinct_rotation_deg` away) scoring at least this fraction of
        the best makes the result ambiguous (0-1): a symmetric object's twin poses score alike.
    decide_ratio : float
        The full-resolution decision (both ways, up to 2,000 points of each cloud) runs when the
        runner-up scores at least this fraction of the best on the subsample (0-1): the one early
        exit of the verification, for cost.
    confident_score : float
        ``"auto"`` stops after the rotation search when its best pose puts at least this soft
        fraction of the source on the target (0-1; above 1: never, either way) and is
        unambiguous and confident on the overlap or covers the target. When either cloud carries
        scattered points, which never lie on the other cloud, an unambiguous pose confident on the
        overlap (measured on the surface) stops it whatever its score, when it stays unambiguous
        once its twins are verified beside it.
    full_cover : float
        Such a pose is also final when at least this fraction (0-1) of the target's points lie
        within two score widths of the placed source: the full overlap the score assumes holds
        (``docs/design.md``, "Tuned values").
    settle_from : float
        A rotation-search pose scoring at least this fraction of ``confident_score`` is refined a
        little further ("settled") and final when it then reaches ``confident_score`` and
        ``confident`` on the overlap: a right pose can end a little short of the bar.
    scan_margin : float
        The scan strategy's confident pose wins before the feature strategy runs when its overlap
        score is above this many times the rotation search's pose's (ratio, >= 1).
    sharper_score_ratio : float
        ... or when it overlaps at least this fraction as much (0-1) and its overlap confidence is
        higher by ``sharper_by``: a pose slid along a wall can overlap a little more, while only
        the true one makes the overlap coincide.
    sharper_by : float
        See ``sharper_score_ratio`` (confidence units, 0-1).
    sharper_than_chosen : float
        A chosen pose not ``confident`` on the overlap gives way to the scan strategy's pose most
        confident there when that is higher by at least this much (confidence units, 0-1); the
        result is then ambiguous: a cut object's flip can lie on more of the other part than the
        truth does.
    scan_candidates : int
        The scan strategy's best poses (count) that join the verification when its best is not
        ``confident``.
    confident : float
        The search's own bar on the overlap confidence (0-1): a scan search reaching it ends the
        scan searches, and a pose reaching it may win over the other strategies'. Below
        :attr:`~esmicp.trust.policy.TrustPolicy.trusted`, the bar a result must reach to be trusted.
    scan_searches : int or None
        At most this many searches of the scan strategy in one ``"auto"`` search (count; None:
        each setting and voxel of :func:`~esmicp.globalreg.scan.scan_estimate_until_confident`
        in turn until one is confident, which a pair that cannot be registered runs to the end).
        A caller with a second chance at a pair (the merge searches an untrusted pair again on
        other points) can stop sooner: :attr:`esmicp.config.MergeConfig.pair_scan_searches`.
    keypoints : int
        Occupied voxels of the target the scan strategy's keypoint voxel aims at (count): the
        one length scale of the scan strategy and of the confidence.
    sharpness_range : tuple of float
        The overlap confidence's sharpness (of the keypoints within 3 voxels of the other cloud,
        the fraction within 1 voxel, the worse direction) mapped linearly from this range onto
        0-1 (dimensionless: fractions of keypoints).
    spread_range : tuple of float
        The middle eigenvalue of the coincident part's normal moments (0 for one plane) mapped
        from this range onto 0-1 (the confidence is the smaller term) when less than half of
        either cloud coincides (dimensionless, 0-1/3, of unit normals; the range separates
        wrong flat-on-flat poses from right ones, ``docs/design.md``, "Tuned values").
    third_range : tuple of float
        The smallest eigenvalue of the same (0 for a floor and one wall, which leave a slide free)
        mapped from this range onto 0-1 (dimensionless; the range separates wrong poses from
        ground truths, ``docs/design.md``, "Tuned values").

    References
    ----------
    ``ambiguity_ratio``, ``confident_score``, ``settle_from``, ``sharper_than_chosen``,
    ``full_cover`` and the confidence's ranges: the data they were chosen and confirmed on and the
    figures, ``docs/design.md``, "Tuned values"; the search's success and cost,
    ``docs/measured-global.md``.
    """

    ambiguity_ratio: float = fraction(0.97)
    decide_ratio: float = fraction(0.9)
    confident_score: float = number(0.6, least=0.0)  # above 1: never
    full_cover: float = fraction(0.99)
    settle_from: float = number(0.9, least=0.0)
    scan_margin: float = number(1.1, above=0.0)
    sharper_score_ratio: float = fraction(0.8)
    sharper_by: float = number(0.2, least=0.0)
    sharper_than_chosen: float = number(0.1, least=0.0)
    scan_candidates: int = count(3, least=0)
    confident: float = fraction(0.5)
    scan_searches: int | None = None
    keypoints: int = count(5000)
    sharpness_range: tuple[float, float] = span((0.5, 0.8))
    spread_range: tuple[float, float] = span((0.05, 0.15))
    third_range: tuple[float, float] = span((0.003, 0.009))
    rotation: RotationSearchConfig = part(RotationSearchConfig)
    verification: VerificationConfig = part(VerificationConfig)
    scan: ScanStrategyConfig = part(ScanStrategyConfig)
    features: FeatureMatchingConfig = part(FeatureMatchingConfig)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.scan_searches is not None and (isinstance(self.scan_searches, bool) or not isinstance(
                self.scan_searches, numbers.Integral) or self.scan_searches < 1):
            raise InvalidInputError(f"SearchConfig.scan_searches: expected None or a whole number >= 1, "
                                    f"got {self.scan_searches!r}")


#: The configuration :func:`esmicp.register` uses unless given another.
DEFAULT = SearchConfig()


def as_config(config) -> SearchConfig:
    """``config`` checked: None gives :data:`DEFAULT`; a :class:`SearchConfig` is kept; a dict is
    read by :meth:`SearchConfig.from_dict`; anything else raises :class:`InvalidInputError`."""
    if config is None:
        return DEFAULT
    return SearchConfig.of(config)
