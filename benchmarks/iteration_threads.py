"""Per-iteration cost of ``esm`` on 1 and 2 threads beside Open3D ICP, in one process, alternating.

Usage::

    python benchmarks/iteration_threads.py --size 10000 --repeats 5
    python benchmarks/iteration_threads.py --size 1000 --repeats 7 --workers 1 2

The clouds, the start and the marginal cost are those of ``benchmarks/speed.py`` (bunny resampled
to ``--size`` points, 10 degrees off; ``(time(k + n) - time(k)) / n`` with k = 5 and n =
``speed.marginal_iterations(size)``, so tree builds never enter it). ``esm`` runs on one index
whose ``workers`` is set to each value of ``--workers`` in turn; each repeat times every variant
and Open3D once, the order rotating. Prints the medians (and minima) in ms per iteration and each
variant's ratio to Open3D's median, with the load average at the start and the end: on a shared
machine read the ratios, and compare runs of different builds only through them.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import speed  # noqa: E402  (the clouds and the protocol of benchmarks/speed.py)

SKIP = 5  # k: iterations run before the timed ones


def marginal_ms(run, extra: int) -> float:
    """ms per iteration of ``run(count)`` between ``SKIP`` and ``SKIP + extra`` iterations."""
    start = time.perf_counter()
    run(SKIP)
    middle = time.perf_counter()
    run(SKIP + extra)
    end = time.perf_counter()
    return 1e3 * ((end - middle) - (middle - start)) / extra


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2], help="esm's thread counts")
    args = parser.parse_args(argv)

    source, target, start, _ = speed._bunny(args.size)
    esm = speed.Esm(source, target, start)
    esm.build()
    esm.iterations(2)  # first-call costs outside the timings
    peer = speed.Open3dIcp(source, target, start)
    peer.build()
    extra = speed.marginal_iterations(args.size)

    def esm_on(workers):
        def run(count):
            esm.index.workers = workers
            return esm.iterations(count)
        return run

    variants = {f"esm, {w} thread{'s' if w > 1 else ''}": esm_on(w) for w in args.workers}
    variants["open3d-icp"] = peer.iterations
    names = list(variants)
    samples: dict[str, list[float]] = {name: [] for name in names}
    print(f"# bunny, {args.size:,} points, n = {extra}, {args.repeats} repeats, "
          f"load average {os.getloadavg()[0]:.1f} at start")
    for repeat in range(args.repeats):
        for name in names[repeat % len(names):] + names[: repeat % len(names)]:
            samples[name].append(marginal_ms(variants[name], extra))
    medians = {name: float(np.median(values)) for name, values in samples.items()}
    print("| variant | ms per iteration (median) | minimum | / Open3D |")
    print("|---|---|---|---|")
    for name in names:
        print(f"| {name} | {medians[name]:.3g} | {min(samples[name]):.3g} | "
              f"{medians[name] / medians['open3d-icp']:.2f} |")
    print(f"# load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
