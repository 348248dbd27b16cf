"""What the global search's exit for cost saves: the default search against the same search with
that exit closed (``SearchConfig(confident_score=2.0)``: no rotation-search pose is final before
the scan strategy runs), on the same trials, interleaved trial by trial (A, B, A, B, ...).

Trials: ``--trials`` per object protocol (``copy``, ``outliers-30``, ``outliers-60``) and ModelNet40
halves cut to 70% / 50%, round-robin over the 12 shapes of ``modelnet40/``. Prints, per group, the
successes of each and the ratio of the summed registration times (closed / default), and the
same over all trials. Figures are measured in the run.

    python benchmarks/global_exit_saving.py --trials 12
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

import esmicp
from esmicp_lab.bench.protocols import make_trials
from esmicp_lab.bench.real_pairs import partial_trial
from esmicp.core.procrustes import bounding_box_diagonal
from esmicp.globalreg.config import DEFAULT
from esmicp.metrics import up_to_symmetry_success

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def trials(data: Path, count: int, seed: int):
    clouds = {path.stem: esmicp.read_points(path) for path in sorted((data / "modelnet40").glob("*/*.txt"))}
    for protocol in ("copy", "outliers-30", "outliers-60"):
        for trial in make_trials(protocol, clouds, count, seed):
            yield protocol, trial.source, trial.target, trial.T_target_source, trial.clean_source, trial.diagonal
    names = list(clouds)
    for number, keep in enumerate((0.7, 0.5)):
        for index in range(count):
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1, number, index)))
            trial = partial_trial(clouds[names[index % len(names)]], keep, rng)
            yield (f"half-{round(100 * keep)}", trial.source, trial.target, trial.T_target_source, trial.source_half,
                   bounding_box_diagonal(trial.target))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--trials", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    closed = dataclasses.replace(DEFAULT, confident_score=2.0)
    totals: dict[str, dict[str, list]] = {}
    for number, (group, source, target, truth, clean, diagonal) in enumerate(trials(args.data, args.trials, args.seed)):
        for name, config in (("default", DEFAULT), ("closed", closed)):
            started = time.perf_counter()
            result = esmicp.register(source, target, rng=number, workers=1, config=config)
            elapsed = time.perf_counter() - started
            ok = bool(up_to_symmetry_success(clean, result.transformation, truth, diagonal))
            totals.setdefault(group, {}).setdefault(name, []).append((elapsed, ok))
    print("| trials | n | right, default | right, exit closed | time closed / default |")
    print("|---|---|---|---|---|")
    every: dict[str, list] = {"default": [], "closed": []}
    for group, runs in totals.items():
        for name in every:
            every[name] += runs[name]
        print(_row(group, runs))
    print(_row("all", every))


def _row(group: str, runs: dict[str, list]) -> str:
    default, closed = runs["default"], runs["closed"]
    ratio = sum(t for t, _ in closed) / max(sum(t for t, _ in default), 1e-12)
    return (f"| {group} | {len(default)} | {sum(ok for _, ok in default)} | {sum(ok for _, ok in closed)} | "
            f"{ratio:.2f} |")


if __name__ == "__main__":
    main()
