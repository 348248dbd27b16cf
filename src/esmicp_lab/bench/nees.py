"""The calibration of the pose covariance (NEES) on objects, scan pairs and cycles: the trials, the
runs of esmicp and its peers from a perturbed start, and the tables (its command line, whose
docstring states the protocol: ``benchmarks/covariance_nees.py``). ``data`` is the shared data
folder."""

from __future__ import annotations

import itertools
import math
import time
from pathlib import Path

import numpy as np

import esmicp
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.procrustes import apply, skew
from esmicp.metrics import random_rotation

from .real_pairs import pose_graph_poses
from esmicp.trust import uncertainty

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


def shapes(data: Path, folder: str, count: int | None, rng) -> list[Path]:
    """``count`` shapes (all: None) of the ModelNet40 folder ``data / folder``, drawn with ``rng``."""
    paths = sorted((data / folder).glob("*/*.txt"))
    if count is not None and count < len(paths):
        paths = [paths[k] for k in sorted(rng.choice(len(paths), size=count, replace=False))]
    return paths


def kitchen_triplets(data: Path, first: int, last: int, count: int, rng):
    """``count`` triplets of kept kitchen frames ``a, b, c`` (frame numbers in ``first..last``), b
    10 or 20 frames after a and c 10 or 20 after b: ``(names, {name: points}, {name: T_world})``."""
    from .sequences import read_frame, read_poses

    folder = data / "sequences" / "redkitchen_seq01_every10"
    poses = read_poses(folder)
    names = [name for name in sorted(poses) if first <= int(name.split("-")[-1]) <= last]
    for k in rng.choice(len(names) - 4, size=count, replace=False):
        b = k + int(rng.integers(1, 3))
        c = b + int(rng.integers(1, 3))
        triplet = (names[k], names[b], names[c])
        yield triplet, {name: read_frame(folder, name) for name in triplet}, {name: poses[name] for name in triplet}


def bunny_scans(data: Path):
    """``({name: points}, {name: T_world}, [(target, source)])``: the bunny's scans and their
    pairs overlapping by at least ``BUNNY_MIN_OVERLAP`` at the truth."""
    from esmicp.io.stanford_conf import load_scans

    scans = load_scans(data / "bunny_scans")
    points = {name: value[0] for name, value in scans.items()}
    poses = {name: value[1] for name, value in scans.items()}
    pairs = []
    for a, b in itertools.combinations(scans, 2):
        index = NearestNeighbors(points[a], workers=1)
        distances, _ = index.query(apply(np.linalg.inv(poses[a]) @ poses[b], points[b][::10]))
        if np.mean(distances < 3 * index.spacing()) >= BUNNY_MIN_OVERLAP:
            pairs.append((a, b))
    return points, poses, pairs


def lidar_pairs(data: Path):
    """``[(family, name, source, target, T_target_source, metres apart)]``: the 10 pairs of the 5
    Newer College scans (truth from ``graph.txt``: ``vK x y z qx qy qz qw`` per scan, world from
    scan), then the KITTI pair (its ``T_target_source.txt``); and the Newer College triplets."""
    from esmicp.io import read_points

    folder = data / "real_pairs" / "newer_college_01"
    world = pose_graph_poses(folder / "graph.txt")
    scans = {k: read_points(folder / f"planes_{10 * k:06d}.bin", bin_columns=3) for k in sorted(world)}
    pairs = []
    for a, b in itertools.combinations(sorted(world), 2):
        truth = np.linalg.inv(world[a]) @ world[b]
        pairs.append(("Newer College", (a, b), scans[b], scans[a], truth, float(np.linalg.norm(truth[:3, 3]))))
    kitti = data / "real_pairs" / "kitti_00"
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


def lidar(data: Path, table: Table, rng, peers: bool) -> str:
    """The ``lidar`` set: the truth check (a Markdown table and what it says), then each pair's
    NEES against the recorded truth and the Newer College cycles into ``table``."""
    pairs, triplets = lidar_pairs(data)
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


def noise_table(by_noise) -> str:
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
