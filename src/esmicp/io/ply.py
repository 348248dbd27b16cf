"""PLY (Stanford polygon file) point clouds, read and written with :mod:`plyfile`.

Only the ``x``, ``y``, ``z`` properties of the ``vertex`` element are read. Other vertex
properties (normals, colours, confidence, a scan index, ...) and other elements (faces, the
Stanford scans' ``range_grid``, ...) are tolerated and ignored. :func:`write_ply` can add a colour
(``uchar red green blue``) and an ``int scan_index`` per vertex.

The header is parsed and checked here first, against the file's size, so that a header that
declares more data than the file holds is refused before anything is allocated. plyfile then reads
only the elements up to and including ``vertex`` (a face list after the vertices is never parsed,
which keeps large meshes fast).
"""

from __future__ import annotations

import dataclasses
import io
import itertools
import os
import warnings

import numpy as np
import plyfile

from ..errors import PointCloudFileError
from ._messages import excerpt, one_line

__all__ = ["PlyHeader", "read_ply", "read_ply_header", "write_ply"]

#: Byte size of each PLY scalar type (both the PLY 1.0 names and the sized aliases).
_SCALAR_SIZES = {
    "char": 1,
    "int8": 1,
    "uchar": 1,
    "uint8": 1,
    "short": 2,
    "int16": 2,
    "ushort": 2,
    "uint16": 2,
    "int": 4,
    "int32": 4,
    "uint": 4,
    "uint32": 4,
    "float": 4,
    "float32": 4,
    "double": 8,
    "float64": 8,
}
_INTEGER_TYPES = {
    "char",
    "int8",
    "uchar",
    "uint8",
    "short",
    "int16",
    "ushort",
    "uint16",
    "int",
    "int32",
    "uint",
    "uint32",
}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
#: A header longer than this is not a PLY header.
_MAX_HEADER_BYTES = 1 << 20


@dataclasses.dataclass(frozen=True)
class _Property:
    name: str
    value_type: str
    list_length_type: str | None = None  # set for list properties

    @property
    def is_list(self) -> bool:
        return self.list_length_type is not None

    def declaration(self) -> str:
        if self.is_list:
            return f"property list {self.list_length_type} {self.value_type} {self.name}"
        return f"property {self.value_type} {self.name}"


@dataclasses.dataclass
class _Element:
    name: str
    count: int
    properties: list[_Property] = dataclasses.field(default_factory=list)

    @property
    def has_lists(self) -> bool:
        return any(p.is_list for p in self.properties)

    def min_binary_row_bytes(self) -> int:
        """Bytes per row in binary form (exact without lists; a lower bound with lists)."""
        return sum(_SCALAR_SIZES[p.list_length_type if p.is_list else p.value_type] for p in self.properties)

    def min_ascii_row_bytes(self) -> int:
        """Lower bound of the bytes per row in ascii form: one character and a separator per value."""
        return max(2 * len(self.properties), 1)

    def property_names(self) -> list[str]:
        return [p.name for p in self.properties]


@dataclasses.dataclass
class PlyHeader:
    """What a PLY header declares, and where its data starts.

    Attributes
    ----------
    format : str
        ``"ascii"``, ``"binary_little_endian"`` or ``"binary_big_endian"``.
    elements : list
        The declared elements, in file order.
    data_offset : int
        Byte offset of the first data byte (just after ``end_header``).
    data_bytes : int
        Number of bytes after the header.
    """

    format: str
    elements: list[_Element]
    data_offset: int
    data_bytes: int

    @property
    def is_ascii(self) -> bool:
        return self.format == "ascii"

    def element(self, name: str) -> _Element | None:
        for element in self.elements:
            if element.name == name:
                return element
        return None

    def element_counts(self) -> dict[str, int]:
        return {element.name: element.count for element in self.elements}


def _parse_property(path, words: list[str], line_number: int) -> _Property:
    if len(words) >= 2 and words[1] == "list":
        if len(words) != 5:
            raise PointCloudFileError(
                path,
                f"malformed PLY header, line {line_number}: expected 'property list <count type> <value type> <name>'",
            )
        _, _, length_type, value_type, name = words
        if length_type not in _INTEGER_TYPES:
            raise PointCloudFileError(
                path,
                f"malformed PLY header, line {line_number}: list length type {excerpt(length_type, 20)} is not an integer type",
            )
        if value_type not in _SCALAR_SIZES:
            raise PointCloudFileError(
                path, f"malformed PLY header, line {line_number}: unknown type {excerpt(value_type, 20)}"
            )
        return _Property(name, value_type, length_type)
    if len(words) != 3:
        raise PointCloudFileError(
            path, f"malformed PLY header, line {line_number}: expected 'property <type> <name>'"
        )
    _, value_type, name = words
    if value_type not in _SCALAR_SIZES:
        raise PointCloudFileError(
            path, f"malformed PLY header, line {line_number}: unknown type {excerpt(value_type, 20)}"
        )
    return _Property(name, value_type)


def _locate_header_end(path, head: bytes) -> tuple[str, int, int]:
    """Return (newline, index of the newline before ``end_header``, data offset)."""
    if not head.startswith(b"ply"):
        raise PointCloudFileError(path, "not a PLY file: it does not start with the 'ply' line")
    if head[3:5] == b"\r\n":
        newline = b"\r\n"
    elif head[3:4] in (b"\n", b"\r"):
        newline = head[3:4]
    else:
        raise PointCloudFileError(path, "not a PLY file: unexpected characters after 'ply' on the first line")
    marker = newline + b"end_header"
    start = 0
    while True:
        index = head.find(marker, start)
        if index < 0:
            if len(head) >= _MAX_HEADER_BYTES:
                raise PointCloudFileError(
                    path, "not a valid PLY file: no 'end_header' line in the first 1 MiB"
                )
            raise PointCloudFileError(path, "truncated PLY file: the header has no 'end_header' line")
        after = index + len(marker)
        rest = head[after:]
        if rest.startswith(newline):
            return newline.decode("ascii"), index, after + len(newline)
        if not rest:  # the header ends the file
            return newline.decode("ascii"), index, len(head)
        stripped = rest.lstrip(b" \t")
        if not stripped or stripped.startswith(newline):
            raise PointCloudFileError(path, "malformed PLY header: 'end_header' must be alone on its line")
        start = after


def read_ply_header(path, handle=None) -> PlyHeader:
    """Parse and check the header of the PLY file at ``path``.

    Parameters
    ----------
    path : str or os.PathLike
        The file, used in error messages (and opened unless ``handle`` is given).
    handle : binary file object, optional
        An open handle on the file; it is left positioned at the start of the data.

    Returns
    -------
    PlyHeader

    Raises
    ------
    PointCloudFileError
        The header is malformed, or declares more data than the file holds.
    """
    if handle is None:
        with open(path, "rb") as own_handle:
            return read_ply_header(path, own_handle)
    handle.seek(0, os.SEEK_END)
    file_size = handle.tell()
    handle.seek(0)
    head = handle.read(_MAX_HEADER_BYTES)
    newline, end_index, data_offset = _locate_header_end(path, head)
    try:
        text = head[:end_index].decode("ascii")
    except UnicodeDecodeError:
        raise PointCloudFileError(path, "malformed PLY header: it contains non-ASCII bytes") from None

    file_format = None
    elements: list[_Element] = []
    for line_number, line in enumerate(text.split(newline)[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        keyword = words[0]
        if keyword == "format":
            if file_format is not None:
                raise PointCloudFileError(
                    path, f"malformed PLY header, line {line_number}: a second 'format' line"
                )
            if len(words) != 3 or words[1] not in _FORMATS or words[2] != "1.0":
                raise PointCloudFileError(
                    path,
                    f"malformed PLY header, line {line_number}: unsupported format {excerpt(' '.join(words[1:]))}",
                )
            file_format = words[1]
        elif keyword == "element":
            if len(words) != 3:
                raise PointCloudFileError(
                    path, f"malformed PLY header, line {line_number}: expected 'element <name> <count>'"
                )
            try:
                count = int(words[2])
            except ValueError:
                count = -1
            if count < 0:
                raise PointCloudFileError(
                    path,
                    f"malformed PLY header, line {line_number}: element count {excerpt(words[2], 20)} is not a whole number",
                )
            elements.append(_Element(words[1], count))
        elif keyword == "property":
            if not elements:
                raise PointCloudFileError(
                    path, f"malformed PLY header, line {line_number}: a property before any element"
                )
            elements[-1].properties.append(_parse_property(path, words, line_number))
        else:
            raise PointCloudFileError(
                path, f"malformed PLY header, line {line_number}: unexpected {excerpt(line.strip())}"
            )
    if file_format is None:
        raise PointCloudFileError(path, "malformed PLY header: no 'format' line")

    header = PlyHeader(file_format, elements, data_offset, max(file_size - data_offset, 0))
    _check_sizes(path, header)
    handle.seek(data_offset)
    return header


def _shortened(items: list[str], limit: int = 6) -> str:
    """``items`` joined by commas, the first ``limit`` only (a corrupt header may declare thousands)."""
    if len(items) <= limit:
        return ", ".join(items)
    return ", ".join(items[:limit]) + f", ... ({len(items)} in all)"


def _describe_count(element: _Element) -> str:
    plural = {"vertex": "vertices", "face": "faces"}.get(element.name, f"{excerpt(element.name, 20)} rows")
    return f"{element.count} {plural}"


def _check_sizes(path, header: PlyHeader) -> None:
    """Refuse a header that declares more data than the file can hold."""
    if header.is_ascii:
        minimum = sum(e.count * e.min_ascii_row_bytes() for e in header.elements if e.count) - 1
    else:
        minimum = sum(e.count * e.min_binary_row_bytes() for e in header.elements)
    if minimum > header.data_bytes:
        declared = _shortened([_describe_count(e) for e in header.elements])
        raise PointCloudFileError(
            path,
            f"truncated or corrupt PLY file: its header declares {declared}, which needs at least "
            f"{minimum} bytes of data, but only {header.data_bytes} bytes follow the header",
        )


def _vertex_element(path, header: PlyHeader) -> tuple[int, _Element]:
    for index, element in enumerate(header.elements):
        if element.name == "vertex":
            break
    else:
        names = _shortened([excerpt(e.name, 20) for e in header.elements]) or "none"
        raise PointCloudFileError(path, f"PLY file has no 'vertex' element (elements: {names})")
    by_name = {p.name: p for p in element.properties}
    for axis in "xyz":
        if element.property_names().count(axis) > 1:
            raise PointCloudFileError(path, f"malformed PLY header: vertex property {axis!r} appears twice")
    missing = [axis for axis in "xyz" if axis not in by_name]
    if missing:
        found = _shortened([excerpt(name, 20) for name in element.property_names()]) or "none"
        raise PointCloudFileError(
            path, f"PLY vertices have no {'/'.join(missing)} coordinate (vertex properties: {found})"
        )
    lists = [axis for axis in "xyz" if by_name[axis].is_list]
    if lists:
        raise PointCloudFileError(path, f"PLY vertex property {excerpt(lists[0], 20)} is a list, expected a number")
    return index, element


def _rewritten_header(header: PlyHeader, elements: list[_Element]) -> str:
    """A minimal header that declares only ``elements`` (so plyfile stops after them)."""
    lines = ["ply", f"format {header.format} 1.0"]
    for element in elements:
        lines.append(f"element {element.name} {element.count}")
        lines.extend(p.declaration() for p in element.properties)
    lines.append("end_header")
    return "\n".join(lines) + "\n"


def _plyfile_read(path, stream, **kwargs) -> plyfile.PlyData:
    try:
        with warnings.catch_warnings(), np.errstate(over="ignore", invalid="ignore"):
            # plyfile's ascii list parser warns on empty lists; that is not a problem. An ascii
            # value beyond its property's type (1e72 for a float) becomes inf: dropped later.
            warnings.simplefilter("ignore", UserWarning)
            return plyfile.PlyData.read(stream, **kwargs)
    except plyfile.PlyParseError as exc:
        raise PointCloudFileError(path, f"malformed PLY data: {one_line(exc, 160)}") from None
    except UnicodeDecodeError:
        raise PointCloudFileError(path, "malformed ascii PLY data: it contains non-ASCII bytes") from None
    except MemoryError:
        raise PointCloudFileError(path, "PLY file is too large to load into memory") from None
    except (ValueError, TypeError, IndexError, KeyError, OverflowError, StopIteration) as exc:
        raise PointCloudFileError(path, f"malformed PLY file: {one_line(exc, 160)}") from None


def _read_ascii(path, handle, header: PlyHeader, needed: list[_Element]) -> np.ndarray:
    """Vertex coordinates of an ascii PLY file whose header was checked.

    One line per row: the rows of the elements before the vertices are counted, not parsed, and
    plyfile parses the vertex rows alone.
    """
    vertex = needed[-1]
    before = sum(e.count for e in needed[:-1])
    text = io.TextIOWrapper(handle, encoding="ascii", newline=None, errors="replace")
    try:
        skipped = 0
        for line in itertools.islice(text, before):
            if "\ufffd" in line:  # a byte that is not ASCII
                raise UnicodeDecodeError("ascii", b"", 0, 1, "not ASCII")
            skipped += 1
        lines = list(itertools.islice(text, vertex.count)) if skipped == before else []
        if any("\ufffd" in line for line in lines):
            raise UnicodeDecodeError("ascii", b"", 0, 1, "not ASCII")
        # The rows after the vertices: those of the elements declared after them, and no more.
        after = header.elements[len(needed):]
        complete = skipped + len(lines) == before + vertex.count
        more = complete and _ascii_data_after(text, sum(element.count for element in after))
    except UnicodeDecodeError:
        raise PointCloudFileError(path, "malformed ascii PLY data: it contains non-ASCII bytes") from None
    finally:
        text.detach()
    if skipped + len(lines) < before + vertex.count:
        raise PointCloudFileError(
            path,
            f"truncated PLY file: its header declares {vertex.count} vertices, but the data ends after "
            f"{skipped + len(lines)} lines",
        )
    if more:
        raise _more_than_declared(path, header, vertex, after, "more data")
    fast = _float_rows(lines, vertex)
    if fast is not None:
        return fast
    return _coordinates(_plyfile_read(path, io.StringIO(_rewritten_header(header, [vertex]) + "".join(lines))))


#: Longest ascii PLY row looked at when checking what follows the declared rows (longer: not a row).
_MAX_ASCII_ROW = 1 << 16


def _ascii_data_after(text, rows: int) -> bool:
    """True when anything but blank space follows the next ``rows`` non-blank lines of ``text``
    (a line of ``_MAX_ASCII_ROW`` characters or more among them is other data, not a row). Reads
    one block at a time (a tail of binary data costs one block); the lines of a block that ends
    before the last of those rows are counted in one pass, not one by one."""
    pending = ""  # the line the last block ended inside
    while rows:
        block = text.read(_MAX_ASCII_ROW)
        if not block:
            return False  # fewer rows than declared after the vertices: not read, not judged here
        lines = (pending + block).split("\n")
        pending = lines.pop()
        filled = len(lines) - lines.count("") - sum(map(str.isspace, lines))
        if filled < rows:
            if (lines and max(map(len, lines)) >= _MAX_ASCII_ROW) or len(pending) >= _MAX_ASCII_ROW:
                return True  # no row is that long: other data
            rows -= filled
            continue
        if filled == len(lines):  # no blank line: the last row is line rows - 1
            if max(map(len, lines[:rows])) >= _MAX_ASCII_ROW:
                return True
            if pending.strip() or any(map(str.strip, lines[rows:])):
                return True
            break
        for index, line in enumerate(lines):
            if len(line) >= _MAX_ASCII_ROW:
                return True
            if line.strip():
                rows -= 1
                if not rows:
                    if pending.strip() or any(map(str.strip, lines[index + 1:])):
                        return True
                    break
    while True:
        block = text.read(_MAX_ASCII_ROW)
        if not block:
            return False
        if block.strip():
            return True


def _float_rows(lines: list[str], vertex: _Element) -> np.ndarray | None:
    """x, y, z of ascii vertex rows whose properties are all ``float`` / ``double`` scalars, parsed
    by NumPy's compiled text reader (plyfile parses one value at a time in Python: 0.16 s for one
    40k-point bunny scan, this 0.02 s). Each value is read as a double and then rounded to its
    property's type, as plyfile does. None whenever the rows are not exactly one number per
    property (or the types differ): plyfile then parses them and names the problem."""
    codes = [_NUMPY_CODES.get(p.value_type) for p in vertex.properties]
    names = [p.name for p in vertex.properties]
    if not lines or vertex.has_lists or len(set(names)) < len(names) or not set(codes) <= {"f4", "f8"}:
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            values = np.loadtxt(lines, dtype=np.float64, comments=None, ndmin=2)
    except (ValueError, TypeError, OverflowError):
        return None
    if values.shape != (vertex.count, len(names)):  # blank lines are skipped by loadtxt, not by plyfile
        return None
    points = np.empty((len(values), 3), dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):  # 1e72 in a float column is inf, as in plyfile
        for column, axis in enumerate("xyz"):
            index = names.index(axis)
            points[:, column] = values[:, index].astype(codes[index])
    return points


#: numpy type codes of the PLY scalar types.
_NUMPY_CODES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
#: Bytes read at a time from a binary PLY body (bounds the memory a read needs beyond its result).
_BLOCK_BYTES = 1 << 24


def _changed(path) -> PointCloudFileError:
    return PointCloudFileError(
        path, "truncated PLY file: the data ends before what its header declares (did the file change while it was read?)"
    )


class _Blocks:
    """Sequential reads of a binary PLY body, block by block, from the current position of a handle.

    The file is read, never memory-mapped: a file that shrinks while it is read (another process
    rewriting it) is then a short read, reported as a truncated file, not a SIGBUS that kills the
    process.
    """

    def __init__(self, path, handle, size: int):
        self.path = path
        self.handle = handle
        self.size = size  # bytes after the header when it was read
        self.buffer = b""
        self.start = 0  # position of buffer[0] relative to where reading began

    def need(self, position: int, size: int) -> memoryview:
        """``size`` bytes at ``position`` (relative; positions only move forwards)."""
        end = position + size
        if position < self.start:  # pragma: no cover - a programming error, never the file's
            raise RuntimeError("PLY blocks are read forwards only")
        if end > self.size:
            raise PointCloudFileError(
                self.path,
                f"truncated or corrupt PLY file: its lists need more than the {self.size} bytes of data that follow the header",
            )
        if end > self.start + len(self.buffer):
            keep = self.buffer[position - self.start:] if position < self.start + len(self.buffer) else b""
            skip = position - self.start - len(self.buffer)
            if skip > 0:
                self.handle.seek(skip, os.SEEK_CUR)
            more = self.handle.read(min(max(_BLOCK_BYTES, end - position - len(keep)), self.size - position - len(keep)))
            self.buffer, self.start = keep + more, position
            if end > self.start + len(self.buffer):
                raise _changed(self.path)
        return memoryview(self.buffer)[position - self.start:end - self.start]


def _step_rows(path, blocks: _Blocks, position, count, remaining, before, length_size, value_size, after,
               order, signed):
    """Walk up to ``count`` rows of one list each, in the bytes already read (a tight loop)."""
    buffer, base = blocks.buffer, blocks.start
    end = base + len(buffer)
    fixed = before + length_size + after
    byte_lengths = length_size == 1 and not signed
    for _ in range(count):
        at = position + before
        if at + length_size > end:
            break  # the caller reads the next block
        if byte_lengths:
            length = buffer[at - base]
        else:
            length = int.from_bytes(buffer[at - base:at - base + length_size], order, signed=signed)
            if length < 0:
                raise PointCloudFileError(path, f"malformed PLY data: a negative list length ({length})")
        position += fixed + length * value_size
        remaining -= 1
    return position, remaining


def _skip_rows(path, blocks: _Blocks, position: int, element: _Element, byte_order: str) -> int:
    """Walk past the rows of an element with list properties; return the position after them."""
    steps = []  # per property: (fixed size, None) or (length size, (length dtype, value size))
    for prop in element.properties:
        if prop.is_list:
            length_type = np.dtype(byte_order + _NUMPY_CODES[prop.list_length_type])
            steps.append((length_type.itemsize, (length_type, _SCALAR_SIZES[prop.value_type])))
        else:
            steps.append((_SCALAR_SIZES[prop.value_type], None))
    lists = [index for index, (_, kind) in enumerate(steps) if kind is not None]
    remaining = element.count
    if len(lists) == 1:
        # One list per row (faces, range grids): rows whose lists have equal lengths are found in
        # runs, checked together with NumPy; only changes of length cost a step in Python.
        index = lists[0]
        before = sum(size for size, _ in steps[:index])
        after = sum(size for size, _ in steps[index + 1:])
        length_size, (length_type, value_size) = steps[index]
        order = "little" if byte_order == "<" else "big"
        signed = length_type.kind == "i"
        while remaining:
            length = int.from_bytes(blocks.need(position, before + length_size)[before:], order, signed=signed)
            if length < 0:
                raise PointCloudFileError(path, f"malformed PLY data: a negative list length ({length})")
            row = before + length_size + length * value_size + after
            run = min(remaining, max(1, (len(blocks.buffer) - (position - blocks.start)) // row))
            window = blocks.need(position, run * row)
            lengths = np.frombuffer(window, dtype=np.uint8).reshape(run, row)[:, before:before + length_size]
            same = np.frombuffer(lengths.tobytes(), dtype=length_type) == length
            equal = run if same.all() else int(np.argmin(same))
            position += equal * row
            remaining -= equal
            if equal < 8 and remaining:  # lengths change often here: rows one by one, without NumPy
                blocks.need(position, before + length_size)
                position, remaining = _step_rows(path, blocks, position, min(remaining, 4096), remaining,
                                                 before, length_size, value_size, after, order, signed)
        return position
    for _ in range(remaining):  # several lists per row: one step per property (rare)
        for size, kind in steps:
            if kind is None:
                position += size
                continue
            length_type, value_size = kind
            length = int(np.frombuffer(blocks.need(position, size), dtype=length_type)[0])
            if length < 0:
                raise PointCloudFileError(path, f"malformed PLY data: a negative list length ({length})")
            position += size + int(length) * value_size
    return position


def _read_binary(path, handle, header: PlyHeader, needed: list[_Element]) -> np.ndarray:
    """Vertex coordinates of a binary PLY file whose header was checked.

    The elements before the vertices are skipped (fixed-size rows by arithmetic, rows with lists by
    walking their lengths), then the vertex rows are read block by block and only x, y, z kept: the
    memory needed is the result plus one block, whatever the file's other content.
    """
    byte_order = "<" if header.format == "binary_little_endian" else ">"
    vertex = needed[-1]
    if vertex.has_lists:
        # Lists inside the vertex rows (very unusual): let plyfile parse them, from a copy in memory.
        handle.seek(0)
        return _coordinates(_plyfile_read(path, io.BytesIO(handle.read())))
    blocks = _Blocks(path, handle, header.data_bytes)
    position = 0
    for element in needed[:-1]:
        if element.has_lists:
            position = _skip_rows(path, blocks, position, element, byte_order)
        else:
            position += element.count * element.min_binary_row_bytes()
    row_type = np.dtype([(p.name if p.name in ("x", "y", "z") else f"_{i}", byte_order + _NUMPY_CODES[p.value_type])
                         for i, p in enumerate(vertex.properties)])  # x, y, z appear once (checked)
    points = np.empty((vertex.count, 3), dtype=np.float64)
    rows_per_block = max(1, _BLOCK_BYTES // row_type.itemsize)
    with np.errstate(invalid="ignore"):  # a signalling NaN in float32 data: dropped later
        for first in range(0, vertex.count, rows_per_block):
            rows = min(rows_per_block, vertex.count - first)
            table = np.frombuffer(blocks.need(position, rows * row_type.itemsize), dtype=row_type)
            for column, axis in enumerate("xyz"):
                points[first:first + rows, column] = table[axis]
            position += rows * row_type.itemsize
    # The data after the vertices: that of the elements declared after them, and no more (less
    # than one row more is tolerated: a writer's trailing newline).
    after = header.elements[len(needed):]
    for element in after:
        if element.has_lists:
            position = _skip_rows(path, blocks, position, element, byte_order)
        else:
            position += element.count * element.min_binary_row_bytes()
            if position > header.data_bytes:
                raise _changed(path)
    left = header.data_bytes - position
    row = (after[-1] if after else vertex).min_binary_row_bytes()
    if left >= max(row, 1):
        raise _more_than_declared(path, header, vertex, after, f"{left:,} bytes of more data")
    return points


def _more_than_declared(path, header: PlyHeader, vertex: _Element, after: list[_Element], more: str) -> PointCloudFileError:
    """The file holds more data than its header declares: most likely more vertices than it says
    (only the declared ones would be read)."""
    if not after:
        return PointCloudFileError(
            path, f"its header declares {vertex.count} vertices, but {more} follows them: the file holds more "
            f"than it declares (a wrong vertex count?), and only {vertex.count} would be read")
    declared = _shortened([_describe_count(e) for e in header.elements])
    return PointCloudFileError(
        path, f"its header declares {declared}, but {more} follows that data (a wrong count in the header?)")


def _coordinates(data: plyfile.PlyData) -> np.ndarray:
    """The vertex x, y, z of parsed PLY data as a new ``(N, 3)`` float64 array."""
    vertices = data["vertex"].data
    points = np.empty((len(vertices), 3), dtype=np.float64)
    with np.errstate(invalid="ignore"):  # a signalling NaN in float32 data: dropped later
        for column, axis in enumerate("xyz"):
            points[:, column] = vertices[axis]
    return points


def read_ply(path) -> np.ndarray:
    """Read the vertex coordinates of a PLY file (ascii or binary, any scalar coordinate type).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` float64 ``x, y, z`` in the file's own frame and units. Rows may contain NaN; the
        caller filters them.

    Raises
    ------
    PointCloudFileError
        The file is not a PLY file, is truncated, or has no ``vertex`` x/y/z.
    """
    with open(path, "rb") as handle:
        header = read_ply_header(path, handle)
        vertex_index, _ = _vertex_element(path, header)
        needed = header.elements[: vertex_index + 1]
        if header.is_ascii:
            return _read_ascii(path, handle, header, needed)
        return _read_binary(path, handle, header, needed)


def write_ply(handle, points: np.ndarray, *, binary: bool = True, scan_index: np.ndarray | None = None,
              colors: np.ndarray | None = None) -> None:
    """Write ``points`` as the ``vertex`` element (``double x, y, z``) of a PLY file.

    Coordinates are stored as float64 ("double") in both variants, so round trips are exact:
    binary little-endian bytes, or ascii with 17 significant digits.

    Parameters
    ----------
    handle : binary file object
        Open for writing.
    points : numpy.ndarray
        ``(N, 3)`` float64, already validated.
    binary : bool
        ``binary_little_endian`` if True, else ``ascii``.
    scan_index : numpy.ndarray, optional
        ``(N,)`` int32 per point: the vertex property ``int scan_index`` (a scalar field in
        CloudCompare).
    colors : numpy.ndarray, optional
        ``(N, 3)`` uint8 per point: the vertex properties ``uchar red, green, blue`` (the colours
        Open3D, CloudCompare and MeshLab show).
    """
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if scan_index is not None:
        fields.append(("scan_index", "<i4"))
    vertices = np.empty(len(points), dtype=fields)
    vertices["x"], vertices["y"], vertices["z"] = points[:, 0], points[:, 1], points[:, 2]
    if colors is not None:
        vertices["red"], vertices["green"], vertices["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    if scan_index is not None:
        vertices["scan_index"] = scan_index
    element = plyfile.PlyElement.describe(vertices, "vertex")
    data = plyfile.PlyData([element], text=not binary, byte_order="<", comments=["written by esmicp"])
    if binary:
        data.write(handle)
        return
    # plyfile's own ascii writer formats every row with a separate numpy.savetxt call (about 15x
    # slower); write its header, then all rows at once with the same round-trip precision.
    handle.write((data.header + "\n").encode("ascii"))
    if len(fields) == 3:
        np.savetxt(handle, points, fmt="%.17g", delimiter=" ")
        return
    np.savetxt(handle, vertices, fmt=["%.17g"] * 3 + ["%d"] * (len(fields) - 3), delimiter=" ")
