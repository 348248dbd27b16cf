"""The paper's six result tables beside ours, in docs/bench-paper.md (generated, never typed).

Two steps, so that the docs can be regenerated (and checked by tests/test_paper_side_by_side.py)
without re-running the bench:

    esmicp bench --paper --out bench-paper                     # our rows (and --paper-1000 for the
    esmicp bench --paper-1000 --out bench-paper-1000           #   1,000-transform tables)
    python benchmarks/paper_side_by_side.py run --out bench-paper-tables
        # or only --paper's printed transforms, with the methods that stand for the paper's
        # (esmicp_lab.bench.side_by_side.PAPER_PEERS), PointNetLK and RPM-Net included: a few minutes
    python benchmarks/paper_side_by_side.py summarize bench-paper-tables bench-paper-1000
        # -> docs/bench-paper-side-by-side.csv: per paper table, cloud, method and size, our means
    python benchmarks/paper_side_by_side.py write
        # -> the tables between the side-by-side markers of docs/bench-paper.md
    python benchmarks/paper_side_by_side.py write --check      # exit 1 if the docs drifted
    python benchmarks/paper_side_by_side.py pictures docs/images
        # -> bench-paper.png and bench-paper-1000.png: the summary CSV's strict success rates, per
        #    paper table (printed transforms: per table and size) and method

The paper's figures come from ``<data>/esm_icp_paper/paper_tables.json`` (``--data``, default
``$ESMICP_SHARED_DATA`` or ../shared/data beside the checkout).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from esmicp_lab.bench import read_rows
from esmicp_lab.bench.side_by_side import PICTURES, regenerate, success_rates, summary_csv, summary_records
from esmicp.errors import EsmicpError

ROOT = Path(__file__).resolve().parents[1]
SUMMARY = ROOT / "docs" / "bench-paper-side-by-side.csv"
DOC = ROOT / "docs" / "bench-paper.md"
PAPER_JSON = Path("esm_icp_paper") / "paper_tables.json"


def default_data_dir() -> Path:
    override = os.environ.get("ESMICP_SHARED_DATA")
    return Path(override) if override else ROOT.parent / "shared" / "data"


def read_paper(data_dir: Path) -> dict:
    path = Path(data_dir) / PAPER_JSON
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        sys.exit(f"{path}: not found (give the shared data folder with --data)")
    except (OSError, ValueError) as exc:
        sys.exit(f"{path}: cannot read the paper's tables ({exc})")


def _summarize(args) -> int:
    rows = []
    for folder in args.results:
        found = read_rows(folder / "rows.jsonl")
        if not found:
            sys.exit(f"{folder / 'rows.jsonl'}: no rows")
        rows.extend(found)
    paper = read_paper(args.data)
    records = summary_records(rows, {table["id"] for table in paper["tables"]})
    if not records:
        sys.exit(f"{', '.join(map(str, args.results))}: no row reproduces a paper table (run esmicp bench --paper)")
    args.out.write_text(summary_csv(records), encoding="utf-8")
    print(f"{args.out}: {len(records)} records")
    return 0


def _run(args) -> int:
    from esmicp_lab.bench import BenchConfig, RunOptions, run_bench
    from esmicp_lab.bench.paper import PAPER_ITERATIONS
    from esmicp_lab.bench.side_by_side import PAPER_PEERS

    methods = tuple(dict.fromkeys(m for peers in PAPER_PEERS.values() for m in peers))
    config = BenchConfig(protocols=(), paper_tables=True, datasets=("modelnet40",), methods=methods,
                         points=(1024, 2048), max_iterations=PAPER_ITERATIONS, seed=0, data_dir=str(args.data))
    outcome = run_bench(config, RunOptions(out_dir=args.out, workers=args.workers, resume=args.resume,
                                           force=args.force, progress=False))
    print(f"{outcome.out_dir}: {outcome.rows_written} rows written, {outcome.rows_skipped} already there")
    return 0


def _write(args) -> int:
    paper = read_paper(args.data)
    try:
        summary_text = args.summary.read_text(encoding="utf-8")
        doc_text = args.doc.read_text(encoding="utf-8")
    except OSError as exc:
        sys.exit(f"{exc.filename}: cannot read ({exc.strerror})")
    new = regenerate(doc_text, paper, summary_text, str(args.summary), str(DOC))
    if args.check:
        if new != doc_text:
            print(f"{args.doc}: the side-by-side tables differ from what {args.summary} gives; "
                  "run python benchmarks/paper_side_by_side.py write", file=sys.stderr)
            return 1
        return 0
    args.doc.write_text(new, encoding="utf-8")
    print(f"{args.doc}: side-by-side tables written")
    return 0


def _pictures(args) -> int:
    from esmicp_lab.figures import success_bars_figure, write_picture

    if not args.folder.is_dir():
        sys.exit(f"{args.folder}: no such folder")
    try:
        summary_text = args.summary.read_text(encoding="utf-8")
    except OSError as exc:
        sys.exit(f"{exc.filename}: cannot read ({exc.strerror})")
    for name, (title, keep) in PICTURES.items():
        rates = success_rates(summary_text, keep)
        if not rates:
            sys.exit(f"{args.summary}: no record for {name}")
        print(write_picture(success_bars_figure(rates, title=title, ylabel="strict success (%)"), args.folder / name))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=default_data_dir(), help="the shared data folder")
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="run --paper's printed transforms with the paper's peers")
    run.add_argument("--out", type=Path, default=Path("bench-paper-tables"))
    run.add_argument("--workers", type=int, default=None)
    run.add_argument("--resume", action="store_true")
    run.add_argument("--force", action="store_true")
    summarize = commands.add_parser("summarize", help="bench results folders -> the summary CSV")
    summarize.add_argument("results", type=Path, nargs="+", help="--out folders of esmicp bench")
    summarize.add_argument("--out", type=Path, default=SUMMARY)
    write = commands.add_parser("write", help="the summary CSV + the paper's tables -> docs/bench-paper.md")
    write.add_argument("--summary", type=Path, default=SUMMARY)
    write.add_argument("--doc", type=Path, default=DOC)
    write.add_argument("--check", action="store_true", help="change nothing; exit 1 if the docs differ")
    pictures = commands.add_parser("pictures", help="the summary CSV -> the bench pages' pictures (matplotlib)")
    pictures.add_argument("folder", type=Path, help="where to write them (replaced if they exist)")
    pictures.add_argument("--summary", type=Path, default=SUMMARY)
    args = parser.parse_args(argv)
    try:
        return {"run": _run, "summarize": _summarize, "write": _write, "pictures": _pictures}[args.command](args)
    except EsmicpError as exc:
        sys.exit(str(exc))


if __name__ == "__main__":
    sys.exit(main())
