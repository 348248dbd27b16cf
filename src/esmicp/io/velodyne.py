"""Headerless float32 ``.bin`` scans: KITTI velodyne files and their 3-column cousins.

A KITTI velodyne scan is a bare sequence of little-endian float32 records, 4 per point:
``x y z intensity`` (16 bytes a point). Other datasets ship the same kind of file with 3 columns,
``x y z`` (12 bytes a point). The file's header says nothing about which, so the layout comes from
``columns`` or, when not given, from the file's size and values:

- a size that is a multiple of 16 bytes but not of 12: 4 columns (KITTI's layout);
- a multiple of 12 but not of 16: 3 columns;
- a multiple of both (of 48 bytes): the values tell the layouts apart when only one is plausible
  (:func:`layout_from_values`); when both are (too few points, or columns that look alike either
  way, such as an isotropic blob), refused: the reader does not guess, since a wrong guess gives
  garbage points; say ``columns=3`` or ``4``;
- a multiple of neither, or a size that does not fit the ``columns`` given: refused (a truncated or
  not-a-scan file).

Only ``x y z`` are returned; further columns (intensity) are ignored. Memory: the file is read
once, its size on disk bounds what is allocated.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from ..errors import InvalidInputError, PointCloudFileError

logger = logging.getLogger(__name__)

__all__ = ["COLUMN_CHOICES", "bin_columns", "layout_from_values", "read_bin"]

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


#: A file read with the wrong number of columns shifts by one value every row, so each column it
#: shows cycles through the file's real columns (x, y, z, intensity): its columns all hold the same
#: mixture of values, while the rows of one phase (row index modulo the other layout's column
#: count) hold one real column and those of another phase another. Read with the right count,
#: the columns differ (a scan's x, y, z and intensity span different ranges) and the phases agree.
#: :func:`layout_from_values` measures both with the Kolmogorov-Smirnov distance (0-1) between the
#: values' distributions. Chosen on the 5 Newer College scans (3 columns, and 4 with a fourth
#: column of uniform [0, 1], zero, 8-bit, range or ring values appended; whole, and the first 8,000
#: and 2,000 points; in file order and shuffled: 180 readings): a misread layout's columns lay
#: within 0.04 of each other and its phases at least 0.41 apart; a right layout's columns at least
#: 0.40 apart and its phases within 0.12. Confirmed on the 2 KITTI scans read the same 36 ways
#: each (misread: columns within 0.04, phases at least 0.47 apart; right: columns at least 0.47
#: apart, phases within 0.11): every reading told apart, none wrong. A misread layout's columns lie
#: within this distance:
COLUMNS_ALIKE = 0.2
#: ... and its phases at least this far apart (see :data:`COLUMNS_ALIKE`).
PHASES_DIFFER = 0.25
#: A layout whose x, y or z column spans more than this ratio between the 95th and the 5th
#: percentile of its nonzero magnitudes does not hold coordinates (the low halves of float64
#: numbers read as float32 span about 70 orders of magnitude; the coordinates of the Newer College
#: and KITTI scans at most 2.7 in either reading).
MAX_MAGNITUDE_SPAN = 1e6
#: Fewest points (read as 3 columns) from which the values are read to tell the layouts apart:
#: with fewer, the phases of a right layout differ by chance by up to about 0.3 (an isotropic
#: Gaussian cloud of 240 points), so the test cannot speak and the file is refused.
LAYOUT_MIN_POINTS = 2_000
#: At most this many blocks of 12 floats (4 points of 3 columns, 3 of 4), evenly spread over the
#: file, are compared: the test adds about 15 ms to the reading of a Newer College or a KITTI scan
#: (1.3 and 27 ms told the layout, on a loaded 2-core machine), whatever the scan's size; the
#: readings above, the 2,000-point ones included, come out the same with 4,000 blocks.
LAYOUT_SAMPLE_BLOCKS = 1_500
_BLOCK_FLOATS = 12  # the least common multiple of 3 and 4: a block starts a row of either layout


def _distribution_distance(a: np.ndarray, b: np.ndarray) -> float:
    """The Kolmogorov-Smirnov distance (0-1) between the finite values of ``a`` and of ``b``: the
    largest gap between their empirical cumulative distributions (1 when either has none)."""
    a, b = np.sort(a[np.isfinite(a)]), np.sort(b[np.isfinite(b)])
    if not len(a) or not len(b):
        return 1.0
    values = np.concatenate([a, b])
    gap = np.searchsorted(a, values, side="right") / len(a) - np.searchsorted(b, values, side="right") / len(b)
    return float(np.abs(gap).max())


def _looks_misread(rows: np.ndarray, other: int) -> bool:
    """True when ``rows`` (one layout's reading) bears the mark of a misread file: every two of
    its columns alike (within :data:`COLUMNS_ALIKE`) and, within some column, two phases of its
    rows (row index modulo ``other``, the other layout's column count) apart (at least
    :data:`PHASES_DIFFER`)."""
    count = rows.shape[1]  # each test stops at its first decisive pair
    alike = all(_distribution_distance(rows[:, a], rows[:, b]) <= COLUMNS_ALIKE
                for a in range(count) for b in range(a + 1, count))
    return alike and any(_distribution_distance(rows[r::other, c], rows[s::other, c]) >= PHASES_DIFFER
                         for c in range(count) for r in range(other) for s in range(r + 1, other))


def _holds_coordinates(rows: np.ndarray) -> bool:
    """True when each of the first three columns of ``rows`` is mostly finite and its nonzero
    magnitudes span at most :data:`MAX_MAGNITUDE_SPAN` (5th to 95th percentile)."""
    for column in rows[:, :3].T:
        magnitude = np.abs(column[np.isfinite(column)])
        if len(magnitude) < len(column) / 2:
            return False
        magnitude = magnitude[magnitude > 0]
        if len(magnitude):
            low, high = np.percentile(magnitude, [5, 95])
            if high > MAX_MAGNITUDE_SPAN * low:
                return False
    return True


def layout_from_values(values: np.ndarray) -> int | None:
    """The number of columns (3 or 4) of a headerless float32 scan whose size fits both, told from
    its ``values`` (the file's floats in order), or None when they cannot tell.

    A layout is plausible when it does not bear the mark of a misread file (see
    :data:`COLUMNS_ALIKE`: its columns all alike while its rows change with their phase) and its
    x, y, z look like coordinates (mostly finite, within :data:`MAX_MAGNITUDE_SPAN`). The one
    plausible layout is returned; None when both are (an isotropic cloud, whose x, y and z look
    alike, reads the same either way) or neither is, or when the file holds fewer than
    :data:`LAYOUT_MIN_POINTS` points.
    """
    blocks = values.size // _BLOCK_FLOATS
    if blocks * 4 < LAYOUT_MIN_POINTS:
        return None
    sample = values[: blocks * _BLOCK_FLOATS].reshape(blocks, _BLOCK_FLOATS)
    if blocks > LAYOUT_SAMPLE_BLOCKS:  # whole blocks: each still starts a row of either layout
        sample = sample[np.linspace(0, blocks - 1, LAYOUT_SAMPLE_BLOCKS).astype(np.int64)]
    with np.errstate(invalid="ignore"):
        sample = sample.astype(np.float64)
    plausible = [count for count in COLUMN_CHOICES if _holds_coordinates(sample.reshape(-1, count))
                 and not _looks_misread(sample.reshape(-1, count), 7 - count)]
    return plausible[0] if len(plausible) == 1 else None


def _layout(path, size: int, columns: int | None) -> int | None:
    """The number of float32 columns of a ``size``-byte file (None: it fits both, the values must
    tell), or one clear error."""
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
    return fits[0] if len(fits) == 1 else None


def read_bin(path, columns: int | None = None) -> np.ndarray:
    """Read ``x y z`` from a headerless float32 ``.bin`` scan (see the module docstring).

    Parameters
    ----------
    path : str or os.PathLike
    columns : {3, 4}, optional
        Floats per point; None takes the layout from the file size, or, when it fits both, from the
        values (:func:`layout_from_values`), and refuses a file whose values cannot tell.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` float64 (NaN rows kept; the caller drops them).

    Raises
    ------
    PointCloudFileError
        The size fits neither layout, does not fit ``columns``, or fits both, ``columns`` is None
        and the values do not tell the layouts apart.
    """
    columns = bin_columns(columns)
    size = os.stat(path).st_size
    count = _layout(path, size, columns)
    data = np.fromfile(path, dtype="<f4")
    if data.size * _FLOAT_BYTES != size:  # the file changed while being read
        raise PointCloudFileError(path, f"changed while being read: expected {size} bytes, read {data.size * _FLOAT_BYTES}")
    if count is None:
        count = layout_from_values(data)
        if count is None:
            points = data.size // 3
            why = (f"{points:,} points are too few to tell them apart by their values (from {LAYOUT_MIN_POINTS:,})"
                   if points < LAYOUT_MIN_POINTS else "its values read as points either way (or neither way)")
            raise PointCloudFileError(
                path,
                f"size {size} bytes fits both 3-column (x y z) and 4-column (x y z intensity, KITTI) float32 "
                f"points, and {why}; say which: bin_columns=3 or 4 (--bin-columns 3 or 4)",
            )
        logger.info("%s: read as %d float32 columns (its size fits 3 and 4; its values fit %d only)", path, count, count)
    with np.errstate(invalid="ignore"):  # a signalling NaN: dropped later
        return data.reshape(-1, count)[:, :3].astype(np.float64)
