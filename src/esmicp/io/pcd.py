"""PCD (Point Cloud Library) point clouds, read and written with :mod:`pypcd4`.

Reading: ``DATA ascii``, ``binary`` and ``binary_compressed``; fields ``x y z`` are required
(any numeric type, COUNT 1), other fields are ignored. Writing: ``x y z`` as float64, and
optionally a colour (``rgb``) and a ``scan_index`` per point. Organized clouds (``HEIGHT > 1``) are read
as their ``WIDTH * HEIGHT`` points in row order; their NaN points (invalid pixels) are dropped
later by :func:`esmicp.types.as_points`, with a warning.

The header is parsed and checked here against the file size before pypcd4 sees the data, because
pypcd4 1.5 (a) only accepts ``VERSION .7`` / ``0.7`` (PCL's own ``bunny.pcd`` says ``.5``),
(b) reads ``POINTS * row size`` bytes and allocates ``POINTS`` rows without checking the file is
that long (a truncated binary file at a row boundary silently loses points), and (c) reads ascii
rows with a single-space delimiter only. pypcd4 is then given a normalized header and exactly the
data block.
"""

from __future__ import annotations

import dataclasses
import io
import os
import struct

import numpy as np

from ..errors import PointCloudFileError
from ._messages import excerpt, one_line

__all__ = ["ENCODINGS", "read_pcd", "write_pcd"]

#: The ``DATA`` encodings this module reads and writes.
ENCODINGS = ("ascii", "binary", "binary_compressed")

_VALID_TYPES = {
    ("F", 4),
    ("F", 8),
    ("U", 1),
    ("U", 2),
    ("U", 4),
    ("U", 8),
    ("I", 1),
    ("I", 2),
    ("I", 4),
    ("I", 8),
}
_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_MAX_HEADER_LINES = 64
_MAX_HEADER_BYTES = 1 << 16
#: LZF turns at most 3 input bytes into 264 output bytes (a ratio of 88); anything claiming more is
#: corrupt, and is refused before any allocation.
_MAX_LZF_RATIO = 100
#: Bytes of an ascii body read at a time.
_ASCII_BLOCK_BYTES = 1 << 20


@dataclasses.dataclass
class _PcdHeader:
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    width: int
    height: int
    points: int
    data: str
    data_offset: int
    data_bytes: int

    @property
    def row_bytes(self) -> int:
        return sum(s * c for s, c in zip(self.sizes, self.counts))

    @property
    def values_per_row(self) -> int:
        return sum(self.counts)


def _integers(path, key: str, words: list[str], *, positive: bool) -> list[int]:
    try:
        values = [int(word) for word in words]
    except ValueError:
        raise PointCloudFileError(
            path, f"malformed PCD header: {key} must be whole numbers, got {excerpt(' '.join(words))}"
        ) from None
    low = 1 if positive else 0
    if any(value < low for value in values):
        raise PointCloudFileError(
            path,
            f"malformed PCD header: {key} must be {'> 0' if positive else '>= 0'}, got {excerpt(' '.join(words))}",
        )
    return values


def _read_header(path, handle) -> _PcdHeader:
    handle.seek(0, os.SEEK_END)
    file_size = handle.tell()
    handle.seek(0)
    entries: dict[str, list[str]] = {}
    offset = 0
    for _ in range(_MAX_HEADER_LINES):
        raw = handle.readline(_MAX_HEADER_BYTES)
        if not raw:
            break
        offset += len(raw)
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise PointCloudFileError(path, "not a PCD file: its header contains non-text bytes") from None
        if not line or line.startswith("#"):
            continue
        key, *words = line.split()
        key = key.upper()
        if key not in _KEYS:
            raise PointCloudFileError(path, f"not a PCD file: unexpected header line {excerpt(line)}")
        if key in entries:
            raise PointCloudFileError(path, f"malformed PCD header: {key} appears twice")
        entries[key] = words
        if key == "DATA":
            break
    if "DATA" not in entries:
        raise PointCloudFileError(path, "not a PCD file, or a truncated one: no DATA line in the header")
    missing = [key for key in ("FIELDS", "SIZE", "TYPE", "WIDTH") if key not in entries]
    if missing:
        raise PointCloudFileError(path, f"malformed PCD header: missing {', '.join(missing)}")

    fields = entries["FIELDS"]
    sizes = _integers(path, "SIZE", entries["SIZE"], positive=True)
    types = [word.upper() for word in entries["TYPE"]]
    counts = (
        _integers(path, "COUNT", entries["COUNT"], positive=True) if "COUNT" in entries else [1] * len(fields)
    )
    if not fields or not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise PointCloudFileError(
            path,
            f"malformed PCD header: FIELDS, SIZE, TYPE and COUNT have different lengths "
            f"({len(fields)}, {len(sizes)}, {len(types)}, {len(counts)})",
        )
    for field, kind, size in zip(fields, types, sizes):
        if (kind, size) not in _VALID_TYPES:
            raise PointCloudFileError(
                path, f"malformed PCD header: field {excerpt(field)} has unsupported TYPE {excerpt(kind, 10)} SIZE {size}"
            )
    for key in ("WIDTH", "HEIGHT", "POINTS"):
        if key in entries and len(entries[key]) != 1:
            raise PointCloudFileError(path, f"malformed PCD header: {key} must be one number")
    (width,) = _integers(path, "WIDTH", entries["WIDTH"], positive=False)
    (height,) = _integers(path, "HEIGHT", entries["HEIGHT"], positive=False) if "HEIGHT" in entries else (1,)
    (points,) = (
        _integers(path, "POINTS", entries["POINTS"], positive=False)
        if "POINTS" in entries
        else (width * height,)
    )
    if points != width * height:
        raise PointCloudFileError(
            path,
            f"inconsistent PCD header: POINTS is {points} but WIDTH x HEIGHT is {width} x {height} = {width * height}",
        )
    data = entries["DATA"][0].lower() if entries["DATA"] else ""
    if data not in ENCODINGS:
        raise PointCloudFileError(
            path, f"unsupported PCD DATA encoding {excerpt(data, 20)} (expected one of {', '.join(ENCODINGS)})"
        )
    return _PcdHeader(fields, sizes, types, counts, width, height, points, data, offset, file_size - offset)


def _check_fields(path, header: _PcdHeader) -> None:
    missing = [axis for axis in "xyz" if axis not in header.fields]
    if missing:
        raise PointCloudFileError(
            path, f"PCD file has no {'/'.join(missing)} field (fields: {excerpt(' '.join(header.fields), 60)})"
        )
    for axis in "xyz":
        count = header.counts[header.fields.index(axis)]
        if count != 1:
            raise PointCloudFileError(path, f"PCD field {axis!r} has COUNT {count}, expected 1")
    for axis in "xyz":
        if header.fields.count(axis) > 1:
            raise PointCloudFileError(path, f"malformed PCD header: field {axis!r} appears twice")


def _truncated(path, header: _PcdHeader, needed: int, what: str = "bytes of data") -> PointCloudFileError:
    return PointCloudFileError(
        path,
        f"truncated or corrupt PCD file: its header declares {header.points} points, which need "
        f"{needed} {what}, but only {header.data_bytes} bytes follow the header",
    )


def _check_lzf(path, compressed: bytes, uncompressed_size: int) -> None:
    """Refuse an LZF block that does not unpack to exactly its declared size (pypcd4 would fail
    with ``object of type 'NoneType' has no len()`` when it unpacks to more)."""
    import lzf

    if len(compressed) == 0 and uncompressed_size == 0:
        return
    try:
        unpacked = lzf.decompress(compressed, uncompressed_size + 1)
    except ValueError as exc:
        raise PointCloudFileError(path, f"malformed PCD binary_compressed data: {one_line(exc, 160)}") from None
    if unpacked is None or len(unpacked) != uncompressed_size:
        got = f"more than {uncompressed_size} bytes" if unpacked is None else f"{len(unpacked)} bytes"
        raise PointCloudFileError(
            path,
            f"malformed PCD binary_compressed data: the compressed block unpacks to {got}, but its "
            f"size field declares {uncompressed_size}",
        )


def _data_block(path, handle, header: _PcdHeader) -> bytes:
    """The data bytes pypcd4 needs, after checking the file really holds them."""
    if header.data == "binary":
        needed = header.points * header.row_bytes
        if needed > header.data_bytes:
            raise _truncated(path, header, needed)
        return handle.read(needed)
    if header.data == "binary_compressed":
        if header.data_bytes < 8:
            raise _truncated(path, header, 8, "bytes at least (the compressed block sizes)")
        compressed_size, uncompressed_size = struct.unpack("<II", handle.read(8))
        expected = header.points * header.row_bytes
        if uncompressed_size != expected:
            raise PointCloudFileError(
                path,
                f"corrupt PCD file: its compressed block unpacks to {uncompressed_size} bytes, but "
                f"{header.points} points of {header.row_bytes} bytes need {expected}",
            )
        if compressed_size > header.data_bytes - 8:
            raise _truncated(path, header, compressed_size + 8, "bytes of compressed data")
        if uncompressed_size > _MAX_LZF_RATIO * compressed_size + 1024:
            raise PointCloudFileError(
                path,
                f"corrupt PCD file: a {compressed_size}-byte compressed block cannot unpack to {uncompressed_size} bytes",
            )
        compressed = handle.read(compressed_size)
        _check_lzf(path, compressed, uncompressed_size)
        return struct.pack("<II", compressed_size, uncompressed_size) + compressed
    # ascii: at least one character and one separator per value on each row.
    needed = header.points * 2 * header.values_per_row - 1
    if needed > header.data_bytes:
        raise _truncated(path, header, needed, "bytes of text at least")
    rows = []
    for line in _ascii_lines(path, handle) if header.points else ():
        words = line.split()
        if not words:
            continue
        if len(words) != header.values_per_row:
            raise PointCloudFileError(
                path,
                f"malformed ascii PCD data: point {len(rows) + 1} has {len(words)} values, the header "
                f"declares {header.values_per_row} per point",
            )
        rows.append(" ".join(words))
        if len(rows) == header.points:
            break  # what follows the declared points is never read
    if len(rows) < header.points:
        raise PointCloudFileError(
            path,
            f"truncated PCD file: its header declares {header.points} points, but only {len(rows)} data lines follow",
        )
    return ("\n".join(rows) + "\n").encode("ascii")


def _ascii_lines(path, handle):
    """The lines of an ascii PCD body, read block by block (never more than one block beyond the
    line being parsed, whatever follows the declared points)."""
    carry = b""
    while True:
        block = handle.read(_ASCII_BLOCK_BYTES)
        lines = (carry + block).split(b"\n")
        carry = lines.pop() if block else b""
        if len(carry) > _ASCII_BLOCK_BYTES:
            raise PointCloudFileError(path, "malformed ascii PCD data: a data line longer than 1 MiB")
        for line in lines:
            try:
                yield from line.decode("ascii").splitlines()
            except UnicodeDecodeError:
                raise PointCloudFileError(path, "malformed ascii PCD data: it contains non-text bytes") from None
        if not block:
            return


def _normalized_header(header: _PcdHeader) -> str:
    """A PCD v0.7 header that pypcd4 accepts.

    pypcd4 refuses VERSION lines other than .7 and parses FIELDS with a regular expression that
    mangles unusual names; the fields other than x, y, z are ignored anyway, so they get plain
    unique names.
    """
    fields = [
        name if name in ("x", "y", "z") else f"ignored{index}" for index, name in enumerate(header.fields)
    ]
    return (
        "VERSION 0.7\n"
        f"FIELDS {' '.join(fields)}\n"
        f"SIZE {' '.join(map(str, header.sizes))}\n"
        f"TYPE {' '.join(header.types)}\n"
        f"COUNT {' '.join(map(str, header.counts))}\n"
        f"WIDTH {header.width}\n"
        f"HEIGHT {header.height}\n"
        "VIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {header.points}\n"
        f"DATA {header.data}\n"
    )


def read_pcd(path) -> np.ndarray:
    """Read the ``x, y, z`` fields of a PCD file (ascii, binary or binary_compressed).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` float64 in the file's own frame and units, ``N = WIDTH * HEIGHT``. NaN points of
        organized clouds are kept here; the caller drops them.

    Raises
    ------
    PointCloudFileError
        The file is not a PCD file, its header is inconsistent or lies about its size, or it has no
        x/y/z fields.
    """
    from pypcd4 import PointCloud

    with open(path, "rb") as handle:
        header = _read_header(path, handle)
        _check_fields(path, header)
        block = _data_block(path, handle, header)
    stream = io.BytesIO(_normalized_header(header).encode("ascii") + block)
    try:
        with np.errstate(over="ignore", invalid="ignore"):  # ascii 1e72 in a float32 field: inf, dropped later
            cloud = PointCloud.from_fileobj(stream)
        table = np.atleast_1d(cloud.pc_data)
        points = np.empty((len(table), 3), dtype=np.float64)
        with np.errstate(invalid="ignore"):  # a signalling NaN in float32 data: dropped later
            for column, axis in enumerate("xyz"):
                points[:, column] = table[axis]
    except MemoryError:
        raise PointCloudFileError(path, "PCD file is too large to load into memory") from None
    except Exception as exc:  # noqa: BLE001 - pypcd4 raises RuntimeError, ValueError, pydantic errors...
        problem = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PointCloudFileError(path, f"malformed PCD {header.data} data: {one_line(problem, 160)}") from None
    if len(points) != header.points:
        raise PointCloudFileError(
            path,
            f"malformed PCD file: its header declares {header.points} points but {len(points)} were read",
        )
    return points


def write_pcd(handle, points: np.ndarray, *, encoding: str = "binary", scan_index: np.ndarray | None = None,
              colors: np.ndarray | None = None) -> None:
    """Write ``points`` as a PCD v0.7 file with fields ``x y z`` of TYPE F SIZE 8 (float64).

    Every encoding keeps full float64 precision, so round trips are exact: ``binary`` and
    ``binary_compressed`` store the raw doubles; ``ascii`` writes 17 significant digits.

    Parameters
    ----------
    handle : binary file object
        Open for writing.
    points : numpy.ndarray
        ``(N, 3)`` float64, already validated.
    encoding : {"ascii", "binary", "binary_compressed"}
    scan_index : numpy.ndarray, optional
        ``(N,)`` int32 per point: the field ``scan_index`` (TYPE I SIZE 4; a scalar field in
        CloudCompare).
    colors : numpy.ndarray, optional
        ``(N, 3)`` uint8 per point: the field ``rgb``, packed as PCL packs it (``r << 16 | g << 8
        | b``), TYPE U SIZE 4 (so the ascii encoding keeps it exactly); Open3D and CloudCompare
        read it as colours.
    """
    import lzf
    from pypcd4 import Encoding, PointCloud

    columns = [points[:, 0], points[:, 1], points[:, 2]]
    names, types = ["x", "y", "z"], [np.float64] * 3
    if colors is not None:
        rgb = colors.astype(np.uint32)
        columns.append((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2])
        names.append("rgb")
        types.append(np.uint32)
    if scan_index is not None:
        columns.append(np.asarray(scan_index, dtype=np.int32))
        names.append("scan_index")
        types.append(np.int32)
    columns = [np.ascontiguousarray(column, dtype=kind) for column, kind in zip(columns, types)]
    cloud = PointCloud.from_points(columns, tuple(names), tuple(types))
    if encoding == "binary":
        cloud.save(handle, encoding=Encoding.BINARY)
        return
    header = cloud.metadata.compose_header(data=Encoding(encoding)).encode("ascii")
    if encoding == "ascii":
        # pypcd4 writes ascii floats with "%.10f" (ten decimals: small values lose their
        # digits); write the rows with round-trip precision instead.
        handle.write(header)
        if len(columns) == 3:
            np.savetxt(handle, points, fmt="%.17g", delimiter=" ")
        else:
            table = np.empty(len(points), dtype=[(name, kind) for name, kind in zip(names, types)])
            for name, column in zip(names, columns):
                table[name] = column
            np.savetxt(handle, table, fmt=["%.17g"] * 3 + ["%d"] * (len(names) - 3), delimiter=" ")
        return
    # binary_compressed: pypcd4 falls back to writing DATA binary when LZF cannot shrink the data
    # (usual for random doubles). Keep the requested encoding, as PCL does, and store an LZF block
    # that may be slightly larger than the raw data.
    raw = b"".join(column.tobytes() for column in columns)  # field by field, as the encoding stores them
    compressed = lzf.compress(raw, len(raw) + len(raw) // 16 + 64) if raw else b""
    if compressed is None:  # pragma: no cover - the bound above is LZF's worst case
        raise RuntimeError("LZF compression failed")
    handle.write(header)
    handle.write(struct.pack("<II", len(compressed), len(raw)))
    handle.write(compressed)
