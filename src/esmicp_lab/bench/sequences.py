"""Scan sequences with ground-truth poses (``../shared/data/sequences``), and the crops that make
real sliding pairs of them.

A sequence folder holds ``poses.txt`` (one line per frame: its name, then the 12 numbers of the
3x4 ``T_world_frame``, row-major) and ``frames/<name>.npy`` (the frame's points in the camera
frame, float32 ``(N, 3)``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from esmicp.errors import InvalidInputError


def read_poses(folder: str | Path) -> dict[str, np.ndarray]:
    """``frame name -> T_world_frame`` (4x4) from ``folder/poses.txt``; ``#`` lines are comments."""
    path = Path(folder) / "poses.txt"
    poses = {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields or line.startswith("#"):
            continue
        if len(fields) != 13:
            raise InvalidInputError(f"{path}: line {number}: expected a name and 12 numbers, got {len(fields)} fields")
        pose = np.eye(4)
        pose[:3, :] = np.array(fields[1:], dtype=np.float64).reshape(3, 4)
        poses[fields[0]] = pose
    return poses


def read_frame(folder: str | Path, name: str) -> np.ndarray:
    """The points of frame ``name`` (camera frame, float64 ``(N, 3)``)."""
    return np.load(Path(folder) / "frames" / f"{name}.npy").astype(np.float64)


def frame_pairs(folder: str | Path, gaps, every: int):
    """``(source_name, target_name, source, target, T_target_source, overlap)`` of the frames of
    ``folder`` ``gap`` apart for each of ``gaps``, starting at every ``every``-th frame (in name
    order): the source the later frame, ``overlap`` the fraction of its points within 3 target
    spacings of the target under the truth (:func:`esmicp_lab.bench.protocols.scan_overlap`)."""
    from esmicp.core.procrustes import rigid_inverse
    from esmicp_lab.bench.protocols import median_spacing, scan_overlap

    poses = read_poses(folder)
    names = sorted(poses)
    for start in range(0, len(names), every):
        for gap in gaps:
            if start + gap >= len(names):
                continue
            target_name, source_name = names[start], names[start + gap]
            target, source = read_frame(folder, target_name), read_frame(folder, source_name)
            truth = rigid_inverse(poses[target_name]) @ poses[source_name]
            yield source_name, target_name, source, target, truth, scan_overlap(source, target, truth,
                                                                                 3.0 * median_spacing(target))


def dominant_plane(points: np.ndarray, tolerance: float, rng: np.random.Generator,
                   tries: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """``(unit normal, a point on it)`` of the plane with the most ``points`` within ``tolerance``
    (cloud units), among ``tries`` planes through three random points (RANSAC)."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 3:
        raise InvalidInputError(f"points: need at least 3 for a plane, got {len(points)}")
    best, best_count = None, -1
    for _ in range(tries):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        normal = np.cross(b - a, c - a)
        length = np.linalg.norm(normal)
        if length < 1e-12:
            continue
        normal /= length
        count = int(np.count_nonzero(np.abs((points - a) @ normal) < tolerance))
        if count > best_count:
            best, best_count = (normal, a), count
    if best is None:
        raise InvalidInputError("points: every sampled triple was collinear; no plane found")
    return best


def plane_crop_pair(target: np.ndarray, source: np.ndarray, T_target_source: np.ndarray, tolerance: float,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A real pair cut down to one surface: ``(source crop, target crop, plane normal)``, the
    points of each within ``tolerance`` of the target's :func:`dominant_plane` (the source's
    placed by the true ``T_target_source``; normal in the target frame). A wall or floor seen
    alone: its pose may slide along the plane."""
    normal, on_plane = dominant_plane(target, tolerance, rng)
    placed = source @ T_target_source[:3, :3].T + T_target_source[:3, 3]
    keep_target = np.abs((target - on_plane) @ normal) < tolerance
    keep_source = np.abs((placed - on_plane) @ normal) < tolerance
    return source[keep_source], target[keep_target], normal
