"""Calibration of the pose covariance: NEES of esmicp, Open3D and small_gicp on the same trials.

For each trial a source and a target are made from a real scan with an exactly known pose
(``exact`` sets: two disjoint random resamples of one scan, each with its own Gaussian noise,
cropped by random planes, some with the bench's outlier noise, the source moved by a random pose),
or taken from a real pair with its recorded ground truth (``real-GT`` sets, whose truth has its own
error). Every method starts from the same perturbed pose. With ``e`` the left error vector of the
result (``T_true = Exp(e) @ T_est``, rotation vector then translation, target frame),
``NEES = e^T Sigma^-1 e``; a calibrated 6x6 covariance gives a mean of 6 and 95% of trials below
the chi-square(6) 95% bound (12.59).

Peers: Open3D point-to-plane ICP and its ``get_information_matrix_from_point_clouds`` (inverse
taken as the covariance: as returned, i.e. unit noise, and scaled by the per-axis mean square of
the inlier distances, ``inlier_rmse^2 / 3``); small_gicp GICP and its Hessian ``H`` (``H^-1`` as
returned, and scaled by the mean squared Mahalanobis residual ``2 error / (3 inliers - 6)``),
mapped from its right (source-frame) perturbation to the left one.

    python benchmarks/covariance_nees.py --trials 20 [--plot docs/images/covariance_predicted_observed.png]

Prints Markdown. Timings are ratios within the run (the covariance's cost over the registration
that computed it).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

import esmicp  # noqa: E402
from esmicp.trust import uncertainty  # noqa: E402
from esmicp_lab.bench.protocols import paper_noise  # noqa: E402
from esmicp.core.correspondence import NearestNeighbors  # noqa: E402
from esmicp.core.procrustes import apply, bounding_box_diagonal, skew  # noqa: E402
from esmicp.metrics import random_rotation  # noqa: E402

DATA = REPO.parent / "shared" / "data"
CHI2_6_95 = 12.591587243743977

#: The start is the truth moved by a random rotation of this many degrees and a translation of this
#: many target spacings (random directions).
START_DEGREES = 3.0
START_SPACINGS = 8.0


def spacing_of(points: np.ndarray) -> float:
    return NearestNeighbors(points, workers=1).spacing()


def random_pose(rng, degrees: float, distance: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = random_rotation(rng, degrees)
    direction = rng.normal(size=3)
    pose[:3, 3] = distance * direction / np.linalg.norm(direction)
    return pose


def exact_trial(cloud: np.ndarray, rng: np.random.Generator, points: int):
    """Two disjoint resamples of ``cloud`` with their own noise, each cut by a random plane, the source
    moved by a random pose; a third of the trials add the bench's outlier noise to 20% of the source.
    Returns ``(source, target, truth, noise)``: ``noise`` the added noise's standard deviation in
    point spacings of ``cloud`` (uniform in 0-1)."""
    spacing = spacing_of(cloud)
    order = rng.permutation(len(cloud))
    half = min(points, len(cloud) // 2)
    source, target = cloud[order[:half]].astype(np.float64), cloud[order[half:2 * half]].astype(np.float64)
    fraction = rng.uniform(0.0, 1.0)
    noise = fraction * spacing
    source = source + rng.normal(0.0, noise, source.shape)
    target = target + rng.normal(0.0, noise, target.shape)
    source, target = _cut(source, rng, 0.75), _cut(target, rng, 0.75)
    if rng.uniform() < 1 / 3:
        source, _ = paper_noise(source, 0.2, rng, 0.5 * bounding_box_diagonal(cloud))
    truth = random_pose(rng, 180.0, 0.5 * bounding_box_diagonal(cloud))
    source = apply(np.linalg.inv(truth), source)  # truth maps the source back onto the target
    return source, target, truth, fraction


def _cut(points: np.ndarray, rng, keep: float) -> np.ndarray:
    normal = rng.normal(size=3)
    heights = (points - points.mean(axis=0)) @ (normal / np.linalg.norm(normal))
    return points[heights <= np.quantile(heights, keep)]


def kitchen_frames():
    from esmicp_lab.bench.sequences import read_poses

    folder = DATA / "sequences" / "redkitchen_seq01_every10"
    return folder / "frames", read_poses(folder)


def real_pairs():
    from esmicp_lab.bench.real_pairs import load_pair, read_pairs

    for pair in read_pairs(DATA / "real_pairs"):
        if pair.dataset == "kitti_00":
            continue  # its ground truth is coarse (0.18 m): no use for a covariance
        source, target, truth = load_pair(pair, bin_columns=3)
        yield pair.dataset, source, target, truth


def trial_sets(count: int, rng: np.random.Generator, names: list[str], points_scale: float = 1.0):
    """``{set name: [(source, target, truth, kind, noise)]}`` (``noise``: :func:`exact_trial`'s, None
    for real pairs). ``points_scale`` scales the resamples' sizes (15,000 points of the 3DMatch
    fragment's 80,000, 8,000 of a kitchen frame's about 17,000), each at most half of its scan."""
    sets = {}
    frames, poses = kitchen_frames()
    if "3dmatch-resampled" in names:
        import esmicp.io as io

        cloud = io.read_points(DATA / "real_pairs" / "3dmatch_redkitchen" / "cloud_bin_0.ply")
        cloud = cloud[rng.permutation(len(cloud))[:80_000]]
        sets["3dmatch-resampled"] = [_exact(exact_trial(cloud, rng, round(15_000 * points_scale))) for _ in range(count)]
    if "kitchen-resampled" in names:
        chosen = rng.choice(sorted(poses), size=count, replace=False)
        sets["kitchen-resampled"] = [
            _exact(exact_trial(np.load(frames / f"{name}.npy").astype(np.float64), rng, round(8_000 * points_scale))) for name in chosen]
    if "kitchen-walk-GT" in names:
        ordered = sorted(poses)
        trials = []
        for k in rng.choice(len(ordered) - 1, size=count, replace=False):
            a, b = ordered[k], ordered[k + 1]
            truth = np.linalg.inv(poses[a]) @ poses[b]
            trials.append((np.load(frames / f"{b}.npy").astype(np.float64), np.load(frames / f"{a}.npy").astype(np.float64),
                           truth, "real-GT", None))
        sets["kitchen-walk-GT"] = trials
    if "real-pairs-GT" in names:
        for dataset, source, target, truth in real_pairs():
            sets.setdefault(f"real_pairs {dataset}", []).append((source, target, truth, "real-GT", None))
    return sets


def _exact(trial):
    source, target, truth, noise = trial
    return source, target, truth, "exact", noise


def nees(error: np.ndarray, covariance: np.ndarray | None) -> float:
    if covariance is None or not np.all(np.isfinite(covariance)):
        return math.nan
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    if values[0] <= 0:
        return math.inf
    projected = vectors.T @ error
    return float(np.sum(projected ** 2 / values))


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


def run_ours(source, target, start):
    """``(estimate, {name: covariance}, share)``: ``share`` is the covariance's part of the run time."""
    timed = _Timed()
    uncertainty.from_registration = timed
    try:
        result = esmicp.register(source, target, init=start, workers=1)
    finally:
        uncertainty.from_registration = timed.inner
    return result.transformation, {"esmicp": result.covariance}, timed.seconds / result.runtime_s


def global_cost(trials, count: int) -> np.ndarray:
    """The covariance's share of the run time of default registrations (global search) of the
    first ``count`` trials."""
    shares = []
    for source, target, *_ in trials[:count]:
        timed = _Timed()
        uncertainty.from_registration = timed
        try:
            result = esmicp.register(source, target, workers=1)
        finally:
            uncertainty.from_registration = timed.inner
        shares.append(timed.seconds / result.runtime_s)
    return np.array(shares)


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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=20, help="trials per exact set (default 20)")
    parser.add_argument("--starts", type=int, default=2, help="perturbed starts per real-GT pair (default 2)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sets", default="3dmatch-resampled,kitchen-resampled,kitchen-walk-GT,real-pairs-GT")
    parser.add_argument("--no-peers", action="store_true", help="esmicp only")
    parser.add_argument("--points-scale", type=float, default=1.0,
                        help="scale the exact sets' resample sizes (default 1: 15,000 and 8,000 points)")
    parser.add_argument("--global-cost", type=int, default=0, help="also time N default (global) registrations")
    parser.add_argument("--plot", type=Path, help="write a PNG of predicted against observed errors (esmicp)")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    names = args.sets.split(",")
    sets = trial_sets(args.trials, rng, names, args.points_scale)
    table, ratios, points, by_noise = {}, [], [], {}
    for set_name, trials in sets.items():
        for source, target, truth, kind, noise in trials:
            spacing = spacing_of(target)
            for _ in range(args.starts if kind == "real-GT" else 1):
                start = random_pose(rng, START_DEGREES, START_SPACINGS * spacing) @ truth
                runs = []
                estimate, covariances, ratio = run_ours(source, target, start)
                ratios.append(ratio)
                runs.append((estimate, covariances))
                if not args.no_peers:
                    runs.append(run_open3d(source, target, start, spacing))
                    runs.append(run_small_gicp(source, target, start, spacing))
                for estimate, covariances in runs:
                    error = uncertainty.left_error(truth, estimate)
                    for peer, covariance in covariances.items():
                        table.setdefault((set_name, kind, peer), []).append(nees(error, covariance))
                        if peer == "esmicp" and covariance is not None:
                            points.append((set_name, np.abs(error), np.sqrt(np.diag(covariance))))
                        if peer == "esmicp" and noise is not None:
                            band = min(int(3 * noise), 2)
                            by_noise.setdefault((set_name, band), []).append(nees(error, covariance))
    print(f"Trials: {args.trials} per exact set (resample sizes x{args.points_scale:g}), {args.starts} starts per "
          f"real-GT pair, seed {args.seed}; "
          f"start {START_DEGREES:g} deg and {START_SPACINGS:g} target spacings from the truth.\n")
    print("| set | truth | method | trials | mean NEES | median NEES | inside chi2(6) 95% |")
    print("|---|---|---|---:|---:|---:|---:|")
    for (set_name, kind, peer), values in table.items():
        values = np.array(values, dtype=np.float64)
        valid = values[np.isfinite(values)]
        mean = f"{valid.mean():.3g}" if len(valid) else "n/a"
        median = f"{np.median(valid):.3g}" if len(valid) else "n/a"
        inside = np.mean(np.nan_to_num(values, nan=np.inf) <= CHI2_6_95)
        print(f"| {set_name} | {kind} | {peer} | {len(values)} | {mean} | {median} | {100 * inside:.0f}% |")
    if by_noise:
        print("\nesmicp on the exact sets, by the added noise (standard deviation, in point spacings):\n")
        print("| set | added noise | trials | mean NEES | median NEES | inside chi2(6) 95% |")
        print("|---|---|---:|---:|---:|---:|")
        for (set_name, band), values in sorted(by_noise.items()):
            values = np.array(values, dtype=np.float64)
            print(f"| {set_name} | {band / 3:.2f}-{(band + 1) / 3:.2f} | {len(values)} | {np.nanmean(values):.3g} | "
                  f"{np.nanmedian(values):.3g} | {100 * np.mean(np.nan_to_num(values, nan=np.inf) <= CHI2_6_95):.0f}% |")
    ratios = np.array(ratios)
    print(f"\nCost of the covariance (esmicp): median {100 * np.median(ratios):.1f}% of the registration that "
          f"computed it (max {100 * ratios.max():.1f}%), {len(ratios)} registrations from a given start, one thread.")
    if args.global_cost:
        first = next(iter(sets.values()))
        shares = global_cost(first, args.global_cost)
        print(f"With the default global search ({len(shares)} trials of {next(iter(sets))}): median "
              f"{100 * np.median(shares):.2f}% (max {100 * shares.max():.2f}%).")
    if args.plot is not None:
        _plot(points, args.plot)
    return 0


def _plot(points, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    figure, axes = plt.subplots(1, 2, figsize=(8, 3.6))
    labels = ("rotation (deg)", "translation (cloud units)")
    for panel, (axis, label) in enumerate(zip(axes, labels)):
        for set_name in sorted({name for name, _, _ in points}):
            observed = np.concatenate([e[3 * panel:3 * panel + 3] for name, e, _ in points if name == set_name])
            predicted = np.concatenate([s[3 * panel:3 * panel + 3] for name, _, s in points if name == set_name])
            if panel == 0:
                observed, predicted = np.degrees(observed), np.degrees(predicted)
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
