"""Calibration of the pose covariance: NEES on whole objects, cut objects and real scan pairs.

Sets (each a choice half, on which ``TrustPolicy.border_spacings`` and ``TrustPolicy.inflation``
were chosen, and a confirmation half):

- ``objects``: a ModelNet40 shape (10,000 points) split into two disjoint random halves, each with
  its own Gaussian noise (0-1 point spacing), the source moved by a random pose (any rotation);
  the truth is exact. Choice: the 12 shapes of ``modelnet40``; confirmation: shapes of
  ``modelnet40_extra``.
- ``cut objects``: the same, each half then cut by its own random plane to 70% of its points
  (a partial overlap; the truth is exact).
- ``kitchen``: depth frames of the kitchen walk (``sequences/redkitchen_seq01_every10``), triplets
  ``a, b, c`` of frames 10-20 apart (pairs 10-40 apart), each pair registered; the truth is the
  dataset's KinectFusion tracking, good to about a centimetre. Choice: frames 0-490; confirmation:
  frames 500-990.
- ``bunny``: the Stanford bunny's raw scans, every pair overlapping by at least half, truth from
  ``bun.conf`` (confirmation only).
- ``lidar``: the LiDAR scans of ``real_pairs`` (confirmation only): the 5 Newer College scans, all
  10 pairs, truth from the dataset's pose graph (``graph.txt``), and their 10 cycles; the KITTI
  pair, truth from KITTI's published poses. Before any NEES, whether the truth can judge it:
  each pair registered from the truth itself by ``esm``, Open3D point-to-plane ICP and small_gicp
  GICP; the median of the three poses' offsets from the truth estimates the truth's own error,
  compared with the predicted standard deviation axis by axis (:data:`TRUTH_GOOD_RATIO`). The
  generated text goes between the page's ``<!-- covariance_nees lidar -->`` markers.

With ``e`` the left error vector of the result (``T_true = Exp(e) @ T_est``, rotation vector then
translation, target frame), ``NEES = e^T Sigma^-1 e``; a calibrated covariance gives a mean of 6
and 95% of trials below the chi-square(6) 95% bound (12.59). Only trusted results count (the
covariance describes the local optimum a trusted pose sits in).

A real truth has its own error, which the NEES charges to the covariance. Two ways around it:

- ``+ truth error``: the kitchen truth's error modelled as independent, ``KITCHEN_TRUTH_DEG`` and
  ``KITCHEN_TRUTH_M`` per axis, added to the predicted covariance;
- ``cycles`` (no truth at all): for three scans registered pairwise, ``T_ab @ T_bc`` against
  ``T_ac``, whose covariance is the sum of the three (first order). An error common to the three
  registrations (a scan's own distortion, seen by both of its pairs) cancels in a cycle, so the
  cycle NEES is a lower bound of the pairs' own.

Peers (``--peers``): Open3D point-to-plane ICP and its ``get_information_matrix_from_point_clouds``
(inverse taken as the covariance: as returned, i.e. unit noise, and scaled by the per-axis mean
square of the inlier distances, ``inlier_rmse^2 / 3``); small_gicp GICP and its Hessian ``H``
(``H^-1`` as returned, and scaled by the mean squared Mahalanobis residual ``2 error / (3 inliers
- 6)``), mapped from its right (source-frame) perturbation to the left one.

    python benchmarks/covariance_nees.py [--peers] [--plot docs/images/covariance_predicted_observed.png]
        [--doc docs/uncertainty.md]

Prints Markdown; ``--doc`` rewrites the generated part of that page (between its
``<!-- covariance_nees -->`` markers). Timings are ratios within the run (the covariance's cost
over the registration that computed it).
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

import esmicp  # noqa: E402
from esmicp.trust import uncertainty  # noqa: E402
from esmicp.core.correspondence import NearestNeighbors  # noqa: E402
from esmicp.core.procrustes import apply, skew  # noqa: E402
from esmicp.metrics import random_rotation  # noqa: E402

DATA = REPO.parent / "shared" / "data"
CHI2_6_95 = 12.591587243743977

#: The start is the truth moved by a random rotation of this many degrees and a translation of this
#: many target spacings (random directions).
START_DEGREES = 3.0
START_SPACINGS = 8.0
#: Share of its points each half of a cut object keeps (a random plane's side).
CUT_KEEP = 0.7
#: The kitchen truth's error per axis (degrees, metres): the sequence's README finds ICP from it
#: moving 0.2-0.5 degrees and 5-12 mm per pair, "good to about a centimetre".
KITCHEN_TRUTH_DEG = 0.3
KITCHEN_TRUTH_M = 0.01
#: Bunny scan pairs used: those of which at least this share of the source lies within 3 target
#: spacings of the target at the truth.
BUNNY_MIN_OVERLAP = 0.5
#: Markers of the generated part of the results page, and of its LiDAR part (``--sets lidar``).
DOC_BEGIN, DOC_END = "<!-- covariance_nees: begin -->", "<!-- covariance_nees: end -->"
LIDAR_BEGIN, LIDAR_END = "<!-- covariance_nees lidar: begin -->", "<!-- covariance_nees lidar: end -->"
#: A recorded truth can judge a covariance when its own error, estimated per axis, is at most this
#: many predicted standard deviations (root mean square over the six axes, median over the pairs):
#: an independent truth error of ``r`` standard deviations per axis adds about ``6 r^2`` to the
#: mean NEES, 1.5 of the 6 at 0.5.
TRUTH_GOOD_RATIO = 0.5
#: The ``lidar`` set draws its starts from its own stream (seed, this), so that it can run alone.
LIDAR_STREAM = 5


def spacing_of(points: np.ndarray) -> float:
    return NearestNeighbors(points, workers=1).spacing()


def random_pose(rng, degrees: float, distance: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = random_rotation(rng, degrees)
    direction = rng.normal(size=3)
    pose[:3, 3] = distance * direction / np.linalg.norm(direction)
    return pose


def _cut(points: np.ndarray, rng, keep: float) -> np.ndarray:
    normal = rng.normal(size=3)
    heights = (points - points.mean(axis=0)) @ (normal / np.linalg.norm(normal))
    return points[heights <= np.quantile(heights, keep)]


def object_trial(path: Path, rng: np.random.Generator, keep: float):
    """Two disjoint random halves of a ModelNet40 shape, each with its own Gaussian noise (0-1 point
    spacing), each cut to ``keep`` of its points by a random plane (1: whole), the source moved by
    a random pose. Returns ``(source, target, truth, fraction)``: the noise's standard deviation is
    ``fraction`` (uniform in 0-1) point spacings of the shape."""
    cloud = np.loadtxt(path, delimiter=",", usecols=(0, 1, 2))
    fraction = rng.uniform(0.0, 1.0)
    noise = fraction * spacing_of(cloud)
    order = rng.permutation(len(cloud))
    half = len(cloud) // 2
    source, target = cloud[order[:half]], cloud[order[half:2 * half]]
    source = source + rng.normal(0.0, noise, source.shape)
    target = target + rng.normal(0.0, noise, target.shape)
    if keep < 1.0:
        source, target = _cut(source, rng, keep), _cut(target, rng, keep)
    truth = random_pose(rng, 180.0, 1.0)
    return apply(np.linalg.inv(truth), source), target, truth, fraction


def shapes(folder: str, count: int | None, rng) -> list[Path]:
    paths = sorted((DATA / folder).glob("*/*.txt"))
    if count is not None and count < len(paths):
        paths = [paths[k] for k in sorted(rng.choice(len(paths), size=count, replace=False))]
    return paths


def kitchen_triplets(first: int, last: int, count: int, rng):
    """``count`` triplets of kept kitchen frames ``a, b, c`` (frame numbers in ``first..last``), b
    10 or 20 frames after a and c 10 or 20 after b: ``(names, {name: points}, {name: T_world})``."""
    from esmicp_lab.bench.sequences import read_frame, read_poses

    folder = DATA / "sequences" / "redkitchen_seq01_every10"
    poses = read_poses(folder)
    names = [name for name in sorted(poses) if first <= int(name.split("-")[-1]) <= last]
    for k in rng.choice(len(names) - 4, size=count, replace=False):
        b = k + int(rng.integers(1, 3))
        c = b + int(rng.integers(1, 3))
        triplet = (names[k], names[b], names[c])
        yield triplet, {name: read_frame(folder, name) for name in triplet}, {name: poses[name] for name in triplet}


def bunny_scans():
    """``({name: points}, {name: T_world}, [(target, source)])``: the bunny's scans and their
    pairs overlapping by at least ``BUNNY_MIN_OVERLAP`` at the truth."""
    from esmicp.io.stanford_conf import load_scans

    scans = load_scans(DATA / "bunny_scans")
    points = {name: value[0] for name, value in scans.items()}
    poses = {name: value[1] for name, value in scans.items()}
    pairs = []
    for a, b in itertools.combinations(scans, 2):
        index = NearestNeighbors(points[a], workers=1)
        distances, _ = index.query(apply(np.linalg.inv(poses[a]) @ poses[b], points[b][::10]))
        if np.mean(distances < 3 * index.spacing()) >= BUNNY_MIN_OVERLAP:
            pairs.append((a, b))
    return points, poses, pairs


def lidar_pairs():
    """``[(family, name, source, target, T_target_source, metres apart)]``: the 10 pairs of the 5
    Newer College scans (truth from ``graph.txt``: ``vK x y z qx qy qz qw`` per scan, world from
    scan), then the KITTI pair (its ``T_target_source.txt``); and the Newer College triplets."""
    from scipy.spatial.transform import Rotation

    from esmicp.io import read_points

    folder = DATA / "real_pairs" / "newer_college_01"
    world = {}
    for line in (folder / "graph.txt").read_text().splitlines():
        fields = line.split()
        if len(fields) == 8 and fields[0].startswith("v"):
            pose = np.eye(4)
            pose[:3, :3] = Rotation.from_quat([float(v) for v in fields[4:8]]).as_matrix()
            pose[:3, 3] = [float(v) for v in fields[1:4]]
            world[int(fields[0][1:])] = pose
    scans = {k: read_points(folder / f"planes_{10 * k:06d}.bin", bin_columns=3) for k in sorted(world)}
    pairs = []
    for a, b in itertools.combinations(sorted(world), 2):
        truth = np.linalg.inv(world[a]) @ world[b]
        pairs.append(("Newer College", (a, b), scans[b], scans[a], truth, float(np.linalg.norm(truth[:3, 3]))))
    kitti = DATA / "real_pairs" / "kitti_00"
    truth = np.loadtxt(kitti / "t0_s1" / "T_target_source.txt")
    pairs.append(("KITTI", (0, 1), read_points(kitti / "000001.bin", bin_columns=3),
                  read_points(kitti / "000000.bin", bin_columns=3), truth, float(np.linalg.norm(truth[:3, 3]))))
    return pairs, list(itertools.combinations(sorted(world), 3))


def truth_offset(source, target, truth, spacing) -> tuple[np.ndarray, np.ndarray]:
    """``(offset, standard deviations)``: the median, per axis, of the left errors of ``esm``,
    Open3D point-to-plane ICP and small_gicp GICP each started at ``truth`` (where the data put the
    pose, by three methods: the truth's own error plus the methods' shared one), and ``esm``'s
    predicted standard deviations there (rotation vector, radians; translation)."""
    result = esmicp.register(source, target, init=truth, workers=1)
    errors = [uncertainty.left_error(truth, result.transformation)]
    for peer in (run_open3d, run_small_gicp):
        estimate, _ = peer(source, target, truth, spacing)
        errors.append(uncertainty.left_error(truth, estimate))
    return np.median(np.array(errors), axis=0), np.sqrt(np.diag(result.covariance))


def lidar(table: Table, rng, peers: bool) -> str:
    """The ``lidar`` set: the truth check (a Markdown table and what it says), then each pair's
    NEES against the recorded truth and the Newer College cycles into ``table``."""
    pairs, triplets = lidar_pairs()
    lines = ["Is the recorded truth good enough to judge the covariance? Each pair registered from the truth "
             "itself by `esm`, Open3D point-to-plane ICP and small_gicp GICP; the median of their offsets from "
             "the truth (target frame) estimates the truth's own error, beside `esm`'s predicted standard "
             "deviation there; `ratio` is the root mean square over the six axes of offset / standard deviation "
             f"(a truth error of `r` standard deviations per axis adds about `6 r^2` to the mean NEES; good "
             f"enough: a median ratio up to {TRUTH_GOOD_RATIO:g}).", "",
             "| pair | apart (m) | truth offset, rotation (deg, x y z) | truth offset, translation (cm, x y z) | "
             "predicted sd, translation (cm, x y z) | ratio |", "|---|---:|---|---|---|---:|"]
    ratios, signs, runs = {}, {}, {}
    for family, (a, b), source, target, truth, apart in pairs:
        spacing = spacing_of(target)
        offset, deviation = truth_offset(source, target, truth, spacing)
        ratio = float(np.sqrt(np.mean((offset / deviation) ** 2)))
        ratios.setdefault(family, []).append(ratio)
        signs.setdefault(family, []).append(np.sign(offset[3:]))
        lines.append(f"| {family} {a}-{b} | {apart:.2f} | {' '.join(f'{v:+.3f}' for v in np.degrees(offset[:3]))} | "
                     f"{' '.join(f'{100 * v:+.1f}' for v in offset[3:])} | "
                     f"{' '.join(f'{100 * v:.1f}' for v in deviation[3:])} | {ratio:.2f} |")
        run = Run(source, target, truth, rng)
        table.count((f"LiDAR pairs ({family})", "confirmation"), run.trusted)
        if run.trusted:
            runs[(family, a, b)] = run
            score(table, f"LiDAR pairs ({family})", "confirmation", "recorded", run, peers)
    for a, b, c in triplets:
        keys = [("Newer College", *pair) for pair in ((a, b), (b, c), (a, c))]
        if all(key in runs for key in keys):
            error, covariance = cycle(*(runs[key] for key in keys))
            table.add(("LiDAR pairs (Newer College)", "confirmation", "cycles", "esmicp"), nees(error, covariance))
    lines.append("")
    for family, values in ratios.items():
        median = float(np.median(values))
        chosen = np.array(signs[family])
        same = np.maximum(np.sum(chosen > 0, axis=0), np.sum(chosen < 0, axis=0))
        verdict = "good enough" if median <= TRUTH_GOOD_RATIO else "not good enough"
        lines.append(f"- {family}: median ratio {median:.2f} over {len(values)} pair(s): {verdict}"
                     + (f"; the translation offsets share their sign on {', '.join(map(str, same))} of "
                        f"{len(values)} pairs (x, y, z)" if len(values) > 1 else "") + ".")
    return "\n".join(lines)


def nees(error: np.ndarray, covariance: np.ndarray | None) -> float:
    if covariance is None or not np.all(np.isfinite(covariance)):
        return math.nan
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    if values[0] <= 0:
        return math.inf
    projected = vectors.T @ error
    return float(np.sum(projected ** 2 / values))


def adjoint(pose: np.ndarray) -> np.ndarray:
    """The 6x6 ``A`` with ``pose @ Exp(delta) = Exp(A @ delta) @ pose`` (rotation vector, then
    translation): a perturbation of the factor right of ``pose``, seen on the left."""
    matrix = np.zeros((6, 6))
    rotation, translation = pose[:3, :3], pose[:3, 3]
    matrix[:3, :3] = rotation
    matrix[3:, 3:] = rotation
    matrix[3:, :3] = skew(translation) @ rotation
    return matrix


class _Timed:
    """``uncertainty.from_registration`` as :func:`esmicp.register` calls it, timed."""

    def __init__(self):
        self.inner, self.seconds = uncertainty.from_registration, 0.0

    def __call__(self, *args, **kwargs):
        began = time.perf_counter()
        try:
            return self.inner(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - began


class Run:
    """One registration from a perturbed start: the estimate, the covariance, the verdict."""

    def __init__(self, source, target, truth, rng):
        self.spacing = spacing_of(target)
        start = random_pose(rng, START_DEGREES, START_SPACINGS * self.spacing) @ truth
        timed = _Timed()
        uncertainty.from_registration = timed
        try:
            result = esmicp.register(source, target, init=start, workers=1)
        finally:
            uncertainty.from_registration = timed.inner
        self.source, self.target, self.truth, self.start = source, target, truth, start
        self.estimate, self.covariance, self.trusted = result.transformation, result.covariance, result.trusted
        self.share = timed.seconds / result.runtime_s
        self.error = uncertainty.left_error(truth, self.estimate)


def run_open3d(source, target, start, spacing):
    import open3d as o3d

    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    fine = 3.0 * spacing
    plane = reg.TransformationEstimationPointToPlane()
    coarse = reg.registration_icp(src, tgt, START_SPACINGS * 2 * spacing, start, plane,
                                  reg.ICPConvergenceCriteria(max_iteration=30))
    result = reg.registration_icp(src, tgt, fine, coarse.transformation, plane,
                                  reg.ICPConvergenceCriteria(max_iteration=50))
    information = reg.get_information_matrix_from_point_clouds(src, tgt, fine, result.transformation)
    raw = _inverse(np.asarray(information))
    scaled = None if raw is None else raw * max(result.inlier_rmse, 1e-12) ** 2 / 3.0
    return np.asarray(result.transformation), {"Open3D (as returned)": raw, "Open3D (x rmse^2/3)": scaled}


def run_small_gicp(source, target, start, spacing):
    import small_gicp

    kwargs = dict(registration_type="GICP", downsampling_resolution=spacing, num_threads=1, max_iterations=50)
    coarse = small_gicp.align(target, source, start, max_correspondence_distance=START_SPACINGS * 2 * spacing, **kwargs)
    result = small_gicp.align(target, source, coarse.T_target_source, max_correspondence_distance=3.0 * spacing,
                              **kwargs)
    estimate = np.asarray(result.T_target_source)
    right = _inverse(np.asarray(result.H))
    if right is None:
        return estimate, {"small_gicp H^-1 (as returned)": None, "small_gicp H^-1 (x MSE)": None}
    adjoint = np.zeros((6, 6))
    rotation, translation = estimate[:3, :3], estimate[:3, 3]
    adjoint[:3, :3] = rotation
    adjoint[3:, 3:] = rotation
    adjoint[3:, :3] = skew(translation) @ rotation
    left = adjoint @ right @ adjoint.T
    mse = 2.0 * result.error / max(3 * result.num_inliers - 6, 1)
    return estimate, {"small_gicp H^-1 (as returned)": left, "small_gicp H^-1 (x MSE)": left * mse}


def _inverse(matrix):
    try:
        inverse = np.linalg.inv(matrix)
    except np.linalg.LinAlgError:
        return None
    return inverse if np.all(np.isfinite(inverse)) else None


def cycle(ab: Run, bc: Run, ac: Run) -> tuple[np.ndarray, np.ndarray]:
    """``(error, covariance)`` of ``T_ab @ T_bc`` against ``T_ac`` (left error, frame a)."""
    error = uncertainty.left_error(ab.estimate @ bc.estimate, ac.estimate)
    moved = adjoint(ab.estimate)
    return error, ab.covariance + moved @ bc.covariance @ moved.T + ac.covariance


class Table:
    """NEES values per ``(set, half, truth, method)``, and the points of the plot."""

    def __init__(self):
        self.rows, self.points, self.trials = {}, [], {}

    def add(self, key, value):
        self.rows.setdefault(key, []).append(value)

    def count(self, key, trusted: bool):
        done, kept = self.trials.get(key, (0, 0))
        self.trials[key] = (done + 1, kept + int(trusted))

    def markdown(self) -> str:
        lines = ["| set | half | truth | method | trusted / trials | mean NEES | median NEES | inside chi2(6) 95% |",
                 "|---|---|---|---|---:|---:|---:|---:|"]
        for (name, half, truth, method), values in self.rows.items():
            values = np.array(values, dtype=np.float64)
            valid = values[np.isfinite(values)]
            mean = f"{valid.mean():.3g}" if len(valid) else "n/a"
            median = f"{np.median(valid):.3g}" if len(valid) else "n/a"
            inside = np.mean(np.nan_to_num(values, nan=np.inf) <= CHI2_6_95) if len(values) else math.nan
            done, kept = self.trials.get((name, half), (len(values), len(values)))
            counted = f"{kept} / {done}" if truth != "cycles" else f"{len(values)} cycles"
            lines.append(f"| {name} | {half} | {truth} | {method} | {counted} | {mean} | {median} "
                         f"| {100 * inside:.0f}% |")
        return "\n".join(lines)


def score(table: Table, name: str, half: str, truth: str, run: Run, peers: bool, extra=None):
    """Add one trusted run's NEES (esmicp, plus the peers from the same start), and its plot point."""
    extra = np.zeros((6, 6)) if extra is None else extra
    table.add((name, half, truth, "esmicp"), nees(run.error, run.covariance + extra))
    if truth == "exact":
        table.points.append((name, np.abs(run.error), np.sqrt(np.diag(run.covariance)), run.spacing))
    if not peers:
        return
    for peer in (run_open3d, run_small_gicp):
        estimate, covariances = peer(run.source, run.target, run.start, run.spacing)
        error = uncertainty.left_error(run.truth, estimate)
        for method, covariance in covariances.items():
            table.add((name, half, truth, method), nees(error, None if covariance is None else covariance + extra))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--objects", type=int, default=2, help="trials per shape of the choice half (default 2)")
    parser.add_argument("--shapes", type=int, default=None, help="paper shapes used (default: all 12)")
    parser.add_argument("--extra", type=int, default=24, help="modelnet40_extra shapes, one trial each (default 24)")
    parser.add_argument("--triplets", type=int, default=6, help="kitchen triplets per half (default 6)")
    parser.add_argument("--sets", default="objects,cut,kitchen,bunny,lidar",
                        help="of objects, cut, kitchen, bunny, lidar")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--peers", action="store_true", help="also Open3D's and small_gicp's matrices")
    parser.add_argument("--plot", type=Path, help="write a PNG of predicted against observed errors (esmicp)")
    parser.add_argument("--doc", type=Path, help="rewrite the generated part of this page (docs/uncertainty.md)")
    args = parser.parse_args(argv)
    began = time.perf_counter()
    rng = np.random.default_rng(args.seed)
    names = args.sets.split(",")
    table, shares, by_noise = Table(), [], {}
    for kind, keep in (("objects", 1.0), ("cut", CUT_KEEP)):
        if kind not in names:
            continue
        name = "whole objects" if keep == 1.0 else f"cut objects ({CUT_KEEP:.0%})"
        for half, paths in (("choice", shapes("modelnet40", args.shapes, rng) * args.objects),
                            ("confirmation", shapes("modelnet40_extra", args.extra, rng))):
            for path in paths:
                source, target, truth, fraction = object_trial(path, rng, keep)
                run = Run(source, target, truth, rng)
                shares.append(run.share)
                table.count((name, half), run.trusted)
                if run.trusted:
                    score(table, name, half, "exact", run, args.peers)
                    band = min(int(3 * fraction), 2)
                    by_noise.setdefault((name, band), []).append(nees(run.error, run.covariance))
    if "kitchen" in names:
        truth_error = np.diag([math.radians(KITCHEN_TRUTH_DEG) ** 2] * 3 + [KITCHEN_TRUTH_M ** 2] * 3)
        for half, (first, last) in (("choice", (0, 490)), ("confirmation", (500, 990))):
            runs = []
            for (a, b, c), frames, poses in kitchen_triplets(first, last, args.triplets, rng):
                triplet = []
                for target, source in ((a, b), (b, c), (a, c)):
                    run = Run(frames[source], frames[target], np.linalg.inv(poses[target]) @ poses[source], rng)
                    shares.append(run.share)
                    table.count(("kitchen pairs", half), run.trusted)
                    triplet.append(run)
                runs.append(triplet)
            for triplet in runs:
                for run in (r for r in triplet if r.trusted):
                    score(table, "kitchen pairs", half, "recorded", run, False)
            for triplet in runs:
                for run in (r for r in triplet if r.trusted):
                    score(table, "kitchen pairs", half, "recorded + truth error", run, args.peers, truth_error)
            for triplet in runs:
                if all(run.trusted for run in triplet):
                    error, covariance = cycle(*triplet)
                    table.add(("kitchen pairs", half, "cycles", "esmicp"), nees(error, covariance))
    if "bunny" in names:
        points, poses, pairs = bunny_scans()
        runs = {}
        for target, source in pairs:
            run = Run(points[source], points[target], np.linalg.inv(poses[target]) @ poses[source], rng)
            shares.append(run.share)
            table.count(("bunny scan pairs", "confirmation"), run.trusted)
            if run.trusted:
                runs[(target, source)] = run
                score(table, "bunny scan pairs", "confirmation", "recorded", run, args.peers)
        for a, b, c in itertools.combinations(list(points), 3):
            if all(key in runs for key in ((a, b), (b, c), (a, c))):
                error, covariance = cycle(runs[(a, b)], runs[(b, c)], runs[(a, c)])
                table.add(("bunny scan pairs", "confirmation", "cycles", "esmicp"), nees(error, covariance))
    texts = {}
    if shares:
        shares = np.array(shares)
        texts[DOC_BEGIN, DOC_END] = "\n".join([
            f"Seed {args.seed}; {args.objects} trial(s) per paper shape, {args.extra} `modelnet40_extra` shapes, "
            f"{args.triplets} kitchen triplets per half; every start {START_DEGREES:g} deg and {START_SPACINGS:g} "
            f"target spacings from the truth; kitchen truth error {KITCHEN_TRUTH_DEG:g} deg and "
            f"{100 * KITCHEN_TRUTH_M:g} cm per axis.", "", table.markdown(), "", _noise_table(by_noise), "",
            f"Cost of the covariance: median {100 * np.median(shares):.1f}% of the registration that computed it "
            f"(max {100 * shares.max():.1f}%), {len(shares)} registrations from a given start, one thread; the "
            f"whole run {(time.perf_counter() - began) / 60:.0f} minutes{' with the peers' if args.peers else ''}."])
    if "lidar" in names:
        began = time.perf_counter()
        lidar_table = Table()
        check = lidar(lidar_table, np.random.default_rng([args.seed, LIDAR_STREAM]), args.peers)
        texts[LIDAR_BEGIN, LIDAR_END] = "\n".join([
            f"Seed {args.seed}; every start {START_DEGREES:g} deg and {START_SPACINGS:g} target spacings from the "
            "truth; the Newer College cycles use no truth.", "", check, "", lidar_table.markdown(), "",
            f"The LiDAR part took {(time.perf_counter() - began) / 60:.0f} minutes"
            f"{' with the peers' if args.peers else ''}."])
    for (begin, end), text in texts.items():
        print(text + "\n")
        if args.doc is not None:
            _write_doc(args.doc, text, begin, end)
    if args.plot is not None and table.points:
        _plot(table.points, args.plot)
    return 0


def _noise_table(by_noise) -> str:
    """esmicp's NEES on the object sets (both halves) by the added noise."""
    lines = ["esmicp on the objects (both halves), by the added noise (standard deviation, in point spacings):", "",
             "| set | added noise | trusted trials | mean NEES | median NEES | inside chi2(6) 95% |",
             "|---|---|---:|---:|---:|---:|"]
    for (name, band), values in sorted(by_noise.items()):
        values = np.array(values, dtype=np.float64)
        inside = np.mean(np.nan_to_num(values, nan=np.inf) <= CHI2_6_95)
        lines.append(f"| {name} | {band / 3:.2f}-{(band + 1) / 3:.2f} | {len(values)} | {np.nanmean(values):.3g} | "
                     f"{np.nanmedian(values):.3g} | {100 * inside:.0f}% |")
    return "\n".join(lines)


def _write_doc(path: Path, text: str, begin: str = DOC_BEGIN, end: str = DOC_END) -> None:
    page = path.read_text(encoding="utf-8")
    if begin not in page or end not in page:
        raise SystemExit(f"{path}: no generated part (the markers {begin} and {end})")
    before, rest = page.split(begin, 1)
    after = rest.split(end, 1)[1]
    path.write_text(f"{before}{begin}\n{text}\n{end}{after}", encoding="utf-8")


def _plot(points, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    figure, axes = plt.subplots(1, 2, figsize=(8, 3.6))
    labels = ("rotation (deg)", "translation (spacings)")
    for panel, (axis, label) in enumerate(zip(axes, labels)):
        for set_name in sorted({name for name, *_ in points}):
            chosen = [(e, s, spacing) for name, e, s, spacing in points if name == set_name]
            observed = np.concatenate([e[3 * panel:3 * panel + 3] for e, _, _ in chosen])
            predicted = np.concatenate([s[3 * panel:3 * panel + 3] for _, s, _ in chosen])
            if panel == 0:
                observed, predicted = np.degrees(observed), np.degrees(predicted)
            else:
                scale = np.repeat([spacing for _, _, spacing in chosen], 3)
                observed, predicted = observed / scale, predicted / scale
            axis.loglog(predicted, observed, ".", ms=3, label=set_name, alpha=0.7)
        low, high = axis.get_xlim()
        grid = np.geomspace(low, high, 10)
        axis.loglog(grid, grid, "k-", lw=0.8, label="1 sigma")
        axis.loglog(grid, 2 * grid, "k--", lw=0.8, label="2 sigma")
        axis.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        axis.set_xlabel(f"predicted std, {label}")
        axis.set_ylabel(f"observed |error|, {label}")
    axes[0].legend(fontsize=7)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=90)


if __name__ == "__main__":
    sys.exit(main())
