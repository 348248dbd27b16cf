"""Quick check of global registration on real scan pairs, against the peers *without* their ICP
(``esmicp bench --datasets real-pairs`` gives them ICP): every pair of ``pairs.csv``, as recorded
and turned.

The folder is laid out like ``shared/data/real_pairs`` (read by
:func:`esmicp_lab.bench.real_pairs.read_pairs`; ``.bin`` scans have ``--bin-columns`` float32 columns,
3 in the shared data).

Variants: ``as-recorded``, and ``turned``: the source turned by a random rotation (uniform on
SO(3), seeded per pair) about its centroid (:func:`~esmicp_lab.bench.real_pairs.turn_source`), the
estimate mapped back before it is judged.

Success: each kind's criteria (:func:`~esmicp_lab.bench.real_pairs.criteria_for`: 3DMatch rotation
error < 15 deg and translation error < 0.30 m; LiDAR < 5 deg and < 0.6 m). Methods (``--methods``): ``esm`` (``esmicp.register(source, target)`` with every
default, or ``--init``), and any name of :data:`esmicp_lab.baselines.BASELINES`, which get the voxel
their documentation recommends (0.05 m indoor, 0.3 m LiDAR). Methods take turns pair by pair;
only the registration call is timed. Prints one line per (pair, variant, method), a summary,
each method's median time ratio to the last one, and a Markdown table: one row per (pair,
variant), every method's success, errors and time, and the first method's time over the fastest
of the others (the peers) that succeed on that row: a peer that fails is no bar to beat.

    python benchmarks/scan_pairs_quick.py --methods esm,kiss-matcher-icp,open3d-ransac-fpfh-icp
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

import esmicp
from esmicp_lab.bench.real_pairs import (
    criteria_for, estimate_in_pair_frame, load_pair, pair_errors, quick_markdown_table, read_pairs, turn_source,
)

DEFAULT_FOLDER = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_pairs"


def run_method(name: str, source, target, kind: str, seed: int, init: str | None):
    if name == "esm":
        started = time.perf_counter()
        result = esmicp.register(source, target, init=init, rng=seed)
        return result.transformation, time.perf_counter() - started, result
    from esmicp_lab.baselines import get_baseline

    result = get_baseline(name)(source, target, voxel_size=criteria_for(kind).voxel_m, rng=seed)
    return result.transformation, result.runtime_s, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", type=Path, default=DEFAULT_FOLDER)
    parser.add_argument("--methods", default="esm,kiss-matcher-icp")
    parser.add_argument("--init", default=None, help="esm's init (default: register()'s default)")
    parser.add_argument("--variants", default="as-recorded,turned")
    parser.add_argument("--pairs", default=None, help="comma-separated pair names (dataset/pair or pair)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bin-columns", type=int, choices=(3, 4), default=3,
                        help="columns of the .bin scans (3: x y z, as in shared/data; 4: KITTI's x y z intensity)")
    args = parser.parse_args()
    methods = args.methods.split(",")
    variants = args.variants.split(",")
    wanted = None if args.pairs is None else set(args.pairs.split(","))
    rows = []
    for number, pair in enumerate(read_pairs(args.folder)):
        label = pair.name
        if wanted is not None and label not in wanted and pair.pair not in wanted:
            continue
        kind = pair.kind
        source0, target, truth = load_pair(pair, bin_columns=args.bin_columns)
        criteria = criteria_for(kind)
        for variant in variants:
            seed = args.seed * 1000 + number
            source, moved_by = source0, None
            if variant != "as-recorded":
                source, _, moved_by = turn_source(source0, truth, np.random.default_rng(seed))
            for name in methods:
                estimate, seconds, result = run_method(name, source, target, kind, seed, args.init)
                rot, trans = pair_errors(estimate_in_pair_frame(estimate, moved_by), truth)
                ok = criteria.success(rot, trans)
                extra = ""
                if name == "esm":
                    extra = f" init={result.init} ambiguous={result.ambiguous} fitness={result.fitness:.3f}"
                    confidence = getattr(result, "confidence", None)
                    if confidence is not None:
                        extra += f" confidence={confidence:.2f}"
                print(
                    f"{label:32s} {variant:11s} {name:18s} {'ok  ' if ok else 'FAIL'} "
                    f"rot {rot:7.2f} deg  t {trans:7.3f} m  {seconds:6.2f} s{extra}",
                    flush=True,
                )
                rows.append((label, variant, name, ok, rot, trans, seconds))
    print()
    for name in methods:
        mine = [row for row in rows if row[2] == name]
        successes = sum(row[3] for row in mine)
        print(f"{name:18s} {successes}/{len(mine)} successes, median time {statistics.median(r[6] for r in mine):.2f} s")
        if name != methods[-1] and len(methods) > 1:
            peer = methods[-1]
            ratios = [
                row[6] / other[6]
                for row in mine
                for other in rows
                if other[2] == peer and other[0] == row[0] and other[1] == row[1]
            ]
            print(f"{'':18s} time ratio to {peer}: median {statistics.median(ratios):.2f}, max {max(ratios):.2f}")
    if len(methods) > 1:
        print()
        print(quick_markdown_table(rows, methods))


if __name__ == "__main__":
    main()
