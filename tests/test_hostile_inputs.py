"""Hostile and careless inputs: files that change while they are read, sources that are not files,
sparse multi-gigabyte tails, decimal commas, list elements before the vertices, and scan lists that
point outside their folder.

docs/reliability.md ("Careless and hostile use") lists each case and what it returns.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import plyfile
import pytest
from conftest import require_module

from esmicp.errors import PointCloudFileError
from esmicp.io import read_points, read_transform, write_points

TIMEOUT_S = 60  # a child that has not answered by then is hanging (blocked on a FIFO, ...)
TWO_GB = 2 * 2**30
#: Address space a child may use above its size after import: far below the sparse tails.
CHILD_HEADROOM_BYTES = 384 * 2**20


def _run_child(code: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                          timeout=TIMEOUT_S)


# --- Item 3: a binary PLY that shrinks while it is read --------------------------------------

SHRINK_CHILD = r"""
import json, os, sys
import numpy as np
import esmicp.io, esmicp.io.ply
from esmicp.errors import PointCloudFileError

path, when = sys.argv[1], sys.argv[2]
keep = int(sys.argv[3])

def shrink():
    os.truncate(path, keep)  # another process rewriting the file, shortened

if when == "after-map":  # the file shrinks once it is memory-mapped (if the reader maps it)
    original_memmap = np.memmap
    def memmap(*args, **kwargs):
        mapped = original_memmap(*args, **kwargs)
        shrink()
        return mapped
    np.memmap = memmap
else:  # the file shrinks between the header check and the data
    original_header = esmicp.io.ply.read_ply_header
    def read_ply_header(*args, **kwargs):
        header = original_header(*args, **kwargs)
        shrink()
        return header
    esmicp.io.ply.read_ply_header = read_ply_header
try:
    points = esmicp.io.read_points(path)
    print(json.dumps({"read": len(points)}))
except PointCloudFileError as exc:
    print(json.dumps({"error": str(exc)}))
"""


def _big_binary_ply(path: Path) -> int:
    """A binary PLY of 200,000 double vertices (4.8 MB); returns its header length."""
    write_points(path, np.random.default_rng(0).normal(size=(200_000, 3)))
    return path.read_bytes().index(b"end_header\n") + len(b"end_header\n")


@pytest.mark.parametrize("faces", [False, True], ids=["vertices-only", "face-list-after"])
def test_binary_ply_shrinking_after_it_is_opened_is_no_sigbus(tmp_path, faces):
    path = tmp_path / "shrinking.ply"
    header_bytes = _big_binary_ply(path)
    if faces:  # a face list after the vertices takes the other binary branch
        data = plyfile.PlyData.read(str(path))
        face = np.zeros(10, dtype=[("vertex_indices", "O")])
        face["vertex_indices"] = [np.array([0, 1, 2], dtype="i4")] * 10
        plyfile.PlyData([data["vertex"], plyfile.PlyElement.describe(face, "face")]).write(str(path))
        header_bytes = path.read_bytes().index(b"end_header\n") + len(b"end_header\n")
    process = _run_child(SHRINK_CHILD, path, "after-map", header_bytes + 100)
    assert process.returncode == 0, f"exit {process.returncode} (-7 is SIGBUS): {process.stderr[-2000:]}"
    outcome = json.loads(process.stdout.strip().splitlines()[-1])
    if "error" in outcome:  # the shrink was seen: one line naming the file
        assert outcome["error"].startswith(str(path)) and "truncated" in outcome["error"], outcome


def test_binary_ply_shrinking_after_its_header_is_a_clean_error_and_exit_2(tmp_path):
    path = tmp_path / "shrinking.ply"
    header_bytes = _big_binary_ply(path)
    process = _run_child(SHRINK_CHILD, path, "after-header", header_bytes + 100)
    assert process.returncode == 0, process.stderr[-2000:]
    outcome = json.loads(process.stdout.strip().splitlines()[-1])
    assert "error" in outcome, outcome
    message = outcome["error"]
    assert message.startswith(str(path)) and "truncated" in message and "\n" not in message, message


# --- Item 4: --init FILE that is not a regular file, or far too large ------------------------

def _fifo(tmp_path: Path) -> Path:
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this system")
    path = tmp_path / "init.txt"
    os.mkfifo(path)
    return path


def _dev_zero_link(tmp_path: Path) -> Path:
    if not os.path.exists("/dev/zero"):
        pytest.skip("no /dev/zero")
    path = tmp_path / "T.txt"
    path.symlink_to("/dev/zero")
    return path


READ_TRANSFORM_CHILD = r"""
import sys
from esmicp.io import read_transform
from esmicp.errors import PointCloudFileError
try:
    read_transform(sys.argv[1])
    print("read")
except PointCloudFileError as exc:
    print(exc)
"""


@pytest.mark.parametrize("kind", ["fifo", "dev-zero-link"])
def test_read_transform_refuses_what_is_not_a_regular_file(tmp_path, kind):
    path = _fifo(tmp_path) if kind == "fifo" else _dev_zero_link(tmp_path)
    try:  # in a child: on a FIFO the old reader blocked forever
        process = _run_child(READ_TRANSFORM_CHILD, path)
    except subprocess.TimeoutExpired:
        pytest.fail(f"read_transform({kind}) still blocked after {TIMEOUT_S} s")
    assert process.stdout.strip() == f"{path}: is not a regular file", process.stdout + process.stderr[-2000:]


def test_read_transform_refuses_an_oversized_file_unread(tmp_path):
    from esmicp.io.transform import MAX_TRANSFORM_BYTES

    path = tmp_path / "T.txt"
    with open(path, "wb") as handle:  # sparse: 2 GB that take no disk space
        handle.write(b"1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
        handle.truncate(TWO_GB)
    with pytest.raises(PointCloudFileError, match="too large for a 4x4 transform") as excinfo:
        read_transform(path)
    assert str(excinfo.value).startswith(str(path)) and str(MAX_TRANSFORM_BYTES) in str(excinfo.value)


def test_read_transform_still_reads_a_commented_transform(tmp_path):
    path = tmp_path / "T.txt"
    path.write_text("# T_target_source\n[1, 0, 0, 0.5]\n[0, 1, 0, 0]\n[0, 0, 1, 0]\n[0, 0, 0, 1]\n")
    assert read_transform(path)[0, 3] == 0.5


def _cloud(tmp_path: Path, name: str) -> Path:
    path = tmp_path / name
    write_points(path, np.random.default_rng(1).normal(size=(50, 3)))
    return path


@pytest.mark.parametrize("command", ["register", "view"])
@pytest.mark.parametrize("kind", ["fifo", "dev-zero-link"])
def test_command_line_init_that_is_not_a_regular_file_is_one_line_exit_2(tmp_path, command, kind):
    if command == "view":
        require_module("plotly", "viz")
    init = _fifo(tmp_path) if kind == "fifo" else _dev_zero_link(tmp_path)
    source, target = _cloud(tmp_path, "s.xyz"), _cloud(tmp_path, "t.xyz")
    output = tmp_path / ("aligned.xyz" if command == "register" else "view.html")
    argv = [command, str(source), str(target), "--init", str(init), "--output", str(output)]
    try:
        process = subprocess.run([sys.executable, "-m", "esmicp.cli", *argv], capture_output=True, text=True,
                                 timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"esmicp {command} --init {kind} still blocked after {TIMEOUT_S} s")
    assert process.returncode == 2, process.stderr[-2000:]
    assert process.stderr == f"esmicp {command}: error: {init}: is not a regular file\n", process.stderr
    assert not output.exists()


# --- Item 9: decimal-comma exports -----------------------------------------------------------

@pytest.mark.parametrize("name", ["export.csv", "export.xyz", "export.txt"])
def test_decimal_comma_export_is_refused_not_misread(tmp_path, name):
    path = tmp_path / name
    path.write_text("0,125730;-0,132100;0,640400\n0,2;0,3;0,4\n1,5;2,5;3,5\n1;2;3,25\n")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    message = str(excinfo.value)
    assert message.startswith(f"{path}: line 1 mixes commas and semicolons") and "decimal" in message, message


def test_semicolons_alone_and_commas_alone_still_read(tmp_path):
    semicolons, commas = tmp_path / "a.csv", tmp_path / "b.csv"
    semicolons.write_text("0.5;1;2\n3;4;5\n6;7;8.25\n")
    commas.write_text("0.5,1,2\n3,4,5\n6,7,8.25\n")
    expected = [[0.5, 1, 2], [3, 4, 5], [6, 7, 8.25]]
    np.testing.assert_array_equal(read_points(semicolons), expected)
    np.testing.assert_array_equal(read_points(commas), expected)


# --- Item 10: memory follows what a file declares, not its size on disk ------------------------

MEMORY_CHILD = r"""
import json, resource, sys
import esmicp.io, pypcd4, lzf  # everything a read may import, before the cap
from esmicp.errors import PointCloudFileError

def address_space():
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024

cap = address_space() + int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
results = {}
for path in sys.argv[2:]:
    try:
        results[path] = f"read {len(esmicp.io.read_points(path))} points"
    except PointCloudFileError as exc:
        results[path] = "PointCloudFileError: " + str(exc)
    except BaseException as exc:
        results[path] = f"{type(exc).__name__}: {exc}"
print(json.dumps(results))
"""


def _sparse_tail(path: Path, content: bytes, size: int = TWO_GB) -> Path:
    with open(path, "wb") as handle:
        handle.write(content)
        handle.truncate(size)  # a hole: no disk space, reads as NUL bytes
    return path


def _ascii_pcd(points: int) -> bytes:
    rows = "".join(f"{i} {i % 7} {i % 5}\n" for i in range(points))
    return (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {points}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA ascii\n{rows}").encode()


@pytest.mark.skipif(sys.platform != "linux", reason="address-space limits via /proc and RLIMIT_AS (Linux)")
def test_sparse_2gb_tails_are_read_or_refused_within_bounded_memory(tmp_path):
    rows = b"".join(b"%d %d %d\n" % (i, i % 7, i % 5) for i in range(1000))
    cases = {
        # declared content first, then 2 GB of NUL bytes: PCD reads what is declared, never the tail;
        # PLY refuses data beyond what its header declares, from the tail's first block
        str(_sparse_tail(tmp_path / "tail.pcd", _ascii_pcd(1000))): "read 1000 points",
        str(_sparse_tail(tmp_path / "tail-ascii.ply", b"ply\nformat ascii 1.0\nelement vertex 1000\n"
                         b"property float x\nproperty float y\nproperty float z\nend_header\n" + rows)):
            "PointCloudFileError: ",
        # a text cloud whose tail is binary: refused at its first block
        str(_sparse_tail(tmp_path / "sparse.xyz", b"")): "PointCloudFileError: ",
        str(_sparse_tail(tmp_path / "tail.xyz", rows)): "PointCloudFileError: ",
    }
    process = _run_child(MEMORY_CHILD, CHILD_HEADROOM_BYTES, *cases)
    assert process.returncode == 0, process.stderr[-3000:]
    results = json.loads(process.stdout.strip().splitlines()[-1])
    for path, expected in cases.items():
        assert results[path].startswith(expected), (path, results[path])
        assert "memory" not in results[path], (path, results[path])
    assert "binary data" in results[str(tmp_path / "sparse.xyz")]
    assert "more data follows them" in results[str(tmp_path / "tail-ascii.ply")]


def test_text_cloud_read_in_blocks_equals_the_whole(tmp_path, monkeypatch):
    """Lines, CRLF pairs and UTF-8 characters cut by block boundaries are read as if whole."""
    from esmicp.io import text

    points = np.random.default_rng(2).normal(size=(300, 3))
    path = tmp_path / "cloud.xyz"
    body = "\ufeff# caf\u00e9 \u00e9\u00e9\r\n" + "".join(f"{x:.17g} {y:.17g} {z:.17g}\r\n" for x, y, z in points)
    path.write_bytes(body.encode("utf-8"))
    expected = read_points(path)
    np.testing.assert_array_equal(expected, points)
    for block in (1, 2, 3, 7, 64):
        monkeypatch.setattr(text, "BLOCK_BYTES", block)
        np.testing.assert_array_equal(read_points(path), points)


def test_text_reader_reports_invalid_utf8_at_its_byte_across_blocks(tmp_path, monkeypatch):
    from esmicp.io import text

    path = tmp_path / "bad.xyz"
    path.write_bytes(b"1 2 3\n4 5 6\n7 8 \xe9\n")
    for block in (1, 4, 1 << 20):
        monkeypatch.setattr(text, "BLOCK_BYTES", block)
        with pytest.raises(PointCloudFileError, match="byte 16 is not valid UTF-8"):
            read_points(path)


# --- Item 11: a list element before the vertices ----------------------------------------------

def _ply_with_lists_before(path: Path, lengths, *, order="<", length_type="u1", value_type="i4",
                           two_lists=False, text=False) -> np.ndarray:
    rng = np.random.default_rng(3)
    vertices = np.empty(500, dtype=[("x", order + "f4"), ("nx", order + "f8"), ("y", order + "f4"),
                                    ("z", order + "f4")])
    for axis in ("x", "nx", "y", "z"):
        vertices[axis] = rng.normal(size=500)
    fields = [("vertex_indices", "O")] + ([("texcoord", "O")] if two_lists else [])
    grid = np.empty(len(lengths), dtype=[("flag", "u1")] + fields)
    grid["flag"] = 1
    grid["vertex_indices"] = [np.arange(n, dtype=value_type) for n in lengths]
    if two_lists:
        grid["texcoord"] = [np.zeros(n % 3, dtype="f4") for n in lengths]
    element = plyfile.PlyElement.describe(grid, "range_grid",
                                          len_types={"vertex_indices": length_type, "texcoord": length_type})
    plyfile.PlyData([element, plyfile.PlyElement.describe(vertices, "vertex")], text=text,
                    byte_order=order).write(str(path))
    return np.column_stack([vertices[axis].astype(np.float64) for axis in "xyz"])


@pytest.mark.parametrize("layout", ["uniform", "mixed", "big-endian-int16", "two-lists", "empty-lists", "ascii"])
def test_list_element_before_the_vertices_reads_the_right_vertices(tmp_path, layout):
    rng = np.random.default_rng(4)
    lengths = {"uniform": [3] * 3000, "mixed": list(rng.integers(0, 9, 3000)),
               "big-endian-int16": list(rng.choice([3, 4], 3000)), "two-lists": list(rng.integers(0, 5, 3000)),
               "empty-lists": [0] * 3000, "ascii": list(rng.integers(0, 5, 3000))}[layout]
    kwargs = {"big-endian-int16": dict(order=">", length_type="i2"), "two-lists": dict(two_lists=True),
              "ascii": dict(text=True)}.get(layout, {})
    path = tmp_path / "lists-first.ply"
    expected = _ply_with_lists_before(path, lengths, **kwargs)
    np.testing.assert_array_equal(read_points(path), expected)


def test_list_element_before_the_vertices_with_a_lying_list_length_is_refused(tmp_path):
    path = tmp_path / "lists-first.ply"
    _ply_with_lists_before(path, [3] * 100)
    data = bytearray(path.read_bytes())
    start = data.index(b"end_header\n") + len(b"end_header\n")
    data[start + 1] = 255  # the first row's list now claims 255 values
    data[start + 14] = 250  # and the second one's
    path.write_bytes(bytes(data[: start + 2000]))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert "truncated" in str(excinfo.value), str(excinfo.value)


def test_negative_list_length_is_refused(tmp_path):
    path = tmp_path / "lists-first.ply"
    _ply_with_lists_before(path, [3] * 100, length_type="i1")
    data = bytearray(path.read_bytes())
    start = data.index(b"end_header\n") + len(b"end_header\n")
    data[start + 1] = 0xFF  # -1 as int8
    path.write_bytes(bytes(data))
    with pytest.raises(PointCloudFileError, match="negative list length"):
        read_points(path)


# --- Minor: messages the reader contract forbids ----------------------------------------------

@pytest.mark.parametrize("count", ["\u00b3", "9" * 5000, "\u0663"])
def test_odd_count_lines_get_a_plain_message(tmp_path, count):
    path = tmp_path / "count.xyz"
    path.write_text(f"{count}\n1 2 3\n4 5 6\n7 8 9\n", encoding="utf-8")
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    message = str(excinfo.value)
    assert "could not be read" not in message and "ValueError" not in message, message
    assert len(message) < 400, message


def test_compressed_pcd_that_unpacks_to_more_than_declared_is_a_clean_message(tmp_path):
    import lzf

    raw = np.arange(120, dtype="<f4").tobytes()  # 40 points of x y z float32, column-major
    compressed = lzf.compress(raw)
    header = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 30\nHEIGHT 1\n"
              "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 30\nDATA binary_compressed\n").encode()
    path = tmp_path / "small-size.pcd"
    path.write_bytes(header + struct.pack("<II", len(compressed), 360) + compressed)  # 30 points claimed
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    message = str(excinfo.value)
    assert "NoneType" not in message and "unpacks to more than 360 bytes" in message, message


# --- Item 7 (readers): a Stanford .conf names files outside its folder ------------------------

@pytest.mark.parametrize("name", ["../outside.ply", "sub/../../outside.ply", "{outside}"])
def test_stanford_conf_cannot_read_scans_outside_its_folder(tmp_path, name):
    from esmicp.io.stanford_conf import load_scans

    folder = tmp_path / "scans"
    folder.mkdir()
    outside = tmp_path / "outside.ply"
    write_points(outside, np.random.default_rng(5).normal(size=(20, 3)))
    write_points(folder / "inside.ply", np.random.default_rng(6).normal(size=(20, 3)))
    name = name.format(outside=outside)
    (folder / "scans.conf").write_text(f"bmesh inside.ply 0 0 0 0 0 0 1\nbmesh {name} 0 0 0 0 0 0 1\n")
    with pytest.raises(PointCloudFileError) as excinfo:
        load_scans(folder)
    assert "is not inside the conf's folder" in str(excinfo.value), str(excinfo.value)


def test_stanford_conf_reads_scans_in_a_subfolder(tmp_path):
    from esmicp.io.stanford_conf import load_scans

    (tmp_path / "data").mkdir()
    write_points(tmp_path / "data" / "a.ply", np.random.default_rng(7).normal(size=(20, 3)))
    (tmp_path / "scans.conf").write_text("bmesh data/a.ply 1 2 3 0 0 0 1\n")
    scans = load_scans(tmp_path)
    assert list(scans) == ["a"] and scans["a"][1][0, 3] == 1.0


# --- A PLY whose header declares fewer rows than it holds ----------------------------------------

def _ply_bytes(fmt: str, declared: int, rows: np.ndarray, after: str = "", after_data: bytes = b"") -> bytes:
    header = (f"ply\nformat {fmt} 1.0\nelement vertex {declared}\nproperty float x\nproperty float y\n"
              f"property float z\n{after}end_header\n").encode()
    if fmt == "ascii":
        body = "".join(f"{x:g} {y:g} {z:g}\n" for x, y, z in rows).encode()
    else:
        body = rows.astype("<f4").tobytes()
    return header + body + after_data


@pytest.mark.parametrize("case", ["ascii", "binary", "ascii, faces after", "binary, a fixed-size element after"])
def test_a_ply_holding_more_vertices_than_it_declares_is_refused(tmp_path, case):
    """A PLY declaring 5 vertices but holding 8 read the first 5 silently: it is refused, naming
    the file and the declared count."""
    rows = np.arange(24, dtype=np.float64).reshape(8, 3) % 7
    path = tmp_path / "undercounted.ply"
    if case == "ascii":
        data = _ply_bytes("ascii", 5, rows)
    elif case == "binary":
        data = _ply_bytes("binary_little_endian", 5, rows)
    elif case == "ascii, faces after":
        data = _ply_bytes("ascii", 5, rows, "element face 1\nproperty list uchar int vertex_indices\n") + b"3 0 1 2\n"
    else:
        data = _ply_bytes("binary_little_endian", 5, rows, "element marker 1\nproperty int id\n",
                          struct.pack("<i", 7))
    path.write_bytes(data)
    with pytest.raises(PointCloudFileError) as caught:
        read_points(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: its header declares 5 vertices"), message
    assert "more data follows" in message and "\n" not in message, message


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_a_ply_with_what_it_declares_and_a_final_newline_reads(tmp_path, fmt):
    rows = np.arange(24, dtype=np.float64).reshape(8, 3) % 7
    path = tmp_path / "exact.ply"
    path.write_bytes(_ply_bytes(fmt, 8, rows) + b"\n\n")
    np.testing.assert_array_equal(read_points(path), rows)


# --- An ascii STL whose facet normal is not a number ------------------------------------------------

def test_ascii_stl_with_a_non_numeric_normal_reads_without_a_traceback(tmp_path):
    """trimesh logged "failed to extract face_normals" with two tracebacks on stderr (through
    Python's last-resort handler), though the read succeeded: the vertices are read, quietly."""
    path = tmp_path / "odd-normal.stl"
    path.write_text("solid t\nfacet normal x y z\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\n"
                    "endfacet\nfacet normal 0 0 1\nouter loop\nvertex 0 0 1\nvertex 1 0 1\nvertex 0 1 2\nendloop\n"
                    "endfacet\nendsolid t\n")
    code = "import sys, esmicp.io\nprint(esmicp.io.read_points(sys.argv[1]).tolist())"
    done = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=TIMEOUT_S)
    assert done.returncode == 0, done.stderr
    assert done.stderr == "", done.stderr
    assert json.loads(done.stdout) == [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 2]]
