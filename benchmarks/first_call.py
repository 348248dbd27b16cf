"""How fast esmicp answers the first time: install, import, the command line, the first call.

Usage::

    python benchmarks/first_call.py                      # (b)-(d) with this interpreter's esmicp
    python benchmarks/first_call.py --fresh-venv /tmp/v  # (a) too, then (b)-(d) in that new venv
    python benchmarks/first_call.py --repeats 9 --json first_call.json

What it measures, wall time of whole processes (``time.perf_counter`` around ``subprocess.run``),
each in a new process so that nothing is warm but the operating system's file cache:

(a) ``--fresh-venv DIR``: ``python -m venv DIR``, then ``DIR/bin/pip install REPO`` (pip builds
    the C++ kernels with the system compiler; its wheel cache and index are whatever pip is
    configured with), then the first ``DIR/bin/esmicp demo`` and a few later ones;
(b) ``import esmicp``; ``import esmicp; esmicp.register`` (the registration path loaded: NumPy and
    the compiled kernels; SciPy only when the feature strategy runs); ``esmicp --version``; against
    ``python -c "import scipy.spatial"`` (the floor the issue set: SciPy's KD-tree module, which the
    registration path loaded until the kernels replaced it there) and ``python -c pass``,
    interleaved, medians of ``--repeats`` processes;
(c) ``esmicp register bun045.ply bun000.ply`` (the two 40k-point Stanford bunny scans, default
    global start), the first run and the median of the later ones;
(d) inside one new process: ``import numpy, esmicp``, loading ``esmicp.register``, then the first
    ``esmicp.register()`` and a second identical call, on a 2,000-point pair of the demo's shape
    (a quarter turn, shuffled) and on the bunny scans.

The clouds come from ``--data`` (default ``$ESMICP_SHARED_DATA`` or ``../shared/data`` beside the
repository). The machine may be shared: read each figure against its floor in the same run.
Nothing is written unless ``--json`` is given.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = Path(os.environ.get("ESMICP_SHARED_DATA", REPO.parent / "shared" / "data"))

#: (d): run in a new interpreter; prints one JSON object of perf_counter timings.
FIRST_CALLS = r"""
import json, sys, time
start = time.perf_counter()
import numpy as np
import esmicp
from esmicp.shapes import asymmetric_shape
imported = time.perf_counter()
esmicp.register  # the registration path: NumPy, the compiled kernels
out = {"import_s": imported - start, "load_register_s": time.perf_counter() - imported}
rng = np.random.default_rng(0)
target = asymmetric_shape(2000, rng)
source = asymmetric_shape(2000, rng)[::-1] @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]).T + 0.3
pairs = {"demo_pair": lambda: (source, target),
         "bunny_scans": lambda: (esmicp.read_points(sys.argv[1]), esmicp.read_points(sys.argv[2]))}
for name, pair in pairs.items():
    s, t = pair()
    times = []
    for _ in range(2):
        begin = time.perf_counter()
        esmicp.register(s, t, rng=0)
        times.append(time.perf_counter() - begin)
    out[name] = times
print(json.dumps(out))
"""


#: The children's environment: PYTHONPATH made absolute (they run in /tmp), or dropped for a fresh venv.
ENV = dict(os.environ)


def timed(command: list[str], **kwargs) -> float:
    """Wall seconds of one process; its failure is an error (stderr shown)."""
    begin = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=ENV, **kwargs)
    elapsed = time.perf_counter() - begin
    if done.returncode != 0:
        raise SystemExit(f"first_call.py: {' '.join(command)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return elapsed


def fresh_venv(folder: Path, repo: Path, later: int) -> tuple[dict, Path, list[str]]:
    if folder.exists():
        raise SystemExit(f"first_call.py: {folder}: already exists (give a new folder to --fresh-venv)")
    figures = {"venv_s": timed([sys.executable, "-m", "venv", str(folder)])}
    python = folder / "bin" / "python"
    figures["pip_install_s"] = timed([str(python), "-m", "pip", "install", "--quiet", str(repo)], cwd="/tmp")
    esmicp = [str(folder / "bin" / "esmicp")]
    figures["first_demo_s"] = timed([*esmicp, "demo"], cwd="/tmp")
    figures["later_demos_s"] = [timed([*esmicp, "demo"], cwd="/tmp") for _ in range(later)]
    figures["install_plus_first_demo_s"] = figures["pip_install_s"] + figures["first_demo_s"]
    return figures, python, esmicp


def imports(python: Path, esmicp: list[str], repeats: int) -> dict:
    probes = {
        "python -c pass": [str(python), "-c", "pass"],
        "import scipy.spatial (floor)": [str(python), "-c", "import scipy.spatial"],
        "import esmicp": [str(python), "-c", "import esmicp"],
        "import esmicp; esmicp.register": [str(python), "-c", "import esmicp; esmicp.register"],
        "esmicp --version": [*esmicp, "--version"],
    }
    runs: dict[str, list[float]] = {name: [] for name in probes}
    for repeat in range(repeats):
        names = list(probes)
        names = names[repeat % len(names):] + names[: repeat % len(names)]  # rotate the order
        for name in names:
            runs[name].append(timed(probes[name], cwd="/tmp"))
    return {name: statistics.median(values) for name, values in runs.items()}


def register_cli(esmicp: list[str], data: Path, repeats: int) -> dict:
    scans = [str(data / "bunny_scans" / "bun045.ply"), str(data / "bunny_scans" / "bun000.ply")]
    times = [timed([*esmicp, "register", *scans], cwd="/tmp") for _ in range(max(repeats, 2))]
    return {"first_s": times[0], "later_median_s": statistics.median(times[1:])}


def first_calls(python: Path, data: Path) -> dict:
    scans = [str(data / "bunny_scans" / "bun045.ply"), str(data / "bunny_scans" / "bun000.ply")]
    done = subprocess.run([str(python), "-c", FIRST_CALLS, *scans], capture_output=True, text=True, cwd="/tmp",
                          env=ENV)
    if done.returncode != 0:
        raise SystemExit(f"first_call.py: the first-call probe failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fresh-venv", type=Path, metavar="DIR", help="make a new virtual environment here "
                        "and time pip install + the first demo, then measure (b)-(d) in it")
    parser.add_argument("--repo", type=Path, default=REPO, help="what --fresh-venv installs (default this checkout)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder (bunny_scans/)")
    parser.add_argument("--repeats", type=int, default=5, help="processes per import probe (default 5)")
    parser.add_argument("--json", type=Path, help="also write every figure here")
    args = parser.parse_args()
    for scan in ("bun045.ply", "bun000.ply"):
        if not (args.data / "bunny_scans" / scan).is_file():
            parser.error(f"{args.data / 'bunny_scans' / scan}: not found (give the data folder with --data)")

    report = {"python": platform.python_version(), "cpus": os.cpu_count(), "load_average": os.getloadavg()}
    if args.fresh_venv:
        ENV.pop("PYTHONPATH", None)  # the new venv's own install, nothing else
        report["fresh_venv"], python, esmicp = fresh_venv(args.fresh_venv.resolve(), args.repo.resolve(), later=3)
        f = report["fresh_venv"]
        print(f"(a) fresh venv {args.fresh_venv}: pip install {f['pip_install_s']:.1f} s, first esmicp demo "
              f"{f['first_demo_s']:.2f} s, later demos " + " ".join(f"{t:.2f}" for t in f["later_demos_s"])
              + f" s; install + first demo {f['install_plus_first_demo_s']:.1f} s")
    else:
        if ENV.get("PYTHONPATH"):
            ENV["PYTHONPATH"] = os.pathsep.join(str(Path(p).resolve()) for p in ENV["PYTHONPATH"].split(os.pathsep))
        python = Path(sys.executable)
        script = shutil.which("esmicp", path=str(python.parent))
        esmicp = [script] if script else [str(python), "-m", "esmicp"]
    report["imports_median_s"] = imports(python, esmicp, args.repeats)
    floor = report["imports_median_s"]["import scipy.spatial (floor)"]
    print(f"(b) medians of {args.repeats} new processes ({' '.join(esmicp)}):")
    for name, value in report["imports_median_s"].items():
        print(f"    {name:34s} {value:6.3f} s   {value / floor:5.2f} x the scipy.spatial floor")
    report["register_cli"] = register_cli(esmicp, args.data, args.repeats)
    r = report["register_cli"]
    print(f"(c) esmicp register bun045.ply bun000.ply: first {r['first_s']:.2f} s, later (median) "
          f"{r['later_median_s']:.2f} s wall")
    report["first_calls"] = calls = first_calls(python, args.data)
    print(f"(d) one new process: import numpy, esmicp {calls['import_s']:.3f} s, then esmicp.register "
          f"{calls['load_register_s']:.3f} s; register() first / second: demo pair "
          f"{calls['demo_pair'][0]:.3f} / {calls['demo_pair'][1]:.3f} s, bunny scans "
          f"{calls['bunny_scans'][0]:.3f} / {calls['bunny_scans'][1]:.3f} s")
    print(f"load average {report['load_average'][0]:.1f} on {report['cpus']} cores")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
