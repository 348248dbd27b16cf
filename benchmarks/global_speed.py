"""Speed of global registration at 2,000 vs 2,000 points: ``esmicp.register`` against KISS-Matcher.

What it measures: the median time of ``esmicp.register(source, target)`` (no initial pose) over the
suite's 2,000-point trials, against KISS-Matcher's median on the same trials in the same run.

Trials: :func:`esmicp_lab.bench.protocols.make_trials` on the 12 ModelNet40 objects and the bunny
(``--protocols``, default ``copy`` and ``shuffled``, where every method succeeds and the time is
the search's, not a failure's), ``--trials`` each, as ``benchmarks/global_protocols.py`` makes
them (same seeds, same per-trial method seed). Methods take turns trial by trial (the order
rotating), after one untimed warm-up call each; only the registration call is timed
(``time.perf_counter``). Methods: ``esm-global``; ``kiss-matcher`` (KISS-Matcher's pose alone)
and ``kiss-matcher-icp`` (then Open3D point-to-point ICP, as the suite compares it), both from
:mod:`esmicp_lab.baselines` (``pip install 'esmicp[baselines]'``).

Prints, per protocol and over all trials: each method's median, p90 and strict success, and
esm-global's time against each peer's: the ratio of the medians and, in brackets, the median of
the per-trial ratios (same trial, consecutive calls). Nothing is written.

    python benchmarks/global_speed.py --trials 130
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from global_protocols import DEFAULT_DATA, build_trials, load_clouds, make_runner, run_one  # noqa: E402

PEERS = ("kiss-matcher", "kiss-matcher-icp")


def _summary(rows: list[dict]) -> tuple[float, float, float]:
    """(median ms, p90 ms, strict success %) of one method's rows."""
    times = [1e3 * row["time_s"] for row in rows if "time_s" in row]
    if not times:
        return float("nan"), float("nan"), 0.0
    return (statistics.median(times), float(np.percentile(times, 90)),
            100.0 * sum(bool(row["strict"]) for row in rows) / len(rows))


def _paired(mine: list[dict], theirs: list[dict]) -> float:
    """Median over the trials both timed of (my time / their time)."""
    ratios = [a["time_s"] / b["time_s"] for a, b in zip(mine, theirs) if "time_s" in a and "time_s" in b]
    return statistics.median(ratios) if ratios else float("nan")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    parser.add_argument("--trials", type=int, default=130, help="trials per protocol")
    parser.add_argument("--points", type=int, default=2000, help="points per cloud")
    parser.add_argument("--protocols", default="copy,shuffled")
    parser.add_argument("--methods", default=",".join(("esm-global", *PEERS)))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.protocols = args.protocols.split(",")
    methods = args.methods.split(",")
    args.scan_points, args.scan_trials = 0, None
    trials = build_trials(args, load_clouds(args.data))
    runners = {method: make_runner(method) for method in methods}
    first = next(iter(trials.values()))[0]
    for method, runner in runners.items():  # imports and first calls outside the timings
        runner(first.source, first.target, 0)
    print(f"load average {os.getloadavg()[0]:.1f} at the start; {len(trials)} protocols x {args.trials} trials, "
          f"{args.points} points")
    rows: dict[str, dict[str, list]] = {p: {m: [] for m in methods} for p in trials}
    for protocol, protocol_trials in trials.items():
        for k, trial in enumerate(protocol_trials):
            turn = methods[k % len(methods):] + methods[: k % len(methods)]
            for method in turn:
                rows[protocol][method].append(run_one(runners[method], method, trial))
    print(f"load average {os.getloadavg()[0]:.1f} at the end")
    print("| protocol | " + " | ".join(f"{m} median / p90 ms (strict %)" for m in methods) + " | "
          + " | ".join(f"esm-global / {m}" for m in methods if m != "esm-global") + " |")
    print("|---" * (2 * len(methods)) + "|")
    groups = {**{p: rows[p] for p in rows}, "all": {m: [r for p in rows for r in rows[p][m]] for m in methods}}
    for name, by_method in groups.items():
        figures = {m: _summary(by_method[m]) for m in methods}
        cells = [f"{figures[m][0]:.1f} / {figures[m][1]:.1f} ({figures[m][2]:.0f})" for m in methods]
        ratios = [f"{figures['esm-global'][0] / figures[m][0]:.2f} "
                  f"({_paired(by_method['esm-global'], by_method[m]):.2f})"
                  for m in methods if m != "esm-global" and "esm-global" in figures]
        print(f"| {name} | " + " | ".join(cells) + " | " + " | ".join(ratios) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
