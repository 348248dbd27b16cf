"""How a pose is judged: the trust bars and the values of the measures behind them, in one frozen
object.

:class:`TrustPolicy` holds the bar a registration's overlap confidence must reach, the free-space
test's bars (:mod:`.free_space`), the overlap confidence's (:mod:`.confidence`; its ranges are
the search's, :class:`esmicp.globalreg.config.SearchConfig`) and the pose covariance's values
(:mod:`.uncertainty`).
``register(..., config=RegistrationConfig(trust=TrustPolicy(...)))`` judges with other values, and
the result keeps the policy it was judged by (:attr:`esmicp.RegistrationResult.policy`); a merge
judges its pairs and its scans with ``MergeConfig.registration.trust``
(:class:`esmicp.config.MergeConfig`). The default is :data:`DEFAULT_POLICY`.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..core.config import Config, count, fraction, number


@dataclass(frozen=True)
class TrustPolicy(Config):
    """The bars a pose must pass to be trusted, and the values of the measures behind them.

    Lengths are gains times a length the data give: a registration's inlier distance
    (:attr:`esmicp.RegistrationResult.inlier_distance`: 3 target point spacings by default) or
    the target's point spacing.

    Attributes
    ----------
    min_coincident : int
        The overlap confidence is 0 when fewer than this many keypoints of either cloud coincide
        with the other: too little evidence to certify a pose (count).
    overlap_voxels : float
        The overlap confidence's overlap: the keypoints within this many keypoint voxels of the
        other cloud (gain; of them, those within one voxel coincide).
    isolated_voxels : float
        A keypoint is isolated when no keypoint of its own cloud lies within this many keypoint
        voxels (gain; :func:`esmicp.trust.confidence.surface_part`).
    max_scattered : float
        A cloud carries scattered points when more than this share (0-1) of its keypoints are
        isolated; the overlap confidence then measures it on its surface keypoints only.
    scatter_points : int
        Whether a registered pair's clouds carry scattered points is read first on at most this
        many evenly strided points of each (count; :func:`esmicp.trust.judge.scattered_keypoints`).
    surface_neighbours : int
        A keypoint's own nearest keypoints (at most) whose plane says whether it lies on its
        cloud's surface (count) ...
    surface_radius_voxels : float
        ... within this many keypoint voxels (gain).
    surface_band_voxels : float
        A keypoint lies on its cloud's surface when within this many keypoint voxels of that
        plane (gain); the plane is refitted on the neighbours within as far of it ...
    surface_fits : int
        ... this many times (count) ...
    surface_min_neighbours : int
        ... and at least this many of them must lie in the band (count).
    spread_below : float
        The coincident part's normals are asked to hold the pose only when less than this share
        (0-1) of either cloud's keypoints coincides; more is held by the clouds' whole shape.
    spread_points : int
        Coincident keypoints (at most, evenly strided) whose normals measure that spread (count).
    spread_normal_neighbours : int
        Nearest keypoints (at most) of each of those normals' PCA (count).
    spread_normal_radius_voxels : float
        ... within this many keypoint voxels (gain).
    trusted : float
        The overlap confidence a result must reach to be trusted (0-1; above 1: nothing is); above
        the global search's own bar (:attr:`esmicp.globalreg.config.SearchConfig.confident`),
        where the search stops.
    max_free_space_pair : float
        One registered pair of range images (``register(..., range_images=True)``) is not trusted
        when its pose puts more than this fraction (0-1) of either cloud in the space the other's
        sensor saw empty.
    max_free_space : float
        The same bar for two scans a merge placed (fraction, 0-1), at poses a whole set of scans
        agreed on: above it, the two scans' poses conflict.
    free_space_tolerance_inliers : float
        A point counts as in free space when it lies more than this many inlier distances in front
        of the surface the other sensor saw in its direction (gain).
    free_space_points : int
        Points of each cloud the free-space test uses (count).
    free_space_min_seen : int
        A pair is judged only when at least this many points of one cloud lie in the other's field
        of view (count).
    seen_radius_spacings : float
        A direction counts as near one of a scan's own within this many of the scan's median
        angular spacings (the angle to a direction's nearest; gain).
    seen_directions : int
        A point lies in a scan's field of view when at least this many of the scan's directions
        are near its own (count): just past the border of the field of view only one or two are,
        and the surface there is extrapolated, not seen.
    max_sampling_slope : float
        A scan is a range image seen from its origin only when the upper 95% bound of the log-log
        slope of its points' angular spacing against ``sqrt(cos(incidence)) / range`` is below this
        (an exponent: 0 for a sensor's grid, 1 for points spread evenly over the surface).
    max_hidden : float
        ... and at most this fraction (0-1) of its points lie hidden behind another of its points
        seen from the origin.
    hidden_pixel : float
        A point is hidden behind another when its direction lies within this fraction of the
        other's angular spacing (``spacing_directions``) of the other's direction (ratio) ...
    hidden_depth_spacings : float
        ... and it lies farther from the origin by more than this many local point spacings
        (``spacing_points``, the larger of the two's; gain).
    hidden_directions : int
        The nearest directions of each point among which the range-image test looks for one it
        lies hidden behind (count).
    spacing_directions : int
        A point's angular spacing is the mean angle to this many of its nearest directions (count).
    spacing_points : int
        A point's local spacing is the mean distance to this many of its nearest points (count).
    min_incidence_cosine : float
        Points whose normal makes a cosine below this with their direction from the origin (seen
        edge-on, where the normal says little of the sampling) are left out of the sampling
        slope (cosine, 0-1).
    sampling_normal_neighbours : int
        Nearest points of each normal whose incidence the range-image test reads (count).
    premise_min_points : int
        Fewer points than this are too few to judge a scan a range image (count; at least 17, the
        ``hidden_directions`` nearest directions the test reads by default and the point itself).
    min_angular_radius_deg : float
        A scan whose points lie within this angle of their mean direction (the median angle,
        degrees) is far from its origin for its size, as no sensor sees a scan: not a range image.
    cluster_spacings : float
        Side of the cubes whose pairs' residuals may be correlated in the cluster-robust pose
        covariance, in target point spacings (gain).
    min_clusters : int
        Fewest cubes the cluster-robust covariance is computed over: the cube is halved until
        there are this many (count).
    inflation : float
        The pose covariance is the cluster-robust sandwich times this factor (dimensionless): what
        the residuals do not show (an overlap border's pull beyond the one cluster it is counted
        as, a cloud's smooth distortions).
    border_spacings : float
        Pairs farther apart than this many target point spacings (where a partial overlap ends,
        a source point is paired with the target's border) pull the pose as one: the covariance
        counts their summed gradient as a single cluster (gain).
    degenerate_ratio : float
        A direction whose eigenvalue in the scaled point-to-plane Hessian is below this fraction
        of the largest is a degenerate direction, and the result is not trusted (ratio, 0-1).
    singular_ratio : float
        Eigenvalues of the scaled Hessian below this fraction of the largest are taken as zero:
        no information at all along them (ratio, 0-1).
    negligible_weight : float
        Pairs whose weight is below this fraction of the largest are left out of the covariance
        (ratio, 0-1).
    covariance_normals : int
        The covariance's Hessian comes from target normals at the matches of at most this many
        pairs, evenly strided (count); each cloud's noise is measured at as many of its points.
    covariance_normal_neighbours : int
        Nearest target points whose PCA gives the target normal at each of those matches (count;
        ``esm-plane``'s, :attr:`esmicp.methods.config.PlaneConfig.normal_neighbours`, by default).
    noise_neighbours : int
        A cloud's noise is the scatter of this many nearest points about their plane (count;
        fewer: less of the surface's curvature read as noise, a noisier reading).
    mirror_margin : float
        A pose is doubted as mirrored when the best mirror image of the source, fitted near it,
        coincides with the target on more than this share (0-1) of the overlapping keypoints
        beyond the pose's own share (:func:`esmicp.trust.handedness.handedness`).
    mirror_iterations : int
        Iterations of the trimmed ICP on keypoints that fits the pose and the best mirror image in
        that test (count) ...
    mirror_planes : int
        Mirror planes tried besides the three principal planes of the source keypoints: their
        normals spread evenly over a hemisphere (count).
    mirror_points : int
        ... on at most this many source keypoints, evenly strided (count).
    mirror_coarse_iterations : int
        Iterations that fit each mirror image before the best is chosen (count) ...
    mirror_coarse_points : int
        ... on at most this many source keypoints, evenly strided (count).
    mirror_candidates : int
        The mirror images that coincide best after that coarse fit and are fitted on (count).
    mirror_share_points : int
        The shares of coinciding keypoints that judge the pose against those mirror images are
        measured on at most this many keypoints of each cloud, evenly strided (count; the share's
        sampling scatter, about ``0.5 / sqrt(count)``, stays well inside ``mirror_margin``).

    References
    ----------
    Each value was chosen on one data set and confirmed on another; the data sets and the pages
    with the figures are in ``docs/design.md``, "Tuned values": ``min_coincident``
    (``docs/measured-global.md``, "Sparse clouds"), ``trusted`` (``docs/scans-partial-overlap.md``),
    ``max_free_space_pair`` and ``max_free_space`` (``docs/measured-global.md``), the range-image
    test's bars (``docs/merge.md``, step 5), ``cluster_spacings``, ``min_clusters``,
    ``border_spacings``, ``inflation`` and ``degenerate_ratio`` (``docs/uncertainty.md``), and
    ``mirror_*`` (a right pose's mirror image coincides on less of the overlap than the pose; a
    mirrored pose's on more).
    """

    min_coincident: int = count(60)
    overlap_voxels: float = number(3.0, above=0.0)
    isolated_voxels: float = number(2.0, above=0.0)
    max_scattered: float = fraction(0.06)
    scatter_points: int = count(25000)
    surface_neighbours: int = count(16, least=3)
    surface_radius_voxels: float = number(3.0, above=0.0)
    surface_band_voxels: float = number(0.5, above=0.0)
    surface_fits: int = count(3, least=0)
    surface_min_neighbours: int = count(6, least=3)
    spread_below: float = fraction(0.5)
    spread_points: int = count(500)
    spread_normal_neighbours: int = count(30, least=3)
    spread_normal_radius_voxels: float = number(3.0, above=0.0)
    trusted: float = number(0.55, least=0.0)
    max_free_space_pair: float = fraction(0.08)
    max_free_space: float = fraction(0.12)
    free_space_tolerance_inliers: float = number(3.0, least=0.0)
    free_space_points: int = count(4000)
    free_space_min_seen: int = count(200)
    seen_radius_spacings: float = number(2.0, above=0.0)
    seen_directions: int = count(4)
    max_sampling_slope: float = number(0.5)
    max_hidden: float = fraction(0.005)
    hidden_pixel: float = number(0.25, above=0.0)
    hidden_depth_spacings: float = number(2.0, least=0.0)
    hidden_directions: int = count(16)
    spacing_directions: int = count(4)
    spacing_points: int = count(4)
    min_incidence_cosine: float = fraction(0.05)
    sampling_normal_neighbours: int = count(12, least=3)
    premise_min_points: int = count(1000, least=17)
    min_angular_radius_deg: float = number(0.5, least=0.0, below=180.0)
    cluster_spacings: float = number(16.0, above=0.0)
    min_clusters: int = count(30)
    inflation: float = number(1.5, above=0.0)
    border_spacings: float = number(2.0, above=0.0)
    degenerate_ratio: float = fraction(0.01)
    singular_ratio: float = fraction(1e-9)
    negligible_weight: float = number(1e-6, least=0.0, below=1.0)
    covariance_normals: int = count(600)
    covariance_normal_neighbours: int = count(20, least=3)
    noise_neighbours: int = count(10, least=4)
    mirror_margin: float = fraction(0.1)
    mirror_iterations: int = count(30)
    mirror_planes: int = count(16)
    mirror_points: int = count(120)
    mirror_coarse_iterations: int = count(10)
    mirror_coarse_points: int = count(100)
    mirror_candidates: int = count(3)
    mirror_share_points: int = count(1000)


#: The policy every judgement uses unless given another.
DEFAULT_POLICY = TrustPolicy()
