"""Triangle meshes (``.off``, and ``.obj`` / ``.stl`` / ``.ply`` with faces) read with :mod:`trimesh`.

By default the mesh vertices are the points. With ``sample_points=N``, N points are drawn
uniformly (area-weighted) on the surface, e.g. to turn a ModelNet ``.off`` shape into a cloud.
trimesh is imported lazily: it is slow to import.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import re
import struct
import threading
import warnings
from pathlib import Path

import numpy as np

from ..errors import PointCloudFileError
from ._messages import excerpt, one_line
from . import ply
from .text import read_text_file

__all__ = ["MESH_EXTENSIONS", "read_mesh"]

#: Extensions read as meshes by this module (``.ply`` only when sampling its faces).
MESH_EXTENSIONS = (".off", ".obj", ".stl", ".ply")

_OFF_START = re.compile(r"^(C?OFF)\s*(.*)$")

logger = logging.getLogger(__name__)


class _ThreadsLoading(logging.Filter):
    """Keeps trimesh's log records of the threads inside :func:`_trimesh_log_kept` off the
    handlers (and off Python's last-resort stderr handler), as debug records of this module."""

    def __init__(self):
        super().__init__()
        self.threads: dict[int, int] = {}  # thread id -> nesting depth
        self.lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.thread not in self.threads:
            return True
        logger.debug("trimesh: %s", record.getMessage())
        return False


_TRIMESH_LOG_FILTER = _ThreadsLoading()


def _trimesh_loggers() -> list[logging.Logger]:
    """trimesh's loggers (``trimesh.util``, ``trimesh.sample``, ...: a filter on the ``trimesh``
    logger would not see the records of its children)."""
    names = [name for name in list(logging.root.manager.loggerDict) if name == "trimesh" or name.startswith("trimesh.")]
    return [logging.getLogger(name) for name in names]


@contextlib.contextmanager
def _trimesh_log_kept():
    """While trimesh parses a file, what it logs (e.g. "failed to extract face_normals" with a
    traceback, for an ascii STL whose facet normal is not a number: it then computes the normals
    itself, and only the vertices are read here) is not printed, but logged at debug level here."""
    me = threading.get_ident()
    with _TRIMESH_LOG_FILTER.lock:
        for trimesh_log in _trimesh_loggers():
            if _TRIMESH_LOG_FILTER not in trimesh_log.filters:
                trimesh_log.addFilter(_TRIMESH_LOG_FILTER)
        _TRIMESH_LOG_FILTER.threads[me] = _TRIMESH_LOG_FILTER.threads.get(me, 0) + 1
    try:
        yield
    finally:
        with _TRIMESH_LOG_FILTER.lock:
            _TRIMESH_LOG_FILTER.threads[me] -= 1
            if not _TRIMESH_LOG_FILTER.threads[me]:
                del _TRIMESH_LOG_FILTER.threads[me]
            if not _TRIMESH_LOG_FILTER.threads:
                for trimesh_log in _trimesh_loggers():
                    trimesh_log.removeFilter(_TRIMESH_LOG_FILTER)


def _check_off(path, text: str) -> None:
    """Check the OFF header and that the file has as many lines as it declares."""
    lines = [line.split("#", 1)[0].strip() for line in text.splitlines()]
    lines = [line for line in lines if line]
    if not lines:
        raise PointCloudFileError(path, "contains no mesh (only blank or comment lines)")
    match = _OFF_START.match(lines[0])
    if match is None:
        raise PointCloudFileError(path, "not an OFF file: the first line does not start with 'OFF'")
    rest = lines[1:]
    counts_text = match.group(2)
    if not counts_text:
        if not rest:
            raise PointCloudFileError(path, "truncated OFF file: no vertex/face count line")
        counts_text, rest = rest[0], rest[1:]
    words = counts_text.split()
    try:
        vertices, faces = int(words[0]), int(words[1])
    except (IndexError, ValueError):
        raise PointCloudFileError(
            path,
            f"malformed OFF file: expected a 'vertices faces edges' count line, got {excerpt(counts_text)}",
        ) from None
    if vertices < 0 or faces < 0:
        raise PointCloudFileError(path, f"malformed OFF file: negative counts {vertices} {faces}")
    if len(rest) < vertices + faces:
        raise PointCloudFileError(
            path,
            f"truncated OFF file: its header declares {vertices} vertices and {faces} faces, but only "
            f"{len(rest)} data lines follow",
        )


_STL_HEADER_BYTES = 84  # an 80-byte comment and the uint32 triangle count
_STL_TRIANGLE_BYTES = 50  # normal, three vertices (12 float32) and a uint16 attribute


def _check_stl(path) -> None:
    """Refuse a binary STL whose triangle count disagrees with its size, in plain words.

    An ascii STL starts with ``solid``; some binary ones do too (in their 80-byte comment), so a
    file is binary when its size is exactly what its triangle count needs. Otherwise trimesh would
    fall back to parsing the bytes as ascii and find nothing.
    """
    size = os.path.getsize(path)
    with open(path, "rb") as handle:
        head = handle.read(_STL_HEADER_BYTES)
    if len(head) == _STL_HEADER_BYTES:
        (count,) = struct.unpack("<I", head[80:84])
        if size == _STL_HEADER_BYTES + _STL_TRIANGLE_BYTES * count:
            return
    if head.lstrip()[:5].lower() == b"solid":
        return  # ascii: trimesh parses it (and reports what it cannot)
    if len(head) < _STL_HEADER_BYTES:
        raise PointCloudFileError(
            path, f"not an STL file: {size} bytes is too short for a binary STL, and it does not start with 'solid'"
        )
    needed = _STL_HEADER_BYTES + _STL_TRIANGLE_BYTES * count
    raise PointCloudFileError(
        path,
        f"truncated or corrupt binary STL file: its header declares {count} triangles, which need "
        f"{needed} bytes, but the file has {size} bytes",
    )


def _load(path: Path, extension: str):
    """Load the mesh at ``path`` with trimesh, unprocessed (vertices kept as in the file)."""
    import trimesh

    source = None
    if extension == ".off":
        text = read_text_file(path)
        _check_off(path, text)
        source = io.BytesIO(text.encode("utf-8"))
    elif extension == ".ply":
        ply.read_ply_header(path)  # refuses lying / truncated headers before trimesh allocates
    elif extension == ".stl":
        _check_stl(path)
    try:
        # trimesh computes normals of whatever the file holds: NaN / infinite coordinates (dropped
        # later, with a warning of our own) must not surface as NumPy's RuntimeWarnings.
        with np.errstate(all="ignore"), warnings.catch_warnings(), _trimesh_log_kept():
            warnings.simplefilter("ignore", RuntimeWarning)
            if source is not None:
                loaded = trimesh.load(source, file_type="off", process=False)
            else:
                loaded = trimesh.load(str(path), file_type=extension[1:], process=False)
            vertices, faces = _geometry(path, loaded)
    except PointCloudFileError:
        raise
    except MemoryError:
        raise PointCloudFileError(path, "mesh is too large to load into memory") from None
    except Exception as exc:  # noqa: BLE001 - trimesh raises many kinds (ValueError, NameError, ...)
        problem = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PointCloudFileError(
            path, f"could not read the {extension[1:].upper()} mesh: {one_line(problem, 160)}"
        ) from None
    # A plain mesh, without the file's materials or textures: trimesh handles those lazily and
    # needs optional packages (Pillow) for them, which reading coordinates must not depend on.
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def _geometry(path, loaded) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` and triangles ``(F, 3)`` of what ``trimesh.load`` returned.

    A file of vertices only (an OBJ of ``v`` lines) gives a trimesh ``PointCloud``: its vertices
    and no faces. A ``Scene`` (an OBJ with several objects or materials) gives all its meshes,
    concatenated in the file's order.
    """
    import trimesh

    if isinstance(loaded, trimesh.Scene):
        parts = list(loaded.geometry.values())
    else:
        parts = [loaded]
    vertices, faces, offset = [], [], 0
    for part in parts:
        if not isinstance(part, (trimesh.Trimesh, trimesh.PointCloud)):
            raise PointCloudFileError(path, f"could not read a triangle mesh from it (got {type(part).__name__})")
        part_vertices = np.asarray(part.vertices, dtype=np.float64).reshape(-1, 3)
        if isinstance(part, trimesh.Trimesh):
            part_faces = np.asarray(part.faces).reshape(-1, 3)
            if part_faces.size and (part_faces.min() < 0 or part_faces.max() >= len(part_vertices)):
                raise PointCloudFileError(
                    path, f"malformed mesh: a face refers to a vertex that does not exist ({len(part_vertices)} vertices)"
                )
            faces.append(part_faces.astype(np.int64) + offset)
        vertices.append(part_vertices)
        offset += len(part_vertices)
    if not vertices:
        return np.empty((0, 3)), np.empty((0, 3), dtype=np.int64)
    return np.concatenate(vertices), np.concatenate(faces) if faces else np.empty((0, 3), dtype=np.int64)


def read_mesh(
    path, *, sample_points: int | None = None, rng: np.random.Generator | None = None
) -> np.ndarray:
    """Read a mesh's vertices, or sample points uniformly on its surface.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.off``, ``.obj``, ``.stl`` or ``.ply`` mesh.
    sample_points : int, optional
        If given, draw this many points on the surface, with probability proportional to area.
        Otherwise return the vertices (for STL, each distinct vertex once, in first-seen order).
    rng : numpy.random.Generator, optional
        Random source for sampling; a seeded generator gives deterministic points.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` float64 points in the mesh's own frame and units.

    Raises
    ------
    PointCloudFileError
        The mesh cannot be read, or has no faces / zero area when sampling is requested.
    """
    path = Path(path)
    extension = path.suffix.lower()
    mesh = _load(path, extension)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if len(vertices) == 0:
        hint = " (an ascii STL without facets, or a binary one whose triangle count is wrong)" if extension == ".stl" else ""
        raise PointCloudFileError(path, f"no vertices could be read from this {extension[1:].upper()} file{hint}")
    if sample_points is None:
        if extension == ".stl":
            _, first = np.unique(vertices, axis=0, return_index=True)
            vertices = vertices[np.sort(first)]
        return np.array(vertices, dtype=np.float64)

    import trimesh

    faces = np.asarray(mesh.faces)
    if faces.ndim != 2 or len(faces) == 0:
        raise PointCloudFileError(
            path, "has no faces to sample points from (it is a point cloud, not a mesh)"
        )
    with np.errstate(all="ignore"):  # non-finite vertices give a non-finite area, refused below
        area = float(mesh.area)
    if not np.isfinite(area) or area <= 0:
        raise PointCloudFileError(
            path, "cannot sample points: the mesh surface has zero (or non-finite) area"
        )
    try:
        points, _ = trimesh.sample.sample_surface(mesh, int(sample_points), seed=rng)
    except MemoryError:
        raise PointCloudFileError(path, f"too many points requested ({sample_points})") from None
    return np.asarray(points, dtype=np.float64)
