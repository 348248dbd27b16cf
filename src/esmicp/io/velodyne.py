"""Headerless float32 ``.bin`` scans: KITTI velodyne files and their 3-column cousins.

A KITTI velodyne scan is a bare sequence of little-endian float32 records, 4 per point:
``x y z intensity`` (16 bytes a point). Other datasets ship the same kind of file with 3 columns,
``x y z`` (12 bytes a point). The file says nothing about which, so the layout comes from
``columns`` or, when not given, from the file's size:

- a size that is a multiple of 16 bytes but not of 12: 4 columns (KITTI's layout);
- a multiple of 12 but not of 16: 3 columns;
- a multiple of both (of 48 bytes): **ambiguous**, refused: the reader does not guess, since
  either guess silently gives garbage points when wrong; say ``columns=3`` or ``4``;
- a multiple of neither, or a size that does not fit the ``columns`` given: refused (a truncated or
  not-a-scan file).

Only ``x y z`` are returned; further columns (intensity) are ignored. Memory: the file is read
once, its size on disk bounds what is allocated.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import InvalidInputError, PointCloudFileError

__all__ = ["COLUMN_CHOICES", "bin_columns", "read_bin"]

#: Layouts a ``.bin`` scan can have: floats per point.
COLUMN_CHOICES = (3, 4)
_FLOAT_BYTES = 4


def bin_columns(columns) -> int | None:
    """``columns`` checked: None (from the size) or one of :data:`COLUMN_CHOICES`."""
    if columns is None:
        return None
    if isinstance(columns, (bool, np.bool_)) or not isinstance(columns, (int, np.integer)) or int(columns) not in COLUMN_CHOICES:
        raise InvalidInputError(f"bin_columns: expected 3 (x y z) or 4 (x y z intensity, KITTI), got {columns!r}")
    return int(columns)


def _layout(path, size: int, columns: int | None) -> int:
    """The number of float32 columns of a ``size``-byte file, or one clear error."""
    fits = [count for count in COLUMN_CHOICES if size % (count * _FLOAT_BYTES) == 0]
    if columns is not None:
        if columns not in fits:
            other = [count for count in fits if count != columns]
            hint = f"; it fits {other[0]} columns: pass bin_columns={other[0]} (--bin-columns {other[0]})" if other else ""
            raise PointCloudFileError(
                path,
                f"size {size} bytes is not a whole number of {columns}-column float32 points "
                f"({columns * _FLOAT_BYTES} bytes each): truncated or not a float32 scan{hint}",
            )
        return columns
    if not fits:
        raise PointCloudFileError(
            path,
            f"size {size} bytes fits neither 3-column (x y z, 12 bytes a point) nor 4-column "
            "(x y z intensity, 16 bytes a point) float32 points: truncated or not a float32 scan",
        )
    if len(fits) > 1:
        raise PointCloudFileError(
            path,
            f"size {size} bytes fits both 3-column (x y z) and 4-column (x y z intensity, KITTI) float32 "
            "points; say which: bin_columns=3 or 4 (--bin-columns 3 or 4)",
        )
    return fits[0]


def read_bin(path, columns: int | None = None) -> np.ndarray:
    """Read ``x y z`` from a headerless float32 ``.bin`` scan (see the module docstring).

    Parameters
    ----------
    path : str or os.PathLike
    columns : {3, 4}, optional
        Floats per point; None takes the layout from the file size and refuses an ambiguous one.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` float64 (NaN rows kept; the caller drops them).

    Raises
    ------
    PointCloudFileError
        The size fits neither layout, does not fit ``columns``, or fits both and ``columns`` is None.
    """
    columns = bin_columns(columns)
    size = os.stat(path).st_size
    count = _layout(path, size, columns)
    data = np.fromfile(path, dtype="<f4")
    if data.size * _FLOAT_BYTES != size:  # the file changed while being read
        raise PointCloudFileError(path, f"changed while being read: expected {size} bytes, read {data.size * _FLOAT_BYTES}")
    with np.errstate(invalid="ignore"):  # a signalling NaN: dropped later
        return data.reshape(-1, count)[:, :3].astype(np.float64)
