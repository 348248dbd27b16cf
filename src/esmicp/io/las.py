"""LAS / LAZ point clouds (the format LiDAR surveys ship in), through laspy.

The points' scaled coordinates (``X * scale + offset``) are returned as float64, in the file's
own coordinate system and units; every other dimension (intensity, classification, GPS time,
colour) is ignored. LAZ needs a decompression backend: ``pip install 'esmicp[las]'`` installs
laspy with lazrs.

Memory: an uncompressed file's header is checked against its size before any point is read (a
header declaring more points than the file holds is refused as truncated); points are read in
chunks of :data:`CHUNK_POINTS`, so what is allocated follows the points actually present, not
the count a (possibly corrupt) header declares.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import MissingDependencyError, PointCloudFileError
from ._messages import one_line

__all__ = ["CHUNK_POINTS", "LAS_INSTALL_HINT", "read_las"]

#: Points decoded at a time.
CHUNK_POINTS = 1 << 20
LAS_INSTALL_HINT = "pip install 'esmicp[las]' (laspy with the lazrs LAZ backend)"


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


def read_las(path) -> np.ndarray:
    """Read the scaled ``x, y, z`` of every point of a LAS / LAZ file.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` float64 (NaN rows kept; the caller drops them).

    Raises
    ------
    PointCloudFileError
        Not a LAS file (bad signature or header), truncated, or corrupt compressed data.
    MissingDependencyError
        laspy (or, for compressed points, a LAZ backend) is not installed.
    """
    laspy = _laspy(path)
    size = os.stat(path).st_size
    chunks = []
    stage = "not a valid LAS / LAZ file"
    try:
        with laspy.open(path) as reader:
            header = reader.header
            count = int(header.point_count)
            if header.are_points_compressed:
                _check_laz_backend(path, laspy)
            else:
                needed = int(header.offset_to_point_data) + count * int(header.point_format.size)
                if needed > size:
                    raise PointCloudFileError(
                        path,
                        f"truncated LAS file: its header declares {count} points of {header.point_format.size} "
                        f"bytes from byte {header.offset_to_point_data}, which needs {needed} bytes, but the file "
                        f"has {size}",
                    )
            stage = f"corrupt or truncated {'LAZ' if header.are_points_compressed else 'LAS'} point data"
            read = 0
            for chunk in reader.chunk_iterator(CHUNK_POINTS):
                block = np.empty((len(chunk), 3), dtype=np.float64)
                block[:, 0] = chunk.x
                block[:, 1] = chunk.y
                block[:, 2] = chunk.z
                chunks.append(block)
                read += len(block)
    except (PointCloudFileError, MissingDependencyError):
        raise
    except MemoryError:
        raise PointCloudFileError(path, "too large to load into memory") from None
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot read: {exc.strerror or exc}") from None
    except Exception as exc:  # noqa: BLE001 - laspy / lazrs errors of a corrupt file (LaspyException, ValueError, ...)
        raise PointCloudFileError(path, f"{stage}: {one_line(exc, 160)}") from None
    if read < count:
        raise PointCloudFileError(path, f"truncated LAS / LAZ file: its header declares {count} points, {read} could be read")
    if not chunks:
        return np.empty((0, 3), dtype=np.float64)
    return np.concatenate(chunks)
