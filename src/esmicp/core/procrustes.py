"""Closed-form rigid fits (Kabsch / weighted Procrustes, one and batched), small SE(3) helpers, and
the size of a cloud (its bounding-box diagonal): the one home of each.

All transforms are ``T_target_source``: ``target ~= source @ R.T + t``.
"""

from __future__ import annotations

import numpy as np

from .. import _kernels
from . import pose_kernels


def rotation_from_cross_covariance(cross_covariance: np.ndarray) -> np.ndarray:
    """Rotation ``R = V diag(1, 1, d) U^T`` maximising ``trace(R H)`` for ``H = U S V^T``.

    ``H`` is the 3x3 cross-covariance ``sum_i w_i (s_i - s_bar)(t_i - t_bar)^T``; ``d`` fixes a
    reflection so that ``det R = +1`` (the standard Kabsch/Umeyama correction).
    """
    return pose_kernels.kabsch_rotation(np.asarray(cross_covariance, dtype=np.float64))


def batched_rotation_from_cross_covariance(cross_covariances: np.ndarray) -> np.ndarray:
    """Kabsch rotations ``(K, 3, 3)`` maximising ``trace(R H_k)`` for each ``H_k`` (reflection-fixed),
    as :func:`rotation_from_cross_covariance` does for one."""
    u, _, vt = np.linalg.svd(cross_covariances)
    v = np.swapaxes(vt, -1, -2)
    ut = np.swapaxes(u, -1, -2)
    sign = np.sign(np.linalg.det(v @ ut))
    sign[sign == 0] = 1.0
    v = v.copy()
    v[:, :, 2] *= sign[:, None]
    return v @ ut


def weighted_procrustes(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid fit of paired points.

    Minimises ``sum_i w_i ||R s_i + t - t_i||^2`` over rotations ``R`` and translations ``t``.

    Parameters
    ----------
    source, target : (N, 3) arrays
        Paired points: ``source[i]`` corresponds to ``target[i]``.
    weights : (N,) array of non-negative numbers, optional
        Per-pair weights; only their ratios matter. None means all ones.

    Returns
    -------
    rotation : (3, 3) array, translation : (3,) array
        ``T_target_source`` as ``(R, t)``.
    """
    if weights is None:
        weights = np.ones(len(source))
    total = weights.sum()
    normalised = weights / total
    source_centroid = normalised @ source
    target_centroid = normalised @ target
    cross_covariance = (source - source_centroid).T @ ((target - target_centroid) * normalised[:, None])
    rotation = rotation_from_cross_covariance(cross_covariance)
    return rotation, target_centroid - rotation @ source_centroid


def batched_weighted_procrustes(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`weighted_procrustes` of many paired point sets at once (feature correspondences under
    many hypotheses, groups of them).

    Parameters
    ----------
    source, target : (B, n, 3) arrays, or (n, 3) shared by every fit
        Paired points of each fit (at least one of the two batched when ``weights`` is None).
    weights : (B, n) array, optional
        Non-negative per-pair weights, a positive sum per fit (e.g. a 0/1 inlier mask); None
        means all ones.

    Returns
    -------
    rotations : (B, 3, 3) array, translations : (B, 3) array
        ``target ~= source @ R.T + t`` for each fit.
    """
    source, target = np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64)
    if weights is None:
        batch = source.shape[0] if source.ndim == 3 else target.shape[0]
        weights = np.ones((batch, source.shape[-2]))
    normalised = weights / weights.sum(axis=1, keepdims=True)
    source_centroid = np.matmul(normalised[:, None], source)[:, 0]
    target_centroid = np.matmul(normalised[:, None], target)[:, 0]
    centred_source = np.swapaxes(source - source_centroid[:, None], 1, 2)
    cross = np.matmul(centred_source, (target - target_centroid[:, None]) * normalised[:, :, None])
    rotations = batched_rotation_from_cross_covariance(cross)
    return rotations, target_centroid - np.einsum("bij,bj->bi", rotations, source_centroid)


def to_matrix(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """4x4 homogeneous matrix from a 3x3 rotation and a 3-vector translation."""
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = translation
    return matrix


def apply(transform: np.ndarray, points: np.ndarray, workers: int | None = None) -> np.ndarray:
    """Map ``(N, 3)`` points through a 4x4 transform: ``points @ R.T + t`` (a new array), in the
    compiled kernels on ``workers`` threads (None: every core): NumPy's product would wake BLAS's
    own threads, which then compete with the kernels' (measured under load: 0.9 s for 1M points)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        return points @ transform[:3, :3].T + transform[:3, 3]
    transform = np.asarray(transform, dtype=np.float64)
    out = np.empty_like(points)
    _kernels.transform_points(points, np.ascontiguousarray(transform[:3, :3]), np.ascontiguousarray(transform[:3, 3]),
                              out, 0 if workers is None else int(workers))
    return out


def rigid_inverse(transform: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform, or of each of ``(..., 4, 4)``: ``[R^T | -R^T t]``."""
    transform = np.asarray(transform, dtype=np.float64)
    rotation = np.swapaxes(transform[..., :3, :3], -1, -2)
    out = np.zeros_like(transform)
    out[..., :3, :3] = rotation
    out[..., :3, 3] = -np.einsum("...ab,...b->...a", rotation, transform[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def skew(vectors: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]_x`` (``[v]_x w = v x w``) of a 3-vector, or of each of ``(..., 3)``."""
    vectors = np.asarray(vectors, dtype=np.float64)
    out = np.zeros(vectors.shape[:-1] + (3, 3))
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    out[..., 0, 1], out[..., 0, 2] = -z, y
    out[..., 1, 0], out[..., 1, 2] = z, -x
    out[..., 2, 0], out[..., 2, 1] = -y, x
    return out


def axis_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis minimum and maximum ``(low, high)`` of an ``(N, D)`` array (a cloud: its
    axis-aligned bounding box, in its units; NaN propagates as in ``min``).

    Reduced column by column: NumPy's ``min(axis=0)`` over 3 columns runs a strided inner loop that
    is several times slower than three contiguous reductions (``docs/speed.md``).
    """
    points = np.asarray(points)
    columns = range(points.shape[1])
    return np.array([points[:, axis].min() for axis in columns]), np.array([points[:, axis].max() for axis in columns])


def centroid(points: np.ndarray) -> np.ndarray:
    """``points.mean(axis=0)`` of an ``(N, 3)`` array, to the last bit (cloud units): a C-contiguous
    float64 cloud's column sums are compiled (NumPy adds the rows in order, as the kernel does, but
    its inner loop of three values per row costs a 300k-point cloud some milliseconds)."""
    points = np.asarray(points)
    if points.dtype != np.float64 or points.ndim != 2 or points.shape[1] != 3 or len(points) == 0 \
            or not points.flags.c_contiguous:
        return points.mean(axis=0)
    sums = np.empty(3)
    _kernels.column_sums(points, sums)
    return sums / len(points)


def bounding_box_diagonal(points: np.ndarray) -> float:
    """Length of the diagonal of the axis-aligned bounding box of ``(N, 3)`` points (the size of a
    cloud, in its units)."""
    low, high = axis_bounds(np.asarray(points, dtype=np.float64))
    return float(np.linalg.norm(high - low))


def rotation_angle(rotation: np.ndarray) -> float:
    """Geodesic angle of a 3x3 rotation, in radians, in ``[0, pi]``.

    Accurate for tiny angles too (uses ``atan2`` of the skew part and the trace).
    """
    return pose_kernels.angle_of(np.asarray(rotation, dtype=np.float64))


def batched_rotation_angle(rotations: np.ndarray) -> np.ndarray:
    """Geodesic angles (radians, ``[0, pi]``) of ``(..., 3, 3)`` rotations: :func:`rotation_angle`'s
    ``atan2`` of the skew part and the trace, for a whole array at once."""
    skew_x = rotations[..., 2, 1] - rotations[..., 1, 2]
    skew_y = rotations[..., 0, 2] - rotations[..., 2, 0]
    skew_z = rotations[..., 1, 0] - rotations[..., 0, 1]
    trace = rotations[..., 0, 0] + rotations[..., 1, 1] + rotations[..., 2, 2]
    return np.arctan2(0.5 * np.sqrt(skew_x * skew_x + skew_y * skew_y + skew_z * skew_z), 0.5 * (trace - 1.0))


def project_to_rotation(matrix: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (in Frobenius norm) to a 3x3 matrix; removes accumulated drift."""
    return pose_kernels.nearest_rotation(np.asarray(matrix, dtype=np.float64))
