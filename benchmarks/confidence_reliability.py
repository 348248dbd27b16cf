"""Reliability of ``RegistrationResult.confidence``: bins of confidence against the fraction right.

Reads the JSON-lines files written by ``benchmarks/global_regression.py`` (one registration per
line, with its ``confidence``, ``trusted`` and ``success``) and prints, per file group, a Markdown
table: for each confidence bin, the results in it, how many were right, and that fraction; then
the trusted results (:attr:`~esmicp.result.RegistrationResult.trusted`) and how many of them were
wrong (the "confident and wrong" rate the library promises to keep low). Rows registered with
``range_images=True`` (they carry ``free_space``) also get the trusted line without the free-space
test, and a table of the wrong results with their free space.

    python benchmarks/confidence_reliability.py dev=/tmp/runs/dev.jsonl confirm=/tmp/runs/confirm.jsonl
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

EDGES = (0.0, 0.1, 0.3, 0.5, 0.55, 0.7, 0.9, 1.0001)


def table(rows: list[dict]) -> str:
    lines = ["| confidence | results | right | fraction right |", "|---|---|---|---|"]
    for low, high in zip(EDGES[:-1], EDGES[1:]):
        inside = [row for row in rows if row["confidence"] is not None and low <= row["confidence"] < high]
        right = sum(row["success"] for row in inside)
        fraction = f"{right / len(inside):.2f}" if inside else "-"
        lines.append(f"| {low:.2f}-{min(high, 1.0):.2f} | {len(inside)} | {right} | {fraction} |")
    lines.append(_trusted_line("trusted", [row for row in rows if row["trusted"]]))
    if any("trusted_without_free_space" in row for row in rows):
        lines.append(_trusted_line("trusted without the free-space test",
                                   [row for row in rows if row.get("trusted_without_free_space")]))
    right = sum(row["success"] for row in rows)
    lines.append(f"| all | {len(rows)} | {right} | {right / max(len(rows), 1):.2f} |")
    return "\n".join(lines)


def _trusted_line(label: str, trusted: list[dict]) -> str:
    wrong = sum(not row["success"] for row in trusted)
    share = f"{100 * wrong / len(trusted):.1f}%" if trusted else "-"
    return f"| **{label}** | {len(trusted)} | {len(trusted) - wrong} | wrong: {wrong} ({share}) |"


def wrong_results(rows: list[dict]) -> str:
    """The wrong results of rows that carry ``free_space``: error, confidence, trust with and
    without the free-space test, the truth overlap (when recorded) and the free space."""
    lines = ["| row | error (deg / units) | confidence | trusted | without the test | truth overlap | free space |",
             "|---|---|---|---|---|---|---|"]

    def number(value, digits):
        return "-" if value is None else f"{value:.{digits}f}"

    for row in rows:
        if row["success"]:
            continue
        trusted = "yes" if row["trusted"] else ("no (ambiguous)" if row["ambiguous"] else "no")
        lines.append(f"| {row['row'].split('/', 1)[1]} | {row['rotation_error_deg']:.1f} / "
                     f"{row['translation_error']:.2f} | {number(row['confidence'], 2)} | {trusted} | "
                     f"{'yes' if row['trusted_without_free_space'] else 'no'} | {number(row.get('truth_overlap'), 2)} | "
                     f"{number(row['free_space'], 3)} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("files", nargs="+", help="NAME=PATH (JSON lines of global_regression.py)")
    args = parser.parse_args()
    for item in args.files:
        name, _, path = item.partition("=")
        rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
        groups: dict[str, list] = {}
        for row in rows:
            groups.setdefault(row["row"].split("/")[0] + "/" + row["row"].split("/")[1].split("-")[0], []).append(row)
        print(f"### {name}: {len(rows)} registrations ({', '.join(f'{k} {len(v)}' for k, v in groups.items())})\n")
        print(table(rows))
        print()
        if any("free_space" in row for row in rows):
            print(f"{name}, the wrong results:\n")
            print(wrong_results(rows))
            print()


if __name__ == "__main__":
    main()
