"""Degenerate directions on shapes, real scan pairs and synthetic corridors: the smallest eigenvalue
ratio of the scaled point-to-plane Hessian and the directions reported below
``esmicp.trust.policy.TrustPolicy.degenerate_ratio``.

Each cloud is registered from its ground truth (objects: a resample of the shape with a little
noise onto the shape; real pairs: their recorded pose; kitchen-walk frames 10 apart: the walk's
poses), so the figures describe the overlap, not a search.

    python benchmarks/degenerate_directions.py [--plot docs/images/degenerate_corridor.png]

Prints Markdown.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
sys.path.insert(0, str(REPO / "benchmarks"))

import esmicp  # noqa: E402
from esmicp.trust import uncertainty  # noqa: E402
from esmicp_lab.bench.datasets import load_dataset  # noqa: E402
from esmicp.trust.policy import DEFAULT_POLICY  # noqa: E402

DATA = REPO.parent / "shared" / "data"


def smallest_ratio(result) -> float:
    """The smallest eigenvalue ratio of the scaled point-to-plane Hessian (1 when none is below
    the threshold is not known: computed from the result's information about the overlap)."""
    ratios = [direction.ratio for direction in result.degenerate_directions]
    return min(ratios) if ratios else float("nan")


def hessian_ratio(source, target, transformation) -> float:
    """The smallest eigenvalue ratio of the scaled point-to-plane Hessian at ``transformation``."""
    from esmicp.core.correspondence import NearestNeighbors
    from esmicp.core.procrustes import apply
    from esmicp.core.features import NormalEstimator

    index = NearestNeighbors(target, workers=1)
    placed = apply(transformation, source)
    distances, indices = index.query_near(placed)
    sigma = 2.0 * index.spacing()
    weights = np.exp(-np.square(distances) / (2 * sigma * sigma))
    keep = weights > 1e-6
    placed, matched, weights = placed[keep], target[indices[keep]], weights[keep]
    normals = NormalEstimator(target, 20).at(matched)
    centre = weights @ placed / weights.sum()
    offsets = placed - centre
    radius = np.sqrt(weights @ np.einsum("ij,ij->i", offsets, offsets) / weights.sum())
    hessian = uncertainty._hessian(offsets / radius, weights, normals)
    values = np.linalg.eigvalsh(hessian)
    return float(values[0] / values[-1])


def objects(name: str, folder, rng):
    dataset = load_dataset(str(folder) if folder else name, DATA, 2000)
    for shape, cloud in sorted(dataset.clouds.items()):
        source = cloud + rng.normal(0.0, 0.002 * np.ptp(cloud, axis=0).max(), cloud.shape)
        yield shape, source, cloud, np.eye(4)


def real_pairs():
    from esmicp_lab.bench.real_pairs import load_pair, read_pairs

    for pair in read_pairs(DATA / "real_pairs"):
        source, target, truth = load_pair(pair, bin_columns=3)
        yield pair.name, source, target, truth


def kitchen_pairs(step: int = 10):
    from esmicp_lab.bench.sequences import read_poses

    folder = DATA / "sequences" / "redkitchen_seq01_every10"
    frames, poses = folder / "frames", read_poses(folder)
    names = sorted(poses)
    for a, b in zip(names[::step], names[step // 2::step]):
        truth = np.linalg.inv(poses[a]) @ poses[b]
        yield f"{a}<-{b}", np.load(frames / f"{b}.npy").astype(np.float64), np.load(frames / f"{a}.npy").astype(np.float64), truth


KITCHEN_CROPS = ("frame-000000", "frame-000300", "frame-000600", "frame-000900")


def kitchen_crops():
    """Real surfaces seen alone: kitchen-walk frames and the next kept frame, both cut down to the
    target's dominant plane (points within 1.5 cm; ``esmicp_lab.bench.sequences.plane_crop_pair``)."""
    from esmicp_lab.bench.sequences import plane_crop_pair, read_frame, read_poses

    folder = DATA / "sequences" / "redkitchen_seq01_every10"
    poses = read_poses(folder)
    names = sorted(poses)
    for name in KITCHEN_CROPS:
        after = names[names.index(name) + 1]
        truth = np.linalg.inv(poses[name]) @ poses[after]
        source, target, normal = plane_crop_pair(read_frame(folder, name), read_frame(folder, after), truth, 0.015,
                                                 np.random.default_rng(0))
        yield f"{name}<-{after}", source, target, truth


def slide_check(source, target, truth, result) -> tuple[float, float, float]:
    """(predicted standard deviation along the weakest translation, and the distance left off the
    truth after starts 5 cm off along it, each way): does the pose really slide there?"""
    spread = result.covariance[3:, 3:]
    weakest = np.linalg.eigh(spread)[1][:, -1]
    left = []
    for sign in (1.0, -1.0):
        start = truth.copy()
        start[:3, 3] += 0.05 * sign * weakest
        moved = esmicp.register(source, target, init=start, workers=1).transformation
        left.append(abs(float((moved[:3, 3] - truth[:3, 3]) @ weakest)))
    return float(np.sqrt(weakest @ spread @ weakest)), left[0], left[1]


def synthetic(rng):
    sys.path.insert(0, str(REPO / "tests"))
    from test_uncertainty import corridor

    yield "corridor", corridor(15_000, rng) + rng.normal(0, 0.005, (15_000, 3)), corridor(15_000, rng), np.eye(4)
    plane = np.column_stack([rng.uniform(-1, 1, (4000, 2)), np.zeros(4000)])
    noisy = np.column_stack([rng.uniform(-1, 1, (4000, 2)), rng.normal(0, 0.002, 4000)])
    yield "plane on plane", noisy, plane, np.eye(4)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--plot", type=Path, help="write a picture of the synthetic examples here")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    groups = {
        "synthetic": synthetic(rng),
        "modelnet40 (tuning)": objects("modelnet40", None, rng),
        "modelnet40_extra (confirmation)": objects("modelnet40_extra", DATA / "modelnet40_extra", rng),
        "real_pairs (3DMatch, Newer College, KITTI)": real_pairs(),
        "kitchen walk, pairs 5 kept frames (50 raw frames) apart": kitchen_pairs(),
        "kitchen walk frames cut to their dominant plane (real surfaces)": kitchen_crops(),
    }
    print(f"Threshold: eigenvalue ratio < {DEFAULT_POLICY.degenerate_ratio:g} "
          "(scaled point-to-plane Hessian, rotation x overlap radius).\n")
    print("| set | clouds | smallest ratio (min / median) | clouds with a degenerate direction | directions reported |")
    print("|---|---:|---:|---:|---|")
    examples, slides = {}, []
    for group, items in groups.items():
        ratios, flagged, words = [], 0, []
        for name, source, target, truth in items:
            result = esmicp.register(source, target, init=truth, workers=1)
            ratios.append(hessian_ratio(source, target, result.transformation))
            if result.degenerate_directions:
                flagged += 1
                words.append(f"{name}: " + "; ".join(d.describe().split(" (ratio")[0]
                                                     for d in result.degenerate_directions))
            if group == "synthetic":
                examples[name] = (source, target, result)
            if "real surfaces" in group:
                slides.append((name, bool(result.degenerate_directions), *slide_check(source, target, truth, result)))
        ratios = np.array(ratios)
        print(f"| {group} | {len(ratios)} | {ratios.min():.2g} / {np.median(ratios):.2g} | {flagged} | "
              f"{'<br>'.join(words) if words else '-'} |")
    print("\nDoes a real surface slide? Each crop registered from starts 5 cm off the truth along its "
          "weakest translation (the covariance's widest), each way:\n")
    print("| crop | degenerate direction reported | predicted sd along it (cm) | left off after +5 cm / -5 cm (cm) |")
    print("|---|---|---:|---:|")
    for name, reported, deviation, plus, minus in slides:
        print(f"| {name} | {'yes' if reported else 'no'} | {100 * deviation:.1f} | {100 * plus:.1f} / {100 * minus:.1f} |")
    if args.plot is not None:
        _plot(examples, args.plot)
    return 0


def _plot(examples, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure = plt.figure(figsize=(8, 3.6))
    for panel, (name, (source, target, result)) in enumerate(examples.items(), start=1):
        axis = figure.add_subplot(1, len(examples), panel, projection="3d")
        shown = target[:: max(1, len(target) // 3000)]
        axis.scatter(*shown.T, s=0.5, c="0.6")
        centre = result.degenerate_directions[0].centre if result.degenerate_directions else shown.mean(axis=0)
        scale = 0.5 * np.ptp(shown, axis=0).max()
        for direction in result.degenerate_directions:
            axis_vector = direction.axis * scale
            colour = "tab:red" if direction.kind == "translation" else "tab:blue"
            axis.quiver(*centre, *axis_vector, color=colour, linewidth=2, arrow_length_ratio=0.15)
        axis.set_title(f"{name}: " + ", ".join(
            f"{d.kind[:5]}. {'along' if d.kind == 'translation' else 'about'} "
            f"{uncertainty.AXES[int(np.argmax(np.abs(d.axis)))]}" for d in result.degenerate_directions), fontsize=8)
        low, high = shown.min(axis=0), shown.max(axis=0)
        middle, half = 0.5 * (low + high), np.maximum(0.5 * (high - low), 0.6 * scale)
        axis.set_xlim(middle[0] - half[0], middle[0] + half[0])
        axis.set_ylim(middle[1] - half[1], middle[1] + half[1])
        axis.set_zlim(middle[2] - half[2], middle[2] + half[2])
        axis.set_box_aspect(half)
        axis.tick_params(labelsize=5)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=90)


if __name__ == "__main__":
    sys.exit(main())
