"""The small per-iteration pose arithmetic of a local registration, in plain NumPy.

Every iteration turns a 3x3 cross-covariance into a rotation (:func:`kabsch_rotation`), composes
the increment with the current pose (:func:`compose`) and measures how far it moved
(:func:`motion_between`). Each is a
handful of 3x3 operations, so their cost is the calls, not the arithmetic: the local loop's
compiled step (:meth:`esmicp.core.correspondence.NearestNeighbors.step`) does the Kabsch rotation
and the composition inside the kernel; these functions serve the path with callbacks,
``esm-paper`` and ``esm-plane``'s step (Anderson acceleration's pose arithmetic is compiled whole:
:mod:`esmicp.methods.acceleration`).

All transforms are 4x4 ``T_target_source`` matrices; angles are in radians.
"""

from __future__ import annotations

import math

import numpy as np

def _mul(a, b):
    """``a @ b`` for 3x3 matrices and 3-vectors (NumPy's own small-matrix loop: no BLAS threads)."""
    return np.matmul(a, b)


def kabsch_rotation(cross_covariance):
    """``R = V diag(1, 1, d) U^T`` maximising ``trace(R H)`` for ``H = U S V^T`` (``d`` makes
    ``det R = +1``); see :func:`esmicp.core.procrustes.rotation_from_cross_covariance`. NumPy's
    SVD: where the rotation is not unique (a rank-1 ``H``, every weight but one ~0 in
    ``esm-paper``'s first steps from a full turn) its choice is the one the measured protocols
    were run with. (The one-call iteration of ``esm`` / ``icp`` uses Horn's method in the kernel:
    the same rotation, to rounding, wherever it is unique.)"""
    u, _, vt = np.linalg.svd(np.ascontiguousarray(cross_covariance))
    v = np.ascontiguousarray(vt.T)
    ut = np.ascontiguousarray(u.T)
    if np.linalg.det(_mul(v, ut)) < 0.0:
        v[:, 2] = -v[:, 2]
    return _mul(v, ut)


def nearest_rotation(matrix):
    """The rotation nearest to a 3x3 matrix (Frobenius norm): removes accumulated rounding drift."""
    u, _, vt = np.linalg.svd(np.ascontiguousarray(matrix))
    if np.linalg.det(_mul(u, vt)) < 0.0:
        u = u.copy()
        u[:, 2] = -u[:, 2]
    return _mul(u, vt)


def angle_of(rotation):
    """Geodesic angle of a 3x3 rotation in ``[0, pi]`` (accurate for tiny angles)."""
    sx = rotation[2, 1] - rotation[1, 2]
    sy = rotation[0, 2] - rotation[2, 0]
    sz = rotation[1, 0] - rotation[0, 1]
    trace = rotation[0, 0] + rotation[1, 1] + rotation[2, 2]
    return math.atan2(0.5 * math.sqrt(sx * sx + sy * sy + sz * sz), 0.5 * (trace - 1.0))


def compose(rotation, translation, transformation):
    """``[rotation | translation] @ transformation`` (4x4), its rotation re-orthonormalised (an
    increment composed on the left, as every iteration does, without accumulating drift)."""
    pose = np.eye(4)
    pose[:3, :3] = nearest_rotation(_mul(rotation, transformation[:3, :3]))
    pose[:3, 3] = _mul(rotation, transformation[:3, 3]) + translation
    return pose


def motion_between(before, after):
    """``(angle, translation_norm)`` of the rigid motion ``after @ inv(before)`` (radians, cloud
    units): how far one iteration moved the pose."""
    rotation = _mul(after[:3, :3], before[:3, :3].T)
    translation = after[:3, 3] - _mul(rotation, before[:3, 3])
    return angle_of(rotation), math.sqrt(translation @ translation)


def rotation_exp(vector):
    """3x3 rotation of a rotation vector (axis x angle, radians): Rodrigues' formula.

    ``esm-plane``'s Gauss-Newton step solves for a rotation vector and applies it through this.
    """
    angle = math.sqrt(vector @ vector)
    k = np.array([
        [0.0, -vector[2], vector[1]],
        [vector[2], 0.0, -vector[0]],
        [-vector[1], vector[0], 0.0],
    ])
    if angle < 1e-4:
        a = 1.0 - angle * angle / 6.0
        b = 0.5 - angle * angle / 24.0
    else:
        a = math.sin(angle) / angle
        b = (1.0 - math.cos(angle)) / (angle * angle)
    return np.eye(3) + a * k + b * _mul(k, k)
