"""LAS / LAZ point clouds (the format LiDAR surveys ship in), through laspy.

The points' scaled coordinates (``X * scale + offset``) are returned as float64, in the file's
own coordinate system and units; every other dimension (intensity, classification, GPS time,
colour) is ignored. LAZ needs a decompression backend: ``pip install 'esmicp[las]'`` installs
laspy with lazrs.

Memory and time: before laspy reads anything, :func:`check_header` checks every count and
offset of the header against the file's size (the header's own size, the offset to the point
data, the number of variable-length records and each record's length, the point format and
record length, the point count, the extended records of LAS 1.4 and, for LAZ, the LASzip record
and the chunk table), and its scale factors (positive, and large enough to be seen next to the
offsets). A header that declares more than the file holds is refused at once, in a
message naming the field, instead of letting laspy allocate or loop over what it declares.
Points are then read in chunks of :data:`CHUNK_POINTS`, so what is allocated follows the points
actually present.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass

import numpy as np

from ..errors import MissingDependencyError, PointCloudFileError
from ._messages import one_line

__all__ = ["CHUNK_POINTS", "LAS_INSTALL_HINT", "LasLayout", "check_header", "read_las"]

#: Points decoded at a time.
CHUNK_POINTS = 1 << 20
LAS_INSTALL_HINT = "pip install 'esmicp[las]' (laspy with the lazrs LAZ backend)"

#: Bytes of the public header block, by minor version (LAS 1.0 to 1.5, the versions laspy reads).
HEADER_BYTES = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375, 5: 393}
#: Bytes of each standard point format's record (extra bytes may follow in a file's records).
POINT_FORMAT_BYTES = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}
#: Byte of the header where the x, y, z scale factors (three float64) start; the offsets follow.
SCALE_BYTE = 131
#: Bytes of the header of a variable-length record (VLR) and of an extended one (EVLR, LAS 1.4).
VLR_HEADER_BYTES = 54
EVLR_HEADER_BYTES = 60
#: ``user_id`` and ``record_id`` of the LASzip record that describes compressed points.
LASZIP_USER_ID = b"laszip encoded"
LASZIP_RECORD_ID = 22204
#: LASzip ``chunk_size`` meaning "chunks of variable size" (their sizes are in the chunk table).
VARIABLE_CHUNK_SIZE = 0xFFFFFFFF


@dataclass(frozen=True)
class LasLayout:
    """What :func:`check_header` found consistent with the file's size."""

    size: int  #: bytes of the file
    version: str  #: "1.2", "1.4", ...
    point_format: int  #: 0 to 10
    record_bytes: int  #: bytes per point record
    point_count: int  #: points the header declares
    point_data: int  #: byte offset of the point data
    compressed: bool  #: LAZ
    chunk_points: int | None = None  #: LAZ: points per chunk (None: variable-size chunks, or not chunked)


def _laspy(path):
    try:
        import laspy
    except (ImportError, OSError) as exc:
        raise MissingDependencyError(
            f"{path}: reading LAS / LAZ files needs laspy, which cannot be imported ({one_line(exc, 120)}); "
            f"install it with: {LAS_INSTALL_HINT}"
        ) from None
    return laspy


def _check_laz_backend(path, laspy) -> None:
    try:
        available = laspy.LazBackend.detect_available()
    except Exception:  # noqa: BLE001 - an old or broken laspy: let the read say what is wrong
        return
    if not available:
        raise MissingDependencyError(
            f"{path}: reading compressed LAZ points needs a LAZ backend (lazrs or laszip), none is "
            f"installed; install one with: {LAS_INSTALL_HINT}"
        )


def _read_at(handle, offset: int, count: int) -> bytes:
    handle.seek(offset)
    return handle.read(count)


def check_header(path, handle, size: int) -> LasLayout:
    """Check a LAS / LAZ header's counts and offsets against the file's ``size`` (bytes).

    Reads the header and walks the headers of the variable-length records (each read is bounded
    by the file's size), and for LAZ reads the LASzip record and the chunk table's first bytes.

    Raises
    ------
    PointCloudFileError
        The file is not LAS, or one of its header fields declares more than the file holds (the
        message names the field, its value and the file's size).
    """

    def refuse(problem: str) -> PointCloudFileError:
        return PointCloudFileError(path, problem)

    head = _read_at(handle, 0, max(HEADER_BYTES.values()))
    if head[:4] != b"LASF":
        raise refuse(f"not a valid LAS / LAZ file: it does not start with the signature 'LASF' (it starts with {head[:4]!r})")
    if size < HEADER_BYTES[0]:
        raise refuse(f"truncated LAS file: {size:,} bytes, fewer than the {HEADER_BYTES[0]} of a LAS header")
    major, minor = head[24], head[25]
    if major != 1 or minor not in HEADER_BYTES:
        raise refuse(f"not a valid LAS / LAZ file: header says version {major}.{minor}; LAS 1.0 to 1.5 can be read")
    version = f"{major}.{minor}"
    header_bytes, point_data, vlr_count, format_byte, record_bytes, legacy_count = struct.unpack_from("<HIIBHI", head, 94)
    needed = HEADER_BYTES[minor]
    if size < needed:
        raise refuse(f"truncated LAS file: {size:,} bytes, fewer than the {needed} of a LAS {version} header")
    if header_bytes < needed:
        raise refuse(f"LAS header says its size is {header_bytes} bytes, fewer than the {needed} of a LAS {version} header")
    if point_data > size:
        raise refuse(f"LAS header says the point data start at byte {point_data:,}, past the end of the file's {size:,} bytes")
    if point_data < header_bytes:
        raise refuse(f"LAS header says the point data start at byte {point_data:,}, inside its own {header_bytes} bytes")
    # Coordinates are integer * scale + offset: a scale that is not a positive number flattens or
    # mirrors the cloud, one below what the offset resolves makes every coordinate the offset.
    scales, offsets = struct.unpack_from("<3d", head, SCALE_BYTE), struct.unpack_from("<3d", head, SCALE_BYTE + 24)
    for axis, scale, offset in zip("xyz", scales, offsets):
        if not scale > 0 or scale == float("inf"):
            raise refuse(f"LAS header says the {axis} scale factor is {scale!r} (bytes {SCALE_BYTE}-{SCALE_BYTE + 23} "
                         "hold x, y, z); a scale factor must be a positive number")
        if offset + scale == offset:
            raise refuse(f"LAS header says the {axis} scale factor is {scale:g}, too small to tell points apart at its "
                         f"{axis} offset {offset:g}: every {axis} would be the offset")

    # Variable-length records: between the header and the point data, 54 bytes of header each.
    if vlr_count * VLR_HEADER_BYTES > size - header_bytes:
        raise refuse(f"LAS header says {vlr_count} variable-length records, more than fit in the file's {size:,} bytes")
    if vlr_count * VLR_HEADER_BYTES > point_data - header_bytes:
        raise refuse(
            f"LAS header says {vlr_count} variable-length records, more than fit between its header "
            f"(byte {header_bytes}) and the point data (byte {point_data:,})"
        )
    laszip = None
    position = header_bytes
    for index in range(vlr_count):
        record = _read_at(handle, position, VLR_HEADER_BYTES)
        user_id, record_id, length = struct.unpack_from("<16sHH", record, 2)
        end = position + VLR_HEADER_BYTES + length
        if end > point_data:
            raise refuse(
                f"corrupt LAS file: variable-length record {index + 1} of {vlr_count} says it holds {length:,} bytes, "
                f"past the start of the point data (byte {point_data:,})"
            )
        if user_id.split(b"\0")[0] == LASZIP_USER_ID and record_id == LASZIP_RECORD_ID:
            laszip = (position + VLR_HEADER_BYTES, length)
        position = end

    compressed = bool(format_byte & 0xC0)
    point_format = format_byte & 0x3F
    if point_format not in POINT_FORMAT_BYTES:
        raise refuse(f"LAS header says point format {point_format} (byte {format_byte}); LAS point formats are 0 to 10")
    if record_bytes < POINT_FORMAT_BYTES[point_format]:
        raise refuse(
            f"LAS header says points of {record_bytes} bytes, fewer than the "
            f"{POINT_FORMAT_BYTES[point_format]} of point format {point_format}"
        )
    count = struct.unpack_from("<Q", head, 247)[0] if minor >= 4 else legacy_count

    if minor >= 4:
        _check_extended_records(refuse, handle, head, size, point_data)
    chunk_points = None
    if compressed:
        chunk_points = _check_laz(refuse, handle, size, point_data, count, record_bytes, laszip)
    else:
        needed = point_data + count * record_bytes
        if needed > size:
            raise refuse(
                f"truncated LAS file: its header declares {count} points of {record_bytes} bytes from byte "
                f"{point_data}, which needs {needed} bytes, but the file has {size}"
            )
    return LasLayout(size, version, point_format, record_bytes, count, point_data, compressed, chunk_points)


def _check_extended_records(refuse, handle, head: bytes, size: int, point_data: int) -> None:
    """LAS 1.4: the extended variable-length records, after the point data, must fit in the file."""
    start, count = struct.unpack_from("<QI", head, 235)
    if count == 0:
        return
    if not point_data <= start <= size:
        raise refuse(
            f"LAS header says the extended variable-length records start at byte {start:,}, outside "
            f"the file's {size:,} bytes after the point data (byte {point_data:,})"
        )
    if count * EVLR_HEADER_BYTES > size - start:
        raise refuse(
            f"LAS header says {count} extended variable-length records from byte {start:,}, more "
            f"than fit in the file's {size:,} bytes"
        )
    position = start
    for index in range(count):
        record = _read_at(handle, position, EVLR_HEADER_BYTES)
        length = struct.unpack_from("<Q", record, 20)[0]
        position += EVLR_HEADER_BYTES + length
        if position > size:
            raise refuse(
                f"truncated LAS file: extended variable-length record {index + 1} of {count} says it holds "
                f"{length:,} bytes, past the end of the file's {size:,} bytes"
            )


def _check_laz(refuse, handle, size: int, point_data: int, count: int, record_bytes: int, laszip) -> int | None:
    """LAZ: a LASzip record that holds its items, and a chunk table inside the file whose number of
    chunks (at least one byte each) and chunk size can hold the declared points, and whose items
    make points of the header's record length (else the decoder reads, and laspy allocates, points
    of the size the items say). Returns the
    number of points per chunk (None: variable-size chunks, or points not in chunks)."""
    if laszip is None:
        raise refuse(
            "corrupt LAZ file: its header says the points are compressed, but it has no LASzip record "
            "('laszip encoded', 22204) describing them"
        )
    where, length = laszip
    record = _read_at(handle, where, length)
    if length < 34:
        raise refuse(f"corrupt LAZ file: its LASzip record has {length} bytes, fewer than the 34 it needs")
    compressor = struct.unpack_from("<H", record, 0)[0]
    chunk_size = struct.unpack_from("<I", record, 12)[0]
    items = struct.unpack_from("<H", record, 32)[0]
    if 34 + 6 * items > length:
        raise refuse(f"corrupt LAZ file: its LASzip record says {items} items, more than its {length} bytes hold")
    item_bytes = sum(struct.unpack_from("<H", record, 34 + 6 * k + 2)[0] for k in range(items))
    if item_bytes != record_bytes:
        raise refuse(
            f"corrupt LAZ file: its LASzip record's items make points of {item_bytes:,} bytes, but the LAS header "
            f"says {record_bytes}"
        )
    if compressor not in (2, 3):  # not chunked: no chunk table to check
        return None
    if point_data + 8 > size:
        raise refuse(f"truncated LAZ file: no chunk table offset after the point data start (byte {point_data:,})")
    table = struct.unpack("<q", _read_at(handle, point_data, 8))[0]
    if table == -1 and size >= 8:  # LASzip's "written at the end of the file" (its writer could not seek back)
        table = struct.unpack("<q", _read_at(handle, size - 8, 8))[0]
    if table > size - 8:
        raise refuse(
            f"truncated LAZ file: its chunk table offset says byte {table:,}, past the end of the file's {size:,} bytes"
        )
    if table < point_data + 8:
        raise refuse(
            f"corrupt LAZ file: its chunk table offset says byte {table:,}, before the compressed points "
            f"(from byte {point_data + 8:,})"
        )
    chunks = struct.unpack("<I", _read_at(handle, table + 4, 4))[0]
    room = table - point_data - 8
    if chunks > room:
        raise refuse(
            f"corrupt LAZ file: its chunk table says {chunks} chunks, more than fit in the {room:,} bytes of "
            f"compressed points of the file's {size:,} bytes"
        )
    if chunk_size != VARIABLE_CHUNK_SIZE and count > chunks * chunk_size:
        raise refuse(
            f"corrupt LAZ file: its header declares {count} points, more than its {chunks} chunk(s) of "
            f"{chunk_size:,} points hold"
        )
    return None if chunk_size == VARIABLE_CHUNK_SIZE else chunk_size


def _laz_backend(laspy, layout: LasLayout):
    """The LAZ decoders laspy may use for ``layout``: lazrs's parallel decoder allocates whole
    chunks, as large as the header's chunk size says (a corrupt one aborts the process when the
    allocation fails), so it is used only for chunks of at most :data:`CHUNK_POINTS` points; the
    sequential decoder, which fills the caller's buffer, otherwise. None: laspy's default."""
    if layout.chunk_points is not None and layout.chunk_points <= CHUNK_POINTS:
        return None
    try:
        sequential = tuple(b for b in laspy.LazBackend.detect_available() if b != laspy.LazBackend.LazrsParallel)
    except Exception:  # noqa: BLE001 - an old or broken laspy: let the read say what is wrong
        return None
    return sequential or None


def read_las(path) -> np.ndarray:
    """Read the scaled ``x, y, z`` of every point of a LAS / LAZ file.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` float64 (NaN rows kept; the caller drops them).

    Raises
    ------
    PointCloudFileError
        Not a LAS file (bad signature or header), a header field that declares more than the file
        holds (see :func:`check_header`), truncated or corrupt point data.
    MissingDependencyError
        laspy (or, for compressed points, a LAZ backend) is not installed.
    """
    laspy = _laspy(path)
    with open(path, "rb") as handle:
        layout = check_header(path, handle, os.fstat(handle.fileno()).st_size)
    if layout.compressed:
        _check_laz_backend(path, laspy)
    kind = "LAZ" if layout.compressed else "LAS"
    chunks = []
    read = 0
    stage = f"laspy could not read the {kind} {layout.version} header and its variable-length records"
    try:
        with laspy.open(path, laz_backend=_laz_backend(laspy, layout) if layout.compressed else None) as reader:
            stage = f"corrupt or truncated {kind} point data"
            for chunk in reader.chunk_iterator(CHUNK_POINTS):
                block = np.empty((len(chunk), 3), dtype=np.float64)
                block[:, 0] = chunk.x
                block[:, 1] = chunk.y
                block[:, 2] = chunk.z
                chunks.append(block)
                read += len(block)
    except MemoryError:
        raise PointCloudFileError(path, "too large to load into memory") from None
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot read: {exc.strerror or exc}") from None
    except Exception as exc:  # noqa: BLE001 - laspy / lazrs errors of a corrupt file (LaspyException, ValueError, ...)
        raise PointCloudFileError(path, f"{stage} ({_library_error(exc)})") from None
    except BaseException as exc:  # lazrs's Rust panics reach Python as PanicException, a BaseException
        if type(exc).__name__ != "PanicException":
            raise
        raise PointCloudFileError(path, f"{stage} ({_library_error(exc)})") from None
    if read < layout.point_count:
        raise PointCloudFileError(
            path, f"truncated {kind} file: its header declares {layout.point_count} points, {read} could be read"
        )
    if not chunks:
        return np.empty((0, 3), dtype=np.float64)
    return np.concatenate(chunks)


def _library_error(exc: BaseException) -> str:
    """``exc`` as ``"laspy: Type: text"`` on one line (a library's own words, labelled as such)."""
    library = (type(exc).__module__ or "").split(".")[0] or "laspy"
    if library in ("builtins", "pyo3_runtime"):
        library = "laspy / lazrs"
    return f"{library}: {type(exc).__name__}: {one_line(exc, 160)}"
