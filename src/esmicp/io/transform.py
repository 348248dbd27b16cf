"""4x4 rigid transforms as text: four rows of four numbers, row-major.

Transforms are ``T_target_source`` (they map source coordinates into the target frame), in the
clouds' units. Written with 17 significant digits, so a write/read round trip is exact.
"""

from __future__ import annotations

import stat
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError, PointCloudFileError, PointCloudFileNotFoundError
from ..types import as_transform
from ._files import as_path
from ._messages import excerpt
from .atomic import atomic_write
from .text import read_text_file

__all__ = ["MAX_TRANSFORM_BYTES", "read_transform", "write_transform"]

_SEPARATORS = str.maketrans({",": " ", ";": " ", "\t": " ", "[": " ", "]": " "})


def _problem(exc: InvalidInputError, name: str) -> str:
    """The message of ``exc`` without its leading ``name: `` (PointCloudFileError adds the path)."""
    return str(exc).removeprefix(f"{name}: ")


#: Largest transform file read: 16 numbers with comments fit in far less. A bigger "transform" is
#: not one (a link to /dev/zero, a point cloud given by mistake) and is refused unread.
MAX_TRANSFORM_BYTES = 64 * 1024


def _check_readable(path: Path) -> None:
    """Refuse a missing, non-regular (FIFO, device: reading one may block forever or never end) or
    oversized file before opening it."""
    try:
        info = path.stat()
    except FileNotFoundError:
        raise PointCloudFileNotFoundError(path) from None
    except NotADirectoryError:
        raise PointCloudFileNotFoundError(path, "no such file (a part of the path is not a folder)") from None
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot access: {exc.strerror or exc}") from None
    if stat.S_ISDIR(info.st_mode):
        raise PointCloudFileError(path, "is a directory, not a file")
    if not stat.S_ISREG(info.st_mode):
        raise PointCloudFileError(path, "is not a regular file")
    if info.st_size > MAX_TRANSFORM_BYTES:
        raise PointCloudFileError(
            path, f"too large for a 4x4 transform: {info.st_size} bytes (at most {MAX_TRANSFORM_BYTES})"
        )


def read_transform(path) -> np.ndarray:
    """Read a 4x4 rigid transform from a text file.

    Numbers may be separated by spaces, tabs, commas or semicolons (brackets are ignored); blank
    lines and lines starting with ``#`` or ``//`` are skipped. The 16 numbers are read row-major.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    numpy.ndarray
        4x4 float64 homogeneous matrix, checked rigid (see :func:`esmicp.types.as_transform`).

    Raises
    ------
    PointCloudFileError
        The file is missing, not a regular file (a FIFO, a device), larger than
        :data:`MAX_TRANSFORM_BYTES`, unreadable, does not hold exactly 16 numbers, or the matrix is
        not a rigid transform.
    """
    path = as_path(path)
    _check_readable(path)
    try:
        text = read_text_file(path, max_bytes=MAX_TRANSFORM_BYTES)  # the cap again: it may grow
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot read: {exc.strerror or exc}") from None
    words: list[str] = []
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped or stripped.startswith(("#", "//")):
            continue
        words.extend(stripped.translate(_SEPARATORS).split())
    if len(words) != 16:
        raise PointCloudFileError(
            path, f"expected a 4x4 transform (16 numbers, row-major), found {len(words)} values"
        )
    try:
        values = [float(word) for word in words]
    except ValueError:
        bad = next(word for word in words if not _is_number(word))
        raise PointCloudFileError(path, f"{excerpt(bad, 30)} is not a number") from None
    try:
        return as_transform(np.array(values).reshape(4, 4), name=str(path))
    except InvalidInputError as exc:
        raise PointCloudFileError(path, _problem(exc, str(path))) from None


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def write_transform(path, T, *, overwrite: bool = False) -> None:
    """Write a 4x4 rigid transform as text: four rows, 17 significant digits, space-separated.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; written atomically.
    T : array_like
        4x4 rigid transform ``T_target_source``.
    overwrite : bool
        Replace an existing file.

    Raises
    ------
    InvalidInputError
        ``T`` is not a 4x4 rigid transform (nothing is written).
    OutputExistsError
        ``path`` exists and ``overwrite`` is False.
    PointCloudFileError
        The file cannot be written.
    """
    path = as_path(path)
    matrix = as_transform(T, name="T")
    text = "".join(" ".join(f"{value:.17g}" for value in row) + "\n" for row in matrix)
    with atomic_write(path, overwrite, mode="w") as handle:
        handle.write(text)
