"""Hostile clouds and starts: what each registration returns (docs/reliability.md).

Two tables, all methods in the same run on the same trials:

1. Hostile clouds (the built-in asymmetric shape, 600 points, or an asymmetric planar patch): far
   from the origin (1e8), tiny (1e-8), every point three times, planar. Sources are moved copies
   (shuffled; in file order for esm-paper), 10 degrees off for the local methods from the identity
   and a uniformly random rotation for the global default. Cell: correct / converged-but-wrong /
   reported not converged, and the median rotation error.
2. Source entirely outside the target: the same shape moved ``d`` target sizes away in a random
   direction, with a rotation of 0, 10 or 30 degrees about a random axis, from the identity; the
   global default from a uniformly random rotation. Same cells.

Correct: rotation error below 1e-4 degrees and translation error (at the source's centroid)
below 1e-5 target sizes.

    python benchmarks/hostile_starts.py --trials 20
    python benchmarks/hostile_starts.py --compare-shift   # 1e8 coordinates with / without the shifted frame

Prints Markdown tables; figures are measured in this run, never stored.
"""

from __future__ import annotations

import argparse
import statistics
import warnings

import numpy as np

import esmicp
from esmicp.core.procrustes import apply, to_matrix
from esmicp.errors import IndexAlignmentWarning
from esmicp.metrics import random_rotation, rotation_error_deg, translation_error
from esmicp.shapes import asymmetric_shape

CONFIGS = [("esm", None, "global (default)"), ("esm", "identity", "esm"), ("esm-paper", "identity", "esm-paper"),
           ("icp", "identity", "icp")]


def size_of(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def about_centroid(points: np.ndarray, rotation: np.ndarray, shift: np.ndarray) -> np.ndarray:
    centre = points.mean(axis=0)
    return to_matrix(rotation, centre - rotation @ centre + shift)


def planar(rng: np.random.Generator) -> np.ndarray:
    uv = rng.uniform(0.0, 1.0, size=(1500, 2))
    uv = uv[(uv[:, 0] < 0.3) | (uv[:, 1] < 0.25)] * [2.0, 1.3]
    return np.c_[uv, np.zeros(len(uv))]


def axis_rotation(rng: np.random.Generator, angle_deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    return Rotation.from_rotvec(np.deg2rad(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()


def outcome(target, truth, method, init, rng) -> tuple[str, float]:
    order = np.arange(len(target)) if method == "esm-paper" else rng.permutation(len(target))
    source = apply(np.linalg.inv(truth), target[order])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IndexAlignmentWarning)
        result = esmicp.register(source, target, method=method, init=init)
    matrix = result.transformation
    if not np.isfinite(matrix).all():
        return "NaN", float("nan")
    error = rotation_error_deg(matrix, truth)
    correct = error < 1e-4 and translation_error(matrix, truth, pivot=source.mean(axis=0)) < 1e-5 * size_of(target)
    if correct:
        return "correct", error
    return ("wrong" if result.converged else "not converged"), error


def cell(outcomes: list[tuple[str, float]]) -> str:
    counts = {kind: sum(1 for k, _ in outcomes if k == kind) for kind in ("correct", "wrong", "not converged", "NaN")}
    median = statistics.median(error for _, error in outcomes)
    text = f"{counts['correct']} / {counts['wrong']} / {counts['not converged']} ({median:.2g} deg)"
    return text + (f", {counts['NaN']} NaN" if counts["NaN"] else "")


def compare_shift(shape: np.ndarray) -> None:
    """1e8 coordinates, 10 degrees off: register with and without the shifted working frame."""
    import esmicp.working_frame

    target = shape + [1e8, -2e8, 5e7]
    rng = np.random.default_rng(0)
    truth = about_centroid(target, axis_rotation(rng, 10.0), np.array([0.05, -0.02, 0.03]) * size_of(target))
    print("A 2.4-unit object 2.3e8 units from the origin, 10 degrees off: converged, iterations, rotation error\n")
    print("| | " + " | ".join(label for _, _, label in CONFIGS) + " |")
    print("|---" * (len(CONFIGS) + 1) + "|")
    default = esmicp.working_frame.FAR_FROM_ORIGIN
    for label, threshold in (("without the shifted frame", float("inf")), ("with it (default)", default)):
        esmicp.working_frame.FAR_FROM_ORIGIN = threshold
        cells = []
        for method, init, _ in CONFIGS:
            order = np.arange(len(target)) if method == "esm-paper" else rng.permutation(len(target))
            source = apply(np.linalg.inv(truth), target[order])
            result = esmicp.register(source, target, method=method, init=init)
            state = "converged" if result.converged else "not converged"
            cells.append(f"{state}, {result.num_iterations}, {rotation_error_deg(result.transformation, truth):.2g} deg")
        print(f"| {label} | " + " | ".join(cells) + " |")
    esmicp.working_frame.FAR_FROM_ORIGIN = default
    try:
        import open3d as o3d
    except ImportError:
        return
    # Peer: Open3D's point-to-point ICP on the same 1e8 pair and on the same pair at the origin.
    source = apply(np.linalg.inv(truth), target[rng.permutation(len(target))])
    cells = []
    for label, offset in (("at 2.3e8", np.zeros(3)), ("moved to the origin", -target.mean(axis=0))):
        clouds = [o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points + offset)) for points in (source, target)]
        shift = to_matrix(np.eye(3), offset)
        criteria = o3d.pipelines.registration.ICPConvergenceCriteria(1e-8, 1e-8, 100)
        result = o3d.pipelines.registration.registration_icp(
            clouds[0], clouds[1], 0.5 * size_of(target), np.eye(4),
            o3d.pipelines.registration.TransformationEstimationPointToPoint(), criteria,
        )
        estimate = np.linalg.inv(shift) @ np.asarray(result.transformation) @ shift
        cells.append(f"{label}: {rotation_error_deg(estimate, truth):.2g} deg (fitness {result.fitness:.2f})")
    print("\nPeer, Open3D point-to-point ICP from the identity (100 iterations, tolerance 1e-8): " + "; ".join(cells))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--compare-shift", action="store_true", help="only the shifted-frame comparison")
    args = parser.parse_args()
    seeds = np.random.SeedSequence(args.seed)

    shape = asymmetric_shape(600, rng=7)
    if args.compare_shift:
        compare_shift(shape)
        return
    clouds = {
        "far from the origin (1e8)": shape + [1e8, -2e8, 5e7],
        "tiny (1e-8)": shape * 1e-8,
        "every point three times": np.repeat(shape, 3, axis=0),
        "planar patch": planar(np.random.default_rng(3)),
    }
    print(f"Hostile clouds, {args.trials} trials each: correct / converged but wrong / not converged (median rotation error)\n")
    print("| cloud | " + " | ".join(label for _, _, label in CONFIGS) + " |")
    print("|---" * (len(CONFIGS) + 1) + "|")
    for name, target in clouds.items():
        cells = []
        for method, init, _ in CONFIGS:
            rng = np.random.default_rng(seeds.spawn(1)[0])
            results = []
            for _ in range(args.trials):
                rotation = random_rotation(rng) if init is None else axis_rotation(rng, 10.0)
                shift = rng.uniform(-0.05, 0.05, 3) * size_of(target)
                results.append(outcome(target, about_centroid(target, rotation, shift), method, init, rng))
            cells.append(cell(results))
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)

    print(f"\nSource entirely outside the target (from the identity; global from a random rotation), {args.trials} trials each\n")
    print("| target sizes away | rotation | " + " | ".join(label for _, _, label in CONFIGS) + " |")
    print("|---" * (len(CONFIGS) + 2) + "|")
    for away in (3.0, 10.0, 100.0, 1e6):
        for angle in (0.0, 10.0, 30.0):
            cells = []
            for method, init, _ in CONFIGS:
                rng = np.random.default_rng(seeds.spawn(1)[0])
                results = []
                for _ in range(args.trials):
                    direction = rng.normal(size=3)
                    shift = direction / np.linalg.norm(direction) * away * size_of(shape)
                    rotation = random_rotation(rng) if init is None else axis_rotation(rng, angle)
                    results.append(outcome(shape, about_centroid(shape, rotation, shift), method, init, rng))
                cells.append(cell(results))
            rotation_text = "uniform (global) / " + f"{angle:g} deg"
            print(f"| {away:g} | {rotation_text} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
