"""``esmicp bench``: the command line of the benchmark suite (:mod:`esmicp_lab.bench`), a thin layer:
parse flags into a :class:`~esmicp_lab.bench.BenchConfig`, run, print where the results are.

Hooked into ``esmicp`` by :func:`add_parser` (called from :func:`esmicp.cli.build_parser`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from esmicp.cli.args import EXIT_INTERRUPTED, EXIT_OK, EXIT_TERMINATED, nonnegative_int, positive_int

#: Flags that take part in the configuration, and the BenchConfig field each one sets.
_CONFIG_FLAGS = {
    "protocols": "protocols", "datasets": "datasets", "methods": "methods", "trials": "trials",
    "points": "points", "seed": "seed", "max_iterations": "max_iterations", "init": "init",
    "init_angle": "init_perturbation_deg", "init_shift": "init_perturbation_fraction",
    "translation_ranges": "translation_ranges", "sigma_sweep": "sigma_sweep", "data": "data_dir",
    "slow_trials": "slow_trials",
}


def _names(text: str) -> tuple[str, ...]:
    names = tuple(part.strip() for part in text.split(",") if part.strip())
    if not names:
        raise argparse.ArgumentTypeError(f"expected a comma-separated list, got {text!r}")
    return names




def _numbers(kind):
    def parse(text: str) -> tuple:
        try:
            values = tuple(kind(part) for part in _names(text))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
        return values

    return parse




def add_parser(commands) -> argparse.ArgumentParser:
    """Add the ``bench`` subcommand to ``commands`` (the subparsers of ``esmicp``)."""
    bench = commands.add_parser(
        "bench",
        help="run the benchmark suite (paper protocol and tables, honest protocols, every method)",
        description="Run registration methods on seeded trials and write one JSON row per (trial, method) "
        "to OUT/rows.jsonl, the resolved configuration (config.json) and library versions (versions.json) "
        "beside it, and summary tables (summary.md, summary.csv; with --paper one paper-*.md per paper "
        "table). Defaults: the honest protocols on the built-in synthetic clouds, every method. "
        "Exit status: 0 done, 2 bad input (nothing run), 130 interrupted (finished trials kept: "
        "continue with --resume). See docs/bench.md.",
    )
    presets = bench.add_mutually_exclusive_group()
    presets.add_argument("--paper", action="store_true",
                         help="the paper's experiments: protocols paper, paper-noise-30, paper-noise-60 at translation "
                         "ranges 1,100,1000 plus the paper's printed transforms, on modelnet40, with our methods and "
                         "the geometric baselines and dcp-v1, 40 iterations (other flags override)")
    presets.add_argument("--paper-1000", action="store_true",
                         help="the paper's 1,000-transform tables against KISS-Matcher: 1,000 trials (--trials) "
                         "of protocol paper-1000 on airplane, person, stool and paper-1000-noise-30 on stool, "
                         "translations in [-1000, 1000], the whole 10,000-point clouds, 100 iterations, methods "
                         "esm-paper, esm-global, kiss-matcher, kiss-matcher-icp (15-20 minutes on a quiet 2-core machine)")
    bench.add_argument("--protocols", type=_names, help="comma-separated (default: copy,shuffled,resampled,"
                       "outliers-30,outliers-60,partial,shuffled-45,scan-pairs)")
    bench.add_argument("--datasets", type=_names, help="comma-separated: synthetic (default), modelnet40, bunny, "
                       "bunny-scans, lidar-pair, or folders of point-cloud / mesh files")
    bench.add_argument("--methods", type=_names, help="comma-separated method names, or 'all' (default), 'ours', "
                       "'geometric' (all but the learned baselines)")
    bench.add_argument("--trials", type=positive_int, help="trials per protocol, dataset and size (default 10; --paper 12; "
                       "--paper-1000: per table group, 1000)")
    bench.add_argument("--points", type=_numbers(int), help="cloud sizes, comma-separated (default 1024,2048)")
    bench.add_argument("--seed", type=int, help="base seed of every trial (default 0)")
    bench.add_argument("--slow-trials", type=nonnegative_int, metavar="N",
                       help="run the slow methods (cpd, icp-nl: a second or more per trial) on the first N "
                       "trials of each randomised group only and on every paper-table case, go-icp on the "
                       "paper-table cases without outliers only (default 1; 0: every method on every trial)")
    bench.add_argument("--max-iterations", type=positive_int, help="iteration budget of every local method (default 40)")
    bench.add_argument("--init", choices=("identity", "perturbed"),
                       help="start of every local method: identity (default) or perturbed (the truth moved by "
                       "--init-angle degrees and --init-shift diagonals)")
    bench.add_argument("--init-angle", type=float, help="perturbed start: rotation, degrees (default 30)")
    bench.add_argument("--init-shift", type=float, help="perturbed start: shift, fraction of the diagonal (default 0.1)")
    bench.add_argument("--translation-ranges", type=_numbers(float),
                       help="paper protocols: translation ranges, cloud units (default 1000; --paper 1,100,1000)")
    bench.add_argument("--sigma-sweep", type=_numbers(float), metavar="S1,S2,...",
                       help="run esm and esm-paper once per fixed sigma (cloud units) instead of their default, "
                       "e.g. 0.005,0.01,0.02,0.05,0.1,0.2")
    bench.add_argument("--data", type=str, help="the shared data folder (default $ESMICP_SHARED_DATA or ../shared/data)")
    bench.add_argument("--out", type=Path, default=Path("bench-results"), help="results folder (default bench-results)")
    bench.add_argument("--workers", type=positive_int, help="worker processes (default: every local core; 1 = serial)")
    bench.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                       help="run on this existing Dask scheduler (default: a local Dask cluster)")
    bench.add_argument("--resume", action="store_true",
                       help="continue the run in --out: skip finished (trial, method) rows; flags not given are "
                       "taken from its config.json")
    bench.add_argument("--force", action="store_true", help="replace the results in --out")
    bench.add_argument("--no-progress", action="store_true", help="no progress bar")
    bench.add_argument("--plots", action="store_true", help="also draw the figures (needs matplotlib: the viz or bench extra)")
    scans = bench.add_argument_group(
        "scan benchmark (--datasets real-pairs and/or partial-overlap; see docs/real-scans.md)",
        "Every global method on the real pairs of a folder (variants as-recorded and turned) and on "
        "ModelNet40 objects cut to 70%% and 50%% (protocols partial-70, partial-50): writes OUT/rows.jsonl and "
        "OUT/real-scans.md. --methods: esm-global, kiss-matcher-icp, kiss-matcher-gicp, open3d-ransac-fpfh-icp, "
        "fgr-icp (default all); --protocols: as-recorded, turned, partial-70, partial-50 (default all), and cropped (each real pair "
        "cropped by a seeded plane so that 20%% of the source lies on the target, 3DLoMatch's range); --trials: partial trials per fraction "
        "(default 24).",
    )
    scans.add_argument("--real-pairs-dir", type=Path, metavar="DIR",
                       help="a folder laid out like shared/data/real_pairs (pairs.csv; default <data>/real_pairs)")
    scans.add_argument("--pairs", type=_names, metavar="DATASET/PAIR,...", help="only these pairs of pairs.csv")
    scans.add_argument("--bin-columns", type=int, choices=(3, 4), default=3,
                       help="float32 columns of the pairs' .bin scans (default 3, as in the shared folder; "
                       "KITTI's own files: 4)")
    bench.set_defaults(handler=run)
    return bench


#: The methods of ``--paper-1000``: the paper's ESM-ICP (``esm-paper``), the library's default
#: (``esm-global``), KISS-Matcher alone (the paper's peer) and refined by ICP.
PAPER_1000_METHODS = ("esm-paper", "esm-global", "kiss-matcher", "kiss-matcher-icp")
#: ``--paper-1000`` registers the whole clouds (the paper uses them raw; the shared ModelNet40
#: files hold 10,000 points each).
PAPER_1000_POINTS = 10_000


def _defaults(paper: bool, paper_1000: bool = False) -> dict:
    from .bench.config import HONEST_OBJECT_PROTOCOLS, SCAN_PROTOCOL
    from .bench.datasets import default_data_dir
    from .bench.paper import (
        PAPER_1000_ITERATIONS,
        PAPER_1000_TRANSLATION_RANGE,
        PAPER_1000_TRIALS,
        PAPER_ITERATIONS,
        PAPER_TRANSLATION_RANGES,
    )

    common = dict(points=(1024, 2048), seed=0, init="identity", init_perturbation_deg=30.0,
                  init_perturbation_fraction=0.1, sigma_sweep=(), data_dir=str(default_data_dir()))
    if paper_1000:
        return dict(common, protocols=(), datasets=("modelnet40",), methods=PAPER_1000_METHODS, trials=1,
                    points=(PAPER_1000_POINTS,), max_iterations=PAPER_1000_ITERATIONS,
                    translation_ranges=(PAPER_1000_TRANSLATION_RANGE,), paper_tables=False,
                    paper_1000_trials=PAPER_1000_TRIALS)
    if paper:
        return dict(common, protocols=("paper", "paper-noise-30", "paper-noise-60"), datasets=("modelnet40",),
                    methods=("geometric", "dcp-v1"), trials=12, max_iterations=PAPER_ITERATIONS,
                    translation_ranges=PAPER_TRANSLATION_RANGES, paper_tables=True)
    return dict(common, protocols=(*HONEST_OBJECT_PROTOCOLS, SCAN_PROTOCOL), datasets=("synthetic",),
                methods=("all",), trials=10, max_iterations=40, translation_ranges=(1000.0,), paper_tables=False)


def _expand_methods(names) -> tuple[str, ...]:
    from .bench.methods import OUR_METHODS, is_learned, method_names

    expanded = []
    for name in names:
        if name == "all":
            expanded.extend(method_names())
        elif name == "ours":
            expanded.extend(OUR_METHODS)
        elif name == "geometric":
            expanded.extend(m for m in method_names() if not is_learned(m))
        else:
            expanded.append(name)
    return tuple(dict.fromkeys(expanded))


def build_config(args):
    """The :class:`~esmicp_lab.bench.BenchConfig` of ``args``: with ``--resume``, the saved one with the
    flags given on top; otherwise the defaults (``--paper``'s or the honest ones) with the flags."""
    from .bench import BenchConfig
    from .bench.results import CONFIG, read_json

    values = None
    if args.resume:
        values = read_json(args.out / CONFIG)
        if values is None:
            from esmicp.errors import InvalidInputError

            raise InvalidInputError(f"{args.out / CONFIG}: not found, nothing to resume")
        values = {key: tuple(value) if isinstance(value, list) else value for key, value in values.items()}
    if values is None:
        values = _defaults(args.paper, args.paper_1000)
    # A run of the 1,000-transform tables alone: --trials is the trials per table group.
    only_1000 = values.get("paper_1000_trials", 0) > 0 and not values["protocols"]
    for flag, field in _CONFIG_FLAGS.items():
        value = getattr(args, flag)
        if value is not None:
            values["paper_1000_trials" if field == "trials" and only_1000 else field] = value
    if args.paper:
        values["paper_tables"] = True
    values["methods"] = _expand_methods(values["methods"])
    return BenchConfig.from_dict(values)


#: ``--datasets`` names that select the scan benchmark (:mod:`esmicp_lab.bench.scans`).
SCAN_DATASETS = ("real-pairs", "partial-overlap")
_SCAN_PROTOCOLS = ("as-recorded", "turned", "partial-70", "partial-50")
#: Accepted as well, run only when asked for (the real pairs cropped to a low overlap).
_SCAN_EXTRA_PROTOCOLS = ("cropped",)


def run_scans(args) -> int:
    """``esmicp bench --datasets real-pairs[,partial-overlap]``: the scan benchmark."""
    from .bench.datasets import default_data_dir
    from .bench.scans import SCAN_METHODS, ScanBenchConfig, partial_markdown, real_pairs_markdown, run_scan_bench
    from esmicp.errors import InvalidInputError, OutputExistsError
    from esmicp.io.atomic import atomic_write

    unknown = [name for name in args.datasets if name not in SCAN_DATASETS]
    if unknown:
        raise InvalidInputError(f"datasets: {', '.join(unknown)} cannot be mixed with {', '.join(SCAN_DATASETS)} "
                                "(the scan benchmark runs alone)")
    protocols = args.protocols or _SCAN_PROTOCOLS
    for name in protocols:
        if name not in _SCAN_PROTOCOLS + _SCAN_EXTRA_PROTOCOLS:
            raise InvalidInputError(f"protocols: {name!r} is not a scan-benchmark protocol; choose from "
                                    f"{', '.join(_SCAN_PROTOCOLS + _SCAN_EXTRA_PROTOCOLS)}")
    data_dir = Path(args.data) if args.data else default_data_dir()
    real_dir = args.real_pairs_dir or data_dir / "real_pairs"
    variants = tuple(p for p in protocols if p in ("as-recorded", "turned", "cropped"))
    keeps = tuple(k for p, k in (("partial-70", 0.7), ("partial-50", 0.5)) if p in protocols)
    methods = SCAN_METHODS if args.methods in (None, ("all",)) else args.methods
    config = ScanBenchConfig(
        real_pairs_dir=str(real_dir) if "real-pairs" in args.datasets and variants else None,
        data_dir=str(data_dir), methods=tuple(methods), variants=variants or ("as-recorded",),
        partial_keeps=keeps, partial_trials=(args.trials or 24) if "partial-overlap" in args.datasets and keeps else 0,
        seed=args.seed or 0, bin_columns=args.bin_columns, pairs=args.pairs or (),
    )
    if config.real_pairs_dir is None and not config.partial_trials:
        raise InvalidInputError("nothing to run: the protocols given apply to none of the datasets given")
    out = args.out
    rows_path = out / "rows.jsonl"
    if rows_path.exists() and not args.force:
        raise OutputExistsError(rows_path)
    out.mkdir(parents=True, exist_ok=True)

    def progress(row):
        if not args.no_progress:
            what = row.get("pair") or f"{row.get('cloud')}#{row.get('trial_index')}"
            state = "ok" if row.get("success") else ("failed" if row["status"] != "ok" else "no")
            print(f"{row['protocol']} {what} {row.get('variant', '')} {row['method']}: {state} "
                  f"{row['time_s']:.2f} s", file=sys.stderr, flush=True)

    rows = run_scan_bench(config, rows_path, progress)
    text = ""
    if config.real_pairs_dir is not None:
        text += f"## Real pairs ({real_dir})\n\n" + real_pairs_markdown(rows) + "\n"
    if config.partial_trials:
        text += "## Partial overlap (ModelNet40)\n\n" + partial_markdown(rows)
    tables = out / "real-scans.md"
    with atomic_write(tables, overwrite=True, mode="w") as handle:
        handle.write(text)
    print(text)
    print(f"{len(rows)} rows in {rows_path}; tables written to {tables}")
    return EXIT_OK


def run(args) -> int:
    from .bench import Interrupted, RunOptions, run_bench, read_rows
    from .bench.results import ROWS

    if args.datasets and any(name in SCAN_DATASETS for name in args.datasets):
        return run_scans(args)

    if args.plots:
        # Before the run, not after it: a missing plotting library must not cost a whole run.
        from esmicp.viz import require

        require("matplotlib")
    config = build_config(args)
    options = RunOptions(out_dir=args.out, workers=args.workers, scheduler=args.scheduler, resume=args.resume,
                         force=args.force, progress=not args.no_progress)
    try:
        outcome = run_bench(config, options)
    except Interrupted as stop:
        what = "terminated (SIGTERM)" if stop.terminated else "interrupted"
        print(f"esmicp bench: {what}; {stop.rows_written} finished rows of this session are in {stop.rows_path}; "
              f"continue with: esmicp bench --out {args.out} --resume", file=sys.stderr)
        return EXIT_TERMINATED if stop.terminated else EXIT_INTERRUPTED
    print(f"{outcome.rows_written} rows run, {outcome.rows_skipped} already done, {outcome.rows_total} in "
          f"{outcome.out_dir / ROWS}")
    for path in outcome.files:
        print(f"table written to {path}")
    if args.plots:
        from .plots import write_bench_plots

        # The plots are derived from every row on disk, so a resumed run redraws them.
        paths = write_bench_plots(read_rows(outcome.out_dir / ROWS), outcome.out_dir,
                                  overwrite=args.resume or args.force)
        for path in paths:
            print(f"plot written to {path}")
    return EXIT_OK
