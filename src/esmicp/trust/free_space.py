"""Free-space checks of a merge: does a placed scan lie where another scan saw empty space?

A depth-camera frame or a LiDAR scan in its sensor frame is a *range image from its origin*: along
each direction from the origin, the sensor saw the first surface, and the space in front of it is
empty. Two scans placed correctly never put a surface in the other's empty space (up to noise);
two scans placed 90 degrees apart do, over a large part of their overlap. This is the
visibility test of Huber and Hebert (2003) for multi-view surface matching, and it catches what
cycle checks cannot: wrong edges that agree with each other (two views of one repeated structure
matched to the same wrong place) pass every cycle, but not the free-space test.

Not every scan is a range image from its origin (a mesh, a scan stored in a shared frame): the
merge applies the check only when its kept edges pass it (:func:`applies`).
"""

from __future__ import annotations

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

#: The check applies when at least this fraction of the pairs joined by a kept edge pass it
#: (:func:`applies`): the kitchen walk's kept edges pass it but for the few wrong ones, the Newer
#: College scans' all pass, the Stanford bunny's raw scans (stored in a frame near the object,
#: not the scanner's) 56%.
APPLIES_FRACTION = 0.75

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


def applies(fractions: list[float]) -> bool:
    """Whether the scans are range images from their origins, as far as the merge can tell: at
    least :data:`APPLIES_FRACTION` of the pairs joined by a kept edge (right, as far as the cycles
    can tell) pass the free-space test. A mesh, or scans stored in a frame other than the sensor's,
    fail it; so does a merge most of whose kept edges are wrong, where the check is not needed to
    doubt it."""
    return len(fractions) >= 3 and float(np.mean(np.asarray(fractions) <= MAX_FREE_SPACE)) >= APPLIES_FRACTION
