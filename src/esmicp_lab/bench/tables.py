"""Summary tables from rows: Markdown in the paper's layout (rows = methods, columns = metrics)
and CSV; and the generated part of a results page, rewritten between its markers.

Conventions (also in ``docs/bench.md``):

- Success rates count every row that ran or crashed (``ok``, ``failed``, ``timeout``): a crash is
  a failure to register. ``unavailable`` rows are not counted; the method shows as unavailable.
- The paper's metrics (MSE / RMSE / MAE of the rotation-matrix entries and of the translation
  vector) are means over the ``ok`` rows, as the paper averages; rotation / translation errors
  and times are medians over the ``ok`` rows.
"""

from __future__ import annotations

import csv
import io
import re
import statistics
from collections import defaultdict

SUMMARY_MD = "summary.md"
SUMMARY_CSV = "summary.csv"
#: The 1,000-transform tables (rows of the ``paper-1000*`` protocols), Markdown and CSV.
PAPER_1000_MD = "paper-1000.md"
PAPER_1000_CSV = "paper-1000.csv"
#: Globs of every table file a run writes (``--force`` removes them).
TABLE_FILES_GLOB = ("summary.*", "paper-*.md", "paper-*.csv")

PAPER_METRICS = (("mse_r", "MSE(R)"), ("rmse_r", "RMSE(R)"), ("mae_r", "MAE(R)"),
                 ("mse_t", "MSE(t)"), ("rmse_t", "RMSE(t)"), ("mae_t", "MAE(t)"))
CSV_COLUMNS = ("protocol", "method", "sigma", "method_kind", "init", "max_iterations", "rows", "ok", "failed",
               "timeout", "unavailable", "success_strict_pct", "success_symmetry_pct",
               "median_rotation_error_deg", "median_translation_error", *[key for key, _ in PAPER_METRICS],
               "median_time_s", "reason")


def protocol_label(row: dict) -> str:
    """The protocol as tables group it: with the translation range (``paper-t1000``) or the
    printed case (``paper-table:airplane``) where there is one."""
    if row.get("case"):
        return f"{row['protocol']}:{row['case']}"
    if row.get("translation_range") is not None:
        return f"{row['protocol']}-t{row['translation_range']:g}"
    return row["protocol"]


def method_label(row: dict) -> str:
    return row["method"] if row.get("sigma") is None else f"{row['method']} (sigma={row['sigma']:g})"


def _median(values):
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def _mean(values):
    values = [v for v in values if v is not None]
    return statistics.fmean(values) if values else None


def _fmt(value, digits=3) -> str:
    if value is None:
        return "-"
    if isinstance(value, str):
        return value
    return f"{value:.{digits}g}"


def group_stats(rows: list[dict]) -> dict:
    """Counts, success rates, medians and the paper's means for the rows of one group."""
    ok = [r for r in rows if r["status"] == "ok"]
    counted = [r for r in rows if r["status"] != "unavailable"]
    stats = {
        "rows": len(rows),
        "ok": len(ok),
        "failed": sum(r["status"] == "failed" for r in rows),
        "timeout": sum(r["status"] == "timeout" for r in rows),
        "unavailable": sum(r["status"] == "unavailable" for r in rows),
        "success_strict_pct": 100.0 * sum(bool(r["success_strict"]) for r in ok) / len(counted) if counted else None,
        "success_symmetry_pct": 100.0 * sum(bool(r["success_symmetry"]) for r in ok) / len(counted) if counted else None,
        "median_rotation_error_deg": _median(r["rotation_error_deg"] for r in ok),
        "median_translation_error": _median(r["translation_error"] for r in ok),
        "median_time_s": _median(r["time_s"] for r in ok),
        "reason": without_folders(next((r["reason"] for r in rows if r["status"] != "ok"), "")),
    }
    for key, _ in PAPER_METRICS:
        stats[key] = _mean(r[key] for r in ok)
    first = rows[0]
    stats.update(method_kind=first["method_kind"], init=first["init"], max_iterations=first["max_iterations"])
    return stats


def _groups(rows, key):
    groups = defaultdict(list)
    for row in rows:
        groups[key(row)].append(row)
    return groups


def _ordered_methods(rows) -> list[str]:
    seen = {}
    for row in rows:
        seen.setdefault(method_label(row), None)
    return list(seen)


def _success_cell(stats) -> str:
    if stats["ok"] == 0 and stats["unavailable"] == stats["rows"]:
        return "unavailable"
    cell = f"{_fmt(stats['success_strict_pct'], 3)} / {_fmt(stats['success_symmetry_pct'], 3)}"
    if stats["median_time_s"] is not None:
        cell += f" ({1000 * stats['median_time_s']:.3g} ms)"
    crashed = stats["failed"] + stats["timeout"]
    return cell + (f" [{crashed} failed]" if crashed else "")


def overview_table(rows: list[dict]) -> str:
    """Methods x protocols; cell: strict success % / success up to symmetry % (median time)."""
    protocols = list(dict.fromkeys(protocol_label(r) for r in rows))
    by_cell = _groups(rows, lambda r: (method_label(r), protocol_label(r)))
    counts = {p: len({r["trial_id"] for r in rows if protocol_label(r) == p}) for p in protocols}
    header = "| method | kind | " + " | ".join(f"{p} ({counts[p]} trials)" for p in protocols) + " |"
    lines = [header, "|" + "---|" * (len(protocols) + 2)]
    for method in _ordered_methods(rows):
        kind = next(r["method_kind"] for r in rows if method_label(r) == method)
        cells = [_success_cell(group_stats(by_cell[(method, p)])) if by_cell.get((method, p)) else "-"
                 for p in protocols]
        lines.append(f"| {method} | {kind} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


_OVERVIEW_HEADER = re.compile(r"^\| method \| kind \|(?P<protocols>.+)\|\s*$")
_OVERVIEW_CELL = re.compile(r"^(?P<strict>[\d.e+-]+) / (?P<symmetry>[\d.e+-]+)\b")


def overview_rates(markdown: str) -> list[dict]:
    """The cells of the first :func:`overview_table` in ``markdown`` (a results page the table was
    written into), read back: one dict per method and protocol with ``method``, ``kind``,
    ``group`` (the protocol), ``trials`` (the header's count), ``percent`` (strict success %) and
    ``symmetry_percent``; both None where the cell says the method did not run."""
    lines = markdown.splitlines()
    start = next((k for k, line in enumerate(lines) if _OVERVIEW_HEADER.match(line)), None)
    if start is None:
        raise ValueError("no overview table (a line '| method | kind | ...') in the text")
    protocols = []
    for heading in _OVERVIEW_HEADER.match(lines[start])["protocols"].split("|"):
        found = re.match(r"\s*(?P<name>.+?) \((?P<trials>\d+) trials\)\s*$", heading)
        if found is None:
            raise ValueError(f"overview table: unexpected protocol heading {heading.strip()!r}")
        protocols.append((found["name"], int(found["trials"])))
    rates = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) != len(protocols) + 2:
            raise ValueError(f"overview table: {len(cells)} cells in {line[:60]!r}, expected {len(protocols) + 2}")
        method, kind = cells[0], cells[1]
        for (protocol, trials), cell in zip(protocols, cells[2:]):
            found = _OVERVIEW_CELL.match(cell)
            rates.append({"method": method, "kind": kind, "group": protocol, "trials": trials,
                          "percent": float(found["strict"]) if found else None,
                          "symmetry_percent": float(found["symmetry"]) if found else None})
    return rates


def metrics_table(rows: list[dict]) -> str:
    """The paper's layout for one group of trials: rows = methods, columns = metrics."""
    names = " | ".join(label for _, label in PAPER_METRICS)
    lines = [
        f"| method | kind | start | iterations | ran / failed / unavailable | strict % | symmetry % | "
        f"median rot. err. (deg) | median transl. err. | {names} | median time (ms) |",
        "|" + "---|" * 16,
    ]
    by_method = _groups(rows, method_label)
    for method in _ordered_methods(rows):
        stats = group_stats(by_method[method])
        if stats["unavailable"] == stats["rows"]:
            lines.append(f"| {method} | {stats['method_kind']} | {stats['init']} | - | unavailable: "
                         f"{_short(stats['reason'])} |" + " - |" * 11)
            continue
        paper = " | ".join(_fmt(stats[key]) for key, _ in PAPER_METRICS)
        time_ms = None if stats["median_time_s"] is None else 1000 * stats["median_time_s"]
        lines.append(
            f"| {method} | {stats['method_kind']} | {stats['init']} | {_fmt(stats['max_iterations'])} | "
            f"{stats['ok'] + stats['failed'] + stats['timeout']} / {stats['failed'] + stats['timeout']} / "
            f"{stats['unavailable']} | {_fmt(stats['success_strict_pct'])} | {_fmt(stats['success_symmetry_pct'])} | "
            f"{_fmt(stats['median_rotation_error_deg'])} | {_fmt(stats['median_translation_error'])} | {paper} | "
            f"{_fmt(time_ms)} |"
        )
    return "\n".join(lines) + "\n"


#: An absolute path in a row's reason (``/home/me/shared/weights/x/y.pth``): the folders of the
#: machine that ran the benchmark, which a results table does not show.
_ABSOLUTE_PATH = re.compile(r"(?<![\w.~])(?:/[^\s/;,'\"()]+){3,}")


def without_folders(reason: str) -> str:
    """``reason`` with every absolute path of three or more components cut to its last two
    (``.../x/y.pth``)."""
    return _ABSOLUTE_PATH.sub(lambda m: ".../" + "/".join(m.group(0).split("/")[-2:]), reason)


def _short(text: str, limit: int = 90) -> str:
    text = text.replace("|", "/").replace("\n", " ")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _describe(rows: list[dict]) -> str:
    datasets = sorted({r["dataset"] for r in rows})
    clouds = sorted({r["cloud"] for r in rows})
    points = sorted({r["points"] for r in rows if r.get("points") is not None})
    trials = len({r["trial_id"] for r in rows})
    budgets = sorted({r["max_iterations"] for r in rows if r["max_iterations"] is not None})
    starts = sorted({r["init"] for r in rows if r["method_kind"] == "local"})
    local = (f"every local method started from: {', '.join(starts)}, with an iteration budget of "
             f"{', '.join(map(str, budgets))}" if starts else "no local methods")
    return (
        f"{trials} trials; datasets {', '.join(datasets)} ({len(clouds)} clouds); points {', '.join(map(str, points))}; "
        f"{local}; global methods get no start and use their own budgets."
    )


def summary_markdown(rows: list[dict], title: str = "Benchmark summary") -> str:
    """The overview table, then one metrics table per protocol."""
    parts = [f"# {title}\n", _describe(rows) + "\n",
             "Cells of the overview: strict success % / success up to symmetry % (median time of the "
             "registration call). Definitions: docs/bench.md.\n", overview_table(rows)]
    for protocol, group in _groups(rows, protocol_label).items():
        parts.append(f"## {protocol}\n\n{_describe(group)}\n\n{metrics_table(group)}")
    return "\n".join(parts)


def summary_csv(rows: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for (protocol, method, sigma), group in _groups(rows, lambda r: (protocol_label(r), r["method"], r.get("sigma"))).items():
        stats = group_stats(group)
        writer.writerow({"protocol": protocol, "method": method, "sigma": sigma,
                         **{key: stats[key] for key in CSV_COLUMNS if key in stats}})
    return out.getvalue()


def _file_word(text) -> str:
    """``text`` as a safe piece of a file name: letters, digits and ``.-_=+``, nothing else (a
    ``case`` of ``x/../../tmp/y`` from a handed-over rows file must not become a path)."""
    word = re.sub(r"[^A-Za-z0-9._=+-]+", "_", str(text)).strip(".")
    return word[:80] or "unnamed"


def paper_tables(rows: list[dict]) -> dict[str, str]:
    """One Markdown file per paper table: ``paper-table-<case>.md`` for each printed transform and
    ``paper-<protocol>-t<range>.md`` for each randomised paper protocol; rows = methods, columns =
    the paper's metrics; one table per cloud size."""
    files = {}
    paper_rows = [r for r in rows if r["protocol"].startswith("paper") and not r["protocol"].startswith("paper-1000")]
    for label, group in _groups(paper_rows, protocol_label).items():
        name = "paper-table-" + _file_word(group[0]["case"]) if group[0].get("case") else _file_word(label)
        parts = [f"# {label}\n", _describe(group) + "\n"]
        if group[0].get("case"):
            parts.append(f"One trial per cloud size: {group[0]['cloud']} under the transform the paper prints "
                         f"for {group[0]['case']}; initial rotation {group[0]['initial_rotation_deg']:.1f} deg.\n")
        for points, sized in _groups(group, lambda r: r.get("points")).items():
            parts.append(f"## {points} points\n\n{metrics_table(sized)}")
        files[f"{name}.md"] = "\n".join(parts)
    return files


#: Columns of :data:`PAPER_1000_CSV` / records of :func:`paper_1000_stats`, one per (table, cloud,
#: method): the trial counts, the success rates, the mean (as the paper reports) and the median of
#: each of the paper's metrics over the ``ok`` rows, the share (%) of each mean's sum that comes
#: from the trials that are not strict successes, and the median time.
PAPER_1000_COLUMNS = (
    "table", "protocol", "cloud", "method", "points", "max_iterations", "rows", "ok", "failed", "timeout",
    "unavailable", "strict_failures", "success_strict_pct", "success_symmetry_pct",
    *[f"{kind}_{key}" for key, _ in PAPER_METRICS for kind in ("mean", "median")],
    *[f"failures_share_{key}_pct" for key, _ in PAPER_METRICS],
    "median_time_s", "reason",
)


def paper_1000_table(row: dict) -> str | None:
    """The id (in ``paper_tables.json``) of the 1,000-transform table ``row`` belongs to, or None."""
    from .paper import PAPER_1000_GROUPS

    cloud = row.get("cloud") or ""
    for table, name, protocol in PAPER_1000_GROUPS:
        if row["protocol"] == protocol and (cloud == name or cloud.split("_")[0] == name):
            return table
    return None


def paper_1000_stats(rows: list[dict]) -> list[dict]:
    """One record (:data:`PAPER_1000_COLUMNS`) per (table, cloud, method, points) of the
    ``paper-1000*`` rows, in the order the rows first name them."""
    groups = _groups([r for r in rows if paper_1000_table(r)],
                     lambda r: (paper_1000_table(r), r["protocol"], r["cloud"], method_label(r), r.get("points")))
    records = []
    for (table, protocol, cloud, method, points), group in groups.items():
        stats = group_stats(group)
        ok = [r for r in group if r["status"] == "ok"]
        failures = [r for r in ok if not r["success_strict"]]
        record = {"table": table, "protocol": protocol, "cloud": cloud, "method": method, "points": points,
                  "strict_failures": len(failures) + stats["failed"] + stats["timeout"],
                  **{key: stats[key] for key in PAPER_1000_COLUMNS if key in stats}}
        for key, _ in PAPER_METRICS:
            values = [r[key] for r in ok if r[key] is not None]
            record[f"mean_{key}"] = statistics.fmean(values) if values else None
            record[f"median_{key}"] = statistics.median(values) if values else None
            total = sum(values)
            failed = sum(r[key] for r in failures if r[key] is not None)
            record[f"failures_share_{key}_pct"] = 100.0 * failed / total if total > 0 else None
        records.append(record)
    return records


def paper_1000_markdown(rows: list[dict]) -> str:
    """The 1,000-transform tables: per paper table, rows = (object, method), cells of the paper's
    metrics ``mean / median`` over the trials, with the success rates and the share of the mean
    MSE(t) that the strict failures make."""
    records = paper_1000_stats(rows)
    parts = ["# The paper's 1,000-transform tables\n",
             "Cells of the metrics: mean / median over the trials that ran (the paper reports the mean). "
             "strict %: rotation error < 2 deg and translation error < 2% of the diagonal; symmetry %: "
             "placed within 2% of the diagonal as a point set. Failure share: the part (%) of the sum "
             "behind each mean that comes from the trials that are not strict successes.\n"]
    names = " | ".join(label for _, label in PAPER_METRICS)
    for table, group in _groups(records, lambda r: r["table"]).items():
        first = [r for r in rows if paper_1000_table(r) == table]
        parts.append(f"## {table}\n\n{_describe(first)}\n")
        lines = [f"| object | method | points | ran / crashed | strict % | symmetry % | {names} | "
                 "failure share of mean MSE(R) / MSE(t) (%) | median time (ms) |", "|" + "---|" * 14]
        for record in group:
            if record["unavailable"] == record["rows"]:
                lines.append(f"| {record['cloud']} | {record['method']} | {record['points']} | unavailable: "
                             f"{_short(record['reason'])} |" + " - |" * 10)
                continue
            cells = " | ".join(f"{_fmt(record[f'mean_{key}'])} / {_fmt(record[f'median_{key}'])}"
                               for key, _ in PAPER_METRICS)
            crashed = record["failed"] + record["timeout"]
            time_ms = None if record["median_time_s"] is None else 1000 * record["median_time_s"]
            lines.append(
                f"| {record['cloud']} | {record['method']} | {record['points']} | {record['ok'] + crashed} / {crashed} | "
                f"{_fmt(record['success_strict_pct'])} | {_fmt(record['success_symmetry_pct'])} | {cells} | "
                f"{_fmt(record['failures_share_mse_r_pct'])} / {_fmt(record['failures_share_mse_t_pct'])} | "
                f"{_fmt(time_ms)} |"
            )
        parts.append("\n".join(lines) + "\n")
    return "\n".join(parts)


def paper_1000_csv(rows: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=PAPER_1000_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for record in paper_1000_stats(rows):
        writer.writerow({key: record.get(key) for key in PAPER_1000_COLUMNS})
    return out.getvalue()


def write_between(path, text: str, begin: str, end: str) -> None:
    """Rewrite the part of the page at ``path`` between the marker lines ``begin`` and ``end`` (kept)
    with ``text``; the rest of the page is kept. Exits with a one-line message naming the page when
    a marker is missing."""
    page = path.read_text(encoding="utf-8")
    if begin not in page or end not in page:
        raise SystemExit(f"{path}: no generated part (the markers {begin} and {end})")
    before, rest = page.split(begin, 1)
    after = rest.split(end, 1)[1]
    path.write_text(f"{before}{begin}\n{text}\n{end}{after}", encoding="utf-8")
