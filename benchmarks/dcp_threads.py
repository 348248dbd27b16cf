"""``dcp-v1``'s time per call alone and on ``esmicp bench``'s local Dask cluster, in one run.

Usage::

    nice -n 5 python benchmarks/dcp_threads.py                 # 2 workers, 3 rounds of 6 calls
    nice -n 5 python benchmarks/dcp_threads.py --workers 2 --calls 6 --rounds 3

What it measures, each figure the ``time_s`` the bench writes in its rows (``time.perf_counter``
around the adapter's forward passes, through :func:`esmicp_lab.bench.methods.run_method`), on one
ModelNet40 object (``airplane_0126``, 1,024 points, a 45-degree turn and a shift of 0.3, source
and target in independent point orders):

- the threads of every worker of :func:`esmicp_lab.bench.runner.local_cluster` (Dask's ``nthreads``,
  torch's intra-op threads, ``OMP_NUM_THREADS``), as ``esmicp bench`` starts them;
- *alone*: ``--calls`` calls in this process, one after the other (``esmicp bench --workers 1``);
- *on Dask*: every worker making ``--calls`` calls at once (``esmicp bench`` with ``--workers``
  busy workers).

The two alternate for ``--rounds`` rounds, so that both see the same load of a shared machine;
the script prints the median per round and over all rounds, their ratio, and the load average
before and after. The object comes from ``--data`` (default ``$ESMICP_SHARED_DATA`` or
``../shared/data`` beside the repository), the weights from where ``esmicp_lab.baselines.weights``
looks for them.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = Path(os.environ.get("ESMICP_SHARED_DATA", REPO.parent / "shared" / "data"))
OBJECT = "modelnet40/airplane/airplane_0126.txt"


def _pair(data: Path, points: int):
    from scipy.spatial.transform import Rotation

    path = data / OBJECT
    if not path.is_file():
        sys.exit(f"--data: {path} not found")
    rng = np.random.default_rng(0)
    cloud = np.loadtxt(path, delimiter=",")[:, :3]
    cloud = cloud[rng.choice(len(cloud), points, replace=False)]
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("zyx", [45.0, 0.0, 0.0], degrees=True).as_matrix()
    truth[:3, 3] = 0.3
    target = (cloud @ truth[:3, :3].T + truth[:3, 3])[rng.permutation(points)]
    return cloud[rng.permutation(points)], target


def dcp_call_times(source, target, calls: int, seed: int) -> list[float]:
    """``calls`` timed ``dcp-v1`` calls as the bench makes them, after one untimed (warm) call."""
    from esmicp_lab.bench.methods import run_method

    call = dict(init=np.eye(4), max_iterations=1, sigma=None)
    run_method("dcp-v1", source, target, seed=seed, **call)
    return [run_method("dcp-v1", source, target, seed=seed + k, **call).time_s for k in range(calls)]


def worker_threads() -> dict:
    """What one worker process runs its methods on."""
    import torch

    return {"torch_threads": torch.get_num_threads(), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS")}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--calls", type=int, default=6)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--points", type=int, default=1024)
    args = parser.parse_args(argv)

    from dask.distributed import Client

    from esmicp_lab.bench.runner import local_cluster

    source, target = _pair(args.data, args.points)
    print(f"load average before: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    alone, on_dask = [], []
    with local_cluster(args.workers) as cluster, Client(cluster) as client:
        nthreads = client.nthreads()
        for address, threads in client.run(worker_threads).items():
            print(f"worker {address}: dask nthreads={nthreads[address]}, {threads}")
        for round_ in range(args.rounds):
            here = dcp_call_times(source, target, args.calls, seed=100 * round_)
            futures = [client.submit(dcp_call_times, source, target, args.calls, 100 * round_ + 10 * w, pure=False)
                       for w in range(args.workers)]
            there = [t for future in futures for t in future.result()]
            alone += here
            on_dask += there
            print(f"round {round_ + 1}: alone {statistics.median(here):.3f} s/call, "
                  f"on Dask ({args.workers} busy workers) {statistics.median(there):.3f} s/call")
    median_alone, median_dask = statistics.median(alone), statistics.median(on_dask)
    print(f"dcp-v1, {args.points} points, medians over {len(alone)} / {len(on_dask)} calls: alone {median_alone:.3f} s, "
          f"on Dask {median_dask:.3f} s, ratio {median_dask / median_alone:.2f}")
    print(f"load average after: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
