"""LAS / LAZ scans: round trips, chunked reading, missing extras, and damaged or lying files
refused with one clear error."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys

import numpy as np
import pytest
from conftest import assert_file_error, random_cloud

from esmicp.cli import main
from esmicp.errors import MissingDependencyError, PointCloudFileError
from esmicp.io import read_points


# ---- LAS / LAZ ---------------------------------------------------------------------------------------

if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
    import laspy  # CI installs the `las` extra: its absence there is a broken setup, not a skip
else:
    laspy = pytest.importorskip("laspy", reason="laspy cannot be imported: pip install 'esmicp[las]'")


def write_las(path, points: np.ndarray, scale: float = 0.001, offset=(1000.0, 2000.0, 10.0)) -> np.ndarray:
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.full(3, scale)
    header.offsets = np.asarray(offset, dtype=np.float64)
    data = laspy.LasData(header)
    data.x, data.y, data.z = (points[:, axis] + offset[axis] for axis in range(3))
    data.write(path)
    return np.stack([np.asarray(data.x), np.asarray(data.y), np.asarray(data.z)], axis=1)


@pytest.mark.parametrize("name", ["survey.las", "survey.laz", "SURVEY.LAZ"])
def test_las_round_trip(tmp_path, name):
    path = tmp_path / name
    expected = write_las(path, random_cloud(6, 500))
    points = read_points(path)
    assert points.dtype == np.float64 and points.shape == (500, 3)
    np.testing.assert_array_equal(points, expected)
    # scaled coordinates, not the raw integers: within the scale of what was written
    np.testing.assert_allclose(points - [1000.0, 2000.0, 10.0], random_cloud(6, 500), atol=0.001)


def test_las_read_in_chunks(tmp_path, monkeypatch):
    import esmicp.io.las as las_module

    monkeypatch.setattr(las_module, "CHUNK_POINTS", 64)
    path = tmp_path / "survey.laz"
    expected = write_las(path, random_cloud(7, 300))
    np.testing.assert_array_equal(read_points(path), expected)


def test_las_missing_laspy_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "survey.las"
    write_las(path, random_cloud(8, 10))
    monkeypatch.setitem(sys.modules, "laspy", None)  # import laspy now raises ImportError
    with pytest.raises(MissingDependencyError) as excinfo:
        read_points(path)
    message = str(excinfo.value)
    assert message.startswith(str(path)) and "laspy" in message and "esmicp[las]" in message
    assert "\n" not in message


def test_laz_without_backend_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "survey.laz"
    write_las(path, random_cloud(9, 10))
    monkeypatch.setattr(laspy.LazBackend, "detect_available", staticmethod(lambda: ()))
    with pytest.raises(MissingDependencyError, match=r"LAZ backend.*esmicp\[las\]"):
        read_points(path)


@pytest.mark.parametrize(
    ("damage", "words"),
    [
        (lambda data: b"NOPE" + data[4:], ["not a valid LAS"]),
        (lambda data: data[:100], ["LAS"]),  # header cut in half
        (lambda data: data[:-340], ["truncated", "500 points"]),  # 10 of 500 points cut off
        (lambda data: b"hello world, not a LAS file\n" * 20, ["not a valid LAS"]),
    ],
)
def test_corrupt_las_is_one_clear_error(tmp_path, damage, words):
    path = tmp_path / "bad.las"
    write_las(path, random_cloud(10, 500))
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, *words)


def test_las_header_declaring_too_many_points_is_refused_before_reading(tmp_path):
    path = tmp_path / "liar.las"
    write_las(path, random_cloud(11, 50))
    data = bytearray(path.read_bytes())
    data[107:111] = (10**9).to_bytes(4, "little")  # LAS 1.2 legacy point count
    path.write_bytes(bytes(data))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "truncated", "1000000000 points")


def test_truncated_laz_is_one_clear_error(tmp_path):
    path = tmp_path / "bad.laz"
    write_las(path, random_cloud(12, 2000))
    data = bytearray(path.read_bytes())
    cut = len(data) // 2
    path.write_bytes(bytes(data[:cut]))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "truncated LAZ file", "chunk table", f"{cut:,} bytes")


def test_corrupt_laz_data_is_one_clear_error(tmp_path):
    path = tmp_path / "bad.laz"
    write_las(path, random_cloud(12, 2000))
    data = bytearray(path.read_bytes())
    start = struct.unpack_from("<I", data, 96)[0] + 8
    data[start:start + 2000] = np.random.default_rng(0).integers(0, 256, 2000, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "LAZ")


# ---- LAS / LAZ headers that lie: refused from the header, before laspy reads or allocates -------------

LAS_LIAR_CHILD = r"""
import json, resource, sys, time
import esmicp.io, laspy, lazrs  # everything a read may import, before the cap
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
    start = time.perf_counter()
    try:
        esmicp.io.read_points(path)
        outcome = "read"
    except PointCloudFileError as exc:
        outcome = "PointCloudFileError: " + str(exc)
    except BaseException as exc:
        outcome = f"{type(exc).__name__}: {exc}"
    results[path] = [outcome, time.perf_counter() - start]
    print(json.dumps(results), flush=True)
"""

#: Address space the child may use above what it has after its imports (a lying file costs a few KB).
LAS_CHILD_HEADROOM_BYTES = 256 * 2**20


def _las_and_laz(directory) -> dict:
    """One small LAS 1.2, LAS 1.4, LAZ 1.2 and LAZ 1.4 file (6000 points each), by name."""
    files = {}
    for version, point_format in (("1.2", 3), ("1.4", 6)):
        for extension in (".las", ".laz"):
            header = laspy.LasHeader(point_format=point_format, version=version)
            header.scales = np.full(3, 0.001)
            header.offsets = np.array([1000.0, 2000.0, 10.0])
            data = laspy.LasData(header)
            points = random_cloud(13, 6000)
            data.x, data.y, data.z = points[:, 0] + 1000.0, points[:, 1] + 2000.0, points[:, 2] + 10.0
            path = directory / f"good{version}{extension}"
            data.write(path)
            files[f"{version}{extension}"] = path
    return files


def _patched(source, target, edits):
    """Copy ``source`` to ``target`` with ``edits``: (where, struct format, value); ``where`` is a byte
    of the file, ``("vlr", k)`` byte k of the first VLR's data (negative: its 54-byte header),
    ``"point data"`` the first byte of the point data (of a LAZ: the chunk table's offset) or
    ``("chunk table", k)`` byte k of the LAZ chunk table."""
    data = bytearray(source.read_bytes())
    header_bytes, point_data = struct.unpack_from("<HI", data, 94)
    for where, fmt, value in edits:
        if where == "point data":
            where = point_data
        elif isinstance(where, int):
            pass
        elif where[0] == "vlr":
            where = header_bytes + 54 + where[1]
        elif where[0] == "chunk table":
            where = struct.unpack_from("<q", data, point_data)[0] + where[1]
        struct.pack_into(fmt, data, where, value)
    target.write_bytes(bytes(data))
    return target


#: name: (good file, [(byte, struct format, value)], words the message must hold). Bytes of the LAS
#: header: 94 header size, 96 offset to the point data, 100 number of VLRs, 104 point format,
#: 105 record length, 107 legacy point count, 235 first EVLR, 243 number of EVLRs, 247 point count (1.4).
LAS_LIARS = {
    "vlr-count-ffffffff.las": ("1.2.las", [(100, "<I", 0xFFFFFFFF)], ["4294967295 variable-length records", "more than fit in the file's"]),
    "vlr-count-ffffffff.laz": ("1.2.laz", [(100, "<I", 0xFFFFFFFF)], ["4294967295 variable-length records"]),
    "vlr-count-2-of-1.laz": ("1.2.laz", [(100, "<I", 2)], ["2 variable-length records", "between its header"]),
    "vlr-length-ffff.laz": ("1.2.laz", [(("vlr", -34), "<H", 0xFFFF)], ["variable-length record 1 of 1", "65,535 bytes"]),
    "point-data-at-4gb.las": ("1.2.las", [(96, "<I", 0xFFFFFFFF)], ["point data start at byte 4,294,967,295", "past the end"]),
    "point-data-inside-header.las": ("1.2.las", [(96, "<I", 100)], ["point data start at byte 100"]),
    "header-size-10.las": ("1.2.las", [(94, "<H", 10)], ["size is 10 bytes"]),
    "header-size-65535.las": ("1.2.las", [(94, "<H", 0xFFFF)], ["65535 bytes"]),
    "record-length-1.las": ("1.2.las", [(105, "<H", 1)], ["points of 1 bytes", "point format 3"]),
    "point-format-35.las": ("1.2.las", [(104, "<B", 99)], ["point format 35"]),
    "version-1.9.las": ("1.2.las", [(25, "<B", 9)], ["version 1.9"]),
    "count-ffffffff.las": ("1.2.las", [(107, "<I", 0xFFFFFFFF)], ["truncated", "4294967295 points"]),
    "count-2e62.las": ("1.4.las", [(247, "<Q", 2**62)], ["truncated", "4611686018427387904 points"]),
    "count-ffffffff.laz": ("1.2.laz", [(107, "<I", 0xFFFFFFFF)], ["4294967295 points", "chunk(s) of 50,000 points"]),
    "evlr-count-ffffffff.las": ("1.4.las", [(235, "<Q", 180375), (243, "<I", 0xFFFFFFFF)], ["4294967295 extended variable-length records"]),
    "evlr-start-2e62.las": ("1.4.las", [(235, "<Q", 2**62), (243, "<I", 1)], ["extended variable-length records start at byte"]),
    "compressed-without-laszip-record.las": ("1.2.las", [(104, "<B", 131)], ["compressed", "no LASzip record"]),
    "laszip-items-ffff.laz": ("1.2.laz", [(("vlr", 32), "<H", 0xFFFF)], ["LASzip record says 65535 items"]),
    "chunk-table-at-2e62.laz": ("1.2.laz", [("point data", "<q", 2**62)], ["chunk table offset says byte"]),
    "chunk-table-at-0.laz": ("1.2.laz", [("point data", "<q", 0)], ["chunk table offset says byte 0"]),
    "chunks-ffffffff.laz": ("1.2.laz", [(("chunk table", 4), "<I", 0xFFFFFFFF)], ["4294967295 chunks"]),
    "chunks-ffffffff-1.4.laz": ("1.4.laz", [(("chunk table", 4), "<I", 0xFFFFFFFF)], ["4294967295 chunks"]),
    "laszip-item-size-46k.laz": ("1.2.laz", [(("vlr", 37), "<B", 0xB5)], ["items make points of 46,", "says 34"]),
    "chunk-size-1.laz": ("1.2.laz", [(("vlr", 12), "<I", 1)], ["6000 points", "chunk(s) of 1 points"]),
}
#: Odd but harmless headers: read in full, within the same cap (lazrs's parallel decoder allocates a
#: whole chunk as the header sizes it, and aborted the process on these).
LAS_READABLE = {
    "chunk-size-4e9.laz": ("1.2.laz", [(("vlr", 12), "<I", 0xFF00C350)]),
    "chunk-size-7e8-1.4.laz": ("1.4.laz", [(("vlr", 12), "<I", 0x2C00C350)]),
}


@pytest.mark.skipif(sys.platform != "linux", reason="address-space limits via /proc and RLIMIT_AS (Linux)")
def test_las_headers_that_lie_are_refused_in_a_child_with_capped_address_space(tmp_path):
    """Each lying count or offset is refused by name, in a child that may not allocate more than
    256 MB: not "too large to load into memory", not a crash of the LAZ decoder, not a hang."""
    good = _las_and_laz(tmp_path)
    paths = {name: _patched(good[source], tmp_path / name, edits) for name, (source, edits, _) in LAS_LIARS.items()}
    readable = {name: _patched(good[source], tmp_path / name, edits) for name, (source, edits) in LAS_READABLE.items()}
    process = subprocess.run(
        [sys.executable, "-c", LAS_LIAR_CHILD, str(LAS_CHILD_HEADROOM_BYTES), *map(str, [*paths.values(), *readable.values()])],
        capture_output=True, text=True, timeout=300,
    )
    lines = process.stdout.strip().splitlines()
    results = json.loads(lines[-1]) if lines else {}
    assert process.returncode == 0 and len(results) == len(paths) + len(readable), (
        f"the child ended with status {process.returncode} after {len(results)} files: {process.stderr[-2000:]}"
    )
    for name, path in paths.items():
        outcome, _ = results[str(path)]
        assert outcome.startswith(f"PointCloudFileError: {path}: "), (name, outcome)
        assert "\n" not in outcome and "memory" not in outcome, (name, outcome)
        for word in LAS_LIARS[name][2]:
            assert word in outcome, (name, word, outcome)
    for name, path in readable.items():
        assert results[str(path)][0] == "read", (name, results[str(path)])


def test_las_with_a_lying_vlr_count_is_refused_from_its_header(tmp_path):
    """The case of the report: a 0xFFFFFFFF VLR count, refused with the field, its value and the file's size."""
    good = _las_and_laz(tmp_path)["1.2.las"]
    path = _patched(good, tmp_path / "liar.las", [(100, "<I", 0xFFFFFFFF)])
    size = path.stat().st_size
    import esmicp.io.las as las_module

    with open(path, "rb") as handle, pytest.raises(PointCloudFileError) as excinfo:
        las_module.check_header(path, handle, size)  # read_points too, shown in a capped child above
    assert_file_error(excinfo, path, f"header says 4294967295 variable-length records, more than fit in the file's {size:,} bytes")


def test_las_library_errors_say_what_was_being_read(tmp_path):
    """An error laspy / lazrs raise after the header checks is labelled with what was read and the
    library's name, never bare library text."""
    good = _las_and_laz(tmp_path)["1.2.laz"]
    path = _patched(good, tmp_path / "item-99.laz", [(("vlr", 34), "<H", 99)])  # first LASzip item: type 99
    with pytest.raises(PointCloudFileError) as excinfo:
        read_points(path)
    assert_file_error(excinfo, path, "corrupt or truncated LAZ point data (lazrs: ", "99")


@pytest.mark.parametrize("name", ["1.2.las", "1.4.las", "1.2.laz", "1.4.laz"])
def test_las_header_checks_pass_good_files(tmp_path, name):
    path = _las_and_laz(tmp_path)[name]
    points = read_points(path)
    np.testing.assert_allclose(points - [1000.0, 2000.0, 10.0], random_cloud(13, 6000), atol=0.001)


def test_las_offset_of_1e300_is_blamed_on_the_file_by_register(tmp_path, capsys):
    """The header's x offset says 1e300 (with a scale factor large enough to be seen next to it):
    the points are read, and esmicp register refuses them naming the file and their magnitude (not
    "degenerate cloud, all points are identical")."""
    good = _las_and_laz(tmp_path)["1.2.las"]
    path = _patched(good, tmp_path / "far.las", [(155, "<d", 1e300), (131, "<d", 1e290)])  # X offset, X scale
    assert main(["register", str(path), str(good)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"esmicp register: error: {path}: coordinates up to 1e+300"), err


@pytest.mark.parametrize("axis", [0, 1, 2], ids=list("xyz"))
@pytest.mark.parametrize("scale, offset, words", [
    (0.0, None, "scale factor is 0.0"),
    (-1e-300, None, "scale factor is -1e-300"),
    (-0.001, None, "scale factor is -0.001"),
    (float("nan"), None, "scale factor is nan"),
    (1e-300, None, "too small to tell points apart at its"),  # next to the file's offsets (1000, 2000, 10)
    (1e-9, 1e12, "too small to tell points apart at its"),
], ids=["zero", "-1e-300", "negative", "nan", "1e-300", "1e-9-at-1e12"])
def test_las_scale_factor_that_flattens_the_cloud_is_refused_naming_the_file(tmp_path, capsys, axis, scale, offset,
                                                                             words):
    """A LAS / LAZ scale factor of 0 (or -1e-300) was accepted and flattened the cloud silently."""
    good = _las_and_laz(tmp_path)["1.2.las"]
    edits = [(131 + 8 * axis, "<d", scale)] + ([] if offset is None else [(155 + 8 * axis, "<d", offset)])
    path = _patched(good, tmp_path / "flat.las", edits)
    with pytest.raises(PointCloudFileError) as caught:
        read_points(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: LAS header says the {'xyz'[axis]} scale factor"), message
    assert words in message and "\n" not in message, message
    assert main(["register", str(path), str(good)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"esmicp register: error: {path}: LAS header says"), err
