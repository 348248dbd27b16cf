"""Markdown tables of one run of ``benchmarks/global_regression.py``, grouped by set, for
``docs/measured-global.md`` and ``docs/real-scans.md``. (``global_regression.py --compare`` sets two
runs side by side, row by row.)

    python benchmarks/global_doc.py groups RUN.jsonl   # one row per group
    python benchmarks/global_doc.py pairs RUN.jsonl    # one row per real pair
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path


def load(path: Path) -> dict[str, dict]:
    return {row["row"]: row for row in map(json.loads, path.read_text().splitlines()) if row}


def group_of(name: str) -> str:
    parts = name.split("/")
    if parts[0] == "kitchen":
        return f"kitchen/{parts[1]}"
    if parts[0] == "crop":
        return f"3DMatch crops/{parts[3]}%"
    if parts[0] == "real":
        return f"real/{parts[1]}"
    return f"{parts[0]}/{parts[1]}"


def groups(run: dict) -> str:
    names: dict[str, list[str]] = {}
    for name in run:
        names.setdefault(group_of(name), []).append(name)
    lines = ["| trials | n | right | trusted | trusted and wrong | median confidence |", "|---|---|---|---|---|---|"]
    for group, rows in names.items():
        right = sum(run[n]["success"] for n in rows)
        trusted = sum(run[n]["trusted"] for n in rows)
        wrong = sum(run[n]["trusted"] and not run[n]["success"] for n in rows)
        confidence = statistics.median(run[n]["confidence"] for n in rows)
        lines.append(f"| {group} | {len(rows)} | {right} | {trusted} | {wrong} | {confidence:.2f} |")
    return "\n".join(lines)


def pairs(run: dict) -> str:
    lines = ["| pair | error (deg / m), confidence | trusted |", "|---|---|---|"]
    for name, row in run.items():
        if "rotation_error_deg" in row:
            verdict = "ok" if row["success"] else "**failed**"
            lines.append(f"| {name} | {verdict} {row['rotation_error_deg']:.2f}° / {row['translation_error']:.3f}, "
                         f"{row['confidence']:.2f} | {'yes' if row['trusted'] else 'no'} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=("groups", "pairs"))
    parser.add_argument("run", type=Path, help="the --out JSONL of benchmarks/global_regression.py")
    args = parser.parse_args()
    run = load(args.run)
    print(groups(run) if args.kind == "groups" else pairs(run))


if __name__ == "__main__":
    main()
