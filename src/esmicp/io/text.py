"""Plain-text point clouds: ``.xyz``, ``.txt``, ``.csv``, ``.pts``.

One point per line; the first three columns are ``x y z`` and further columns (normals,
intensity, colour, ...) are ignored, so ModelNet's ``x,y,z,nx,ny,nz`` rows work. Columns may be
separated by commas, spaces, tabs or semicolons. Blank lines and comment lines starting with ``#``
or ``//`` are skipped. A single leading line holding one integer equal to the number of points
that follow (Go-ICP, ``.pts``) is skipped, as is a leading ``x y z ...`` column-name line. A line
that mixes commas and semicolons (a decimal-comma export such as ``0,125;-0,132;0,640``) is
refused: its commas are decimal marks, not separators.

The file is read in blocks of :data:`BLOCK_BYTES` and parsed block by block, so memory follows the
points the file holds, not its size on disk (binary data, e.g. a sparse tail of NUL bytes, is
refused at its first block).
"""

from __future__ import annotations

import codecs

import numpy as np

from ..errors import PointCloudFileError
from ._messages import excerpt

__all__ = ["BLOCK_BYTES", "read_text", "read_text_file", "text_lines", "write_text"]

_SEPARATORS = str.maketrans({",": " ", ";": " ", "\t": " "})
#: Bytes read (and checked for binary data) at a time.
BLOCK_BYTES = 1 << 20
#: What str.splitlines() splits on.
_LINE_ENDS = "\r\n\v\f\x1c\x1d\x1e\x85\u2028\u2029"
#: Longest line a text cloud may have (a row of numbers is far shorter).
MAX_LINE_CHARS = 1 << 20
#: Lines parsed into numbers at a time.
_LINES_PER_BATCH = 1 << 16
#: A count line longer than this is not a count anyone meant (and ``int`` refuses > 4300 digits).
_MAX_COUNT_DIGITS = 18


def _not_utf8(path, offset: int) -> PointCloudFileError:
    return PointCloudFileError(path, f"not a text file: byte {offset} is not valid UTF-8 text")


def _decoded_blocks(path, max_bytes: int | None = None):
    """The text of ``path`` as decoded UTF-8 pieces, one block at a time.

    Raises PointCloudFileError as soon as a block holds binary data (NUL bytes) or invalid UTF-8,
    or when the file grows beyond ``max_bytes``.
    """
    decoder = codecs.getincrementaldecoder("utf-8-sig")()
    offset = 0
    with open(path, "rb") as handle:
        while True:
            block = handle.read(BLOCK_BYTES)
            if not block:
                break
            if max_bytes is not None and offset + len(block) > max_bytes:
                raise PointCloudFileError(path, f"too large: more than {max_bytes} bytes for this kind of file")
            if b"\x00" in block:
                raise PointCloudFileError(path, "not a text file: it contains binary data (NUL bytes)")
            pending = len(decoder.getstate()[0])
            try:
                yield decoder.decode(block)
            except UnicodeDecodeError as exc:
                raise _not_utf8(path, offset - pending + exc.start) from None
            offset += len(block)
        if offset == 0:
            raise PointCloudFileError(path, "file is empty")
        try:
            yield decoder.decode(b"", final=True)
        except UnicodeDecodeError as exc:
            raise _not_utf8(path, offset - len(decoder.getstate()[0]) + exc.start) from None


def text_lines(path, max_bytes: int | None = None):
    """The lines of the text file ``path`` (without line ends), read block by block.

    Lines are split as :meth:`str.splitlines` splits them; see :func:`read_text_file` for what is
    refused.
    """
    carry = ""
    count = 0
    for piece in _decoded_blocks(path, max_bytes):
        lines = (carry + piece).splitlines(keepends=True)
        carry = ""
        if lines and (lines[-1].endswith("\r") or lines[-1] == lines[-1].rstrip(_LINE_ENDS)):
            carry = lines.pop()  # unfinished, or a "\r" whose "\n" may start the next piece
            if len(carry) > MAX_LINE_CHARS:
                raise PointCloudFileError(
                    path, f"line {count + len(lines) + 1} is longer than {MAX_LINE_CHARS} characters: not a point list"
                )
        count += len(lines)
        for line in lines:
            yield line.rstrip(_LINE_ENDS)
    yield from carry.splitlines()


def read_text_file(path, max_bytes: int | None = None) -> str:
    """Return the content of the text file ``path``.

    Parameters
    ----------
    path : str or os.PathLike
    max_bytes : int, optional
        Refuse a file larger than this (checked while reading, so a device or a growing file is
        cut off there).

    Raises
    ------
    PointCloudFileError
        The file is empty, holds binary data (NUL bytes), is not UTF-8 text, or is larger than
        ``max_bytes``.
    """
    return "".join(_decoded_blocks(path, max_bytes))


def _is_comment(line: str) -> bool:
    return line.startswith(("#", "//"))


def _is_count_line(words: list[str]) -> bool:
    # ASCII digits only: str.isdigit() also accepts '³' and other digits int() refuses.
    return len(words) == 1 and words[0].isascii() and words[0].isdigit()


def _first_bad_value(path, rows: list[list[str]], line_numbers: list[int]) -> PointCloudFileError:
    for words, line_number in zip(rows, line_numbers):
        for column, word in enumerate(words[:3], start=1):
            try:
                float(word)
            except ValueError:
                return PointCloudFileError(
                    path, f"line {line_number}, column {column}: {excerpt(word, 30)} is not a number"
                )
    return PointCloudFileError(path, "could not read the coordinates as numbers")  # pragma: no cover


def _decimal_comma(path, line_number: int, line: str) -> PointCloudFileError:
    return PointCloudFileError(
        path,
        f"line {line_number} mixes commas and semicolons ({excerpt(line, 40)}): a decimal-comma export? "
        "Write the numbers with '.' as the decimal mark",
    )


class _Rows:
    """Numeric rows of a text cloud, parsed batch by batch."""

    def __init__(self, path):
        self.path = path
        self.columns = None
        self.first_line = None
        self.words: list[list[str]] = []
        self.numbers: list[int] = []
        self.arrays: list[np.ndarray] = []
        self.count = 0

    def add(self, words: list[str], line_number: int) -> None:
        if self.columns is None:
            self.columns, self.first_line = len(words), line_number
            if self.columns < 3:
                raise PointCloudFileError(
                    self.path, f"expected at least 3 columns (x y z), found {self.columns} on line {line_number}"
                )
        elif len(words) != self.columns:
            raise PointCloudFileError(
                self.path,
                f"line {line_number} has {len(words)} columns, but line {self.first_line} has "
                f"{self.columns} (truncated or malformed row)",
            )
        self.words.append(words[:3])
        self.numbers.append(line_number)
        self.count += 1
        if len(self.words) >= _LINES_PER_BATCH:
            self.flush()

    def flush(self) -> None:
        if not self.words:
            return
        try:
            self.arrays.append(np.array(self.words, dtype=np.float64))
        except (ValueError, TypeError, OverflowError):
            raise _first_bad_value(self.path, self.words, self.numbers) from None
        self.words, self.numbers = [], []

    def points(self) -> np.ndarray:
        self.flush()
        if len(self.arrays) == 1:
            return self.arrays[0]
        return np.concatenate(self.arrays) if self.arrays else np.empty((0, 3))


def read_text(path) -> np.ndarray:
    """Read the first three columns of a text point-cloud file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` float64 ``x, y, z`` in the file's own frame and units (NaN rows kept; the caller
        drops them).

    Raises
    ------
    PointCloudFileError
        Not text, no points, fewer than three columns, rows with different numbers of columns,
        non-numeric coordinates, commas mixed with semicolons (decimal commas), or a count line
        that disagrees with the number of rows.
    """
    rows = _Rows(path)
    first = True
    declared = None  # (count as text, its line number) when the first line is a count line
    for line_number, line in enumerate(text_lines(path), start=1):
        stripped = line.strip()
        if not stripped or _is_comment(stripped):
            continue
        if ";" in stripped and "," in stripped:
            raise _decimal_comma(path, line_number, stripped)
        words = stripped.translate(_SEPARATORS).split()
        if first:
            first = False
            if _is_count_line(words):
                declared = (words[0], line_number)
                continue
            if [word.lower() for word in words[:3]] == ["x", "y", "z"]:
                continue
        rows.add(words, line_number)
    if first:
        raise PointCloudFileError(path, "contains no points (only blank or comment lines)")
    if declared is not None:
        digits, line_number = declared
        if len(digits) > _MAX_COUNT_DIGITS or int(digits) != rows.count:
            says = digits if len(digits) <= _MAX_COUNT_DIGITS else f"a {len(digits)}-digit number of"
            raise PointCloudFileError(
                path,
                f"the count line (line {line_number}) says {says} points, but "
                f"{rows.count} rows of coordinates follow (truncated or wrong count?)",
            )
    if rows.count == 0:
        raise PointCloudFileError(path, "contains no points")
    return rows.points()


def write_text(handle, points: np.ndarray, *, delimiter: str = " ") -> None:
    """Write ``points`` one per line, ``x y z`` with 17 significant digits (exact float64 round trip).

    Parameters
    ----------
    handle : binary file object
        Open for writing.
    points : numpy.ndarray
        ``(N, 3)`` float64, already validated.
    delimiter : str
        Column separator: ``","`` for ``.csv``, ``" "`` otherwise.
    """
    np.savetxt(handle, points, fmt="%.17g", delimiter=delimiter)
