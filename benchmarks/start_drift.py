"""Refining from a given start: does ``esm`` keep a good start good? (docs/scans-start-drift.md)

``esmicp.register(source, target, init=start)`` (method ``esm``, every other default) from

- the ground truth, and the truth perturbed by a seeded rotation about a random axis through the
  placed source's centroid plus a translation in a random direction: 5 deg / 0.1 m on 3DMatch,
  5 deg / 0.5 m on LiDAR, 5 deg / 5% of the target's diagonal on the ModelNet40 partial-overlap
  trials (``partial-70`` / ``partial-50`` of :mod:`esmicp_lab.bench.scans`, the same seeds);
- poor starts on whole objects (what the coarse phase of the automatic sigma is for): the
  ``resampled`` and ``outliers-30`` ModelNet40 protocols from their truth perturbed by 30 deg / 10%
  and 60 deg / 25% of the diagonal.

Success: real pairs by their kind (3DMatch < 15 deg and < 0.30 m, LiDAR < 5 deg and < 0.6 m);
objects within 2% of the diagonal up to symmetry (:func:`esmicp.metrics.up_to_symmetry_success`).
"moved" is how far the result is from the start (rotation, and translation at the source's
centroid): a start that was already right should barely move.

    python benchmarks/start_drift.py --doc docs/scans-start-drift.md --picture docs/images/scans-start-drift.png
    python benchmarks/start_drift.py --start-quantile 0.1 --out /tmp/q010.json
    python benchmarks/start_drift.py --compare /tmp/q010.json
    python benchmarks/start_drift.py --from-out /tmp/q010.json --picture docs/images/scans-start-drift.png

``--doc`` replaces (or appends) the section "Refining from a given start" of that Markdown file;
``--picture`` draws the picture the page opens on (the share of right results per kind of data
and start, from the same rows);
``--start-quantile Q`` runs with another ``RefineConfig.esm.start_quantile`` (how it was chosen);
``--compare`` puts the rows of another run (``--out`` of a run with other settings) in a column
beside this run's, and lists the cases this run does worse on.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import numpy as np

import esmicp
from esmicp_lab.bench.protocols import make_trial
from esmicp_lab.bench.real_pairs import load_pair, pair_errors, partial_trial, read_pairs
from esmicp_lab.bench.scans import _modelnet_clouds, _seed_of
from esmicp_lab.bench.trials import perturbed_start
from esmicp.core.procrustes import bounding_box_diagonal
from esmicp.config import RefineConfig, RegistrationConfig
from esmicp.methods.config import EsmConfig
from esmicp.metrics import rotation_error_deg, translation_error, up_to_symmetry_success

SECTION = "## Refining from a given start"
#: (rotation degrees, translation) of the perturbed start; translation in metres for real pairs,
#: as a fraction of the target's diagonal for objects.
REAL_PERTURBATION = {"3DMatch": (5.0, 0.1), "LiDAR": (5.0, 0.5), "LiDAR-coarse-GT": (5.0, 0.5)}
PARTIAL_PERTURBATION = (5.0, 0.05)
POOR_STARTS = ((30.0, 0.10), (60.0, 0.25))


def _moved(result, start, source):
    return rotation_error_deg(result, start), translation_error(result, start, source.mean(axis=0))


def real_rows(folder: Path, seed: int, config: RegistrationConfig | None = None):
    for index, pair in enumerate(read_pairs(folder)):
        source, target, truth = load_pair(pair, bin_columns=3)
        angle, shift = REAL_PERTURBATION[pair.kind]
        rng = np.random.default_rng(_seed_of(seed, 2, index))
        for start_name, start in (("truth", truth), (f"{angle:g}° / {shift:g} m", perturbed_start(truth, source, angle, shift, rng))):
            result = esmicp.register(source, target, init=start, config=config)
            rot, trans = pair_errors(result.transformation, truth)
            moved_rot, moved_trans = _moved(result.transformation, start, source)
            yield {"group": "real", "kind": pair.kind.replace("-coarse-GT", ""), "case": pair.name, "start": start_name,
                   "rotation_error_deg": rot,
                   "translation_error": trans, "success": pair.criteria.success(rot, trans),
                   "moved_deg": moved_rot, "moved": moved_trans, "seconds": result.runtime_s}


def object_rows(data_dir: Path, trials: int, seed: int, config: RegistrationConfig | None = None):
    clouds = _modelnet_clouds(data_dir)
    names = list(clouds)
    for number, keep in enumerate((0.7, 0.5)):
        for index in range(trials):
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1, number, index)))
            trial = partial_trial(clouds[names[index % len(names)]], keep, rng, 2000)
            diagonal = bounding_box_diagonal(trial.target)
            angle, shift = PARTIAL_PERTURBATION
            start_rng = np.random.default_rng(_seed_of(seed, 3, number, index))
            starts = (("truth", trial.T_target_source),
                      (f"{angle:g}° / {shift:g} diag",
                       perturbed_start(trial.T_target_source, trial.source, angle, shift * diagonal, start_rng)))
            yield from _object_rows(f"partial-{round(100 * keep)}", trial.source, trial.target,
                                    trial.T_target_source, diagonal, starts, config)
    for protocol in ("resampled", "outliers-30"):
        for index in range(trials):
            trial = make_trial(protocol, clouds[names[index % len(names)]], seed, index)
            diagonal = bounding_box_diagonal(trial.target)
            start_rng = np.random.default_rng(_seed_of(seed, 4, protocol == "resampled", index))
            starts = [(f"{angle:g}° / {shift:g} diag",
                       perturbed_start(trial.T_target_source, trial.source, angle, shift * diagonal, start_rng))
                      for angle, shift in POOR_STARTS]
            yield from _object_rows(protocol, trial.source, trial.target, trial.T_target_source, diagonal, starts, config)


def _object_rows(protocol, source, target, truth, diagonal, starts, config=None):
    for start_name, start in starts:
        result = esmicp.register(source, target, init=start, config=config)
        moved_rot, moved_trans = _moved(result.transformation, start, source)
        yield {"group": "objects", "case": protocol, "start": start_name,
               "rotation_error_deg": rotation_error_deg(result.transformation, truth),
               "translation_error": translation_error(result.transformation, truth, source.mean(axis=0)),
               "success": up_to_symmetry_success(source, result.transformation, truth, diagonal),
               "moved_deg": moved_rot, "moved": moved_trans / diagonal, "seconds": result.runtime_s}


def _cell(rows):
    if not rows:
        return "-"
    if len(rows) == 1:
        row = rows[0]
        verdict = "**ok**" if row["success"] else "no"
        return f"{verdict} {row['rotation_error_deg']:.2f}° {row['translation_error']:.3f} m (moved {row['moved']:.3f} m)"
    ok = sum(row["success"] for row in rows)
    moved = statistics.median(row["moved"] for row in rows)
    return f"{ok}/{len(rows)} ({100 * ok / len(rows):.0f}%), median moved {moved:.3f} diag"


def markdown(rows: list[dict], command: str, compared: list[dict] | None = None) -> str:
    """The page's section: one row per case and start, the result of ``rows``; with ``compared``
    (the rows of a run with other settings) a column of those first, and the cases ``rows`` do worse
    on."""
    def keyed(rows):
        table = {}
        for row in rows:
            table.setdefault((row["group"], row["case"], row["start"]), []).append(row)
        return table

    now, other = keyed(rows), keyed(compared or [])
    lines = [SECTION, "",
             f"Generated by `{command}` (see its docstring for the starts and criteria). "
             "`esmicp.register(source, target, init=start)`, method `esm`, every other default. \"moved\": "
             "translation between the start and the result (at the source's centroid).", ""]
    if compared is None:
        lines += ["| case | start | result |", "|---|---|---|"]
        lines += [f"| {case} | {start} | {_cell(now[group, case, start])} |" for group, case, start in now]
    else:
        lines += ["| case | start | compared run | this run |", "|---|---|---|---|"]
        worse = []
        for key in now:
            group, case, start = key
            lines.append(f"| {case} | {start} | {_cell(other.get(key, []))} | {_cell(now[key])} |")
            if key in other and _worse(other[key], now[key]):
                worse.append(f"{case} from {start}")
        lines += ["", "Worse in this run than in the compared one (fewer successes, or a single pair's translation "
                  "error up by more than half): " + ("; ".join(worse) if worse else "none") + "."]
    lines += ["", "The coarse sigma from a given start is `RefineConfig.esm.sigma_median_factor` times the `start_quantile` "
              "quantile of the start's distances; rerun with `--start-quantile Q` to compare another quantile."]
    return "\n".join(lines) + "\n"


def _worse(compared, rows) -> bool:
    if sum(row["success"] for row in rows) < sum(row["success"] for row in compared):
        return True
    return len(rows) == 1 and rows[0]["translation_error"] > 1.5 * compared[0]["translation_error"]


def picture(rows: list[dict], path: Path) -> Path:
    """The page's picture: the share of right results per kind of data (real pairs by kind,
    objects by protocol), one bar per start."""
    from esmicp_lab.figures import success_bars_figure, write_picture

    counts: dict[tuple[str, str], list[bool]] = {}
    for row in rows:
        group = f"{row['kind']} pairs" if row["group"] == "real" else row["case"]
        counts.setdefault((group, f"from {row['start']}"), []).append(bool(row["success"]))
    rates = [{"group": group, "method": start, "successes": sum(found), "trials": len(found)}
             for (group, start), found in counts.items()]
    figure = success_bars_figure(rates, title="register(init=start), method esm: right results per kind of data and start",
                                 ylabel="right (%)")
    return write_picture(figure, path)


def write_section(path: Path, section: str) -> None:
    text = path.read_text()
    start = text.find(SECTION)
    if start < 0:
        text = text.rstrip("\n") + "\n\n" + section
    else:
        end = text.find("\n## ", start + len(SECTION))
        text = text[:start] + section + ("" if end < 0 else text[end:])
    path.write_text(text)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[1] / ".." / "shared" / "data")
    parser.add_argument("--trials", type=int, default=24, help="trials per object protocol (default 24)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-real", action="store_true", help="objects only")
    parser.add_argument("--start-quantile", type=float, default=EsmConfig().start_quantile,
                        help=f"RefineConfig.esm.start_quantile for this run (default {EsmConfig().start_quantile})")
    parser.add_argument("--out", type=Path, help="write this run's rows (JSON)")
    parser.add_argument("--compare", type=Path, help="rows of another run (its --out JSON) to show beside")
    parser.add_argument("--doc", type=Path, help="Markdown file whose section to replace")
    parser.add_argument("--from-out", type=Path, help="take the rows of an earlier run (its --out JSON) instead of "
                        "running (for --doc and --picture)")
    parser.add_argument("--picture", type=Path, help="draw the page's picture (PNG, replaced if it exists; "
                        "needs matplotlib): right results per kind of data and start")
    args = parser.parse_args(argv)
    config = RegistrationConfig(refine=RefineConfig(esm=EsmConfig(start_quantile=args.start_quantile)))
    rows = json.loads(args.from_out.read_text()) if args.from_out else []
    if not args.from_out and not args.skip_real:
        for row in real_rows(args.data / "real_pairs", args.seed, config):
            print(json.dumps(row), flush=True)
            rows.append(row)
    if not args.from_out:
        rows.extend(object_rows(args.data, args.trials, args.seed, config))
    if args.out:
        args.out.write_text(json.dumps(rows))
    compared = json.loads(args.compare.read_text()) if args.compare else None
    command = "python benchmarks/start_drift.py" + (f" --trials {args.trials}" if args.trials != 24 else "")
    section = markdown(rows, command, compared)
    print(section)
    if args.doc:
        write_section(args.doc, section)
    if args.picture:
        print(picture(rows, args.picture))


if __name__ == "__main__":
    main()
