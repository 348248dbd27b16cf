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
    python benchmarks/baselines_table.py --from-page docs/baselines.md --picture docs/images/baselines.png

The rows of a run are not kept (several baselines need torch, probreg or py-goicp): ``--from-page``
draws the picture from the table this script printed into the page, so that picture and table
have one source.
"""

from __future__ import annotations

import argparse
import re
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


def kind_of(method: str) -> str:
    """``local`` or ``global``, as the table says."""
    return "local" if method == "esm (local)" else "global" if method in PEERS else BASELINE_KINDS[method]


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
    parser.add_argument("--from-page", type=Path, help="draw --picture from the table this script wrote into this "
                        "page (no run; prints nothing else)")
    args = parser.parse_args(argv)
    if args.from_page is not None:
        if args.picture is None:
            parser.error("--from-page draws the picture: give --picture too")
        try:
            rates = rates_from_page(args.from_page.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            sys.exit(f"{args.from_page}: {exc}")
        print(draw(rates, args.picture), file=sys.stderr)
        return 0

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
        kind = kind_of(method)
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
#: The table's header (see :func:`main`) and a success cell (``k/n``, maybe with time-outs).
TABLE_HEADER = "| method | kind | 15 deg: success |"
SUCCESS_CELL = re.compile(r"^(?P<successes>\d+)/(?P<trials>\d+)\b")


def picture(rows: dict, path: Path) -> Path:
    """The page's picture from a run's rows: strict success per method (rows of the grid) and set of
    trials (columns), the methods that could not run in grey."""
    rates = [{"group": SET_LABELS[trial_set], "method": row_label(method, kind_of(method)),
              "percent": 100.0 * sum(r[0] for r in results) / len(results) if results else None}
             for method, by_set in rows.items() for trial_set, results in by_set.items()]
    return draw(rates, path)


def row_label(method: str, kind: str) -> str:
    """A method's row in the picture: its name and kind (the peers from esmicp name theirs)."""
    return method if method in PEERS else f"{method} ({kind})"


def rates_from_page(markdown: str) -> list[dict]:
    """The success cells of the table :func:`main` printed, read back from the page it was
    written into: dicts with ``group`` (the set of trials), ``method`` and ``percent`` (None where
    the method did not run)."""
    lines = markdown.splitlines()
    start = next((k for k, line in enumerate(lines) if line.startswith(TABLE_HEADER)), None)
    if start is None:
        raise ValueError(f"no table of this script (a line {TABLE_HEADER!r} ...)")
    rates = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) != 9:
            raise ValueError(f"{len(cells)} cells in {line[:60]!r}, expected 9")
        for trial_set, cell in (("15deg", cells[2]), ("so3", cells[5])):
            found = SUCCESS_CELL.match(cell)
            rates.append({"group": SET_LABELS[trial_set], "method": row_label(cells[0], cells[1]),
                          "percent": 100.0 * int(found["successes"]) / int(found["trials"]) if found else None})
    if not rates:
        raise ValueError("the table has no rows")
    return rates


def draw(rates: list[dict], path: Path) -> Path:
    from esmicp_lab.figures import success_grid_figure, write_picture

    figure = success_grid_figure(rates, title="The bunny, two samples of its surface: strict success (%) per method",
                                 legend="strict success (%)")
    return write_picture(figure, path)


if __name__ == "__main__":
    sys.exit(main())
