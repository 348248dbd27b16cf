"""Hostile sizes: how fast, and at what memory cost, each lying file is refused (docs/reliability.md).

The files are those of ``tests/test_hostile_files.py`` (about 1 KB each, headers claiming 10^12
points, 4 GB, or compressed sizes that lie). For each: esmicp's time to refuse it (median of 5)
and its peak of Python / NumPy allocations (tracemalloc), and, as a peer measured in the same run,
what Open3D's ``read_point_cloud`` / ``read_triangle_mesh`` does with the same file, in a child
process capped at 2 GB of address space above its imports and 20 s (Open3D's C++ allocations are
invisible to tracemalloc; the cap makes an attempt to allocate the claimed size fail visibly).

    python benchmarks/hostile_files.py [--no-open3d]

Prints one Markdown table; figures are measured in this run, never stored.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import test_hostile_files as hostile  # noqa: E402

from esmicp.io import read_points  # noqa: E402

OPEN3D_CHILD = r"""
import resource, sys
import open3d as o3d
def address_space():
    for line in open("/proc/self/status"):
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
cap = address_space() + 2 * 2**30
resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
path = sys.argv[1]
if path.endswith((".off", ".stl", ".obj")):
    mesh = o3d.io.read_triangle_mesh(path)
    print(f"returned a mesh of {len(mesh.vertices)} vertices")
else:
    cloud = o3d.io.read_point_cloud(path)
    print(f"returned a cloud of {len(cloud.points)} points")
"""


def open3d_outcome(path: Path) -> str:
    try:
        process = subprocess.run(
            [sys.executable, "-c", OPEN3D_CHILD, str(path)], capture_output=True, text=True, timeout=20
        )
    except subprocess.TimeoutExpired:
        return "still running after 20 s (killed)"
    said = [line for line in (process.stdout + process.stderr).splitlines() if line.strip()]
    if process.returncode != 0:
        last = said[-1][:80] if said else ""
        return f"crashed (exit {process.returncode}) {last}".strip()
    warned = any("[Open3D WARNING]" in line or "[Open3D Error]" in line for line in said)
    result = next((line for line in said if line.startswith("returned")), "returned nothing")
    return result + (", with a warning" if warned else ", silently")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-open3d", action="store_true", help="skip the Open3D peer")
    args = parser.parse_args()
    import pypcd4  # noqa: F401  (imported before timing, as read_points would on first use)
    import trimesh  # noqa: F401

    directory = Path(tempfile.mkdtemp(prefix="esmicp-hostile-"))
    print("| file | bytes | esmicp: refused in (median of 5) | esmicp: peak allocation | esmicp: message | Open3D (same file) |")
    print("|---|---|---|---|---|---|")
    for name in sorted(hostile.HOSTILE):
        path = hostile.write_hostile(directory, name)
        times, peaks, message = [], [], ""
        for _ in range(5):
            tracemalloc.start()
            start = time.perf_counter()
            try:
                read_points(path)
                message = "READ (not refused)"
            except Exception as exc:  # noqa: BLE001 - reported as measured
                message = str(exc)[len(str(path)) + 2 :]
            times.append(time.perf_counter() - start)
            peaks.append(tracemalloc.get_traced_memory()[1])
            tracemalloc.stop()
        peer = "n/a" if args.no_open3d or name.endswith(".npy") else open3d_outcome(path)
        print(
            f"| `{name}` | {path.stat().st_size} | {statistics.median(times) * 1000:.2f} ms | "
            f"{max(peaks) / 1024:.0f} KB | {message[:90]} | {peer} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
