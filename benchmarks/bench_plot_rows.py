"""The benchmark plots of docs/visualisation.md from a few real local registrations.

Runs :func:`esmicp_lab.bench.trial_rows.local_trial_rows` (esm, icp, esm-paper from the identity on
seeded trials of the built-in shape, initial rotations spread over 0-180 degrees, plus a
fixed-sigma sweep of esm) and draws them with :func:`esmicp_lab.plots.write_bench_plots`.

    python benchmarks/bench_plot_rows.py docs/images/bench [--rows-out rows.jsonl] [--force]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from esmicp_lab.bench.trial_rows import local_trial_rows
from esmicp.errors import EsmicpError
from esmicp.io.atomic import atomic_write
from esmicp_lab.plots import write_bench_plots


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="bench_plot_rows.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--trials", type=int, default=12)
    parser.add_argument("--points", type=int, default=600)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rows-out", type=Path, metavar="FILE", help="also write the rows here (JSON Lines)")
    parser.add_argument("--force", action="store_true", help="overwrite existing files")
    args = parser.parse_args(argv)
    try:
        rows = local_trial_rows(trials=args.trials, points=args.points, seed=args.seed)
        if args.rows_out is not None:
            with atomic_write(args.rows_out, args.force, mode="w") as handle:
                handle.writelines(json.dumps(row) + "\n" for row in rows)
        for path in write_bench_plots(rows, args.out_dir, overwrite=args.force):
            print(path)
    except EsmicpError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
