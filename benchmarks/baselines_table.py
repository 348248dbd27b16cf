"""Every baseline adapter (esmicp_lab.baselines.BASELINES) and ESM-ICP on the same trials of the bunny.

Trials: the Stanford bunny (``bun_zipper.ply``); per trial the target is ``--points`` random
vertices and the source ``--points`` other vertices (two different samples of one surface: no
point pairs exactly), rotated about the target's centroid and translated by up to
``--shift`` (10 %) of the target's diagonal per axis. Two sets of ``--trials`` trials each:
``15deg`` (a random axis, exactly 15 degrees) and ``so3`` (rotations uniform on SO(3)). Every
method gets the same trials, the same seed per trial, starts from the identity (local methods;
global ones need no start) with the same budget of ``--max-iterations`` iterations; methods run
interleaved trial by trial, after one untimed warm-up call each (imports not counted). Time: the
adapter's ``runtime_s`` (the registration only).

Peers from esmicp itself: ``esm (local)`` = ``esmicp.register(..., init="identity")`` and
``esmicp (global)`` = ``esmicp.register(...)`` (the default global start).

Success: :func:`esmicp.metrics.strict_success` (rotation error < 2 deg, translation error at the
source's centroid < 2 % of the target's diagonal). Prints one Markdown table: per set, success
``k/n``, median rotation error (deg) and median time (ms); and the ratio of each method's median
time to ``esm (local)``'s on the 15-degree set. A method that cannot run says why in its row.

    python benchmarks/baselines_table.py --trials 20 --picture docs/images/baselines.png
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import esmicp
from esmicp_lab.baselines import (
    BASELINE_KINDS,
    BASELINES,
    BaselineTimeoutError,
    MissingDependencyError,
    WeightsNotAvailableError,
)
from esmicp.io import read_points
from esmicp.metrics import rotation_error_deg, strict_success

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
PEERS = ("esm (local)", "esmicp (global)")


def make_trials(cloud: np.ndarray, points: int, trials: int, shift: float, seed: int):
    """``[(set, seed, source, target, T_target_source)]`` for the two sets."""
    out = []
    children = np.random.SeedSequence(seed).spawn(2 * trials)
    for index, child in enumerate(children):
        rng = np.random.default_rng(child)
        kind = "15deg" if index < trials else "so3"
        order = rng.permutation(len(cloud))
        target, source_object = cloud[order[:points]], cloud[order[points : 2 * points]]
        diagonal = float(np.linalg.norm(np.ptp(target, axis=0)))
        if kind == "15deg":
            axis = rng.normal(size=3)
            rotation = Rotation.from_rotvec(np.radians(15.0) * axis / np.linalg.norm(axis)).as_matrix()
        else:
            rotation = Rotation.random(random_state=rng).as_matrix()
        centre = target.mean(axis=0)
        motion = np.eye(4)  # source = motion(source_object)
        motion[:3, :3] = rotation
        motion[:3, 3] = centre - rotation @ centre + rng.uniform(-shift, shift, 3) * diagonal
        source = source_object @ motion[:3, :3].T + motion[:3, 3]
        out.append((kind, int(rng.integers(2**31 - 1)), source, target, np.linalg.inv(motion)))
    return out


def run(method: str, source, target, seed: int, max_iterations: int):
    """(T_target_source, runtime_s) or raises."""
    if method == "esm (local)":
        result = esmicp.register(source, target, init="identity", max_iterations=max_iterations, rng=seed)
        return result.transformation, result.runtime_s
    if method == "esmicp (global)":
        result = esmicp.register(source, target, max_iterations=max_iterations, rng=seed)
        return result.transformation, result.runtime_s
    result = BASELINES[method](source, target, init=None, max_iterations=max_iterations, rng=seed)
    return result.transformation, result.runtime_s


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--points", type=int, default=1000)
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--shift", type=float, default=0.1)
    parser.add_argument("--max-iterations", type=int, default=50)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--methods", default=",".join(PEERS + tuple(BASELINES)))
    parser.add_argument("--picture", type=Path, help="also draw the page's picture (PNG, replaced if it exists; "
                        "needs matplotlib): success per set of trials and method")
    args = parser.parse_args(argv)

    cloud = read_points(args.data / "bunny" / "bun_zipper.ply")
    trials = make_trials(cloud, args.points, args.trials, args.shift, args.seed)
    methods = [name.strip() for name in args.methods.split(",") if name.strip()]
    unavailable: dict[str, str] = {}
    for method in methods:  # warm-up (imports, weights), untimed
        kind, seed, source, target, _ = trials[0]
        try:
            run(method, source, target, seed, args.max_iterations)
        except WeightsNotAvailableError:
            unavailable[method] = "weights not available"
        except MissingDependencyError as exc:
            unavailable[method] = f"not installed ({str(exc).split(';')[0]})"
        except BaselineTimeoutError:
            pass
    rows: dict[str, dict[str, list]] = {m: {"15deg": [], "so3": []} for m in methods}
    for number, (kind, seed, source, target, truth) in enumerate(trials, 1):
        diagonal = float(np.linalg.norm(np.ptp(target, axis=0)))
        pivot = source.mean(axis=0)
        for method in methods:
            if method in unavailable:
                continue
            try:
                estimate, runtime = run(method, source, target, seed, args.max_iterations)
                ok = strict_success(estimate, truth, diagonal, pivot=pivot)
                rows[method][kind].append((ok, rotation_error_deg(estimate, truth), runtime))
            except BaselineTimeoutError:
                rows[method][kind].append((False, float("nan"), float("nan")))
        print(f"trial {number}/{len(trials)} done", file=sys.stderr, flush=True)

    def median(values):
        values = [v for v in values if np.isfinite(v)]
        return statistics.median(values) if values else float("nan")

    reference = median([r[2] for r in rows.get("esm (local)", {}).get("15deg", [])])
    print(
        f"Bunny, {args.points} + {args.points} points (two samples), {args.trials} trials per set, "
        f"max_iterations={args.max_iterations}, local methods from the identity, seed {args.seed}.\n"
    )
    print("| method | kind | 15 deg: success | median rot. err. (deg) | median time (ms) | SO(3): success | median rot. err. (deg) | median time (ms) | time / esm (15 deg) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for method in methods:
        kind = "local" if method == "esm (local)" else "global" if method in PEERS else BASELINE_KINDS[method]
        if method in unavailable:
            print(f"| {method} | {kind} | {unavailable[method]} | | | | | | |")
            continue
        cells = []
        for trial_set in ("15deg", "so3"):
            results = rows[method][trial_set]
            timeouts = sum(1 for r in results if not np.isfinite(r[2]))
            success = f"{sum(r[0] for r in results)}/{len(results)}" + (f" ({timeouts} timeouts)" if timeouts else "")
            cells += [success, f"{median([r[1] for r in results]):.3g}", f"{1000 * median([r[2] for r in results]):.3g}"]
        ratio = median([r[2] for r in rows[method]["15deg"]]) / reference if reference else float("nan")
        print(f"| {method} | {kind} | " + " | ".join(cells) + f" | {ratio:.2g}x |")
    if args.picture:
        print(picture(rows, args.picture), file=sys.stderr)
    return 0


#: The picture's names of the two sets of trials.
SET_LABELS = {"15deg": "15 degrees", "so3": "any rotation (SO(3))"}


def picture(rows: dict, path: Path) -> Path:
    """The page's picture: strict success per set of trials (groups) and method (bars), the
    methods that could not run left out."""
    from esmicp_lab.figures import success_bars_figure, write_picture

    rates = [{"group": SET_LABELS[trial_set], "method": method, "successes": sum(r[0] for r in results),
              "trials": len(results)}
             for trial_set in ("15deg", "so3") for method, by_set in rows.items()
             if (results := by_set[trial_set])]
    figure = success_bars_figure(rates, title="The bunny, two samples of its surface: strict success per method",
                                 ylabel="strict success (%)")
    return write_picture(figure, path)


if __name__ == "__main__":
    sys.exit(main())
