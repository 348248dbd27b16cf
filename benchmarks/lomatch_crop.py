"""3DLoMatch-like check: the 3DMatch pairs of a real-pairs folder cropped to 10-30% overlap.

Each 3DMatch pair is cropped by seeded planes (:func:`esmicp_lab.bench.real_pairs.crop_to_overlap`)
so that a chosen fraction of the kept source lies on the kept target; the measured overlap of
every crop, each way, is printed with the results. Every method of the scan benchmark then runs
on it, as recorded and turned (a random rotation of the source about its centroid), the peers
with the voxel of the 3DMatch criteria (0.05 m), esmicp with every default. Success: rotation
error < 15 deg and translation error < 0.30 m. Prints a Markdown section; figures are measured in
the run:

    nice -n 5 python benchmarks/lomatch_crop.py --folder ../shared/data/real_pairs > /tmp/lomatch.md
    python benchmarks/lomatch_crop.py --crops 4 --methods esm-global --picture docs/images/scans-partial-overlap.png

``--picture`` also draws esmicp's results (rotation error against confidence, the trust bar
:attr:`esmicp.trust.policy.TrustPolicy.trusted` as a line, trusted results filled), from the same rows.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import numpy as np

from esmicp_lab.bench.real_pairs import (
    crop_to_overlap, criteria_for, estimate_in_pair_frame, load_pair, pair_errors, read_pairs, turn_source,
)
from esmicp_lab.bench.scans import METHOD_LABELS, SCAN_METHODS, _timed
from esmicp.trust.policy import DEFAULT_POLICY


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", default=str(Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real_pairs"))
    parser.add_argument("--overlaps", default="0.25,0.15", help="overlaps to crop to, comma-separated")
    parser.add_argument("--crops", type=int, default=1, help="seeded crops per pair and overlap")
    parser.add_argument("--methods", default=",".join(m for m in SCAN_METHODS if m != "fgr-icp"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--picture", type=Path, help="draw esmicp's rotation error against its confidence (PNG, "
                        "replaced if it exists; needs matplotlib)")
    args = parser.parse_args()
    methods = args.methods.split(",")
    pairs = [p for p in read_pairs(Path(args.folder)) if p.kind == "3DMatch"]
    criteria = criteria_for("3DLoMatch")
    rows = []
    for pair_number, pair in enumerate(pairs):
        source, target, truth = load_pair(pair)
        for overlap_number, overlap in enumerate(float(x) for x in args.overlaps.split(",")):
            for crop in range(args.crops):
                rng = np.random.default_rng(np.random.SeedSequence(args.seed, spawn_key=(pair_number, overlap_number, crop)))
                cropped = crop_to_overlap(source, target, truth, overlap, rng)
                for variant in ("as-recorded", "turned"):
                    used, used_truth, moved_by = cropped.source, truth, None
                    if variant == "turned":
                        used, used_truth, moved_by = turn_source(cropped.source, truth, rng)
                    for method in methods:
                        outcome = _timed(method, used, cropped.target, None if method == "esm-global" else criteria.voxel_m,
                                         args.seed)
                        row = {"pair": pair.name, "crop": crop, "overlap": cropped.source_overlap, "back": cropped.target_overlap,
                               "points": (len(cropped.source), len(cropped.target)), "variant": variant,
                               "method": method, "time_s": outcome["time_s"], "success": False,
                               "rotation": None, "translation": None, "confidence": outcome.get("confidence"),
                               "trusted": outcome.get("trusted"), "asked_overlap": overlap}
                        if outcome["status"] == "ok":
                            rotation, translation = pair_errors(estimate_in_pair_frame(outcome["estimate"], moved_by), truth)
                            row.update(rotation=rotation, translation=translation,
                                       success=criteria.success(rotation, translation))
                        rows.append(row)
    print(markdown(rows, methods))
    if args.picture:
        print(picture(rows, args.picture, args.seed))


def picture(rows, path: Path, seed: int) -> Path:
    """esmicp's rows (those with a confidence that ran): rotation error against confidence, one
    marker per overlap asked for."""
    from esmicp_lab.figures import confidence_error_figure, write_picture

    records = [{"confidence": r["confidence"], "rotation_error_deg": r["rotation"], "success": r["success"],
                "trusted": r["trusted"], "overlap": f"cropped to {round(100 * r['asked_overlap'])}% overlap"}
               for r in rows if r["confidence"] is not None and r["rotation"] is not None]
    figure = confidence_error_figure(
        records, trust_bar=DEFAULT_POLICY.trusted, group=lambda record: record["overlap"],
        title=f"3DMatch pairs cropped (seed {seed}): esmicp's rotation error against its confidence, "
              f"{len(records)} registrations")
    return write_picture(figure, path)


def markdown(rows, methods) -> str:
    lines = ["| pair | overlap (source on target / target on source) | points (source / target) | variant | "
             + " | ".join(METHOD_LABELS[m] for m in methods) + " |", "|---" * (4 + len(methods)) + "|"]
    cases = {}
    for row in rows:
        cases.setdefault((row["pair"], row["crop"], round(row["overlap"], 3), row["variant"]), {})[row["method"]] = row
    several = any(row["crop"] > 0 for row in rows)
    for (pair, crop, _, variant), by_method in cases.items():
        pair = f"{pair} (crop {crop})" if several else pair
        first = next(iter(by_method.values()))
        cells = []
        for method in methods:
            row = by_method.get(method)
            if row is None or row["rotation"] is None:
                cells.append("failed")
                continue
            mark = "**ok**" if row["success"] else "no"
            trust = "" if row["confidence"] is None else f" (confidence {row['confidence']:.2f})"
            cells.append(f"{mark} {row['rotation']:.1f}° {row['translation']:.2f} m {row['time_s']:.1f} s{trust}")
        lines.append(f"| {pair} | {first['overlap']:.2f} / {first['back']:.2f} | {first['points'][0]:,} / "
                     f"{first['points'][1]:,} | {variant} | " + " | ".join(cells) + " |")
    lines.append("")
    reference = "kiss-matcher-icp" if "kiss-matcher-icp" in methods else None
    for method in methods:
        mine = [r for r in rows if r["method"] == method]
        line = f"- {METHOD_LABELS[method]}: {sum(r['success'] for r in mine)}/{len(mine)} successes, median time {statistics.median(r['time_s'] for r in mine):.2f} s"
        if reference and method != reference:
            theirs = {(r["pair"], r["crop"], r["overlap"], r["variant"]): r["time_s"] for r in rows if r["method"] == reference}
            ratios = [r["time_s"] / theirs[(r["pair"], r["crop"], r["overlap"], r["variant"])] for r in mine]
            line += f", {statistics.median(ratios):.2f}x {METHOD_LABELS[reference]}'s time (median of per-case ratios)"
        lines.append(line)
        judged = [r for r in mine if r["confidence"] is not None]
        if judged:  # esmicp's own verdict on its pose (the peers give none)
            wrong = [r for r in judged if not r["success"]]
            lines.append(f"  - its confidence >= {DEFAULT_POLICY.trusted}: {sum(r['confidence'] >= DEFAULT_POLICY.trusted for r in wrong)} of its "
                         f"{len(wrong)} failures (a wrong pose reported as trustworthy), "
                         f"{sum(r['confidence'] >= DEFAULT_POLICY.trusted for r in judged if r['success'])} of its "
                         f"{len(judged) - len(wrong)} successes")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
