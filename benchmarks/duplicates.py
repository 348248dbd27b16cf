"""Coincident points: registration time against the number of copies, and how fast Ctrl-C stops it
(docs/reliability.md, "Coincident points and Ctrl-C in the compiled kernels").

Cases, each registration in a fresh child process (so that one case's caches never help the
next, and a hang is cut at ``--timeout`` seconds):

- three points repeated to 10k / 100k / 300k / 1M (``np.repeat([[0,0,0],[1,0,0],[0,2,0]], ...)``,
  source = target + 0.01), with ``init="identity"`` and with the default global search;
- the two bunny scans ``bun045.ply`` onto ``bun000.ply`` as they are, and with 150,000 (0, 0, 0)
  points added to each (a depth sensor's invalid pixels);
- Ctrl-C: SIGINT sent at several moments into the 1M-point registration (default init, after a
  small warm-up registration has done the lazy imports), the latency from the signal to the
  ``KeyboardInterrupt``.

    python benchmarks/duplicates.py [--sizes 10000 100000 300000 1000000] [--timeout 300]
    python benchmarks/duplicates.py --src /other/checkout/src    # the same cases on other code

Prints Markdown tables; nothing is stored. The load average is printed with them.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("ESMICP_SHARED_DATA", ROOT / ".." / "shared" / "data"))

CHILD = r"""
import sys, time, warnings
import numpy as np
import esmicp

warnings.simplefilter("ignore")
case, size, init = sys.argv[1], int(sys.argv[2]), sys.argv[3]
if case == "three":
    base = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    target = np.repeat(base, -(-size // 3), axis=0)[:size]
    source = target + 0.01
else:
    folder = sys.argv[4]
    source = esmicp.read_points(folder + "/bun045.ply")
    target = esmicp.read_points(folder + "/bun000.ply")
    if size:
        zeros = np.zeros((size, 3))
        source, target = np.vstack([source, zeros]), np.vstack([target, zeros])
started = time.perf_counter()
result = esmicp.register(source, target, init=None if init == "global" else init)
print(f"{time.perf_counter() - started:.3f} {result.num_iterations} {len(source)}")
"""

INTERRUPT_CHILD = r"""
import os, signal, sys, threading, time, warnings
import numpy as np
import esmicp

signal.signal(signal.SIGINT, signal.default_int_handler)
warnings.simplefilter("ignore")
size, delay = int(sys.argv[1]), float(sys.argv[2])
base = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
target = np.repeat(base, -(-size // 3), axis=0)[:size]
source = target + 0.01
warm = np.random.default_rng(0).normal(size=(500, 3))
esmicp.register(warm + 0.01, warm)  # the lazy imports, outside the measured part
sent = []

def fire():
    sent.append(time.perf_counter())
    os.kill(os.getpid(), signal.SIGINT)

threading.Timer(delay, fire).start()
try:
    esmicp.register(source, target)
    print("finished")
except KeyboardInterrupt:
    print(f"{time.perf_counter() - sent[0]:.4f}")
"""


def _run(code: str, args: list[str], src: Path, timeout: float) -> str | None:
    env = {**os.environ, "PYTHONPATH": str(src)}
    try:
        done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                              timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return None
    if done.returncode != 0:
        raise SystemExit(f"child failed: {done.stderr[-1500:]}")
    return done.stdout.strip()


def registrations(sizes, src, timeout) -> list[str]:
    rows = ["| case | points | init | time s | iterations |", "|---|---|---|---|---|"]
    for size in sizes:
        for init in ("identity", "global"):
            out = _run(CHILD, ["three", str(size), init], src, timeout)
            seconds, iterations = ("> %g" % timeout, "-") if out is None else out.split()[:2]
            rows.append(f"| three points repeated | {size:,} | {init} | {seconds} | {iterations} |")
            print(rows[-1], flush=True)
    for zeros in (0, 150_000):
        for init in ("identity", "global"):
            out = _run(CHILD, ["bunny", str(zeros), init, str(SHARED / "bunny_scans")], src, timeout)
            seconds, iterations, count = ("> %g" % timeout, "-", "-") if out is None else out.split()
            label = "bun045 onto bun000" + (f" + {zeros:,} (0, 0, 0) each" if zeros else "")
            rows.append(f"| {label} | {count} | {init} | {seconds} | {iterations} |")
            print(rows[-1], flush=True)
    return rows


def interrupts(src, timeout, delays=(0.2, 0.5, 1.0, 2.0, 3.0, 4.0)) -> list[str]:
    rows = ["| SIGINT after s (1M coincident points, default init) | KeyboardInterrupt after s |", "|---|---|"]
    for delay in delays:
        out = _run(INTERRUPT_CHILD, ["1000000", str(delay)], src, timeout)
        rows.append(f"| {delay} | {'not stopped within %g s' % timeout if out is None else out} |")
        print(rows[-1], flush=True)
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 300_000, 1_000_000])
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds before a case counts as a hang")
    parser.add_argument("--src", type=Path, default=ROOT / "src", help="the esmicp sources to measure")
    parser.add_argument("--no-interrupts", action="store_true")
    args = parser.parse_args(argv)
    print(f"# load average {os.getloadavg()[0]:.1f} at the start", flush=True)
    started = time.perf_counter()
    lines = registrations(args.sizes, args.src, args.timeout)
    if not args.no_interrupts:
        lines += [""] + interrupts(args.src, args.timeout)
    print("\n" + "\n".join(lines))
    print(f"\n# load average {os.getloadavg()[0]:.1f} at the end, {time.perf_counter() - started:.0f} s in all")


if __name__ == "__main__":
    main()
