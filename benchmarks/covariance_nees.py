"""Calibration of the pose covariance: NEES on whole objects, cut objects and real scan pairs.

Sets (each a choice half, on which ``TrustPolicy.border_spacings`` and ``TrustPolicy.inflation``
were chosen, and a confirmation half):

- ``objects``: a ModelNet40 shape (10,000 points) split into two disjoint random halves, each with
  its own Gaussian noise (0-1 point spacing), the source moved by a random pose (any rotation);
  the truth is exact. Choice: the 12 shapes of ``modelnet40``; confirmation: shapes of
  ``modelnet40_extra``.
- ``cut objects``: the same, each half then cut by its own random plane to 70% of its points
  (a partial overlap; the truth is exact).
- ``kitchen``: depth frames of the kitchen walk (``sequences/redkitchen_seq01_every10``), triplets
  ``a, b, c`` of frames 10-20 apart (pairs 10-40 apart), each pair registered; the truth is the
  dataset's KinectFusion tracking, good to about a centimetre. Choice: frames 0-490; confirmation:
  frames 500-990.
- ``bunny``: the Stanford bunny's raw scans, every pair overlapping by at least half, truth from
  ``bun.conf`` (confirmation only).
- ``lidar``: the LiDAR scans of ``real_pairs`` (confirmation only): the 5 Newer College scans, all
  10 pairs, truth from the dataset's pose graph (``graph.txt``), and their 10 cycles; the KITTI
  pair, truth from KITTI's published poses. Before any NEES, whether the truth can judge it:
  each pair registered from the truth itself by ``esm``, Open3D point-to-plane ICP and small_gicp
  GICP; the median of the three poses' offsets from the truth estimates the truth's own error,
  compared with the predicted standard deviation axis by axis (:data:`TRUTH_GOOD_RATIO`). The
  generated text goes between the page's ``<!-- covariance_nees lidar -->`` markers.

With ``e`` the left error vector of the result (``T_true = Exp(e) @ T_est``, rotation vector then
translation, target frame), ``NEES = e^T Sigma^-1 e``; a calibrated covariance gives a mean of 6
and 95% of trials below the chi-square(6) 95% bound (12.59). Only trusted results count (the
covariance describes the local optimum a trusted pose sits in).

A real truth has its own error, which the NEES charges to the covariance. Two ways around it:

- ``+ truth error``: the kitchen truth's error modelled as independent, ``KITCHEN_TRUTH_DEG`` and
  ``KITCHEN_TRUTH_M`` per axis, added to the predicted covariance;
- ``cycles`` (no truth at all): for three scans registered pairwise, ``T_ab @ T_bc`` against
  ``T_ac``, whose covariance is the sum of the three (first order). An error common to the three
  registrations (a scan's own distortion, seen by both of its pairs) cancels in a cycle, so the
  cycle NEES is a lower bound of the pairs' own.

Peers (``--peers``): Open3D point-to-plane ICP and its ``get_information_matrix_from_point_clouds``
(inverse taken as the covariance: as returned, i.e. unit noise, and scaled by the per-axis mean
square of the inlier distances, ``inlier_rmse^2 / 3``); small_gicp GICP and its Hessian ``H``
(``H^-1`` as returned, and scaled by the mean squared Mahalanobis residual ``2 error / (3 inliers
- 6)``), mapped from its right (source-frame) perturbation to the left one.

    python benchmarks/covariance_nees.py [--peers] [--plot docs/images/covariance_predicted_observed.png]
        [--doc docs/uncertainty.md]

Prints Markdown; ``--doc`` rewrites the generated part of that page (between its
``<!-- covariance_nees -->`` markers). Timings are ratios within the run (the covariance's cost
over the registration that computed it).
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import time
from pathlib import Path

import numpy as np

from esmicp_lab.bench.nees import (CUT_KEEP, DOC_BEGIN, DOC_END, KITCHEN_TRUTH_DEG, KITCHEN_TRUTH_M,
                                   LIDAR_BEGIN, LIDAR_END, LIDAR_STREAM, START_DEGREES, START_SPACINGS, Run,
                                   Table, bunny_scans, cycle, kitchen_triplets, lidar, nees, noise_table,
                                   object_trial, score, shapes)
from esmicp_lab.bench.tables import write_between

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--objects", type=int, default=2, help="trials per shape of the choice half (default 2)")
    parser.add_argument("--shapes", type=int, default=None, help="paper shapes used (default: all 12)")
    parser.add_argument("--extra", type=int, default=24, help="modelnet40_extra shapes, one trial each (default 24)")
    parser.add_argument("--triplets", type=int, default=6, help="kitchen triplets per half (default 6)")
    parser.add_argument("--sets", default="objects,cut,kitchen,bunny,lidar",
                        help="of objects, cut, kitchen, bunny, lidar")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--peers", action="store_true", help="also Open3D's and small_gicp's matrices")
    parser.add_argument("--plot", type=Path, help="write a PNG of predicted against observed errors (esmicp)")
    parser.add_argument("--doc", type=Path, help="rewrite the generated part of this page (docs/uncertainty.md)")
    args = parser.parse_args(argv)
    began = time.perf_counter()
    rng = np.random.default_rng(args.seed)
    names = args.sets.split(",")
    table, shares, by_noise = Table(), [], {}
    for kind, keep in (("objects", 1.0), ("cut", CUT_KEEP)):
        if kind not in names:
            continue
        name = "whole objects" if keep == 1.0 else f"cut objects ({CUT_KEEP:.0%})"
        for half, paths in (("choice", shapes(DATA, "modelnet40", args.shapes, rng) * args.objects),
                            ("confirmation", shapes(DATA, "modelnet40_extra", args.extra, rng))):
            for path in paths:
                source, target, truth, fraction = object_trial(path, rng, keep)
                run = Run(source, target, truth, rng)
                shares.append(run.share)
                table.count((name, half), run.trusted)
                if run.trusted:
                    score(table, name, half, "exact", run, args.peers)
                    band = min(int(3 * fraction), 2)
                    by_noise.setdefault((name, band), []).append(nees(run.error, run.covariance))
    if "kitchen" in names:
        truth_error = np.diag([math.radians(KITCHEN_TRUTH_DEG) ** 2] * 3 + [KITCHEN_TRUTH_M ** 2] * 3)
        for half, (first, last) in (("choice", (0, 490)), ("confirmation", (500, 990))):
            runs = []
            for (a, b, c), frames, poses in kitchen_triplets(DATA, first, last, args.triplets, rng):
                triplet = []
                for target, source in ((a, b), (b, c), (a, c)):
                    run = Run(frames[source], frames[target], np.linalg.inv(poses[target]) @ poses[source], rng)
                    shares.append(run.share)
                    table.count(("kitchen pairs", half), run.trusted)
                    triplet.append(run)
                runs.append(triplet)
            for triplet in runs:
                for run in (r for r in triplet if r.trusted):
                    score(table, "kitchen pairs", half, "recorded", run, False)
            for triplet in runs:
                for run in (r for r in triplet if r.trusted):
                    score(table, "kitchen pairs", half, "recorded + truth error", run, args.peers, truth_error)
            for triplet in runs:
                if all(run.trusted for run in triplet):
                    error, covariance = cycle(*triplet)
                    table.add(("kitchen pairs", half, "cycles", "esmicp"), nees(error, covariance))
    if "bunny" in names:
        points, poses, pairs = bunny_scans(DATA)
        runs = {}
        for target, source in pairs:
            run = Run(points[source], points[target], np.linalg.inv(poses[target]) @ poses[source], rng)
            shares.append(run.share)
            table.count(("bunny scan pairs", "confirmation"), run.trusted)
            if run.trusted:
                runs[(target, source)] = run
                score(table, "bunny scan pairs", "confirmation", "recorded", run, args.peers)
        for a, b, c in itertools.combinations(list(points), 3):
            if all(key in runs for key in ((a, b), (b, c), (a, c))):
                error, covariance = cycle(runs[(a, b)], runs[(b, c)], runs[(a, c)])
                table.add(("bunny scan pairs", "confirmation", "cycles", "esmicp"), nees(error, covariance))
    texts = {}
    if shares:
        shares = np.array(shares)
        texts[DOC_BEGIN, DOC_END] = "\n".join([
            f"Seed {args.seed}; {args.objects} trial(s) per paper shape, {args.extra} `modelnet40_extra` shapes, "
            f"{args.triplets} kitchen triplets per half; every start {START_DEGREES:g} deg and {START_SPACINGS:g} "
            f"target spacings from the truth; kitchen truth error {KITCHEN_TRUTH_DEG:g} deg and "
            f"{100 * KITCHEN_TRUTH_M:g} cm per axis.", "", table.markdown(), "", noise_table(by_noise), "",
            f"Cost of the covariance: median {100 * np.median(shares):.1f}% of the registration that computed it "
            f"(max {100 * shares.max():.1f}%), {len(shares)} registrations from a given start, one thread; the "
            f"whole run {(time.perf_counter() - began) / 60:.0f} minutes{' with the peers' if args.peers else ''}."])
    if "lidar" in names:
        began = time.perf_counter()
        lidar_table = Table()
        check = lidar(DATA, lidar_table, np.random.default_rng([args.seed, LIDAR_STREAM]), args.peers)
        texts[LIDAR_BEGIN, LIDAR_END] = "\n".join([
            f"Seed {args.seed}; every start {START_DEGREES:g} deg and {START_SPACINGS:g} target spacings from the "
            "truth; the Newer College cycles use no truth.", "", check, "", lidar_table.markdown(), "",
            f"The LiDAR part took {(time.perf_counter() - began) / 60:.0f} minutes"
            f"{' with the peers' if args.peers else ''}."])
    for (begin, end), text in texts.items():
        print(text + "\n")
        if args.doc is not None:
            write_between(args.doc, text, begin, end)
    if args.plot is not None and table.points:
        _plot(table.points, args.plot)
    return 0


def _plot(points, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    figure, axes = plt.subplots(1, 2, figsize=(8, 3.6))
    labels = ("rotation (deg)", "translation (spacings)")
    for panel, (axis, label) in enumerate(zip(axes, labels)):
        for set_name in sorted({name for name, *_ in points}):
            chosen = [(e, s, spacing) for name, e, s, spacing in points if name == set_name]
            observed = np.concatenate([e[3 * panel:3 * panel + 3] for e, _, _ in chosen])
            predicted = np.concatenate([s[3 * panel:3 * panel + 3] for _, s, _ in chosen])
            if panel == 0:
                observed, predicted = np.degrees(observed), np.degrees(predicted)
            else:
                scale = np.repeat([spacing for _, _, spacing in chosen], 3)
                observed, predicted = observed / scale, predicted / scale
            axis.loglog(predicted, observed, ".", ms=3, label=set_name, alpha=0.7)
        low, high = axis.get_xlim()
        grid = np.geomspace(low, high, 10)
        axis.loglog(grid, grid, "k-", lw=0.8, label="1 sigma")
        axis.loglog(grid, 2 * grid, "k--", lw=0.8, label="2 sigma")
        axis.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        axis.set_xlabel(f"predicted std, {label}")
        axis.set_ylabel(f"observed |error|, {label}")
    axes[0].legend(fontsize=7)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=90)


if __name__ == "__main__":
    sys.exit(main())
