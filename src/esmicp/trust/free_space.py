"""Free-space checks of a merge: does a placed scan lie where another scan saw empty space?

A depth-camera frame or a LiDAR scan in its sensor frame is a *range image from its origin*: along
each direction from the origin, the sensor saw the first surface, and the space in front of it is
empty. Two scans placed correctly never put a surface in the other's empty space (up to noise);
two scans placed 90 degrees apart do, over a large part of their overlap. This is the
visibility test of Huber and Hebert (2003) for multi-view surface matching, and it catches what
cycle checks cannot: wrong edges that agree with each other (two views of one repeated structure
matched to the same wrong place) pass every cycle, but not the free-space test.

Not every scan is a range image from its origin: a mesh, a map's crop, a scan stored in a frame
other than its sensor's (a rotary stage's, an object's, georeferenced coordinates). The premise is
established per scan from the scan's own points (:func:`range_image_test`), never from the poses
the check is to judge, or declared by the caller; the merge checks a pair only when both of its
scans are range images from their origins.

The bars and sizes are :class:`~esmicp.trust.policy.TrustPolicy`'s (``policy.<field>`` below).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.compiled_tree import CompiledTree
from ..core.sampling import evenly_strided

from .policy import DEFAULT_POLICY, TrustPolicy

class RangeView:
    """One scan seen from its origin: the unit direction and range of each point, and the angular
    radius within which a direction counts as near one of its own (``policy.seen_radius_spacings``
    median angular spacings)."""

    def __init__(self, points: np.ndarray, policy: TrustPolicy = DEFAULT_POLICY):
        ranges = np.linalg.norm(points, axis=1)
        keep = ranges > 0
        self.ranges = ranges[keep]
        from scipy.spatial import cKDTree

        self.tree = cKDTree(points[keep] / self.ranges[:, None])
        self.seen_directions = policy.seen_directions
        nearest, _ = self.tree.query(self.tree.data, k=2)
        self.radius = policy.seen_radius_spacings * float(np.median(nearest[:, 1]))

    def free_space_fraction(self, points: np.ndarray, tolerance: float) -> tuple[int, float]:
        """(points in this view's field of view, fraction of them in its free space): ``points``
        in this scan's frame; a point is in the field of view when :attr:`seen_directions` of this
        scan's directions lie within :attr:`radius` of its own, and in free space when it lies more
        than ``tolerance`` (cloud units) in front of the surfaces seen along those."""
        ranges = np.linalg.norm(points, axis=1)
        directions = points / np.maximum(ranges, 1e-300)[:, None]
        distance, index = self.tree.query(directions, k=self.seen_directions, distance_upper_bound=self.radius)
        seen = np.flatnonzero(np.isfinite(distance).all(axis=1))
        count = len(seen)
        if count == 0:
            return 0, 0.0
        nearest_surface = self.ranges[index[seen]].min(axis=1)  # along the seen points' directions only
        return count, float(np.count_nonzero(ranges[seen] < nearest_surface - tolerance) / count)


def pair_free_space(views: dict, points: dict, poses: dict, a: int, b: int, tolerance: float,
                    policy: TrustPolicy = DEFAULT_POLICY) -> float | None:
    """The larger free-space fraction of scans ``a`` and ``b`` at their world poses, each seen from
    the other's origin; None when neither sees at least ``policy.free_space_min_seen`` of the
    other's points."""
    T_a_b = np.linalg.inv(poses[a]) @ poses[b]
    T_b_a = np.linalg.inv(T_a_b)
    worst = None
    for viewer, other, T in ((a, b, T_a_b), (b, a, T_b_a)):
        moved = points[other] @ T[:3, :3].T + T[:3, 3]
        seen, fraction = views[viewer].free_space_fraction(moved, tolerance)
        if seen >= policy.free_space_min_seen:
            worst = fraction if worst is None else max(worst, fraction)
    return worst


def pair_verdict(fraction: float | None, policy: TrustPolicy = DEFAULT_POLICY) -> tuple[bool, str]:
    """``(failed, words)``: whether a pair's free-space fraction (:func:`free_space_fraction`, None:
    not judged) fails ``policy.max_free_space_pair``, and the test's outcome in words."""
    if fraction is None:
        return False, "free-space test: neither sensor sees enough of the other cloud to judge"
    if fraction > policy.max_free_space_pair:
        return True, (f"free-space test failed: {100 * fraction:.0f}% of a cloud lies where the other's sensor "
                      f"saw empty space (bar {100 * policy.max_free_space_pair:.0f}%)")
    return False, f"free-space test passed ({100 * fraction:.1f}% in the other's empty space)"


def free_space_fraction(target: np.ndarray, source: np.ndarray, T_target_source: np.ndarray,
                        tolerance: float, policy: TrustPolicy = DEFAULT_POLICY) -> float | None:
    """The free-space test of one registered pair: the larger fraction of either cloud that
    ``T_target_source`` puts in the space the other's sensor saw empty (0-1), or None when neither
    sees at least ``policy.free_space_min_seen`` of the other's points.

    Both clouds must be range images in their sensor frames (depth-camera frames, LiDAR scans as
    recorded: the sensor at the origin). ``tolerance``: how far in front of a surface a point must
    lie to count (cloud units; :func:`esmicp.register` uses ``policy.free_space_tolerance_inliers``
    times the registration's ``inlier_distance``). Each cloud is reduced to
    ``policy.free_space_points`` evenly strided points. Above ``policy.max_free_space_pair`` the
    pose contradicts what the sensors saw (:func:`pair_verdict`; ``register(..., range_images=True)``
    applies it); the merge, judging poses a whole set of scans agreed on, uses
    ``policy.max_free_space``.
    """
    points = {}
    for key, cloud in ((0, target), (1, source)):
        cloud = np.asarray(cloud, dtype=np.float64)
        points[key] = cloud[evenly_strided(len(cloud), policy.free_space_points)]
    views = {key: RangeView(cloud, policy) for key, cloud in points.items()}
    poses = {0: np.eye(4), 1: np.asarray(T_target_source, dtype=np.float64)}
    return pair_free_space(views, points, poses, 0, 1, tolerance, policy)


@dataclass(frozen=True)
class RangeImageTest:
    """Whether one scan is a range image seen from its origin, as its points tell
    (:func:`range_image_test`): ``range_image``; ``sampling_slope`` and its standard error
    ``slope_error`` (see :attr:`TrustPolicy.max_sampling_slope`; NaN when not measured); ``hidden``,
    the fraction of points hidden behind another (:attr:`TrustPolicy.max_hidden`; NaN when not
    measured: it is measured only on a scan the sampling test passes); and
    ``reason`` in words when it is not."""

    range_image: bool
    sampling_slope: float
    slope_error: float
    hidden: float
    reason: str = ""


def range_image_test(points, policy: TrustPolicy = DEFAULT_POLICY) -> RangeImageTest:
    """Is ``points`` (one scan, in its own frame) a range image seen from its frame's origin, as a
    depth-camera frame or a LiDAR scan in its sensor frame is? Judged from the points alone.

    A sensor at the origin samples directions on its own grid and sees one surface along each;
    two things follow, and both must hold:

    * *Sampling*: the angular spacing of the points (mean angle to the
      ``policy.spacing_directions`` nearest directions) does not depend on the surface. Points
      spread evenly over a surface (a mesh, a fused map, a scan moved into another frame seen from
      that frame's origin) have an angular spacing that grows as ``sqrt(cos(incidence)) / range``
      (solid angle per point ``cos / (density range^2)``). The log-log slope of one against the
      other is 0 for a sensor's grid and 1 for even spreading; its upper 95% bound must be below
      ``policy.max_sampling_slope``.
    * *One surface per direction*: at most ``policy.max_hidden`` of the points lie behind another
      point (within ``policy.hidden_pixel`` of its angular spacing in direction, more than
      ``policy.hidden_depth_spacings`` local spacings farther).

    Fewer than ``policy.premise_min_points`` points, or points within
    ``policy.min_angular_radius_deg`` of one direction, are not judged range images.

    A scan moved a little off its sensor (a few percent of its range) still passes: seen from the
    moved origin it is nearly the same range image, and the free-space test of right poses stays
    low on it. A voxel-downsampled range image fails the sampling test (a voxel grid spreads points
    evenly): declare such scans range images when they are. Cost: a few KD-tree queries on the
    points (the merge passes a ``policy.free_space_points`` subset: about 25 ms a scan); a scan
    the sampling test rejects skips the hidden test's, about half of that.
    """
    from ..core.features import estimate_normals

    nan = float("nan")
    p = np.asarray(points, dtype=np.float64)
    ranges = np.linalg.norm(p, axis=1)
    keep = np.isfinite(ranges) & (ranges > 0)
    p, ranges = p[keep], ranges[keep]
    if len(p) < policy.premise_min_points:
        return RangeImageTest(False, nan, nan, nan, f"too few points to tell how it was sampled ({len(p)})")
    directions = p / ranges[:, None]
    mean = directions.mean(axis=0)
    mean /= max(float(np.linalg.norm(mean)), 1e-300)
    radius = float(np.degrees(np.median(np.arccos(np.clip(directions @ mean, -1.0, 1.0)))))
    if radius < policy.min_angular_radius_deg:
        return RangeImageTest(False, nan, nan, nan,
                              f"its points lie within {radius:.2g} degrees of one direction from its origin: "
                              f"far from the origin for their size, not seen from it (bar {policy.min_angular_radius_deg:g} deg)")
    # The sampling first: a scan it rejects (as most non-range-images are) skips the hidden test's queries.
    directions_tree = CompiledTree(directions)
    k = min(policy.spacing_directions, len(p) - 1)
    spacing = directions_tree.query_k(directions, k + 1)[0][:, 1:].mean(axis=1)  # angular spacing (rad)
    points_tree = CompiledTree(p)
    normals = estimate_normals(p, k=policy.sampling_normal_neighbours, tree=points_tree)
    cosine = np.abs(np.einsum("ij,ij->i", normals, directions))
    ok = (cosine > policy.min_incidence_cosine) & (spacing > 0)
    x = 0.5 * np.log(cosine[ok]) - np.log(ranges[ok])
    y = np.log(spacing[ok])
    if ok.sum() < policy.premise_min_points or not np.ptp(x) > 0:
        return RangeImageTest(False, nan, nan, nan, "its points face the origin edge-on: sampling not measurable")
    xc, yc = x - x.mean(), y - y.mean()
    slope = float(xc @ yc / (xc @ xc))
    residual = yc - slope * xc
    error = float(np.sqrt(residual @ residual / (len(x) - 2) / (xc @ xc)))
    if slope + 1.645 * error > policy.max_sampling_slope:
        return RangeImageTest(False, slope, error, nan,
                              f"not sampled by a sensor at its origin: its angular spacing follows sqrt(cos)/range "
                              f"with slope {slope:.2f} +- {error:.2f} (a sensor's grid: 0, even spreading: 1; "
                              f"bar {policy.max_sampling_slope:g})")
    k = min(policy.hidden_directions, len(p) - 1)
    angle, other = directions_tree.query_k(directions, k + 1)
    angle, other = angle[:, 1:], other[:, 1:]
    local = points_tree.query_k(p, policy.spacing_points + 1)[0][:, 1:].mean(axis=1)  # point spacing (cloud units)
    behind = (angle < policy.hidden_pixel * spacing[other]) & (
        ranges[other] < ranges[:, None] - policy.hidden_depth_spacings * np.maximum(local[:, None], local[other]))
    hidden = float(np.mean(behind.any(axis=1)))
    if hidden > policy.max_hidden:
        return RangeImageTest(False, slope, error, hidden,
                              f"seen from its origin, {100 * hidden:.1f}% of its points lie behind its own surface "
                              f"(a sensor sees one surface per direction; bar {100 * policy.max_hidden:.1f}%)")
    return RangeImageTest(True, slope, error, hidden)
