"""Markdown tables of one run of ``benchmarks/global_regression.py``, grouped by set, for
``docs/measured-global.md`` and ``docs/real-scans.md``. (``global_regression.py --compare`` sets two
runs side by side, row by row.)

    python benchmarks/global_doc.py groups RUN.jsonl   # one row per group
    python benchmarks/global_doc.py pairs RUN.jsonl    # one row per real pair
    python benchmarks/global_doc.py picture RUN.jsonl [RUN.jsonl ...] --picture PICTURE.png --title TITLE

``picture`` draws every registration of the runs that has a rotation error: that error against
its confidence, right and wrong apart, trusted ones filled, the trust bar
(:attr:`esmicp.trust.policy.TrustPolicy.trusted`) as a line, one marker per group of rows
(:func:`group_of`, the first part of the group's name), the page's picture
(``pip install 'esmicp[viz]'`` for matplotlib).
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


def peers_of(row: dict) -> dict[str, dict]:
    """A row's peers (``global_regression.py --peer``), name -> ``{"time_s", "success"}``."""
    if "peers" in row:
        return row["peers"]
    if "peer_time_s" in row:
        return {row["peer"]: {"time_s": row["peer_time_s"], "success": row["peer_success"]}}
    return {}


def groups(run: dict) -> str:
    """One row per group: right, trusted, trusted and wrong, the median confidence; with peers in
    the run, each peer's right count and the median of the per-row time ratios esmicp / peer (both
    timed in the same process, one after the other, on the same clouds)."""
    names: dict[str, list[str]] = {}
    for name in run:
        names.setdefault(group_of(name), []).append(name)
    peers = list(dict.fromkeys(peer for row in run.values() for peer in peers_of(row)))
    header = "| trials | n | right | trusted | trusted and wrong | median confidence |"
    for peer in peers:
        header += f" {peer}: right | time esmicp / {peer} |"
    lines = [header, "|---|---|---|---|---|---|" + "---|---|" * len(peers)]
    for group, rows in names.items():
        right = sum(run[n]["success"] for n in rows)
        trusted = sum(run[n]["trusted"] for n in rows)
        wrong = sum(run[n]["trusted"] and not run[n]["success"] for n in rows)
        confidence = statistics.median(run[n]["confidence"] for n in rows)
        line = f"| {group} | {len(rows)} | {right} | {trusted} | {wrong} | {confidence:.2f} |"
        for peer in peers:
            timed = [n for n in rows if peer in peers_of(run[n])]
            if not timed:
                line += " - | - |"
                continue
            ratio = statistics.median(run[n]["time_s"] / peers_of(run[n])[peer]["time_s"] for n in timed)
            line += f" {sum(bool(peers_of(run[n])[peer]['success']) for n in timed)} | {ratio:.2f} |"
        lines.append(line)
    return "\n".join(lines)


def pairs(run: dict) -> str:
    lines = ["| pair | error (deg / m), confidence | trusted |", "|---|---|---|"]
    for name, row in run.items():
        if "translation_error" in row:
            verdict = "ok" if row["success"] else "**failed**"
            lines.append(f"| {name} | {verdict} {row['rotation_error_deg']:.2f}° / {row['translation_error']:.3f}, "
                         f"{row['confidence']:.2f} | {'yes' if row['trusted'] else 'no'} |")
    return "\n".join(lines)


#: The marker groups of the picture: a row group's kind of data, by the first part of its name.
KINDS = {"modelnet40": "ModelNet40 objects and halves", "modelnet40_extra": "ModelNet40 extra, objects and halves",
         "real": "real pairs (3DMatch, LiDAR)", "3DMatch crops": "3DMatch crops (25%, 15%)",
         "kitchen": "kitchen frame pairs"}


def kind_of(name: str) -> str:
    """The data kind of a row (its marker in the picture)."""
    first = group_of(name).split("/")[0]
    return KINDS.get(first, first)


def picture(runs: list[dict], path: Path, title: str) -> Path:
    """Draw the rows of ``runs`` that have a rotation error (confidence against error, the trust
    bar) into the PNG ``path``."""
    from esmicp.trust.policy import DEFAULT_POLICY
    from esmicp_lab.figures import confidence_error_figure, write_picture

    records = [row | {"kind": kind_of(name)} for run in runs for name, row in run.items()
               if row.get("rotation_error_deg") is not None]
    figure = confidence_error_figure(records, trust_bar=DEFAULT_POLICY.trusted, title=title,
                                     group=lambda record: record["kind"])
    return write_picture(figure, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=("groups", "pairs", "picture"))
    parser.add_argument("runs", type=Path, nargs="+", help="the --out JSONL of benchmarks/global_regression.py "
                        "(one for groups and pairs; any number for picture)")
    parser.add_argument("--picture", type=Path, help="picture: the PNG to write (replaced if it exists)")
    parser.add_argument("--title", default="Rotation error against confidence", help="picture: its title")
    args = parser.parse_args()
    for path in args.runs:
        if not path.is_file():
            parser.error(f"{path}: no such file")
    if args.kind == "picture":
        if args.picture is None:
            parser.error("picture: --picture PATH is needed")
        print(picture([load(path) for path in args.runs], args.picture, args.title))
        return
    if len(args.runs) != 1:
        parser.error(f"{args.kind}: one run, got {len(args.runs)}")
    run = load(args.runs[0])
    print(groups(run) if args.kind == "groups" else pairs(run))


if __name__ == "__main__":
    main()
