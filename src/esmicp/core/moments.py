"""Weighted first and second moments of nearest-neighbour pairs, in one compiled pass.

The Procrustes step of ``esm`` and ``icp`` needs, over the pairs ``(s_i, t_c(i))`` with the source
point as currently placed (``s_i = R0 x_i + t0``), the total weight, the weighted sums of both points
and the weighted sum of ``s_i t_c(i)^T``. :func:`pair_moments` forms them without building the
placed source, the gathered targets or the weights as arrays (one pass, on all cores, no
temporaries), and returns the weighted centroids and cross-covariance
(:func:`esmicp.core.procrustes.weighted_procrustes` on the same pairs gives the same fit).

Sums are taken relative to one point of each side (the first pair), so that neither clouds far
from the origin nor a source far from the target lose precision to cancellation.
"""

from __future__ import annotations

import numpy as np

from .compiled_tree import chunk_count, run_parallel

try:  # numba is a dependency, but the library still works (slower) without it.
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None


def available() -> bool:
    """True when the compiled pass can run (numba importable)."""
    return numba is not None


if numba is not None:

    @numba.njit(cache=True, parallel=True, nogil=True)
    def _moments(source, rotation, translation, target, indices, squared_distances, scale, shift, source_reference,
                 target_reference, chunks):
        count = source.shape[0]
        partial = np.zeros((chunks, 17))
        for chunk in numba.prange(chunks):
            acc = partial[chunk]
            for i in range(chunk * count // chunks, (chunk + 1) * count // chunks):
                if scale > 0.0:
                    w = np.exp(-(squared_distances[i] - shift) * scale)
                else:
                    w = 1.0
                sx = rotation[0, 0] * source[i, 0] + rotation[0, 1] * source[i, 1] + rotation[0, 2] * source[i, 2] + translation[0] - source_reference[0]
                sy = rotation[1, 0] * source[i, 0] + rotation[1, 1] * source[i, 1] + rotation[1, 2] * source[i, 2] + translation[1] - source_reference[1]
                sz = rotation[2, 0] * source[i, 0] + rotation[2, 1] * source[i, 1] + rotation[2, 2] * source[i, 2] + translation[2] - source_reference[2]
                j = indices[i]
                tx = target[j, 0] - target_reference[0]
                ty = target[j, 1] - target_reference[1]
                tz = target[j, 2] - target_reference[2]
                acc[0] += w
                acc[1] += w * w
                acc[2] += w * sx
                acc[3] += w * sy
                acc[4] += w * sz
                acc[5] += w * tx
                acc[6] += w * ty
                acc[7] += w * tz
                wx, wy, wz = w * sx, w * sy, w * sz
                acc[8] += wx * tx
                acc[9] += wx * ty
                acc[10] += wx * tz
                acc[11] += wy * tx
                acc[12] += wy * ty
                acc[13] += wy * tz
                acc[14] += wz * tx
                acc[15] += wz * ty
                acc[16] += wz * tz
        return partial.sum(axis=0)


def pair_moments(
    source: np.ndarray,
    transform: np.ndarray,
    target: np.ndarray,
    indices: np.ndarray,
    distances: np.ndarray,
    sigma: float | None,
) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
    """Moments of the pairs ``(T x_i, target[indices[i]])``, ``x_i`` = ``source[i]``.

    ``T`` is the 4x4 current placement (``T_target_source``); ``distances`` the pairs' lengths
    (cloud units). Weights: ``exp(-(d_i^2 - d_min^2) / (2 sigma^2))`` (the Gaussian weights relative
    to the closest pair, :func:`esmicp.core.kernels.relative_gaussian_weights`), or 1 when
    ``sigma`` is None.

    Returns ``(total_weight, total_squared_weight, source_centroid, target_centroid,
    cross_covariance)``: weighted centroids of the placed source and of the matched target points
    (target frame), and ``H = sum_i w_i (s_i - s_bar)(t_i - t_bar)^T / sum_i w_i``.
    """
    source = np.ascontiguousarray(source, dtype=np.float64)
    squared = np.square(distances)
    if sigma is None:
        scale, shift = 0.0, 0.0
    else:
        scale, shift = 1.0 / (2.0 * sigma * sigma), float(squared.min())
    rotation = np.ascontiguousarray(transform[:3, :3], dtype=np.float64)
    translation = np.ascontiguousarray(transform[:3, 3], dtype=np.float64)
    source_reference = rotation @ source[0] + translation
    target_reference = np.array(target[indices[0]], dtype=np.float64)
    sums = run_parallel(
        _moments,
        source, rotation, translation, target, indices, squared, scale, shift, source_reference,
        target_reference, chunk_count(len(source)),
    )
    total = sums[0]
    source_mean = sums[2:5] / total
    target_mean = sums[5:8] / total
    cross = sums[8:17].reshape(3, 3) / total - np.outer(source_mean, target_mean)
    return float(total), float(sums[1]), source_mean + source_reference, target_mean + target_reference, cross
