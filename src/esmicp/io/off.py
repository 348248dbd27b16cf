"""Triangle meshes (``.off``, and ``.obj`` / ``.stl`` / ``.ply`` with faces) read with :mod:`trimesh`.

By default the mesh vertices are the points. With ``sample_points=N``, N points are drawn
uniformly (area-weighted) on the surface, e.g. to turn a ModelNet ``.off`` shape into a cloud.
trimesh is imported lazily: it is slow to import.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np

from ..errors import PointCloudFileError
from . import ply
from .text import read_text_file

__all__ = ["MESH_EXTENSIONS", "read_mesh"]

#: Extensions read as meshes by this module (``.ply`` only when sampling its faces).
MESH_EXTENSIONS = (".off", ".obj", ".stl", ".ply")

_OFF_START = re.compile(r"^(C?OFF)\s*(.*)$")


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
            f"malformed OFF file: expected a 'vertices faces edges' count line, got {counts_text[:40]!r}",
        ) from None
    if vertices < 0 or faces < 0:
        raise PointCloudFileError(path, f"malformed OFF file: negative counts {vertices} {faces}")
    if len(rest) < vertices + faces:
        raise PointCloudFileError(
            path,
            f"truncated OFF file: its header declares {vertices} vertices and {faces} faces, but only "
            f"{len(rest)} data lines follow",
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
    try:
        if source is not None:
            mesh = trimesh.load(source, file_type="off", force="mesh", process=False)
        else:
            mesh = trimesh.load(str(path), file_type=extension[1:], force="mesh", process=False)
    except MemoryError:
        raise PointCloudFileError(path, "mesh is too large to load into memory") from None
    except Exception as exc:  # noqa: BLE001 - trimesh raises many kinds (ValueError, NameError, ...)
        problem = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PointCloudFileError(
            path, f"could not read the {extension[1:].upper()} mesh: {problem}"
        ) from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise PointCloudFileError(path, f"could not read a triangle mesh from it (got {type(mesh).__name__})")
    return mesh


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
