"""Print the Markdown tables of docs/bench-paper.md or docs/bench-honest.md from a results folder
of ``esmicp bench`` (its rows.jsonl), so that the docs can be regenerated exactly:

    esmicp bench --paper --out bench-paper
    python benchmarks/bench_doc_tables.py paper bench-paper

    esmicp bench --datasets modelnet40,bunny-scans --trials 24 --out bench-honest
    python benchmarks/bench_doc_tables.py honest bench-honest

    esmicp bench --protocols paper --datasets modelnet40 --methods esm,esm-paper --points 1024 --trials 24 \
        --sigma-sweep 0.005,0.01,0.02,0.05,0.1,0.2,0.5,1 --out bench-sigma
    python benchmarks/bench_doc_tables.py sigma bench-sigma

Figures are measured in the run, never stored in the repository.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections import defaultdict
from pathlib import Path

from esmicp.bench import read_rows
from esmicp.bench.tables import metrics_table, overview_table, protocol_label


def _median_times(rows, protocol_filter) -> dict:
    times = defaultdict(list)
    for row in rows:
        if protocol_filter(row) and row["status"] == "ok":
            times[row["method"]].append(row["time_s"])
    return {method: statistics.median(values) for method, values in times.items()}


def ratios(rows, protocol_filter, reference="esm-global") -> str:
    times = _median_times(rows, protocol_filter)
    if reference not in times:
        return ""
    lines = [f"Median time of the registration call, and {reference}'s time divided by each method's "
             "(same trials, same run, interleaved on the same workers):", "",
             "| method | median time (ms) | ratio |", "|---|---|---|"]
    for method, value in times.items():
        lines.append(f"| {method} | {1000 * value:.3g} | {times[reference] / value:.2f} |")
    return "\n".join(lines) + "\n"


def paper(rows) -> str:
    random_rows = [r for r in rows if r["protocol"] != "paper-table"]
    printed = [r for r in rows if r["protocol"] == "paper-table"]
    parts = ["### Random paper protocols (Euler angles uniform in [-pi, pi], translations in [-r, r])\n",
             overview_table(random_rows), "### The paper's printed transforms\n", overview_table(printed)]
    smallest = min(r["points"] for r in rows)
    for label in dict.fromkeys(protocol_label(r) for r in printed):
        group = [r for r in printed if protocol_label(r) == label and r["points"] == smallest]
        parts.append(f"#### {label}, {group[0]['cloud']}, {smallest} points "
                     f"(initial rotation {group[0]['initial_rotation_deg']:.1f} deg)\n")
        parts.append(metrics_table(group))
    widest = max(r["translation_range"] for r in random_rows)
    for label in dict.fromkeys(protocol_label(r) for r in random_rows if r["translation_range"] == widest):
        group = [r for r in random_rows if protocol_label(r) == label]
        parts.append(f"#### {label} (all sizes, means of the paper's metrics over the trials)\n")
        parts.append(metrics_table(group))
    parts.append(ratios(rows, lambda r: True))
    return "\n".join(parts)


def honest(rows) -> str:
    objects = [r for r in rows if r["protocol"] != "scan-pairs"]
    return "\n".join([overview_table(rows), ratios(objects, lambda r: True)])


def sigma(rows) -> str:
    return metrics_table(rows)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=("paper", "honest", "sigma"))
    parser.add_argument("results", type=Path, help="the --out folder of the run")
    args = parser.parse_args(argv)
    rows = read_rows(args.results / "rows.jsonl")
    if not rows:
        sys.exit(f"{args.results / 'rows.jsonl'}: no rows")
    print({"paper": paper, "honest": honest, "sigma": sigma}[args.kind](rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
