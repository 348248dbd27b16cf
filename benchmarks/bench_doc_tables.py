"""Print the Markdown tables of docs/bench-paper.md or docs/bench-honest.md from a results folder
of ``esmicp bench`` (its rows.jsonl), so that the docs can be regenerated exactly:

    esmicp bench --paper --out bench-paper
    python benchmarks/bench_doc_tables.py paper bench-paper

    esmicp bench --datasets modelnet40,bunny-scans --trials 24 --out bench-honest
    python benchmarks/bench_doc_tables.py honest bench-honest --picture docs/images/bench-honest.png
    python benchmarks/bench_doc_tables.py honest --from-page docs/bench-honest.md --picture docs/images/bench-honest.png

    esmicp bench --protocols paper --datasets modelnet40 --methods esm,esm-paper --points 1024 --trials 24 \
        --sigma-sweep 0.005,0.01,0.02,0.05,0.1,0.2,0.5,1 --out bench-sigma
    python benchmarks/bench_doc_tables.py sigma bench-sigma

    esmicp bench --paper-1000 --out bench-paper-1000
    python benchmarks/bench_doc_tables.py paper-1000 bench-paper-1000     # docs/bench-paper-1000.md

    python benchmarks/bench_doc_tables.py times bench-paper     # where a run's time goes, per method

Figures are measured in the run, never stored in the repository. ``--picture PATH`` also draws
the page's picture from the same rows: strict success per protocol and method. A run's rows are
not kept: ``--from-page PAGE`` draws the picture of ``honest`` from the table this script wrote
into the page instead (its strict success per cell), so picture and table have one source.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections import defaultdict
from pathlib import Path

from esmicp_lab.bench import read_rows
from esmicp_lab.bench.tables import (
    PAPER_METRICS,
    metrics_table,
    overview_rates,
    overview_table,
    paper_1000_markdown,
    paper_1000_stats,
    protocol_label,
)

#: The paper's published tables (``--data`` / esm_icp_paper / this file).
PAPER_TABLES = Path("esm_icp_paper") / "paper_tables.json"
#: Which of our methods stands beside each method of the paper's 1,000-transform tables.
PAPER_1000_PEERS = {"ESM-ICP": ("esm-paper", "esm-global"), "KISS-Matcher": ("kiss-matcher", "kiss-matcher-icp")}


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


def _g(value) -> str:
    return "-" if value is None else f"{value:.3g}"


def _paper_rows(data_dir: Path) -> dict:
    """``{(table id, class, method): row}`` of the paper's 1,000-transform tables."""
    path = data_dir / PAPER_TABLES
    try:
        tables = json.loads(path.read_text())["tables"]
    except (OSError, ValueError, KeyError) as exc:
        sys.exit(f"{path}: cannot read the paper's tables ({exc})")
    found = {}
    for table in tables:
        for row in table["rows"]:
            if "(" in row["method"]:  # "Airplane (KISS-Matcher)"
                name, method = row["method"].rstrip(")").split(" (")
                found[(table["id"], name.lower(), method)] = row
    return found


def _beside_the_paper(records, data_dir: Path) -> str:
    """Per paper table and object: the paper's means, then ours (means over the same number of
    trials), each of our methods under the paper's method it stands for."""
    paper_rows = _paper_rows(data_dir)
    by_key = {(r["table"], r["cloud"].split("_")[0], r["method"]): r for r in records}
    names = " | ".join(label for _, label in PAPER_METRICS)
    parts = []
    for table in dict.fromkeys(r["table"] for r in records):
        lines = [f"#### {table}: the paper's means and ours\n", f"| object | method | trials | {names} |",
                 "|" + "---|" * (3 + len(PAPER_METRICS))]
        for cloud in dict.fromkeys(r["cloud"].split("_")[0] for r in records if r["table"] == table):
            for paper_method, ours in PAPER_1000_PEERS.items():
                published = paper_rows.get((table, cloud, paper_method))
                if published is not None:
                    cells = " | ".join(_g(published[label]) for _, label in PAPER_METRICS)
                    lines.append(f"| {cloud} | paper: {paper_method} | 1000 | {cells} |")
                for method in ours:
                    record = by_key.get((table, cloud, method))
                    if record is None:
                        continue
                    cells = " | ".join(_g(record[f"mean_{key}"]) for key, _ in PAPER_METRICS)
                    lines.append(f"| {cloud} | ours: {method} | {record['ok']} | {cells} |")
        parts.append("\n".join(lines) + "\n")
    return "\n".join(parts)


def _failures_dominate(records) -> str:
    """One sentence per (table, object, method) with strict failures: how much of the mean they make."""
    lines = []
    for r in records:
        trials = r["ok"] + r["failed"] + r["timeout"]
        if not trials:
            continue
        mean, median = r["mean_mse_t"], r["median_mse_t"]
        ratio = f"{mean / median:.3g}x the median" if mean and median else "-"
        if r["strict_failures"]:
            lines.append(
                f"- {r['table']}, {r['cloud']}, `{r['method']}`: {r['strict_failures']} of {trials} trials are strict "
                f"failures ({100 * r['strict_failures'] / trials:.3g}%); they make {_g(r['failures_share_mse_t_pct'])}% "
                f"of the sum behind its mean MSE(t) and {_g(r['failures_share_mse_r_pct'])}% of its mean MSE(R). "
                f"Mean MSE(t) {_g(mean)}, median {_g(median)} ({ratio}).")
        else:
            lines.append(f"- {r['table']}, {r['cloud']}, `{r['method']}`: no strict failure in {trials} trials; "
                         f"mean MSE(t) {_g(mean)}, median {_g(median)} ({ratio}).")
    return "\n".join(lines) + "\n"


def paper_1000(rows, data_dir: Path) -> str:
    records = paper_1000_stats(rows)
    ours = paper_1000_markdown(rows).split("\n", 2)[2]  # without its title
    return "\n".join([ours, "### How much of each mean the failures make\n", _failures_dominate(records),
                       "### Beside the paper's figures (means)\n", _beside_the_paper(records, data_dir),
                       ratios(rows, lambda r: True, reference="esm-paper")])


def times(rows) -> str:
    """Per method: rows, the sum of its registration calls' times and its share of all of them (a
    ``timeout`` row counts its limit, read from its reason), what dominates a run's wall time."""
    spent, counts = defaultdict(float), defaultdict(int)
    for row in rows:
        counts[row["method"]] += 1
        if row["time_s"] is not None:
            spent[row["method"]] += row["time_s"]
        elif row["status"] == "timeout":
            spent[row["method"]] += float(row["reason"].split("timeout_s=")[1].split()[0])
    total = sum(spent.values())
    lines = [f"{len(rows)} rows; the methods' calls took {total:.0f} s in all:", "",
             "| method | rows | time (s) | share | per row (s) |", "|---|---|---|---|---|"]
    for method in sorted(counts, key=lambda m: -spent[m]):
        lines.append(f"| {method} | {counts[method]} | {spent[method]:.0f} | {100 * spent[method] / total:.1f}% | "
                     f"{spent[method] / counts[method]:.3g} |")
    return "\n".join(lines) + "\n"


def success_rates(rows) -> list[dict]:
    """Strict successes and trials per protocol and method of the rows that ran (``unavailable``
    rows and sigma-sweep rows left out; ``failed`` / ``timeout`` count as trials not solved)."""
    counts: dict[tuple[str, str], list[bool]] = {}
    for row in rows:
        if row["status"] == "unavailable" or row.get("sigma") is not None:
            continue
        solved = row["status"] == "ok" and bool(row["success_strict"])
        counts.setdefault((protocol_label(row), row["method"]), []).append(solved)
    return [{"group": protocol, "method": method, "successes": sum(found), "trials": len(found)}
            for (protocol, method), found in counts.items()]


def picture(rows, path: Path) -> Path:
    """The page's picture: strict success per protocol (groups) and method (bars), from the rows."""
    from esmicp_lab.figures import success_bars_figure, write_picture

    figure = success_bars_figure(success_rates(rows), title="Strict success per protocol and method",
                                 ylabel="strict success (%)")
    return write_picture(figure, path)


def honest_picture(rates, path: Path) -> Path:
    """The picture of docs/bench-honest.md: strict success of every method (rows) on every protocol
    (columns), a grid (two dozen methods make bars unreadable). ``rates``: dicts with ``group``,
    ``method``, ``kind`` and ``percent`` (:func:`esmicp_lab.bench.tables.overview_rates`)."""
    from esmicp_lab.figures import success_grid_figure, write_picture

    labelled = [{**rate, "method": f"{rate['method']} ({rate['kind']})"} for rate in rates]
    figure = success_grid_figure(labelled, title="Strict success (%) per method and protocol",
                                 legend="strict success (%)")
    return write_picture(figure, path)


def _rates_of_rows(rows) -> list[dict]:
    kinds = {row["method"]: row["method_kind"] for row in rows}
    return [{"group": rate["group"], "method": rate["method"], "kind": kinds[rate["method"]],
             "percent": 100.0 * rate["successes"] / rate["trials"]} for rate in success_rates(rows)]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=("paper", "honest", "sigma", "paper-1000", "times"))
    parser.add_argument("results", type=Path, nargs="?", help="the --out folder of the run")
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data",
                        help="the shared data folder (paper-1000: the paper's tables; default ../shared/data)")
    parser.add_argument("--picture", type=Path, help="also draw the page's picture from the rows (PNG, replaced if "
                        "it exists; needs matplotlib): strict success per protocol and method")
    parser.add_argument("--from-page", type=Path, help="honest only: draw --picture from the table this script "
                        "wrote into this page (a run whose rows were not kept), print nothing else")
    args = parser.parse_args(argv)
    if args.from_page is not None:
        if args.kind != "honest" or args.picture is None:
            parser.error("--from-page draws the picture of 'honest': give the kind honest and --picture")
        try:
            rates = overview_rates(args.from_page.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            sys.exit(f"{args.from_page}: {exc}")
        print(honest_picture(rates, args.picture), file=sys.stderr)
        return 0
    if args.results is None:
        parser.error("the results folder (the --out folder of the run) is required")
    rows = read_rows(args.results / "rows.jsonl")
    if not rows:
        sys.exit(f"{args.results / 'rows.jsonl'}: no rows")
    if args.picture:
        drawn = honest_picture(_rates_of_rows(rows), args.picture) if args.kind == "honest" else picture(rows, args.picture)
        print(drawn, file=sys.stderr)
    if args.kind == "paper-1000":
        print(paper_1000(rows, args.data))
        return 0
    print({"paper": paper, "honest": honest, "sigma": sigma, "times": times}[args.kind](rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
