"""Datasets of the benchmark: named sets of clouds (objects) or of scans with known poses.

Names (``BenchConfig.datasets``):

``synthetic``
    Built in, no files: :func:`esmicp.shapes.asymmetric_shape` (about 2.4 units across) and the
    same shape scaled to 240 units (the protocols must not depend on units).
``modelnet40``
    ``<data>/modelnet40/<class>/*.txt`` (10,000 points each, x,y,z,nx,ny,nz) and any
    ``*.off`` mesh below it (sampled on the surface).
``bunny``
    ``<data>/bunny/bun_zipper.ply`` (35,947 points).
``bunny-scans``, ``lidar-pair``
    Scans with poses, for ``scan-pairs``: the Stanford bunny's 10 range scans
    (``<data>/bunny_scans`` with ``bun.conf``), and small_gicp's LiDAR pair
    (``<data>/lidar_pair_small_gicp``, ``T_target_source.txt``).
anything else
    A folder: every point-cloud or mesh file below it (:data:`esmicp.io.READ_EXTENSIONS`).

Point files are kept whole here and subsampled per trial; meshes (``.off .obj .stl``) are sampled
uniformly on their surface with ``2 x points`` points (a split protocol takes two disjoint halves of
``points`` each), seeded from the file name, through :func:`esmicp.io.read_points`.
"""

from __future__ import annotations

import os
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from esmicp.errors import InvalidInputError

#: Names of the built-in / shared datasets.
BUILTIN = ("synthetic", "modelnet40", "bunny", "bunny-scans", "lidar-pair")
#: Mesh files a dataset folder may hold (sampled to the requested size).
MESH_EXTENSIONS = (".off", ".obj", ".stl")
#: Datasets whose clouds do not depend on the requested size (no meshes to sample).
POINTS_INDEPENDENT = ("synthetic", "bunny", "bunny-scans", "lidar-pair")


@dataclass(frozen=True, eq=False)
class Dataset:
    """A named set of clouds.

    Attributes
    ----------
    name : str
        What rows carry as ``dataset``.
    clouds : dict str -> (N, 3) array
        Object clouds by name, in a fixed (sorted) order; empty for scan datasets.
    scans : dict str -> ((N, 3) array, (4, 4) T_world_scan) or None
        For scan datasets.
    """

    name: str
    clouds: dict
    scans: dict | None = None

    @property
    def is_scans(self) -> bool:
        return self.scans is not None


def default_data_dir() -> Path:
    """``$ESMICP_SHARED_DATA``, else ``../shared/data`` from the working directory."""
    override = os.environ.get("ESMICP_SHARED_DATA")
    return Path(override) if override else Path.cwd().parent / "shared" / "data"


def name_seed(name: str) -> int:
    """A stable 32-bit seed from a name (the same on every machine and Python run)."""
    return zlib.crc32(name.encode("utf-8"))


def _require(path: Path, dataset: str) -> Path:
    if not path.exists():
        raise InvalidInputError(
            f"dataset {dataset!r}: {path} not found (give the shared data folder with --data or "
            f"ESMICP_SHARED_DATA)"
        )
    return path


def _read(path: Path, points: int):
    from esmicp import io

    if path.suffix.lower() in MESH_EXTENSIONS:
        return io.read_points(path, sample_points=2 * points, rng=name_seed(path.name))
    return io.read_points(path)


def _folder(folder: Path, name: str, points: int, pattern: str = "**/*") -> dict:
    from esmicp.io import READ_EXTENSIONS

    files = sorted(p for p in folder.glob(pattern) if p.is_file() and p.suffix.lower() in READ_EXTENSIONS)
    if not files:
        raise InvalidInputError(
            f"dataset {name!r}: no point-cloud or mesh files ({' '.join(READ_EXTENSIONS)}) in {folder}"
        )
    clouds = {}
    for path in files:
        key = path.stem if path.stem not in clouds else str(path.relative_to(folder))
        clouds[key] = _read(path, points)
    return clouds


def load_dataset(name: str, data_dir: Path, points: int) -> Dataset:
    """The dataset ``name`` (see the module docstring) for clouds of ``points`` points.

    Raises :class:`~esmicp.errors.InvalidInputError` (a missing folder) or
    :class:`~esmicp.errors.PointCloudFileError` (a bad file), each naming the path.
    """
    data_dir = Path(data_dir)
    if name == "synthetic":
        from esmicp.shapes import asymmetric_shape

        shape = asymmetric_shape(10_000, name_seed("synthetic"))
        return Dataset(name, {"asymmetric": shape, "asymmetric-x100": 100.0 * shape})
    if name == "modelnet40":
        folder = _require(data_dir / "modelnet40", name)
        clouds = _folder(folder, name, points, "*/*.txt")
        clouds.update(_folder_meshes(folder, name, points))
        return Dataset(name, clouds)
    if name == "bunny":
        path = _require(data_dir / "bunny" / "bun_zipper.ply", name)
        return Dataset(name, {"bun_zipper": _read(path, points)})
    if name == "bunny-scans":
        from esmicp.io.stanford_conf import load_scans

        folder = _require(data_dir / "bunny_scans", name)
        return Dataset(name, {}, load_scans(folder))
    if name == "lidar-pair":
        from esmicp import io

        folder = _require(data_dir / "lidar_pair_small_gicp", name)
        pose = io.read_transform(folder / "T_target_source.txt")
        scans = {"source": (io.read_points(folder / "source.ply"), pose), "target": (io.read_points(folder / "target.ply"), np.eye(4))}
        return Dataset(name, {}, scans)
    folder = Path(name)
    if not folder.is_dir():
        raise InvalidInputError(
            f"dataset {name!r}: not a folder, nor one of {', '.join(BUILTIN)}"
        )
    return Dataset(folder.name or name, _folder(folder, name, points))


def _folder_meshes(folder: Path, name: str, points: int) -> dict:
    meshes = sorted(p for p in folder.glob("**/*") if p.is_file() and p.suffix.lower() in MESH_EXTENSIONS)
    return {path.stem: _read(path, points) for path in meshes}
