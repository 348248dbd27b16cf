"""Free-space checks of a merge: does a placed scan lie where another scan saw empty space?

A depth-camera frame or a LiDAR scan in its sensor frame is a *range image from its origin*: along
each direction from the origin, the sensor saw the first surface, and the space in front of it is
empty. Two scans placed correctly never put a surface in the other's empty space (up to noise);
two scans placed 90 degrees apart do, over a large part of their overlap. This is the
visibility test of Huber and Hebert (2003) for multi-view surface matching, and it catches what
cycle checks cannot: wrong edges that agree with each other (two views of one repeated structure
matched to the same wrong place) pass every cycle, but not the free-space test.

Not every scan is a range image from its origin: a mesh, a map's crop, a scan stored in a frame
other than its sensor's (a turntable's, an object's, georeferenced coordinates). The premise is
established per scan from the scan's own points (:func:`range_image_test`), never from the poses
the check is to judge, or declared by the caller; the merge checks a pair only when both of its
scans are range images from their origins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: The largest fraction of one scan's points, among those in another's field of view, that may
#: lie in that scan's free space (more than :data:`TOLERANCE_INLIERS` inlier distances in front
#: of its surface) for the two scans' poses to be consistent. Chosen on the kitchen walk: in an
#: unordered merge, the pairs of placed scans placed consistently with the ground truth reach 0.065
#: among the pairs the merge checks (0.106 over all 3,653 pairs that see each other), the pairs
#: placed inconsistently (5 deg / 20 cm or more) start at 0.13. Confirmed on the Newer College
#: LiDAR scans: right poses at most 0.02, poses turned about 45 degrees at least 0.13.
MAX_FREE_SPACE = 0.12

#: The same bar for one registered pair (``register(..., range_images=True)``), judged at its own
#: refined pose rather than at poses a whole merge agreed on. Chosen on kitchen depth frames
#: 60-150 frames apart (``benchmarks/global_regression.py --sets kitchen-far``): right poses at
#: most 0.028, poses 0.8 m or more off 0.093-0.452. Confirmed on the kitchen pairs 10-50 frames
#: apart (``--sets kitchen``, all right: at most 0.068, on a pose 8 cm off) and on the pairs of
#: ``real_pairs/`` at their ground truth refined: Newer College and KITTI LiDAR 0.009-0.019, the
#: 3DMatch fragments (fused from many frames, so only nearly range images) 0.030-0.054; turned 10
#: degrees about the vertical, all 0.21 or more.
MAX_FREE_SPACE_PAIR = 0.08

#: How far in front of a surface a point must be to count as in free space, in inlier distances
#: of the merge (its scans' noise and spacing at the registration's resolution).
TOLERANCE_INLIERS = 3.0

#: Points of each scan used by the check (a random subset of the dense one).
CHECK_POINTS = 4000

#: A pair is judged only when at least this many points of one scan fall in the other's field of
#: view (fewer say nothing about free space).
MIN_SEEN = 200


class RangeView:
    """One scan seen from its origin: the unit direction and range of each point, and the angular
    radius within which a direction counts as seen (twice the median angular spacing)."""

    def __init__(self, points: np.ndarray):
        ranges = np.linalg.norm(points, axis=1)
        keep = ranges > 0
        self.ranges = ranges[keep]
        self.tree = cKDTree(points[keep] / self.ranges[:, None])
        nearest, _ = self.tree.query(self.tree.data, k=2)
        self.radius = 2.0 * float(np.median(nearest[:, 1]))

    def free_space_fraction(self, points: np.ndarray, tolerance: float) -> tuple[int, float]:
        """(points in this view's field of view, fraction of them in its free space): ``points``
        in this scan's frame; a point is in the field of view when four of this scan's directions
        lie within :attr:`radius` of its own, and in free space when it lies more than
        ``tolerance`` (cloud units) in front of the surfaces seen along those four."""
        ranges = np.linalg.norm(points, axis=1)
        directions = points / np.maximum(ranges, 1e-300)[:, None]
        distance, index = self.tree.query(directions, k=4, distance_upper_bound=self.radius)
        # seen: four of this scan's directions around it (just past the border of the field of
        # view only one or two are near, and the surface there is extrapolated, not seen)
        seen = np.isfinite(distance).all(axis=1)
        nearest_surface = np.where(seen[:, None], self.ranges[np.where(seen[:, None], index, 0)], np.inf).min(axis=1)
        count = int(seen.sum())
        if count == 0:
            return 0, 0.0
        return count, float(np.count_nonzero(seen & (ranges < nearest_surface - tolerance)) / count)


def pair_free_space(views: dict, points: dict, poses: dict, a: int, b: int, tolerance: float) -> float | None:
    """The larger free-space fraction of scans ``a`` and ``b`` at their world poses, each seen from
    the other's origin; None when neither sees at least :data:`MIN_SEEN` of the other's points."""
    T_a_b = np.linalg.inv(poses[a]) @ poses[b]
    T_b_a = np.linalg.inv(T_a_b)
    worst = None
    for viewer, other, T in ((a, b, T_a_b), (b, a, T_b_a)):
        moved = points[other] @ T[:3, :3].T + T[:3, 3]
        seen, fraction = views[viewer].free_space_fraction(moved, tolerance)
        if seen >= MIN_SEEN:
            worst = fraction if worst is None else max(worst, fraction)
    return worst


def pair_verdict(fraction: float | None) -> tuple[bool, str]:
    """``(failed, words)``: whether a pair's free-space fraction (:func:`free_space_fraction`, None:
    not judged) fails :data:`MAX_FREE_SPACE_PAIR`, and the test's outcome in words."""
    if fraction is None:
        return False, "free-space test: neither sensor sees enough of the other cloud to judge"
    if fraction > MAX_FREE_SPACE_PAIR:
        return True, (f"free-space test failed: {100 * fraction:.0f}% of a cloud lies where the other's sensor "
                      f"saw empty space (bar {100 * MAX_FREE_SPACE_PAIR:.0f}%)")
    return False, f"free-space test passed ({100 * fraction:.1f}% in the other's empty space)"


def free_space_fraction(target: np.ndarray, source: np.ndarray, T_target_source: np.ndarray,
                        tolerance: float) -> float | None:
    """The free-space test of one registered pair: the larger fraction of either cloud that
    ``T_target_source`` puts in the space the other's sensor saw empty (0-1), or None when neither
    sees at least :data:`MIN_SEEN` of the other's points.

    Both clouds must be range images in their sensor frames (depth-camera frames, LiDAR scans as
    recorded: the sensor at the origin). ``tolerance``: how far in front of a surface a point must
    lie to count (cloud units; the merge uses :data:`TOLERANCE_INLIERS` times the registration's
    ``inlier_distance``). Each cloud is reduced to :data:`CHECK_POINTS` evenly strided points.
    Above :data:`MAX_FREE_SPACE_PAIR` the pose contradicts what the sensors saw (:func:`pair_verdict`;
    ``register(..., range_images=True)`` applies it); the merge, judging poses a whole set of scans
    agreed on, uses :data:`MAX_FREE_SPACE`.
    """
    points = {}
    for key, cloud in ((0, target), (1, source)):
        cloud = np.asarray(cloud, dtype=np.float64)
        points[key] = cloud[np.linspace(0, len(cloud) - 1, min(len(cloud), CHECK_POINTS)).astype(np.intp)]
    views = {key: RangeView(cloud) for key, cloud in points.items()}
    poses = {0: np.eye(4), 1: np.asarray(T_target_source, dtype=np.float64)}
    return pair_free_space(views, points, poses, 0, 1, tolerance)


#: A scan is judged sampled by a sensor at its origin when the slope of its points' angular
#: spacing against ``sqrt(cos(incidence)) / range`` (log-log, seen from the origin; see
#: :func:`range_image_test`) is below this, with 95% confidence. The slope is 0 for a sensor's grid
#: (the sensor sets the angular spacing, whatever the surface) and 1 for points spread evenly over
#: the surface seen from anywhere else; this is the midpoint. Measured on 4,000-point subsets:
#: kitchen depth frames -0.11 to 0.07 and the bunny's raw scans moved into their scanner's frame
#: -0.04 to 0.13, against 0.98 to 1.10 for the same scans as stored (in a frame near the object);
#: confirmed on LiDAR scans as recorded (Newer College's feature points 0.24 to 0.32, KITTI
#: 0.05 to 0.06) and on ModelNet objects (0.34 to 1.15). Dimensionless (an exponent).
MAX_SAMPLING_SLOPE = 0.5

#: A scan is judged a range image from its origin only when at most this fraction of its points
#: lie hidden behind another of its points seen from the origin (:data:`HIDDEN_PIXEL`,
#: :data:`HIDDEN_DEPTH_SPACINGS`): a sensor sees one surface along each direction. Measured on
#: 4,000-point subsets: kitchen depth frames under 0.0001 and the bunny's scans in their scanner's
#: frame at most 0.0005 (mixed pixels at depth edges); confirmed on LiDAR scans as recorded (at
#: most 0.0013). Crops of a fused 3DMatch map and ModelNet objects seen from a random origin reach
#: 0.04; most of them, and scans in map coordinates (0.008 to 0.017), are above it. A fraction of
#: the scan's points.
MAX_HIDDEN = 0.005

#: A point is hidden behind another when its direction from the origin lies within this fraction
#: of the other's angular spacing (the mean angle to its 4 nearest directions) of the other's
#: direction: inside the other's pixel. A quarter keeps two samples of one sensor grid apart in
#: the subsets the check uses (up to a quarter of a sensor's points: their spacing is at least
#: twice the grid's); at a half, 0.6-1.4% of the points of LiDAR scans' 4,000-point subsets count
#: as hidden (neighbours across depth edges), against 0.2% of kitchen frames'.
HIDDEN_PIXEL = 0.25

#: ... and when it lies farther from the origin than the other by more than this many local point
#: spacings (the mean distance to the 4 nearest points, the larger of the two's): behind its
#: surface, not on it.
HIDDEN_DEPTH_SPACINGS = 2.0

#: Fewer points than this are too few to judge a scan a range image (:data:`MAX_HIDDEN` of them
#: is then 5 points; of 300 points filling a cube, one to six lie hidden).
PREMISE_MIN_POINTS = 1000

#: A scan whose points lie within this angle of their mean direction (the median angle, in
#: degrees) is far from its origin for its size, as no sensor sees a scan: its origin is not
#: where it was seen from (a scan in map coordinates, UTM: 1e-4 degrees). The bunny's scans in
#: their scanner's frame, 1.3 m from a 0.15 m object, 1.7 to 2.2 degrees; depth frames and LiDAR
#: scans tens of degrees.
MIN_ANGULAR_RADIUS_DEG = 0.5


@dataclass(frozen=True)
class RangeImageTest:
    """Whether one scan is a range image seen from its origin, as its points tell
    (:func:`range_image_test`): ``range_image``; ``sampling_slope`` and its standard error
    ``slope_error`` (see :data:`MAX_SAMPLING_SLOPE`; NaN when not measured); ``hidden``, the
    fraction of points hidden behind another (:data:`MAX_HIDDEN`; NaN when not measured); and
    ``reason`` in words when it is not."""

    range_image: bool
    sampling_slope: float
    slope_error: float
    hidden: float
    reason: str = ""


def range_image_test(points) -> RangeImageTest:
    """Is ``points`` (one scan, in its own frame) a range image seen from its frame's origin, as a
    depth-camera frame or a LiDAR scan in its sensor frame is? Judged from the points alone.

    A sensor at the origin samples directions on its own grid and sees one surface along each;
    two things follow, and both must hold:

    * *Sampling*: the angular spacing of the points (mean angle to the 4 nearest directions) does
      not depend on the surface. Points spread evenly over a surface (a mesh, a fused map, a scan
      moved into another frame seen from that frame's origin) have an angular spacing that grows
      as ``sqrt(cos(incidence)) / range`` (solid angle per point ``cos / (density range^2)``). The
      log-log slope of one against the other is 0 for a sensor's grid and 1 for even spreading;
      its upper 95% bound must be below :data:`MAX_SAMPLING_SLOPE`.
    * *One surface per direction*: at most :data:`MAX_HIDDEN` of the points lie behind another
      point (within :data:`HIDDEN_PIXEL` of its angular spacing in direction, more than
      :data:`HIDDEN_DEPTH_SPACINGS` local spacings farther).

    A scan moved a little off its sensor (a few percent of its range) still passes: seen from the
    moved origin it is nearly the same range image, and the free-space test of right poses stays
    low on it. A voxel-downsampled range image fails the sampling test (a voxel grid spreads points
    evenly): declare such scans range images when they are. Cost: a few KD-tree queries on the
    points (the merge passes a :data:`CHECK_POINTS` subset: about 25 ms a scan).
    """
    from ..core.features import estimate_normals

    nan = float("nan")
    p = np.asarray(points, dtype=np.float64)
    ranges = np.linalg.norm(p, axis=1)
    keep = np.isfinite(ranges) & (ranges > 0)
    p, ranges = p[keep], ranges[keep]
    if len(p) < PREMISE_MIN_POINTS:
        return RangeImageTest(False, nan, nan, nan, f"too few points to tell how it was sampled ({len(p)})")
    directions = p / ranges[:, None]
    mean = directions.mean(axis=0)
    mean /= max(float(np.linalg.norm(mean)), 1e-300)
    radius = float(np.degrees(np.median(np.arccos(np.clip(directions @ mean, -1.0, 1.0)))))
    if radius < MIN_ANGULAR_RADIUS_DEG:
        return RangeImageTest(False, nan, nan, nan,
                              f"its points lie within {radius:.2g} degrees of one direction from its origin: "
                              f"far from the origin for their size, not seen from it (bar {MIN_ANGULAR_RADIUS_DEG} deg)")
    k = min(16, len(p) - 1)
    angle, other = cKDTree(directions).query(directions, k=k + 1)
    angle, other = angle[:, 1:], other[:, 1:]
    spacing = angle[:, :4].mean(axis=1)  # angular spacing (rad)
    local = cKDTree(p).query(p, k=5)[0][:, 1:].mean(axis=1)  # point spacing (cloud units)
    behind = (angle < HIDDEN_PIXEL * spacing[other]) & (
        ranges[other] < ranges[:, None] - HIDDEN_DEPTH_SPACINGS * np.maximum(local[:, None], local[other]))
    hidden = float(np.mean(behind.any(axis=1)))

    normals = estimate_normals(p, k=12)
    cosine = np.abs(np.einsum("ij,ij->i", normals, directions))
    ok = (cosine > 0.05) & (spacing > 0)  # grazing: the normal says little
    x = 0.5 * np.log(cosine[ok]) - np.log(ranges[ok])
    y = np.log(spacing[ok])
    if ok.sum() < PREMISE_MIN_POINTS or not np.ptp(x) > 0:
        return RangeImageTest(False, nan, nan, hidden, "its points face the origin edge-on: sampling not measurable")
    xc, yc = x - x.mean(), y - y.mean()
    slope = float(xc @ yc / (xc @ xc))
    residual = yc - slope * xc
    error = float(np.sqrt(residual @ residual / (len(x) - 2) / (xc @ xc)))
    if slope + 1.645 * error > MAX_SAMPLING_SLOPE:
        return RangeImageTest(False, slope, error, hidden,
                              f"not sampled by a sensor at its origin: its angular spacing follows sqrt(cos)/range "
                              f"with slope {slope:.2f} +- {error:.2f} (a sensor's grid: 0, even spreading: 1; "
                              f"bar {MAX_SAMPLING_SLOPE})")
    if hidden > MAX_HIDDEN:
        return RangeImageTest(False, slope, error, hidden,
                              f"seen from its origin, {100 * hidden:.1f}% of its points lie behind its own surface "
                              f"(a sensor sees one surface per direction; bar {100 * MAX_HIDDEN:.1f}%)")
    return RangeImageTest(True, slope, error, hidden)
