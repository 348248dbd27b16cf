"""The paper's index-aligned copy protocol, and what happens when the point order is shuffled.

Target: a real cloud subsampled to ``--points`` points (ModelNet40 objects and the Stanford bunny
from ``../shared/data``). Source: the same points, in the same order, under a rigid transform with
a rotation uniform on SO(3) and a translation uniform in [-1000, 1000]^3 (protocol "copy"); the same
with the source's point order shuffled (protocol "shuffled"). Every method starts from the identity
with the same iteration budget. Success: rotation error below ``--threshold-deg``.

    python benchmarks/paper_copy_protocol.py --trials 200

Prints one Markdown table; figures are measured in this run, never stored.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import esmicp
from esmicp.core.procrustes import apply, to_matrix
from esmicp.metrics import random_rotation, rotation_error_deg

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def clouds(data_dir: Path, points: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    files = sorted((data_dir / "modelnet40").glob("*/*.txt")) + [data_dir / "bunny" / "bun_zipper.ply"]
    loaded = {}
    for path in files:
        if path.name == "modelnet40_shape_names.txt":
            continue
        cloud = esmicp.read_points(path)
        loaded[path.stem] = cloud[rng.choice(len(cloud), min(points, len(cloud)), replace=False)]
    if not loaded:
        sys.exit(f"no clouds found under {data_dir}")
    return loaded


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--points", type=int, default=1000)
    parser.add_argument("--trials", type=int, default=200, help="trials per protocol, spread over the clouds")
    parser.add_argument("--methods", default="esm-paper,esm,icp")
    parser.add_argument("--max-iterations", type=int, default=100)
    parser.add_argument("--threshold-deg", type=float, default=1e-4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--clouds", help="comma-separated cloud names (file stems) to keep, default all")
    args = parser.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    shapes = clouds(args.data, args.points, rng)
    if args.clouds:
        shapes = {name: shapes[name] for name in args.clouds.split(",")}
    names = list(shapes)
    methods = args.methods.split(",")
    rows = []
    for protocol in ("copy", "shuffled"):
        trial_rng = np.random.default_rng([args.seed, 1])
        outcomes = {method: {"ok": 0, "errors": [], "times": [], "failed_on": {}} for method in methods}
        for trial in range(args.trials):
            target = shapes[names[trial % len(names)]]
            moved_by = to_matrix(random_rotation(trial_rng), trial_rng.uniform(-1000, 1000, 3))
            truth = np.linalg.inv(moved_by)
            source = apply(moved_by, target)
            if protocol == "shuffled":
                source = source[trial_rng.permutation(len(source))]
            for method in methods:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", esmicp.IndexAlignmentWarning)
                    start = time.perf_counter()
                    result = esmicp.register(source, target, method=method, max_iterations=args.max_iterations, init="identity")
                    elapsed = time.perf_counter() - start
                error = rotation_error_deg(result.transformation, truth)
                outcome = outcomes[method]
                outcome["ok"] += error < args.threshold_deg
                if error >= args.threshold_deg:
                    name = names[trial % len(names)]
                    outcome["failed_on"][name] = outcome["failed_on"].get(name, 0) + 1
                outcome["errors"].append(error)
                outcome["times"].append(elapsed)
        for method in methods:
            outcome = outcomes[method]
            failures = ", ".join(f"{name} {count}" for name, count in sorted(outcome["failed_on"].items()))
            rows.append(
                (protocol, method, outcome["ok"], args.trials, statistics.median(outcome["errors"]),
                 1000 * statistics.median(outcome["times"]), failures if len(failures) < 120 else "most clouds")
            )
    print(f"{len(names)} clouds ({', '.join(names)}), {args.points} points, {args.trials} trials per protocol, "
          f"seed {args.seed}, success = rotation error < {args.threshold_deg:g} deg, from the identity\n")
    print("| protocol | method | recovered | median rotation error (deg) | median time (ms) | failures by cloud |")
    print("|---|---|---|---|---|---|")
    for protocol, method, ok, total, error, ms, failures in rows:
        print(f"| {protocol} | {method} | {ok}/{total} ({100 * ok / total:.1f}%) | {error:.3g} | {ms:.1f} | {failures} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
