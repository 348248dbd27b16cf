"""NumPy ``.npy`` point clouds: an ``(N, 3)`` numeric array, or a structured array with x, y, z fields."""

from __future__ import annotations

import os
import warnings

import numpy as np

from ..errors import PointCloudFileError
from ._messages import excerpt, one_line

__all__ = ["read_npy", "write_npy"]


def _read_npy_header(path, handle) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Read and check the ``.npy`` header; return (shape, fortran_order, dtype)."""
    try:
        version = np.lib.format.read_magic(handle)
    except ValueError:
        raise PointCloudFileError(
            path, "not a .npy file: it does not start with the NumPy magic bytes"
        ) from None
    try:
        with warnings.catch_warnings():
            # NumPy warns about quirks of a header it still reads (deprecated type aliases, Python 2
            # headers, escape sequences): they are not the user's concern.
            warnings.simplefilter("ignore")
            if version == (1, 0):
                return np.lib.format.read_array_header_1_0(handle)
            if version == (2, 0):
                return np.lib.format.read_array_header_2_0(handle)
        # Version 3.0 (utf-8 field names): there is no public reader for it, np.load checks it.
        raise PointCloudFileError(path, f"unsupported .npy format version {version[0]}.{version[1]}")
    except PointCloudFileError:
        raise
    except Exception as exc:  # noqa: BLE001 - ValueError, SyntaxError, ... from a corrupt header
        raise PointCloudFileError(path, f"corrupt .npy header: {one_line(exc, 160)}") from None


def read_npy(path) -> np.ndarray:
    """Read points from a ``.npy`` file (never unpickles: object arrays are refused).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` float64 in the file's own frame and units (NaN rows kept; the caller drops them).

    Raises
    ------
    PointCloudFileError
        Not a .npy file, truncated, a pickled object array, or not an ``(N, 3)`` numeric array /
        a structured array with ``x``, ``y``, ``z`` fields.
    """
    with open(path, "rb") as handle:
        handle.seek(0, os.SEEK_END)
        file_size = handle.tell()
        handle.seek(0)
        shape, _, dtype = _read_npy_header(path, handle)
        data_bytes = file_size - handle.tell()
    if dtype.hasobject:
        raise PointCloudFileError(
            path,
            "holds Python objects (a pickled array), which are not loaded for safety; save a numeric array",
        )
    needed = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if needed > data_bytes:
        raise PointCloudFileError(
            path,
            f"truncated or corrupt .npy file: its header declares shape {one_line(str(shape), 40)} of "
            f"{one_line(str(dtype), 40)}, which needs "
            f"{needed} bytes, but only {data_bytes} bytes of data follow the header",
        )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the header quirks again (see _read_npy_header)
            array = np.load(path, allow_pickle=False)
    except MemoryError:
        raise PointCloudFileError(path, ".npy file is too large to load into memory") from None
    except Exception as exc:  # noqa: BLE001 - ValueError (pickled / truncated), OSError, EOFError
        raise PointCloudFileError(path, f"could not read .npy data: {one_line(exc, 160)}") from None

    if array.dtype.names:
        missing = [axis for axis in "xyz" if axis not in array.dtype.names]
        if missing:
            raise PointCloudFileError(
                path,
                f"structured array has no {'/'.join(missing)} field (fields: {excerpt(', '.join(array.dtype.names), 60)})",
            )
        if array.ndim != 1:
            array = array.reshape(-1)
        columns = [array[axis] for axis in "xyz"]
        if any(column.ndim != 1 or not _is_real(column.dtype) for column in columns):
            raise PointCloudFileError(path, "structured array fields x, y, z must be plain numbers")
        with np.errstate(invalid="ignore"):  # a signalling NaN in float32 data: dropped later
            return np.stack(columns, axis=1).astype(np.float64)
    if not _is_real(array.dtype):
        raise PointCloudFileError(path, f"expected numeric (real) coordinates, got dtype {array.dtype}")
    if array.ndim != 2 or array.shape[1] != 3:
        raise PointCloudFileError(path, f"expected an (N, 3) array of points, got shape {array.shape}")
    with np.errstate(invalid="ignore"):  # a signalling NaN in float32 data: dropped later
        return array.astype(np.float64)


def _is_real(dtype: np.dtype) -> bool:
    return dtype.kind in "iuf"


def write_npy(handle, points: np.ndarray) -> None:
    """Write ``points`` as an ``(N, 3)`` float64 ``.npy`` array (exact round trip).

    Parameters
    ----------
    handle : binary file object
        Open for writing.
    points : numpy.ndarray
        ``(N, 3)`` float64, already validated.
    """
    np.save(handle, np.ascontiguousarray(points, dtype=np.float64), allow_pickle=False)
