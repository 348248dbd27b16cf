"""Stanford 3D Scanning Repository ``.conf`` files: the pose of each range scan.

Each scan line reads ``bmesh <file> tx ty tz qx qy qz qw`` (``mesh`` is accepted too). A scan
point goes to the common (world) frame as ``p_world = R(q)^T p + t``, with ``R(q)`` the standard
rotation matrix of the unit quaternion ``(qx, qy, qz, qw)``; so ``T_world_scan = [R(q)^T | t]``
and the relative pose of a pair is ``T_target_source = T_world_target^-1 T_world_source``.
``camera`` lines and meshes whose file name contains ``cybcyl`` (the scanner's calibration
cylinder) are skipped.
"""

from __future__ import annotations

from pathlib import Path, PurePath, PurePosixPath, PureWindowsPath

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import PointCloudFileError, PointCloudFileNotFoundError
from ..types import as_generator
from ._files import check_input_file
from ._messages import excerpt

_MESH_KEYWORDS = ("bmesh", "mesh")
_SKIPPED_KEYWORDS = ("camera",)


def _pose(path, line_number: int, words: list[str]) -> np.ndarray:
    try:
        values = np.array([float(word) for word in words[2:]])
    except ValueError:
        raise PointCloudFileError(
            path, f"line {line_number}: expected 7 numbers after the file name, got {excerpt(' '.join(words[2:]))}"
        ) from None
    if not np.isfinite(values).all():
        raise PointCloudFileError(path, f"line {line_number}: pose has NaN or infinite values")
    translation, quaternion = values[:3], values[3:]
    norm = float(np.linalg.norm(quaternion))
    if abs(norm - 1.0) > 1e-3:
        raise PointCloudFileError(path, f"line {line_number}: quaternion is not unit length (norm {norm:.6g})")
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(quaternion / norm).as_matrix().T
    pose[:3, 3] = translation
    return pose


def _check_inside(path: Path, line_number: int, file_name: str) -> None:
    """A scan file must be a plain name or a relative path below the conf's folder: a conf handed
    over with a dataset must not make esmicp read files elsewhere (``/etc/...``, ``../../``)."""
    parts = PurePath(file_name).parts
    if PurePosixPath(file_name).is_absolute() or PureWindowsPath(file_name).is_absolute() or ".." in parts \
            or "\\" in file_name or PureWindowsPath(file_name).drive:
        raise PointCloudFileError(
            path, f"line {line_number}: scan file {excerpt(file_name)} is not inside the conf's folder"
        )


def _entries(path: Path) -> list[tuple[str, str, np.ndarray]]:
    """``(name, file, T_world_scan)`` per scan line, in file order; name = the file's stem."""

    check_input_file(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise PointCloudFileError(path, "not a text file") from None
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot read: {exc.strerror or exc}") from None
    entries: list[tuple[str, str, np.ndarray]] = []
    seen: dict[str, int] = {}
    for line_number, line in enumerate(text.splitlines(), start=1):
        words = line.split()
        if not words or words[0].startswith("#") or words[0] in _SKIPPED_KEYWORDS:
            continue
        if words[0] not in _MESH_KEYWORDS:
            raise PointCloudFileError(
                path, f"line {line_number}: unknown keyword {excerpt(words[0], 20)} (expected bmesh, mesh or camera)"
            )
        if len(words) != 9:
            raise PointCloudFileError(
                path,
                f"line {line_number}: expected '{words[0]} <file> tx ty tz qx qy qz qw' (9 fields), "
                f"got {len(words)}",
            )
        file_name = words[1]
        if "cybcyl" in file_name:
            continue
        _check_inside(path, line_number, file_name)
        pose = _pose(path, line_number, words)
        name = Path(file_name).stem
        if name in seen:
            raise PointCloudFileError(
                path, f"line {line_number}: scan {excerpt(name)} already listed on line {seen[name]}"
            )
        seen[name] = line_number
        entries.append((name, file_name, pose))
    if not entries:
        raise PointCloudFileError(path, "no bmesh lines: no scan poses found")
    return entries


def read_stanford_conf(path) -> dict[str, np.ndarray]:
    """Read a Stanford ``.conf`` file: scan name (file stem) -> 4x4 ``T_world_scan``.

    Raises
    ------
    PointCloudFileError
        The file is missing or unreadable, or a line is malformed (the message names the line).
    """
    return {name: pose for name, _, pose in _entries(Path(path))}


def _conf_path(folder: Path) -> Path:
    if folder.is_file():
        return folder
    if not folder.is_dir():
        raise PointCloudFileNotFoundError(folder, "no such file or folder")
    confs = sorted(folder.glob("*.conf"))
    if len(confs) != 1:
        raise PointCloudFileError(folder, f"expected exactly one .conf file in the folder, found {len(confs)}")
    return confs[0]


def load_scans(folder, *, max_points: int | None = None, rng=None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read every scan listed in a folder's ``.conf`` file (or in a given ``.conf`` path).

    Returns name -> ``(points, T_world_scan)``, points in the scan's own frame, read with
    :func:`esmicp.io.read_points` from the conf's folder. With ``max_points``, each scan is
    reduced to a random subset of that many points drawn from ``rng`` (a seed or a Generator).
    """
    from . import read_points

    conf = _conf_path(Path(folder))
    generator = as_generator(rng)
    scans = {}
    for name, file_name, pose in _entries(conf):  # file names checked to stay inside the folder
        points = read_points(conf.parent / file_name)
        if max_points is not None and len(points) > max_points:
            points = points[np.sort(generator.choice(len(points), size=max_points, replace=False))]
        scans[name] = (points, pose)
    return scans
