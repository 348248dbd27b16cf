"""Small clouds (1-20k points) against the fastest peer pipelines: esmicp at its defaults beside
KISS-Matcher + small_gicp GICP and KISS-Matcher + Open3D ICP, same pairs, same run, interleaved.

Two kinds of pair:

``turntable``
    Range scans of the Stanford bunny's mesh (``bunny/bun_zipper.ply``) on a turntable turning
    :data:`TURNTABLE_STEP_DEG` at a time (:func:`esmicp_lab.bench.off_sensor.turntable_scans`,
    stored in the turntable's frame), each scan registered onto its neighbour and its second
    neighbour (24 and 48 degrees apart), as recorded and turned once about its centroid
    (:func:`esmicp_lab.bench.real_pairs.turn_source`). The peers get the voxel their docs give for a
    turntable scan, :data:`TURNTABLE_VOXEL` (2 mm).
``outliers-60``
    Whole objects under 60% outliers: the ``outliers-60`` protocol of
    :mod:`esmicp_lab.bench.protocols` on the 12 ModelNet40 shapes of the ESM-ICP paper (2,000
    points a half, the paper's noise on 60% of the source points). The peers get their object
    default (1/40 of the target's diagonal).

Success: :func:`esmicp.metrics.strict_success` (rotation error < 2 deg, translation error at the
source's centroid < 2% of the target's diagonal) on the turntable; on the objects
:func:`esmicp.metrics.up_to_symmetry_success` on the source points the noise left clean (a
bottle turned about its axis counts). Only the registration call is timed, after one untimed
warm-up call per method; the methods take turns pair by pair, their order rotating, so that the
shared machine's load hits them alike: read the ratios (median over the pairs of esmicp's time
over the peer's on the same pair), not the seconds. Wall time and the process's CPU time (every
thread's) are both recorded: on a loaded machine the CPU time varies less.

    python benchmarks/small_clouds.py --doc docs/real-scans.md

Prints Markdown; ``--doc`` rewrites the part of that page between its ``<!-- small_clouds -->``
markers; ``--out`` writes one JSON line per (pair, method), ``--rows`` renders such a file again.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

import esmicp
from esmicp.core.procrustes import bounding_box_diagonal
from esmicp.metrics import rotation_error_deg, strict_success, up_to_symmetry_success
from esmicp_lab.bench.off_sensor import turntable_scans
from esmicp_lab.bench.protocols import make_trials
from esmicp_lab.bench.real_pairs import estimate_in_pair_frame, turn_source
from esmicp_lab.bench.tables import write_between

DOC_BEGIN, DOC_END = "<!-- small_clouds: begin -->", "<!-- small_clouds: end -->"

#: The methods, in the order of the tables: esmicp at its defaults, then the two peers.
METHODS = ("esmicp", "kiss-matcher-gicp", "kiss-matcher-icp")
LABELS = {"esmicp": "esmicp default", "kiss-matcher-gicp": "KISS-Matcher + small_gicp GICP",
          "kiss-matcher-icp": "KISS-Matcher + Open3D ICP"}

#: Turntable scans (count), the turn between two (degrees), the peers' voxel for them (metres).
TURNTABLE_SCANS, TURNTABLE_STEP_DEG, TURNTABLE_VOXEL = 15, 24.0, 0.002

#: The 12 ModelNet40 shapes of the ESM-ICP paper (folder ``modelnet40``), points a half.
OBJECT_POINTS = 2000


def _register(method: str, source, target, voxel, seed: int):
    """``(T_target_source, trusted)``: esmicp's verdict, None for a peer (it gives none)."""
    if method == "esmicp":
        result = esmicp.register(source, target, rng=seed)
        return result.transformation, bool(result.trusted)
    from esmicp_lab import baselines

    result = baselines.get_baseline(method)(source, target, voxel_size=voxel, rng=seed)
    return np.asarray(result.transformation, dtype=np.float64), None


def turntable_pairs(data: Path, seed: int, limit: int | None):
    """``(kind, name, source, target, truth, moved_by, voxel, judge)`` of every turntable pair."""
    surface = esmicp.read_points(data / "bunny" / "bun_zipper.ply")
    (clouds, poses), _ = turntable_scans(surface, TURNTABLE_SCANS, step_deg=TURNTABLE_STEP_DEG)
    pairs = [(k, (k + gap) % TURNTABLE_SCANS) for gap in (1, 2) for k in range(TURNTABLE_SCANS)]
    for number, (i, j) in enumerate(pairs[:limit]):
        source, target = clouds[i], clouds[j]
        truth = np.linalg.inv(poses[j]) @ poses[i]
        diagonal = bounding_box_diagonal(target)

        def judge(estimate, truth=truth, source=source, diagonal=diagonal):
            return strict_success(estimate, truth, diagonal, pivot=source.mean(axis=0))

        step = round(((j - i) % TURNTABLE_SCANS) * TURNTABLE_STEP_DEG)
        yield "turntable", f"turn{i:02d}->turn{j:02d} ({step} deg) as recorded", source, target, None, TURNTABLE_VOXEL, judge
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0, number)))
        turned, _, moved_by = turn_source(source, truth, rng)
        yield "turntable", f"turn{i:02d}->turn{j:02d} ({step} deg) turned", turned, target, moved_by, TURNTABLE_VOXEL, judge


def object_pairs(data: Path, seed: int, count: int):
    """The same tuples for ``count`` trials of ``outliers-60`` on the paper's shapes."""
    clouds = {path.stem: np.loadtxt(path, delimiter=",")[:, :3]
              for path in sorted((data / "modelnet40").glob("*/*.txt"))}
    for trial in make_trials("outliers-60", clouds, count, seed, points=OBJECT_POINTS):
        def judge(estimate, trial=trial):
            return up_to_symmetry_success(trial.clean_source, estimate, trial.T_target_source, trial.diagonal)

        yield "outliers-60", trial.cloud, trial.source, trial.target, None, None, judge


def run(pairs, seed: int, progress) -> list[dict]:
    """Every method on every pair, taking turns (the order rotating pair by pair)."""
    from esmicp.shapes import asymmetric_shape

    warm = asymmetric_shape(500, np.random.default_rng(0))
    for method in METHODS:
        _register(method, warm, warm, None, 0)
    rows = []
    for number, (kind, name, source, target, moved_by, voxel, judge) in enumerate(pairs):
        order = METHODS[number % len(METHODS):] + METHODS[:number % len(METHODS)]
        for method in order:
            started, cpu = time.perf_counter(), time.process_time()
            estimate, trusted = _register(method, source, target, voxel, seed)
            elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu
            estimate = estimate_in_pair_frame(estimate, moved_by)
            rows.append({"kind": kind, "pair": name, "method": method, "time_s": elapsed, "cpu_s": cpu,
                         "right": bool(judge(estimate)), "trusted": trusted,
                         "points": [len(source), len(target)]})
        progress(rows[-3:])
    return rows


def _ratio(rows, kind, peer, key="time_s") -> float:
    """Median over the pairs of esmicp's time (``key``: wall ``time_s`` or CPU ``cpu_s``) over
    ``peer``'s on the same pair."""
    times = {}
    for row in rows:
        if row["kind"] == kind:
            times.setdefault(row["pair"], {})[row["method"]] = row[key]
    return statistics.median(t["esmicp"] / t[peer] for t in times.values())


def markdown(rows) -> str:
    kinds = list(dict.fromkeys(row["kind"] for row in rows))
    lines = ["| kind | method | right | trusted (of them wrong) | median time (wall) | median CPU time (all threads) "
             "| esmicp's time / this method's, wall (CPU), median of per-pair ratios |",
             "|---|---|---|---|---|---|---|"]
    for kind in kinds:
        for method in METHODS:
            mine = [row for row in rows if row["kind"] == kind and row["method"] == method]
            right = sum(row["right"] for row in mine)
            if method == "esmicp":
                trusted = [row for row in mine if row["trusted"]]
                trust = f"{len(trusted)} ({sum(not row['right'] for row in trusted)})"
                ratio = "-"
            else:
                trust = "-"
                ratio = f"{_ratio(rows, kind, method):.2f} ({_ratio(rows, kind, method, 'cpu_s'):.2f})"
            median = statistics.median(row["time_s"] for row in mine)
            cpu = statistics.median(row["cpu_s"] for row in mine)
            lines.append(f"| {kind} | {LABELS[method]} | {right}/{len(mine)} | {trust} | {median:.2f} s | {cpu:.2f} s "
                         f"| {ratio} |")
    sizes = [n for row in rows if row["method"] == "esmicp" for n in row["points"]]
    return "\n".join(lines) + f"\n\nClouds of {min(sizes):,}-{max(sizes):,} points. {summary(rows)}\n"


def summary(rows) -> str:
    """Where esmicp is slower than the faster peer (wall time, median of per-pair ratios), in words."""
    words = []
    for kind in dict.fromkeys(row["kind"] for row in rows):
        ratio = max(_ratio(rows, kind, peer) for peer in METHODS[1:])
        cpu = max(_ratio(rows, kind, peer, "cpu_s") for peer in METHODS[1:])
        verdict = "slower than" if ratio > 1.0 else "at most the time of"
        words.append(f"{kind}: esmicp {verdict} the faster peer ({ratio:.2f}x its wall time, {cpu:.2f}x its CPU time)")
    return "; ".join(words) + "."


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--turntable-pairs", type=int, default=None,
                        help="the first N scan pairs only (each as recorded and turned; default all 30)")
    parser.add_argument("--objects", type=int, default=12, help="outliers-60 trials (round-robin over the 12 shapes)")
    parser.add_argument("--out", type=Path, help="write one JSON line per (pair, method)")
    parser.add_argument("--rows", type=Path, help="render the rows of an earlier run's --out instead of running")
    parser.add_argument("--doc", type=Path, help="rewrite the generated part of this page (docs/real-scans.md)")
    args = parser.parse_args(argv)

    def progress(last):
        print(" ".join(f"{row['method']} {row['time_s']:.2f}s {'ok' if row['right'] else 'WRONG'}" for row in last),
              last[0]["pair"], flush=True)

    if args.rows is not None:
        rows = [json.loads(line) for line in args.rows.read_text(encoding="utf-8").splitlines() if line.strip()]
    else:
        pairs = list(turntable_pairs(args.data, args.seed, args.turntable_pairs)) + list(
            object_pairs(args.data, args.seed, args.objects))
        rows = run(pairs, args.seed, progress)
    if args.out is not None:
        args.out.write_text("".join(json.dumps(row) + "\n" for row in rows), encoding="utf-8")
    text = "\n".join([
        "esmicp at its defaults beside KISS-Matcher + small_gicp GICP and KISS-Matcher + Open3D ICP on",
        "small clouds, in one run, the methods taking turns pair by pair (2 shared cores: read the",
        "ratios, not the seconds): turntable scans of the bunny 24 and 48 degrees apart (as recorded and",
        "turned; the peers at 2 mm) and the 12 paper shapes under 60% outliers (the peers at 1/40 of the",
        "diagonal):",
        "",
        "```bash",
        "python benchmarks/small_clouds.py --doc docs/real-scans.md",
        "```",
        "",
        markdown(rows).rstrip(),
    ])
    print(text)
    if args.doc is not None:
        write_between(args.doc, text, DOC_BEGIN, DOC_END)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
