"""Pairs that cannot be registered: how long esmicp takes to end on them, and whether it trusts any,
beside KISS-Matcher + small_gicp in the same run.

Three kinds of pair share nothing, so every pose is wrong and a trusted result is a wrong one:

``3DMatch, nothing shared``
    Each 3DMatch pair of a real-pairs folder, the source turned
    (:func:`esmicp_lab.bench.real_pairs.turn_source`), onto the part of the target farther than
    :data:`APART_M` from the source placed by the true pose.
``kitchen, apart``
    Frames of the kitchen walk (``sequences/redkitchen_seq01_every10``) 200-600 frames apart whose
    true overlap is at most :data:`KITCHEN_MAX_OVERLAP` (the source's fraction within 3 target
    spacings of the target), as recorded.
``unrelated objects``
    The source of one ``outliers-60`` (or ``resampled``) trial of a paper shape onto the target of
    another shape's trial (:mod:`esmicp_lab.bench.protocols`, 2,000 points a half).

esmicp runs at its defaults, the peer at the voxel its docs give (0.05 m indoor, 1/40 of the
target's diagonal on objects); they take turns pair by pair after one untimed warm-up call each.
Wall and CPU time (the process's, every thread's) are both recorded; read the ratios (median over
the pairs of esmicp's time over the peer's on the same pair), not the seconds.

    nice -n 5 python benchmarks/unregisterable_pairs.py --data ../shared/data
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import esmicp
from esmicp.core.procrustes import apply, bounding_box_diagonal
from esmicp_lab.bench.protocols import make_trials
from esmicp_lab.bench.real_pairs import load_pair, read_pairs, turn_source
from esmicp_lab.bench.sequences import frame_pairs

#: Target points kept in the 3DMatch set lie farther than this from the placed source (metres).
APART_M = 0.5
#: Kitchen frames apart (in kept frames, every 10th of the walk) and the largest true overlap kept.
KITCHEN_GAPS, KITCHEN_MAX_OVERLAP = (20, 30, 40, 50, 60), 0.02
#: The peer's voxel on indoor scans (metres) and on objects (target diagonals).
SCENE_VOXEL, OBJECT_VOXEL_DIAGONALS = 0.05, 1.0 / 40.0
PEER = "kiss-matcher-gicp"


def match_pairs(folder: Path):
    """``(set, name, source, target, peer voxel)`` of the 3DMatch pairs with nothing shared."""
    for number, pair in enumerate(p for p in read_pairs(folder) if p.kind == "3DMatch"):
        source, target, truth = load_pair(pair)
        gaps, _ = cKDTree(apply(truth, source)).query(target, distance_upper_bound=APART_M)
        apart = target[gaps > APART_M]
        turned, _, _ = turn_source(source, truth, np.random.default_rng(np.random.SeedSequence(7, spawn_key=(number,))))
        yield "3DMatch, nothing shared", pair.pair, turned, apart, SCENE_VOXEL


def kitchen_pairs(folder: Path, every: int = 10):
    """The same tuples for kitchen frames far apart that do not overlap."""
    for source_name, target_name, source, target, _, overlap in frame_pairs(folder, KITCHEN_GAPS, every):
        if overlap <= KITCHEN_MAX_OVERLAP:
            yield "kitchen, apart", f"{source_name} onto {target_name}", source, target, SCENE_VOXEL


def object_pairs(folder: Path, count: int = 6):
    """The same tuples for one shape's source onto another shape's target."""
    clouds = {path.stem: np.loadtxt(path, delimiter=",")[:, :3] for path in sorted(folder.glob("*/*.txt"))}
    for protocol in ("outliers-60", "resampled"):
        trials = make_trials(protocol, clouds, len(clouds), 5, points=2000)
        for k in range(min(count, len(trials))):
            source, target = trials[k], trials[(k + len(trials) // 2) % len(trials)]
            voxel = OBJECT_VOXEL_DIAGONALS * bounding_box_diagonal(target.target)
            yield f"unrelated objects ({protocol})", f"{source.cloud} onto {target.cloud}", source.source, \
                target.target, voxel


def _run(method: str, source, target, voxel):
    """``(wall s, CPU s, trusted)``: esmicp's verdict, None for the peer (it gives none)."""
    from esmicp_lab import baselines

    started, cpu = time.perf_counter(), time.process_time()
    if method == "esmicp":
        trusted = bool(esmicp.register(source, target, rng=0).trusted)
    else:
        baselines.get_baseline(method)(source, target, voxel_size=voxel, rng=0)
        trusted = None
    return time.perf_counter() - started, time.process_time() - cpu, trusted


def run(pairs, progress=print) -> list[dict]:
    """Both methods on every pair, taking turns (the order alternating pair by pair)."""
    from esmicp.shapes import asymmetric_shape

    warm = asymmetric_shape(500, np.random.default_rng(0))
    for method in ("esmicp", PEER):
        _run(method, warm, warm, 0.01)
    rows = []
    for number, (kind, name, source, target, voxel) in enumerate(pairs):
        row = {"set": kind, "pair": name}
        for method in (("esmicp", PEER) if number % 2 == 0 else (PEER, "esmicp")):
            wall, cpu, trusted = _run(method, source, target, voxel)
            row[method] = {"time_s": wall, "cpu_s": cpu, "trusted": trusted}
        rows.append(row)
        progress(f"{kind}: {name}: esmicp {row['esmicp']['time_s']:.2f} s (CPU {row['esmicp']['cpu_s']:.2f}), "
                 f"trusted {row['esmicp']['trusted']}; peer {row[PEER]['time_s']:.2f} s")
    return rows


def markdown(rows) -> str:
    lines = ["| set | pairs | esmicp trusted (all wrong) | esmicp median time a pair (s) | "
             "time / KISS-Matcher + small_gicp's (wall) | (CPU) |", "|---|---|---|---|---|---|"]
    for kind in dict.fromkeys(row["set"] for row in rows):
        mine = [row for row in rows if row["set"] == kind]
        wall = statistics.median(row["esmicp"]["time_s"] / row[PEER]["time_s"] for row in mine)
        cpu = statistics.median(row["esmicp"]["cpu_s"] / max(row[PEER]["cpu_s"], 1e-9) for row in mine)
        seconds = statistics.median(row["esmicp"]["time_s"] for row in mine)
        trusted = sum(row["esmicp"]["trusted"] for row in mine)
        lines.append(f"| {kind} | {len(mine)} | {trusted} | {seconds:.2f} | {wall:.2f}x | {cpu:.2f}x |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[1] / ".." / "shared" / "data")
    parser.add_argument("--objects", type=int, default=6, help="unrelated object pairs of each protocol")
    args = parser.parse_args(argv)

    def pairs():
        yield from match_pairs(args.data / "real_pairs")
        yield from kitchen_pairs(args.data / "sequences" / "redkitchen_seq01_every10")
        yield from object_pairs(args.data / "modelnet40", args.objects)

    rows = run(pairs(), progress=lambda line: print(line, flush=True))
    print()
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
