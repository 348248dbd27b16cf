"""Scan sets whose frames are not their sensors' frames, with ground truth: what the merge's
free-space premise (each scan a range image seen from its own origin) must be judged on.

* :func:`bunny_in_scanner_frames`: the Stanford bunny's raw range scans moved into a frame whose
  origin is their scanner's viewpoint (then they are range images from their origins).
* :func:`moved_off`: scans each moved into a frame some distance and angle off its own (the bunny's
  scans from their scanner's frame, 0.1-0.3 m and 5-20 degrees off it, as a turntable's or an
  object's frame would leave them).
* :func:`map_crops`: balls cut from one map (a fused 3DMatch fragment) along a path, each moved by
  a random rigid transform.

Every set comes as ``(clouds, truth)``: ``truth[k]`` is ``T_world_scan`` of ``clouds[k]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from esmicp.errors import InvalidInputError
from esmicp.types import as_generator


def _read_range_grid(path: Path) -> tuple[np.ndarray, np.ndarray, int]:
    """(vertices, grid cell of each vertex, grid columns) of a Stanford raw scan (ascii PLY with a
    ``range_grid`` element: one line per cell, ``0`` or ``1 <vertex index>``, row by row)."""
    lines = Path(path).read_text().splitlines()
    try:
        end = lines.index("end_header")
        vertices = next(int(line.split()[-1]) for line in lines[:end] if line.startswith("element vertex"))
        columns = next(int(line.split()[-1]) for line in lines[:end] if line.startswith("obj_info num_cols"))
    except (ValueError, StopIteration):
        raise InvalidInputError(f"{path}: not a Stanford range scan (ascii PLY with a range grid)") from None
    points = np.array([line.split()[:3] for line in lines[end + 1: end + 1 + vertices]], dtype=np.float64)
    cell = np.full(vertices, -1)
    for number, line in enumerate(lines[end + 1 + vertices:]):
        if line and line[0] != "0":
            cell[int(line.split()[1])] = number
    return points, cell, columns


def bunny_scanner_origin(path) -> np.ndarray:
    """The viewpoint of the scanner of one Stanford raw scan (a Cyberware 3030MS), in the scan's own
    frame (3-vector, metres).

    The scanner sweeps along x (one grid column per step) and fans each frame's rays in the y-z
    plane: the points of one grid row lie on one line of that plane, and the rows' lines meet at
    the fan's centre (least squares; the bunny's rows pass within 3-6 mm of it, about 1.3 m from
    the object). The viewpoint is that centre, at the middle of the sweep. Seen from it, a scan is
    a range image but for the sweep (its rays are parallel along x, not from one point): within a
    few degrees."""
    points, cell, columns = _read_range_grid(Path(path))
    seen = cell >= 0
    row = cell[seen] // columns
    yz = points[seen][:, 1:]
    order = np.argsort(row, kind="stable")
    starts = np.flatnonzero(np.diff(row[order], prepend=-1))
    normal_sum, right = np.zeros((2, 2)), np.zeros(2)
    for line in np.split(yz[order], starts[1:]):
        if len(line) < 20:
            continue
        centre = line.mean(axis=0)
        direction = np.linalg.eigh(np.cov((line - centre).T))[1][:, -1]
        across = np.eye(2) - np.outer(direction, direction)  # distance to the line, squared
        normal_sum += across
        right += across @ centre
    y, z = np.linalg.solve(normal_sum, right)
    x = 0.5 * (points[:, 0].min() + points[:, 0].max())
    return np.array([x, y, z])


def _look_at(origin: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``T_view_scan``: a frame at ``origin`` (scan coordinates) with its z axis towards ``target``."""
    z = (target - origin) / np.linalg.norm(target - origin)
    up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ origin
    return T


def bunny_in_scanner_frames(folder, names=None, *, max_points: int | None = None, rng=0):
    """``(names, clouds, truth)``: the bunny's raw scans (``folder`` holds ``bun.conf`` and the PLYs),
    each in a frame whose origin is its scanner's viewpoint (:func:`bunny_scanner_origin`), z
    towards the scan's centroid; ``truth[k]`` is ``T_world_scan`` in ``bun.conf``'s world.
    ``names`` (default: every scan of the conf, in its order); ``max_points``: a random subset of
    each (from ``rng``)."""
    from esmicp.io.stanford_conf import load_scans

    folder = Path(folder)
    scans = load_scans(folder, max_points=max_points, rng=rng)
    names = list(scans) if names is None else list(names)
    clouds, truth = [], []
    for name in names:
        points, T_world_raw = scans[name]
        T_view_raw = _look_at(bunny_scanner_origin(folder / f"{name}.ply"), points.mean(axis=0))
        clouds.append(points @ T_view_raw[:3, :3].T + T_view_raw[:3, 3])
        truth.append(T_world_raw @ np.linalg.inv(T_view_raw))
    return names, clouds, truth


def _random_motion(generator, distance, degrees) -> np.ndarray:
    """A rigid transform turning ``degrees`` (a range, uniform) about a random axis and moving
    ``distance`` (a range, uniform) in a random direction."""
    axis = generator.normal(size=3)
    turn = np.radians(generator.uniform(*degrees)) * axis / np.linalg.norm(axis)
    shift = generator.normal(size=3)
    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(turn).as_matrix()
    M[:3, 3] = generator.uniform(*distance) * shift / np.linalg.norm(shift)
    return M


def moved_off(clouds, truth, *, distance=(0.1, 0.3), degrees=(5.0, 20.0), rng=0):
    """``(clouds, truth)`` with each scan moved into a frame ``distance`` (a range, cloud units)
    and ``degrees`` (a range) off its own, independently: the origin is then that far from where
    the scan was seen from."""
    generator = as_generator(rng)
    out_clouds, out_truth = [], []
    for points, T in zip(clouds, truth):
        M = _random_motion(generator, distance, degrees)  # T_new_old
        out_clouds.append(np.asarray(points) @ M[:3, :3].T + M[:3, 3])
        out_truth.append(np.asarray(T) @ np.linalg.inv(M))
    return out_clouds, out_truth


def map_crops(points, count: int, *, radius: float = 0.4, step: float = 0.3, distance=(0.5, 3.0),
              min_points: int = 2000, rng=0):
    """``(clouds, truth)``: ``count`` balls of ``radius`` cut from one map (``points``, one fused
    cloud), centred along a path of steps of about ``step`` (neighbours overlap), each moved by a
    random rigid transform (any rotation; its centroid ``distance``, a range, from the origin in a
    random direction). ``truth[k]`` is ``T_map_crop``. Balls with fewer than ``min_points`` points
    are skipped."""
    generator = as_generator(rng)
    points = np.asarray(points, dtype=np.float64)
    tree = cKDTree(points)
    centre = points[generator.integers(len(points))]
    heading = None
    clouds, truth = [], []
    for _ in range(50 * count):
        if len(clouds) == count:
            break
        inside = tree.query_ball_point(centre, radius)
        if len(inside) >= min_points:
            crop = points[inside]
            M = np.eye(4)
            M[:3, :3] = Rotation.random(random_state=generator).as_matrix()
            where = generator.normal(size=3)
            M[:3, 3] = generator.uniform(*distance) * where / np.linalg.norm(where) - M[:3, :3] @ crop.mean(axis=0)
            clouds.append(crop @ M[:3, :3].T + M[:3, 3])
            truth.append(np.linalg.inv(M))
        # the next centre: a map point about one step away, ahead rather than back
        ring = points[tree.query_ball_point(centre, 1.2 * step)]
        ring = ring[np.linalg.norm(ring - centre, axis=1) > 0.8 * step]
        if len(ring) == 0:
            centre = points[generator.integers(len(points))]
            heading = None
            continue
        ahead = ring if heading is None else ring[(ring - centre) @ heading >= 0] if np.any((ring - centre) @ heading >= 0) else ring
        following = ahead[generator.integers(len(ahead))]
        heading = (following - centre) / np.linalg.norm(following - centre)
        centre = following
    if len(clouds) < count:
        raise InvalidInputError(f"map_crops: only {len(clouds)} balls of {min_points}+ points found, {count} asked")
    return clouds, truth


def turntable_scans(surface, count: int = 15, *, step_deg: float = 24.0, distance: float = 0.5,
                    pixel_deg: float = 0.25, axis=(0.0, 1.0, 0.0)):
    """Range scans of an object on a turntable, stored in the turntable's frame and in the sensor's.

    ``surface``: dense points on the object's surface (a mesh's vertices; cloud units). The
    turntable turns about ``axis`` through the surface's centroid, ``step_deg`` between scans; a
    fixed sensor ``distance`` away on the turntable's z axis looks at the axis and keeps, in each
    square pixel of ``pixel_deg``, the nearest surface point (the surface must be dense enough that
    every pixel it covers holds a few points of its front: then the nearest is one the sensor sees).

    Returns ``(turntable, sensor)``, each ``(clouds, truth)``: the same points in the turntable's
    frame (origin on the axis, the sensor at ``(0, 0, distance)``; how a turntable scanner stores
    its scans) and in the sensor's (origin at the sensor, z towards the axis: range images from
    their origin); ``truth[k]`` is ``T_world_scan`` with the world the surface's own frame.
    """
    surface = np.asarray(surface, dtype=np.float64)
    centre = surface.mean(axis=0)
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    T_sensor_table = np.diag([-1.0, 1.0, -1.0, 1.0])  # turned about y to look down -z of the table
    T_sensor_table[:3, 3] = [0.0, 0.0, distance]
    pixel = np.radians(pixel_deg)
    table, sensor = ([], []), ([], [])
    for k in range(count):
        turn = Rotation.from_rotvec(np.radians(k * step_deg) * axis).as_matrix()
        on_table = (surface - centre) @ turn.T
        seen = on_table @ T_sensor_table[:3, :3].T + T_sensor_table[:3, 3]
        ranges = np.linalg.norm(seen, axis=1)
        cell = np.floor(np.stack([np.arctan2(seen[:, 0], seen[:, 2]), np.arctan2(seen[:, 1], seen[:, 2])], 1) / pixel)
        order = np.lexsort((ranges, cell[:, 1], cell[:, 0]))
        first = np.ones(len(order), bool)
        first[1:] = np.any(np.diff(cell[order], axis=0) != 0, axis=1)
        visible = np.sort(order[first])  # the nearest point of each pixel
        T_world_table = np.eye(4)
        T_world_table[:3, :3], T_world_table[:3, 3] = turn.T, centre
        table[0].append(on_table[visible])
        table[1].append(T_world_table)
        sensor[0].append(seen[visible])
        sensor[1].append(T_world_table @ np.linalg.inv(T_sensor_table))
    return table, sensor
