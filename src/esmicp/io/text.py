"""Plain-text point clouds: ``.xyz``, ``.txt``, ``.csv``, ``.pts``.

One point per line; the first three columns are ``x y z`` and further columns (normals,
intensity, colour, ...) are ignored, so ModelNet's ``x,y,z,nx,ny,nz`` rows work. Columns may be
separated by commas, spaces, tabs or semicolons. Blank lines and comment lines starting with ``#``
or ``//`` are skipped. A single leading line holding one integer equal to the number of points
that follow (Go-ICP, ``.pts``) is skipped, as is a leading ``x y z ...`` column-name line.
"""

from __future__ import annotations

import numpy as np

from ..errors import PointCloudFileError
from ._messages import excerpt

__all__ = ["read_text", "read_text_file", "write_text"]

_SEPARATORS = str.maketrans({",": " ", ";": " ", "\t": " "})


def read_text_file(path) -> str:
    """Return the content of the text file ``path``.

    Raises
    ------
    PointCloudFileError
        The file is empty, holds binary data (NUL bytes), or is not UTF-8 text.
    """
    with open(path, "rb") as handle:
        data = handle.read()
    if not data:
        raise PointCloudFileError(path, "file is empty")
    if b"\x00" in data:
        raise PointCloudFileError(path, "not a text file: it contains binary data (NUL bytes)")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise PointCloudFileError(
            path, f"not a text file: byte {exc.start} is not valid UTF-8 text"
        ) from None


def _is_comment(line: str) -> bool:
    return line.startswith(("#", "//"))


def _is_count_line(words: list[str]) -> bool:
    return len(words) == 1 and words[0].isdigit()


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
        non-numeric coordinates, or a count line that disagrees with the number of rows.
    """
    text = read_text_file(path)
    rows: list[list[str]] = []
    line_numbers: list[int] = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or _is_comment(stripped):
            continue
        rows.append(stripped.translate(_SEPARATORS).split())
        line_numbers.append(line_number)
    if not rows:
        raise PointCloudFileError(path, "contains no points (only blank or comment lines)")

    if _is_count_line(rows[0]):
        declared = int(rows[0][0])
        if declared != len(rows) - 1:
            raise PointCloudFileError(
                path,
                f"the count line (line {line_numbers[0]}) says {declared} points, but "
                f"{len(rows) - 1} rows of coordinates follow (truncated or wrong count?)",
            )
        rows, line_numbers = rows[1:], line_numbers[1:]
    elif [word.lower() for word in rows[0][:3]] == ["x", "y", "z"]:
        rows, line_numbers = rows[1:], line_numbers[1:]
    if not rows:
        raise PointCloudFileError(path, "contains no points")

    columns = len(rows[0])
    if columns < 3:
        raise PointCloudFileError(
            path, f"expected at least 3 columns (x y z), found {columns} on line {line_numbers[0]}"
        )
    for words, line_number in zip(rows, line_numbers):
        if len(words) != columns:
            raise PointCloudFileError(
                path,
                f"line {line_number} has {len(words)} columns, but line {line_numbers[0]} has "
                f"{columns} (truncated or malformed row)",
            )
    try:
        return np.array([words[:3] for words in rows], dtype=np.float64)
    except (ValueError, TypeError, OverflowError):
        raise _first_bad_value(path, rows, line_numbers) from None


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
