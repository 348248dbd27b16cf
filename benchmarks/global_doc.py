"""Markdown tables of two runs of ``benchmarks/global_regression.py`` side by side (before / after
a change), grouped by set, for ``docs/measured-global.md`` and ``docs/real-scans.md``.

    python benchmarks/global_doc.py groups BEFORE.jsonl AFTER.jsonl   # one row per group
    python benchmarks/global_doc.py pairs BEFORE.jsonl AFTER.jsonl    # one row per real pair
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import numpy as np

from esmicp.core.procrustes import rotation_angle


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


def moved(a: dict, b: dict) -> bool:
    first, second = np.array(a["transformation"]), np.array(b["transformation"])
    turn = float(np.degrees(rotation_angle(first[:3, :3].T @ second[:3, :3])))
    return turn > 1e-6 or float(np.linalg.norm(first[:3, 3] - second[:3, 3])) > 1e-9 * max(
        1.0, float(np.abs(first[:3, 3]).max()))


def groups(before: dict, after: dict) -> str:
    names: dict[str, list[str]] = {}
    for name in after:
        if name in before:
            names.setdefault(group_of(name), []).append(name)
    lines = ["| trials | n | right (before / after) | trusted (before / after) | trusted and wrong (after) | "
             "median confidence (after) | poses moved |", "|---|---|---|---|---|---|---|"]
    for group, rows in names.items():
        right = [sum(run[n]["success"] for n in rows) for run in (before, after)]
        trusted = [sum(run[n]["trusted"] for n in rows) for run in (before, after)]
        wrong = sum(after[n]["trusted"] and not after[n]["success"] for n in rows)
        confidence = statistics.median(after[n]["confidence"] for n in rows)
        lines.append(f"| {group} | {len(rows)} | {right[0]} / {right[1]} | {trusted[0]} / {trusted[1]} | {wrong} | "
                     f"{confidence:.2f} | {sum(moved(before[n], after[n]) for n in rows)} |")
    return "\n".join(lines)


def pairs(before: dict, after: dict) -> str:
    lines = ["| pair | before: error (deg / m), confidence | after: error (deg / m), confidence | trusted after |",
             "|---|---|---|---|"]

    def cell(row):
        verdict = "ok" if row["success"] else "**failed**"
        return f"{verdict} {row['rotation_error_deg']:.2f}° / {row['translation_error']:.3f}, {row['confidence']:.2f}"

    for name, row in after.items():
        if name in before and "rotation_error_deg" in row:
            lines.append(f"| {name} | {cell(before[name])} | {cell(row)} | {'yes' if row['trusted'] else 'no'} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=("groups", "pairs"))
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    args = parser.parse_args()
    before, after = load(args.before), load(args.after)
    print(groups(before, after) if args.kind == "groups" else pairs(before, after))


if __name__ == "__main__":
    main()
