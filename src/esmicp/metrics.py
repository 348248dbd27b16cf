"""Errors between an estimated and a true transform (both ``T_target_source``, 4x4), and between an
estimated and a true trajectory (``T_world_frame`` per frame)."""

from __future__ import annotations

import math

import numpy as np

from .core.procrustes import batched_rotation_angle, rotation_angle, weighted_procrustes


def rotation_error_deg(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Geodesic angle between the two rotations, in degrees, in ``[0, 180]``."""
    return float(np.degrees(rotation_angle(estimate[:3, :3].T @ truth[:3, :3])))


def translation_error(estimate: np.ndarray, truth: np.ndarray, pivot: np.ndarray | None = None) -> float:
    """Distance (cloud units) between where the two transforms put the point ``pivot``.

    Without ``pivot`` (the origin) this is the distance between the two translation vectors. With
    ``pivot`` = the source's centroid it measures the translation error where the object is, so
    that it does not also count the rotation error times the object's distance from the origin
    (a 0.5-degree error on a source 5 diameters from the origin moves the origin by 4% of a
    diameter, the object itself by much less).
    """
    if pivot is None:
        return float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))
    pivot = np.asarray(pivot, dtype=float)
    return float(np.linalg.norm((estimate[:3, :3] - truth[:3, :3]) @ pivot + estimate[:3, 3] - truth[:3, 3]))


def paper_errors(estimate: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """The ESM-ICP paper's metrics: MSE, RMSE and MAE over the 9 rotation-matrix entries and over
    the 3 translation components of ``estimate - truth``."""
    rotation_diff = estimate[:3, :3] - truth[:3, :3]
    translation_diff = estimate[:3, 3] - truth[:3, 3]
    rotation_mse = float(np.mean(np.square(rotation_diff)))
    translation_mse = float(np.mean(np.square(translation_diff)))
    return {
        "rotation_mse": rotation_mse,
        "rotation_rmse": float(np.sqrt(rotation_mse)),
        "rotation_mae": float(np.mean(np.abs(rotation_diff))),
        "translation_mse": translation_mse,
        "translation_rmse": float(np.sqrt(translation_mse)),
        "translation_mae": float(np.mean(np.abs(translation_diff))),
    }


def random_rotation(rng: np.random.Generator, max_angle_deg: float = 180.0) -> np.ndarray:
    """A random 3x3 rotation: uniform on SO(3) when ``max_angle_deg >= 180``; otherwise a uniformly
    random axis and an angle uniform in ``[0, max_angle_deg]``.

    The draws and the arithmetic are SciPy's (``Rotation.random(random_state=rng)``,
    ``Rotation.from_rotvec``), bit for bit (tested), so protocols keep their trials; written out
    here so that the demo need not import SciPy."""
    if max_angle_deg >= 180.0:
        x, y, z, w = (float(value) for value in rng.normal(size=4))
        norm = math.sqrt(x * x + y * y + z * z + w * w)
        return _quaternion_matrix(x / norm, y / norm, z / norm, w / norm)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    x, y, z = (float(value) for value in np.radians(rng.uniform(0.0, max_angle_deg)) * axis)
    angle = math.sqrt(x * x + y * y + z * z)
    if angle <= 1e-3:  # sin(a/2)/a by its Taylor series near 0
        squared = angle * angle
        scale = 0.5 - squared / 48.0 + squared * squared / 3840.0
    else:
        scale = math.sin(angle / 2.0) / angle
    return _quaternion_matrix(scale * x, scale * y, scale * z, math.cos(angle / 2.0))


def _quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """The rotation matrix of the unit quaternion ``(x, y, z, w)`` (scalar last)."""
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array([
        [x2 - y2 - z2 + w2, 2.0 * (xy - zw), 2.0 * (xz + yw)],
        [2.0 * (xy + zw), -x2 + y2 - z2 + w2, 2.0 * (yz - xw)],
        [2.0 * (xz - yw), 2.0 * (yz + xw), -x2 - y2 + z2 + w2],
    ])


def strict_success(
    estimate: np.ndarray,
    truth: np.ndarray,
    diagonal: float,
    *,
    max_rotation_deg: float = 2.0,
    max_translation_fraction: float = 0.02,
    pivot: np.ndarray | None = None,
) -> bool:
    """True if the rotation error is < ``max_rotation_deg`` degrees and the translation error is
    < ``max_translation_fraction * diagonal`` (``diagonal``: the target's bounding-box diagonal).

    Pass the source's centroid as ``pivot`` to measure the translation error at the object (see
    :func:`translation_error`); the benchmarks do.
    """
    return bool(
        rotation_error_deg(estimate, truth) < max_rotation_deg
        and translation_error(estimate, truth, pivot) < max_translation_fraction * diagonal
    )


def symmetric_placement_error(source: np.ndarray, estimate: np.ndarray, truth: np.ndarray) -> float:
    """Distance between ``source`` placed by ``estimate`` and by ``truth``, as point sets.

    The mean nearest-neighbour distance from each placement to the other, averaged over both
    directions. It ignores point order, so a placement that differs from the truth by a symmetry
    of the shape (a bottle turned about its axis) scores about the sampling spacing.
    """
    from scipy.spatial import cKDTree

    from .core.procrustes import apply

    by_estimate = apply(estimate, source)
    by_truth = apply(truth, source)
    forward, _ = cKDTree(by_truth).query(by_estimate)
    backward, _ = cKDTree(by_estimate).query(by_truth)
    return float(0.5 * (forward.mean() + backward.mean()))


def up_to_symmetry_success(
    source: np.ndarray, estimate: np.ndarray, truth: np.ndarray, diagonal: float, *, fraction: float = 0.02
) -> bool:
    """True if :func:`symmetric_placement_error` is < ``fraction * diagonal``."""
    return bool(symmetric_placement_error(source, estimate, truth) < fraction * diagonal)


def _trajectory(poses, name: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected an (N, 4, 4) array of poses, got shape {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError(f"{name}: every pose must be finite (leave unplaced frames out of both trajectories)")
    return poses


def absolute_trajectory_error(estimate, truth) -> tuple[float, np.ndarray]:
    """Absolute trajectory error as the TUM RGB-D benchmark computes it.

    The estimated frame positions are aligned onto the true ones by the best rigid transform
    (least squares, Horn / Umeyama without scale); the error is the RMSE of the remaining distances.
    Only positions count: the orientations enter through the relative errors
    (:func:`relative_pose_errors`). Both trajectories may be in different world frames.

    Parameters
    ----------
    estimate, truth : (N, 4, 4) arrays
        ``T_world_frame`` of the same N frames (N >= 3 for a unique alignment), finite.

    Returns
    -------
    rmse : float
        In the trajectories' length unit.
    T_truth_estimate : (4, 4) array
        The alignment: maps the estimate's world frame into the truth's.
    """
    estimate, truth = _trajectory(estimate, "estimate"), _trajectory(truth, "truth")
    if len(estimate) != len(truth):
        raise ValueError(f"estimate and truth: {len(estimate)} and {len(truth)} poses, expected the same frames")
    if len(estimate) < 3:
        raise ValueError(f"estimate: {len(estimate)} poses, need at least 3 for the alignment")
    rotation, translation = weighted_procrustes(estimate[:, :3, 3], truth[:, :3, 3])
    aligned = estimate[:, :3, 3] @ rotation.T + translation
    rmse = float(np.sqrt(np.mean(np.sum((aligned - truth[:, :3, 3]) ** 2, axis=1))))
    alignment = np.eye(4)
    alignment[:3, :3], alignment[:3, 3] = rotation, translation
    return rmse, alignment


def relative_pose_errors(estimate, truth, pairs=None) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose errors per frame pair (the TUM benchmark's RPE, one value per pair).

    For a pair ``(i, j)`` the error transform is ``inv(Q_i^-1 Q_j) P_i^-1 P_j`` (``P`` estimated,
    ``Q`` true ``T_world_frame``): how far the estimated ``T_i_j`` is from the true one. It does not
    depend on either world frame.

    Parameters
    ----------
    estimate, truth : (N, 4, 4) arrays
        ``T_world_frame`` of the same N frames, finite.
    pairs : sequence of (i, j), optional
        Frame index pairs; default the consecutive ones ``(k, k + 1)``.

    Returns
    -------
    rotation_deg, translation : (len(pairs),) arrays
        The error's rotation angle in degrees and its translation's length in the trajectories'
        unit (expressed in frame i).
    """
    estimate, truth = _trajectory(estimate, "estimate"), _trajectory(truth, "truth")
    if len(estimate) != len(truth):
        raise ValueError(f"estimate and truth: {len(estimate)} and {len(truth)} poses, expected the same frames")
    if pairs is None:
        pairs = [(k, k + 1) for k in range(len(estimate) - 1)]
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    if len(pairs) and (pairs.min() < 0 or pairs.max() >= len(estimate)):
        raise ValueError(f"pairs: frame indices must be in [0, {len(estimate) - 1}]")
    first, second = pairs[:, 0], pairs[:, 1]
    estimated = np.linalg.inv(estimate[first]) @ estimate[second]
    true = np.linalg.inv(truth[first]) @ truth[second]
    error = np.linalg.inv(true) @ estimated
    rotation_deg = np.degrees(batched_rotation_angle(error[:, :3, :3])) if len(error) else np.zeros(0)
    return rotation_deg, np.linalg.norm(error[:, :3, 3], axis=1)
