"""Reading and writing point clouds and rigid transforms.

Point clouds are ``(N, 3)`` float64 arrays of ``x, y, z`` in the file's own frame and units.
The format is chosen by the file extension (case-insensitive):

========================  =======================================================  =========
extension                 format                                                   write
========================  =======================================================  =========
``.ply``                  PLY, ascii or binary; vertex x/y/z                       float64
``.pcd``                  PCD, ascii / binary / binary_compressed; fields x y z    float64
``.xyz .txt .csv .pts``   text, one point per line, first three columns            17 digits
``.npy``                  NumPy ``(N, 3)`` array (never unpickled)                 float64
``.bin``                  headerless float32 scan (KITTI velodyne), 3 or 4 cols   (read only)
``.las .laz``             LAS / LAZ through laspy (extra ``las``): scaled x/y/z    (read only)
``.off .obj .stl``        triangle mesh: its vertices, or ``sample_points`` on it  (read only)
========================  =======================================================  =========

Every written format keeps full float64 precision, so write/read round trips are exact.
``.ply`` and ``.pcd`` can also hold a scan index and a colour per point (:func:`write_points`).
Poses of many scans (``T_world_scan`` per scan, as text): :func:`write_poses` / :func:`read_poses`
(:mod:`.poses`).

Every problem with an input file raises :class:`~esmicp.errors.PointCloudFileError` whose message
starts with the file's path; NaN / infinite points are dropped with a
:class:`~esmicp.errors.NonFinitePointsWarning`. Writes are atomic (see :mod:`.atomic`).
"""

from __future__ import annotations

import logging
import os
import warnings
from pathlib import Path
from types import MappingProxyType

import numpy as np

from ..errors import EsmicpError, EsmicpWarning, InvalidInputError, PointCloudFileError, PointCloudFileNotFoundError
from ..types import _coordinate_array as coordinate_array
from ..types import as_generator, as_points
from . import las, npy, off, pcd, ply, text, velodyne
from ._messages import one_line
from ._files import as_path, check_input_file
from .atomic import atomic_write, is_stream, output_target
from .palette import scan_palette
from .poses import POSE_FORMATS, PoseFile, read_poses, write_poses
from .transform import read_transform, write_transform

logger = logging.getLogger(__name__)

__all__ = [
    "FIELD_EXTENSIONS",
    "POSE_FORMATS",
    "PoseFile",
    "READ_EXTENSIONS",
    "SUPPORTED_EXTENSIONS",
    "WRITE_EXTENSIONS",
    "atomic_write",
    "DroppedFieldsWarning",
    "check_writable",
    "read_points",
    "read_poses",
    "read_transform",
    "scan_palette",
    "write_points",
    "write_poses",
    "write_transform",
]

_MESH_ONLY_EXTENSIONS = (".off", ".obj", ".stl")

#: Extensions :func:`read_points` accepts.
READ_EXTENSIONS = (
    ".ply", ".pcd", ".xyz", ".txt", ".csv", ".pts", ".npy", ".bin", ".las", ".laz", ".off", ".obj", ".stl",
)
#: Extensions :func:`write_points` accepts.
WRITE_EXTENSIONS = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy")
#: Extensions whose files :func:`write_points` gives the per-point ``scan_index`` and ``colors``.
FIELD_EXTENSIONS = (".ply", ".pcd")
#: Both lists, for help texts: ``SUPPORTED_EXTENSIONS["read"]`` and ``SUPPORTED_EXTENSIONS["write"]``.
SUPPORTED_EXTENSIONS = MappingProxyType({"read": READ_EXTENSIONS, "write": WRITE_EXTENSIONS})

_PLY_FORMATS = ("ascii", "binary")


class DroppedFieldsWarning(EsmicpWarning):
    """:func:`write_points` was given per-point fields (a scan index, colours) for a format that
    holds ``x y z`` only: the file has the points without them."""


def _strip_name(exc: Exception, name: str) -> str:
    return str(exc).removeprefix(f"{name}: ")


def _unsupported(path: Path, supported: tuple[str, ...], action: str) -> PointCloudFileError:
    extension = path.suffix.lower()
    what = f"unsupported file extension {extension!r}" if extension else "no file extension"
    return PointCloudFileError(path, f"{what}; supported for {action}: {', '.join(supported)}")


def _sample_count(sample_points) -> int:
    if isinstance(sample_points, (bool, np.bool_)) or not isinstance(sample_points, (int, np.integer)):
        raise InvalidInputError(f"sample_points: expected a positive integer, got {sample_points!r}")
    if sample_points < 1:
        raise InvalidInputError(f"sample_points: expected a positive integer, got {sample_points}")
    return int(sample_points)


def _read_raw(path: Path, reader) -> np.ndarray:
    """Run a format reader; turn any stray library or OS exception into PointCloudFileError."""
    try:
        return reader()
    except EsmicpError:
        raise
    except MemoryError:
        raise PointCloudFileError(path, "too large to load into memory") from None
    except PermissionError:
        raise PointCloudFileError(path, "permission denied") from None
    except FileNotFoundError:  # removed while being read
        raise PointCloudFileNotFoundError(path) from None
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot read: {exc.strerror or exc}") from None
    except Exception as exc:  # a library failed in a way not anticipated: still one plain error
        raise PointCloudFileError(path, f"could not be read ({type(exc).__name__}: {one_line(exc, 160)})") from exc


def _finish(path: Path, raw: np.ndarray) -> np.ndarray:
    """Validate the raw coordinates: drop NaN rows (warning), need at least 3 points."""
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim == 2 and raw.shape[1] == 3 and len(raw) and not np.isfinite(raw).all(axis=1).any():
        raise PointCloudFileError(
            path, f"no valid points: all {len(raw)} points have NaN or infinite coordinates"
        )
    try:
        return as_points(raw, name=str(path))
    except InvalidInputError as exc:
        raise PointCloudFileError(path, _strip_name(exc, str(path))) from None


def read_points(path, *, sample_points: int | None = None, rng=None, bin_columns: int | None = None) -> np.ndarray:
    """Read a point cloud (or a mesh's vertices / surface samples) from a file.

    Parameters
    ----------
    path : str or os.PathLike
        A file with one of :data:`READ_EXTENSIONS` (case-insensitive).
    sample_points : int, optional
        For meshes (``.off``, ``.obj``, ``.stl``, ``.ply`` with faces): draw this many points
        uniformly on the surface instead of returning the vertices.
    rng : int or numpy.random.Generator, optional
        Seed or generator for ``sample_points`` (a seed makes the samples deterministic).
        Ignored without ``sample_points``.
    bin_columns : {3, 4}, optional
        For ``.bin`` scans: float32 values per point, 4 for KITTI velodyne (``x y z intensity``),
        3 for ``x y z``. None (default) takes the layout from the file size when only one fits and,
        for a size that fits both (a multiple of 48 bytes), from the values when only one layout
        reads as points; a file whose values cannot tell is refused: see :mod:`esmicp.io.velodyne`.
        Ignored for other formats (so one value can serve a ``.bin`` and a ``.ply`` of a pair).

    Returns
    -------
    numpy.ndarray
        New ``(N, 3)`` float64 array, ``N >= 3``, in the file's frame and units. Points with NaN
        or infinite coordinates are dropped with a :class:`~esmicp.errors.NonFinitePointsWarning`.

    Raises
    ------
    PointCloudFileNotFoundError
        The file does not exist (also a :class:`FileNotFoundError`).
    PointCloudFileError
        The file is a directory, empty, unreadable, of an unsupported extension,
        malformed or truncated, has no x/y/z, or fewer than 3 finite points; a ``.bin`` whose
        size fits neither layout, or both without ``bin_columns`` and values that cannot tell.
    InvalidInputError
        ``sample_points``, ``rng`` or ``bin_columns`` is invalid.
    MissingDependencyError
        A ``.las`` / ``.laz`` file and laspy (or a LAZ backend) is not installed.
    """
    path = as_path(path)
    columns = velodyne.bin_columns(bin_columns)
    extension = path.suffix.lower()
    if extension not in READ_EXTENSIONS:
        raise _unsupported(path, READ_EXTENSIONS, "reading")
    if sample_points is not None:
        count = _sample_count(sample_points)
        generator = as_generator(rng)
        if extension not in off.MESH_EXTENSIONS:
            raise PointCloudFileError(
                path,
                f"sample_points needs a mesh file ({', '.join(off.MESH_EXTENSIONS)}), "
                f"but {extension} holds a point cloud",
            )
    check_input_file(path)

    if sample_points is not None:
        raw = _read_raw(path, lambda: off.read_mesh(path, sample_points=count, rng=generator))
    elif extension in _MESH_ONLY_EXTENSIONS:
        raw = _read_raw(path, lambda: off.read_mesh(path))
    elif extension == ".ply":
        raw = _read_raw(path, lambda: ply.read_ply(path))
    elif extension == ".pcd":
        raw = _read_raw(path, lambda: pcd.read_pcd(path))
    elif extension == ".npy":
        raw = _read_raw(path, lambda: npy.read_npy(path))
    elif extension == ".bin":
        raw = _read_raw(path, lambda: velodyne.read_bin(path, columns))
    elif extension in (".las", ".laz"):
        raw = _read_raw(path, lambda: las.read_las(path))
    else:
        raw = _read_raw(path, lambda: text.read_text(path))
    return _finish(path, raw)


def check_writable(path, *, kind: str = "points", overwrite: bool | None = None) -> None:
    """Check, without creating anything, that an output could be written at ``path``.

    For early refusal (before any work): the extension is one :func:`write_points` supports
    (``kind="points"``; transforms are text whatever their extension, ``kind="transform"``), the
    folder exists, and ``path`` names nothing that an output would replace but a regular file or a
    link to one (:func:`esmicp.io.atomic.output_target`: a directory, a FIFO, a device, a socket or
    a dangling link is refused); a stream (``/dev/stdout``, ...) takes text outputs only. With
    ``overwrite`` False, an existing file is refused too; None (default) does not check that.

    Raises
    ------
    PointCloudFileError
        The output cannot be written there.
    OutputExistsError
        ``overwrite`` is False and ``path`` exists.
    """
    path = as_path(path)
    if kind not in ("points", "transform"):
        raise InvalidInputError(f"kind: expected 'points' or 'transform', got {kind!r}")
    if kind == "points" and is_stream(path):
        raise PointCloudFileError(path, "a point cloud's format is chosen by its file extension, and a stream has "
                                  f"none: write a file ({', '.join(WRITE_EXTENSIONS)})")
    if kind == "points" and path.suffix.lower() not in WRITE_EXTENSIONS:
        raise _unsupported(path, WRITE_EXTENSIONS, "writing")
    output_target(path, True if overwrite is None else overwrite)


def write_points(
    path, points, *, overwrite: bool = False, pcd_format: str = "binary", ply_format: str = "binary",
    scan_index=None, colors=None,
) -> None:
    """Write a point cloud, choosing the format by extension; atomic, never partial.

    Precision kept (all exact float64 round trips):

    - ``.ply``: ``double x, y, z`` vertices, binary little-endian or ascii (17 significant digits);
      with ``colors``, ``uchar red, green, blue``; with ``scan_index``, ``int scan_index``.
    - ``.pcd``: fields ``x y z`` TYPE F SIZE 8; ``binary``, ``binary_compressed`` (LZF) or
      ``ascii`` (17 significant digits); with ``colors``, ``rgb`` (packed as PCL packs it, TYPE U
      SIZE 4); with ``scan_index``, ``scan_index`` (TYPE I SIZE 4).
    - ``.xyz``, ``.txt``: ``x y z`` per line, space-separated, 17 significant digits; ``.csv``: the
      same, comma-separated.
    - ``.npy``: an ``(N, 3)`` float64 array.

    The per-point fields (``scan_index``, ``colors``) are written to ``.ply`` and ``.pcd``
    (:data:`FIELD_EXTENSIONS`), which CloudCompare, Open3D and PCL read; the plain formats hold
    ``x y z`` only, and they are left out there with a :class:`DroppedFieldsWarning`.
    :func:`read_points` reads ``x y z`` of any of them.

    Parameters
    ----------
    path : str or os.PathLike
        Output file, one of :data:`WRITE_EXTENSIONS`.
    points : array_like
        ``(N, 3)`` coordinates (NaN / infinite rows are dropped with a warning; at least 3 points).
    overwrite : bool
        Replace an existing file; otherwise an existing ``path`` raises and is left untouched.
    pcd_format : {"binary", "binary_compressed", "ascii"}
        Encoding of ``.pcd`` output.
    ply_format : {"binary", "ascii"}
        Encoding of ``.ply`` output.
    scan_index : array_like, optional
        ``(N,)`` non-negative integers (below 2**31), one per point: which scan each point comes
        from (``MultiRegistrationResult.merged``'s labels).
    colors : array_like, optional
        ``(N, 3)`` integers in 0..255, one red / green / blue per point (e.g.
        ``scan_palette(n)[scan_index]``: one colour per scan).

    Raises
    ------
    PointCloudFileError
        Unsupported extension (raised before anything is created), or the file cannot be written.
    InvalidInputError
        ``points`` is not a valid cloud, ``pcd_format`` / ``ply_format`` is unknown, or
        ``scan_index`` / ``colors`` is not one valid value per point.
    OutputExistsError
        ``path`` exists and ``overwrite`` is False.
    """
    path = as_path(path)
    extension = path.suffix.lower()
    if extension not in WRITE_EXTENSIONS:
        raise _unsupported(path, WRITE_EXTENSIONS, "writing")
    if pcd_format not in pcd.ENCODINGS:
        raise InvalidInputError(f"pcd_format: expected one of {', '.join(pcd.ENCODINGS)}, got {pcd_format!r}")
    if ply_format not in _PLY_FORMATS:
        raise InvalidInputError(f"ply_format: expected one of {', '.join(_PLY_FORMATS)}, got {ply_format!r}")
    array, fields = _points_and_fields(points, scan_index, colors)
    if fields and extension not in FIELD_EXTENSIONS:
        warnings.warn(f"{path}: {extension} holds x y z only; {' and '.join(fields)} left out (write "
                      f"{' or '.join(FIELD_EXTENSIONS)} to keep them)", DroppedFieldsWarning, stacklevel=2)

    if extension == ".ply":

        def writer(handle):
            ply.write_ply(handle, array, binary=ply_format == "binary", **fields)
    elif extension == ".pcd":

        def writer(handle):
            pcd.write_pcd(handle, array, encoding=pcd_format, **fields)
    elif extension == ".npy":

        def writer(handle):
            npy.write_npy(handle, array)
    else:
        delimiter = "," if extension == ".csv" else " "

        def writer(handle):
            text.write_text(handle, array, delimiter=delimiter)

    with atomic_write(path, overwrite) as handle:
        writer(handle)
    logger.debug("wrote %d points to %s", len(array), os.fspath(path))


def _points_and_fields(points, scan_index, colors) -> tuple[np.ndarray, dict]:
    """The validated ``(N, 3)`` points and their per-point fields (``scan_index`` int32,
    ``colors`` uint8), the rows with NaN or infinite coordinates dropped from all of them."""
    if scan_index is None and colors is None:
        return as_points(points, name="points"), {}
    raw = coordinate_array(points, "points")
    fields = {}
    for name, value in (("scan_index", scan_index), ("colors", colors)):
        if value is None:
            continue
        shape = (len(raw),) if name == "scan_index" else (len(raw), 3)
        try:
            array = np.asarray(value)
        except (TypeError, ValueError):
            raise InvalidInputError(f"{name}: expected numbers, got {type(value).__name__}") from None
        if array.shape != shape:
            raise InvalidInputError(f"{name}: expected shape {shape} (one per point), got {array.shape}")
        top = 2**31 - 1 if name == "scan_index" else 255
        if array.dtype.kind not in "iu" and not (array.dtype.kind == "f" and np.isfinite(array).all()
                                                 and (array == np.round(array)).all()):
            raise InvalidInputError(f"{name}: expected integers, got dtype {array.dtype}")
        if len(array) and (array.min() < 0 or array.max() > top):
            raise InvalidInputError(f"{name}: expected integers in [0, {top}], got {array.min()}..{array.max()}")
        fields[name] = array.astype(np.int32 if name == "scan_index" else np.uint8)
    finite = np.isfinite(raw).all(axis=1)
    array = as_points(raw, name="points")  # drops the non-finite rows, with a warning
    if not finite.all():
        fields = {name: value[finite] for name, value in fields.items()}
    return array, fields
