"""Hostile sizes: files whose headers claim far more data than they hold are refused quickly, with
a clear error, and without allocating what they claim.

Checked two ways: the peak of Python / NumPy allocations (tracemalloc) and the time of every read
in this process, and all reads again in a child process whose address space is capped a few
hundred MB above what it uses after import (so that no kind of allocation, memory maps included,
can reach the claimed gigabytes).
"""

from __future__ import annotations

import io
import json
import struct
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from esmicp.errors import PointCloudFileError
from esmicp.io import read_points

HUGE = 10**12  # points
FOUR_GB = 4 * 2**30  # bytes
FILLER = bytes(1000)  # what the file really holds after its header: about 1 KB

#: Generous bounds: a refused file costs a few hundred KB and a few ms (see docs/reliability.md).
MAX_PEAK_BYTES = 8 * 2**20
MAX_SECONDS = 1.0
#: Address space the child may use above what it has after its imports.
CHILD_HEADROOM_BYTES = 384 * 2**20


def pcd(data: str, points: int, *, size="4 4 4", kind="F F F") -> bytes:
    return (
        f"VERSION 0.7\nFIELDS x y z\nSIZE {size}\nTYPE {kind}\nCOUNT 1 1 1\nWIDTH {points}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n"
    ).encode()


def ply(fmt: str, vertices: int, extra: str = "", kind: str = "float") -> bytes:
    return (
        f"ply\nformat {fmt} 1.0\nelement vertex {vertices}\nproperty {kind} x\nproperty {kind} y\n"
        f"property {kind} z\n{extra}end_header\n"
    ).encode()


def npy(shape: tuple[int, ...], descr="<f8") -> bytes:
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": descr, "fortran_order": False, "shape": shape})
    return header.getvalue()


def stl_binary(triangles: int) -> bytes:
    triangle = struct.pack("<12fH", 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0)
    return bytes(80) + struct.pack("<I", triangles) + triangle * 19  # 1 KB of real triangles


def lzf_block(compressed_size: int, uncompressed_size: int, data: bytes) -> bytes:
    return struct.pack("<II", compressed_size, uncompressed_size) + data


FOUR_GB_OF_FLOAT_XYZ = FOUR_GB // 12 + 1  # points of 3 x float32 that need more than 4 GB

#: name -> (file content, words the error must contain (any of them))
HOSTILE = {
    # A header that declares 10^12 points, in every format with a count.
    "1e12-points-binary.ply": (ply("binary_little_endian", HUGE) + FILLER, ["truncated", "1000000000000"]),
    "1e12-points-big-endian.ply": (ply("binary_big_endian", HUGE, kind="double") + FILLER, ["truncated"]),
    "1e12-points-ascii.ply": (ply("ascii", HUGE) + b"1 2 3\n" * 150, ["truncated"]),
    "1e12-faces-after-vertices.ply": (
        ply("binary_little_endian", 3, f"element face {HUGE}\nproperty list uchar int vertex_indices\n")
        + FILLER,
        ["truncated", "faces"],
    ),
    "1e12-points-binary.pcd": (pcd("binary", HUGE) + FILLER, ["truncated", "1000000000000"]),
    "1e12-points-ascii.pcd": (pcd("ascii", HUGE) + b"1 2 3\n" * 150, ["truncated"]),
    "1e12-points-compressed.pcd": (
        pcd("binary_compressed", HUGE) + lzf_block(900, HUGE * 12 % 2**32, FILLER),
        ["corrupt"],
    ),
    "1e12-points.npy": (npy((HUGE, 3)) + FILLER, ["truncated", "1000000000000"]),
    "1e12-structured.npy": (npy((HUGE,), [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]) + FILLER, ["truncated"]),
    "1e12-vertices.off": (f"OFF\n{HUGE} 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n".encode() + b"\n" * 900, ["truncated"]),
    "1e12-count-line.xyz": (f"{HUGE}\n".encode() + b"1 2 3\n" * 150, ["count line"]),
    # A 4 GB claim in a 1 KB file.
    "4GB-binary.ply": (ply("binary_little_endian", FOUR_GB_OF_FLOAT_XYZ) + FILLER, ["truncated"]),
    "4GB-face-list.ply": (
        ply("binary_little_endian", 3, f"element face {FOUR_GB // 13 + 1}\nproperty list uchar int vertex_indices\n")
        + FILLER,
        ["truncated"],
    ),
    "4GB-binary.pcd": (pcd("binary", FOUR_GB_OF_FLOAT_XYZ) + FILLER, ["truncated"]),
    "4GB-ascii.pcd": (pcd("ascii", FOUR_GB // 6 + 1) + b"1 2 3\n" * 150, ["truncated"]),
    "4GB.npy": (npy((FOUR_GB // 24 + 1, 3)) + FILLER, ["truncated"]),
    "4GB-triangles.stl": (stl_binary(FOUR_GB // 50 + 1), ["truncated", "triangles"]),
    "4GB-uint32-triangles.stl": (stl_binary(2**32 - 1), ["truncated", "triangles"]),
    # Compressed PCD whose size fields lie.
    "compressed-size-claims-4GB.pcd": (
        pcd("binary_compressed", 30) + lzf_block(2**32 - 1, 360, FILLER),
        ["truncated", "compressed"],
    ),
    "uncompressed-size-claims-4GB.pcd": (
        pcd("binary_compressed", 357913941) + lzf_block(1000, 357913941 * 12, FILLER),
        ["corrupt", "cannot unpack"],
    ),
    "uncompressed-size-disagrees-with-points.pcd": (
        pcd("binary_compressed", 30) + lzf_block(1000, 2**32 - 1, FILLER),
        ["corrupt", "unpacks to"],
    ),
    "compressed-data-shorter-than-claimed.pcd": (
        pcd("binary_compressed", 80) + lzf_block(1000, 960, b"\x1f" + FILLER[:999]),
        ["binary_compressed"],
    ),
    "compressed-garbage.pcd": (pcd("binary_compressed", 80) + lzf_block(1000, 960, b"\xff" * 1000), ["binary_compressed"]),
}


def write_hostile(directory: Path, name: str) -> Path:
    path = directory / name
    path.write_bytes(HOSTILE[name][0])
    return path


def test_hostile_files_are_about_1_kb():
    for name, (content, _) in HOSTILE.items():
        assert len(content) < 2048, name


@pytest.fixture(scope="module", autouse=True)
def _readers_imported():
    """Import the lazily loaded libraries once, so that their import is not measured."""
    import pypcd4  # noqa: F401
    import trimesh  # noqa: F401


@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_hostile_size_is_refused_fast_without_allocating_it(tmp_path, name):
    path = write_hostile(tmp_path, name)
    words = HOSTILE[name][1]
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(PointCloudFileError) as excinfo:
            read_points(path)
        elapsed = time.perf_counter() - start
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    message = str(excinfo.value)
    assert message.startswith(str(path)) and "\n" not in message, message
    assert any(word in message for word in words), message
    assert elapsed < MAX_SECONDS, f"{name}: {elapsed:.2f} s"
    assert peak < MAX_PEAK_BYTES, f"{name}: peak allocation {peak / 2**20:.1f} MB"


CHILD = r"""
import json, resource, sys, warnings
import esmicp.io, pypcd4, trimesh, lzf  # everything a read may import, before the cap
from esmicp.errors import PointCloudFileError

def address_space() -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmSize")

cap = address_space() + int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
results = {}
for path in sys.argv[2:]:
    try:
        esmicp.io.read_points(path)
        results[path] = "read"
    except PointCloudFileError as exc:
        results[path] = "PointCloudFileError: " + str(exc)
    except BaseException as exc:
        results[path] = f"{type(exc).__name__}: {exc}"
print(json.dumps(results))
"""


@pytest.mark.skipif(sys.platform != "linux", reason="address-space limits via /proc and RLIMIT_AS (Linux)")
def test_hostile_sizes_in_a_child_with_capped_address_space(tmp_path):
    paths = [str(write_hostile(tmp_path, name)) for name in sorted(HOSTILE)]
    process = subprocess.run(
        [sys.executable, "-c", CHILD, str(CHILD_HEADROOM_BYTES), *paths],
        capture_output=True, text=True, timeout=120,
    )
    assert process.returncode == 0, process.stderr[-3000:]
    results = json.loads(process.stdout.strip().splitlines()[-1])
    for path in paths:
        assert results[path].startswith("PointCloudFileError: "), (path, results[path])
        assert "memory" not in results[path], (path, results[path])


def test_the_cap_bites(tmp_path):
    """The child's cap is real: allocating 1 GB under it fails."""
    probe = CHILD.replace("results = {}", "import numpy\ntry:\n    numpy.ones(2**30 // 8)\n    print('allocated')\nexcept MemoryError:\n    print('refused')\nsys.exit(0)\nresults = {}")
    process = subprocess.run([sys.executable, "-c", probe, str(CHILD_HEADROOM_BYTES)], capture_output=True, text=True, timeout=120)
    assert process.stdout.strip() == "refused", process.stdout + process.stderr[-2000:]


@pytest.mark.parametrize("name", ["1e12-points-binary.ply", "4GB.npy", "uncompressed-size-claims-4GB.pcd"])
def test_command_line_refuses_a_hostile_file_in_one_line(tmp_path, capsys, name):
    from esmicp.cli import EXIT_BAD_INPUT, main

    hostile = write_hostile(tmp_path, name)
    good = tmp_path / "good.xyz"
    good.write_text("0 0 0\n1 0 0\n0 1 0\n0 0 1\n")
    out = tmp_path / "aligned.ply"
    assert main(["register", str(hostile), str(good), "--output", str(out)]) == EXIT_BAD_INPUT
    stderr = capsys.readouterr().err
    assert stderr.count("\n") == 1 and stderr.startswith(f"esmicp register: error: {hostile}: "), stderr
    assert not out.exists()
