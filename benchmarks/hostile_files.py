"""Hostile sizes: how fast, and at what memory cost, each lying file is refused (docs/reliability.md).

The files are those of ``tests/test_hostile_files.py`` (about 1 KB each, headers claiming 10^12
points, 4 GB, or compressed sizes that lie). For each: esmicp's time to refuse it (median of 5)
and its peak of Python / NumPy allocations (tracemalloc), and, as a peer measured in the same run,
what Open3D's ``read_point_cloud`` / ``read_triangle_mesh`` does with the same file, in a child
process capped at 2 GB of address space above its imports and 20 s (Open3D's C++ allocations are
invisible to tracemalloc; the cap makes an attempt to allocate the claimed size fail visibly).

    python benchmarks/hostile_files.py [--no-open3d]
    python benchmarks/hostile_files.py --memory [--peer-src /path/to/other/checkout/src]
    python benchmarks/hostile_files.py --las [--peer-src /path/to/other/checkout/src]

Prints one Markdown table; figures are measured in this run, never stored.

``--memory`` measures what big files cost: sparse 2 GB tails behind
declared content (ascii PCD, ascii PLY, ``.xyz``) and 10 MB PLY files whose list element comes
before the vertices. Each read runs in a fresh child, capped at 3 GB of address space above its
imports; the table gives its read time and the growth of its peak resident memory (VmHWM) over
the read. ``--peer-src`` runs the same reads against another checkout's ``src`` in the same run,
as the peer.

``--las`` reads each lying LAS / LAZ header of ``tests/test_io_scans.py`` (laspy's own files with
corrupted header bytes) in a fresh child capped at 1 GB above its imports, 60 s at most: outcome,
time and peak resident memory growth; ``--peer-src`` as above.
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


MEMORY_CHILD = r"""
import json, resource, sys, time
import esmicp.io, pypcd4, lzf, plyfile  # noqa: F401  (imports before the cap and the measure)

def status(key):
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith(key):
                return int(line.split()[1]) * 1024

cap = status("VmSize:") + 3 * 2**30
resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
before = status("VmHWM:")
start = time.perf_counter()
try:
    outcome = f"read {len(esmicp.io.read_points(sys.argv[1]))} points"
except BaseException as exc:  # noqa: BLE001 - reported as measured
    outcome = f"{type(exc).__name__}: {str(exc)[len(sys.argv[1]) + 2:][:70]}"
print(json.dumps({"seconds": time.perf_counter() - start, "peak_growth": status("VmHWM:") - before,
                  "outcome": outcome}))
"""


def _sparse(path: Path, content: bytes, size: int = 2 * 2**30) -> Path:
    with open(path, "wb") as handle:
        handle.write(content)
        handle.truncate(size)
    return path


def _lists_first_ply(path: Path, lengths, text: bool = False) -> Path:
    import numpy as np

    header = (f"ply\nformat {'ascii' if text else 'binary_little_endian'} 1.0\nelement face {len(lengths)}\n"
              "property list uchar int vertex_indices\nelement vertex 500\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n").encode()
    points = np.random.default_rng(0).normal(size=(500, 3)).astype("<f4")
    with open(path, "wb") as handle:
        handle.write(header)
        if text:
            handle.write("".join(f"{n}" + " 0" * n + "\n" for n in lengths).encode())
            np.savetxt(handle, points)
        else:
            handle.write(b"".join(bytes([n]) + bytes(4 * n) for n in lengths))
            handle.write(points.tobytes())
    return path


def memory_cases(directory: Path) -> dict[str, Path]:
    import numpy as np

    rows = "".join(f"{i} {i % 7} {i % 5}\n" for i in range(1000)).encode()
    pcd_header = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1000\nHEIGHT 1\n"
                  "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1000\nDATA ascii\n").encode()
    ply_header = (b"ply\nformat ascii 1.0\nelement vertex 1000\nproperty float x\nproperty float y\n"
                  b"property float z\nend_header\n")
    rng = np.random.default_rng(1)
    return {
        "ascii PCD, 1,000 points + 2 GB sparse tail": _sparse(directory / "tail.pcd", pcd_header + rows),
        "ascii PLY, 1,000 points + 2 GB sparse tail": _sparse(directory / "tail.ply", ply_header + rows),
        ".xyz, 2 GB sparse (all NUL)": _sparse(directory / "sparse.xyz", b""),
        ".xyz, 1,000 points + 2 GB sparse tail": _sparse(directory / "tail.xyz", rows),
        "binary PLY 10 MB, face list (3 each) before 500 vertices": _lists_first_ply(
            directory / "uniform.ply", [3] * (10_000_000 // 13)),
        "binary PLY 10 MB, face list (3 or 4, random) before 500 vertices": _lists_first_ply(
            directory / "mixed.ply", list(rng.choice([3, 4], 10_000_000 // 15))),
        "binary PLY 10 MB, 10M empty lists before 500 vertices": _lists_first_ply(
            directory / "empty.ply", [0] * 10_000_000),
        "ascii PLY 10 MB, face list (3 each) before 500 vertices": _lists_first_ply(
            directory / "ascii-lists.ply", [3] * (10_000_000 // 8), text=True),
    }


#: The child of ``--las``: laspy and lazrs imported before the cap, 1 GB of address space above them.
LAS_CHILD = MEMORY_CHILD.replace("import esmicp.io, pypcd4, lzf, plyfile", "import esmicp.io, laspy, lazrs").replace(
    '+ 3 * 2**30', '+ 2**30')


def _measure(path: Path, src: str | None, child: str = MEMORY_CHILD, timeout: float = 300) -> str:
    import json
    import os

    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = src
    try:
        process = subprocess.run([sys.executable, "-c", child, str(path)], capture_output=True, text=True,
                                 timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return f"still running after {timeout:.0f} s (killed) | - | -"
    if process.returncode != 0:
        return f"crashed (exit {process.returncode}) | - | -"
    result = json.loads(process.stdout.strip().splitlines()[-1])
    return f"{result['outcome']} | {result['seconds']:.2f} s | {result['peak_growth'] / 2**20:.0f} MB"


def memory_main(peer_src: str | None) -> None:
    directory = Path(tempfile.mkdtemp(prefix="esmicp-hostile-memory-"))
    columns = "| file | esmicp: outcome | time | peak RSS growth |"
    if peer_src:
        columns += " peer: outcome | time | peak RSS growth |"
    print(columns)
    print("|" + "---|" * (columns.count("|") - 1))
    for label, path in memory_cases(directory).items():
        cells = _measure(path, None)
        if peer_src:
            cells += " | " + _measure(path, peer_src)
        print(f"| {label} | {cells} |", flush=True)
        path.unlink()


def las_main(peer_src: str | None) -> None:
    """Each lying LAS / LAZ header of ``tests/test_io_scans.py`` (and the odd but readable ones), read
    in a fresh child capped at 1 GB of address space above its imports, 60 s at most."""
    import test_io_scans as las_cases  # noqa: E402  (needs laspy)

    directory = Path(tempfile.mkdtemp(prefix="esmicp-hostile-las-"))
    good = las_cases._las_and_laz(directory)
    cases = {name: (source, edits) for name, (source, edits, _) in las_cases.LAS_LIARS.items()}
    cases.update(las_cases.LAS_READABLE)
    columns = "| file | esmicp: outcome | time | peak RSS growth |"
    if peer_src:
        columns += " peer: outcome | time | peak RSS growth |"
    print(columns)
    print("|" + "---|" * (columns.count("|") - 1))
    for name, (source, edits) in cases.items():
        path = las_cases._patched(good[source], directory / name, edits)
        cells = _measure(path, None, LAS_CHILD, 60)
        if peer_src:
            cells += " | " + _measure(path, peer_src, LAS_CHILD, 60)
        print(f"| `{name}` | {cells} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-open3d", action="store_true", help="skip the Open3D peer")
    parser.add_argument("--memory", action="store_true", help="big files: time and peak memory")
    parser.add_argument("--las", action="store_true", help="lying LAS / LAZ headers: outcome, time and peak memory")
    parser.add_argument("--peer-src", help="with --memory or --las: also run another checkout's src as the peer")
    args = parser.parse_args()
    if args.las:
        las_main(args.peer_src)
        return
    if args.memory:
        memory_main(args.peer_src)
        return
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
