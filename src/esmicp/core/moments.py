"""Weighted first and second moments of nearest-neighbour pairs, in one compiled pass.

The Procrustes step of ``esm`` and ``icp`` needs, over the pairs ``(s_i, t_c(i))`` with the source
point as currently placed (``s_i = R0 x_i + t0``), the total weight, the weighted sums of both points
and the weighted sum of ``s_i t_c(i)^T``. :func:`pair_moments` forms them without building the
placed source, the gathered targets or the weights as arrays (one pass, on all cores, no
temporaries), and returns the weighted centroids and cross-covariance
(:func:`esmicp.core.procrustes.weighted_procrustes` on the same pairs gives the same fit).

The parallel kernels return nothing: they fill a result array the caller gives. (A parallel numba
function that boxes a new array on return calls back into Python to do so, and a Ctrl-C landing
in that call surfaces as a ``SystemError`` instead of ``KeyboardInterrupt``: measured, 1 in 2
interrupts of a bench run were lost that way.)

Sums are taken relative to one point of each side (the first pair), so that neither clouds far
from the origin nor a source far from the target lose precision to cancellation.
"""

from __future__ import annotations

import numpy as np

from . import compiled_tree
from .compiled_tree import chunk_count, run_parallel
from .weights import kernel_scale
from .pose_kernels import kabsch_rotation

try:  # numba is a dependency, but the library still works (slower) without it.
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None


def available() -> bool:
    """True when the compiled pass can run (numba importable)."""
    return numba is not None


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def _smallest_square(distances):
        smallest = np.inf
        for value in distances:
            smallest = min(smallest, value * value)
        return smallest

    @numba.njit(cache=True, parallel=True, nogil=True)
    def _moments(source, rotation, translation, target, indices, distances, scale, shift, chunks, out):
        count = source.shape[0]
        # References: the first pair, so that no offset between or of the clouds cancels digits.
        source_reference = np.empty(3)
        target_reference = np.empty(3)
        for a in range(3):
            source_reference[a] = (rotation[a, 0] * source[0, 0] + rotation[a, 1] * source[0, 1]
                                   + rotation[a, 2] * source[0, 2] + translation[a])
            target_reference[a] = target[indices[0], a]
        partial = np.zeros((chunks, 17))
        for chunk in numba.prange(chunks):
            # Local accumulators (registers), written once per chunk: no false sharing.
            w0 = w1 = ax = ay = az = bx = by = bz = 0.0
            cxx = cxy = cxz = cyx = cyy = cyz = czx = czy = czz = 0.0
            for i in range(chunk * count // chunks, (chunk + 1) * count // chunks):
                if scale > 0.0:
                    w = np.exp(-(distances[i] * distances[i] - shift) * scale)
                else:
                    w = 1.0
                sx, sy, sz = compiled_tree.mapped(source, i, rotation, translation)
                sx, sy, sz = sx - source_reference[0], sy - source_reference[1], sz - source_reference[2]
                j = indices[i]
                tx = target[j, 0] - target_reference[0]
                ty = target[j, 1] - target_reference[1]
                tz = target[j, 2] - target_reference[2]
                w0 += w
                w1 += w * w
                wx, wy, wz = w * sx, w * sy, w * sz
                ax += wx
                ay += wy
                az += wz
                bx += w * tx
                by += w * ty
                bz += w * tz
                cxx += wx * tx
                cxy += wx * ty
                cxz += wx * tz
                cyx += wy * tx
                cyy += wy * ty
                cyz += wy * tz
                czx += wz * tx
                czy += wz * ty
                czz += wz * tz
            row = partial[chunk]
            row[0], row[1], row[2], row[3], row[4], row[5], row[6], row[7] = w0, w1, ax, ay, az, bx, by, bz
            row[8], row[9], row[10], row[11], row[12], row[13] = cxx, cxy, cxz, cyx, cyy, cyz
            row[14], row[15], row[16] = czx, czy, czz
        sums = np.zeros(17)
        for chunk in range(chunks):
            sums += partial[chunk]
        total = sums[0]
        out[0], out[1] = total, sums[1]
        for a in range(3):
            for b in range(3):
                out[8 + 3 * a + b] = sums[8 + 3 * a + b] / total - (sums[2 + a] / total) * (sums[5 + b] / total)
        for a in range(3):
            out[2 + a] = sums[2 + a] / total + source_reference[a]
            out[5 + a] = sums[5 + a] / total + target_reference[a]


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
    to the closest pair, :func:`esmicp.core.weights.relative_gaussian_weights`), or 1 when
    ``sigma`` is None.

    Returns ``(total_weight, total_squared_weight, source_centroid, target_centroid,
    cross_covariance)``: weighted centroids of the placed source and of the matched target points
    (target frame), and ``H = sum_i w_i (s_i - s_bar)(t_i - t_bar)^T / sum_i w_i``.
    """
    if len(source) == 0:
        raise ValueError("pair_moments needs at least one pair")
    if sigma is None:
        scale, shift = 0.0, 0.0
    else:
        scale, shift = kernel_scale(sigma), _smallest_square(distances)
    out = np.empty(17)
    run_parallel(
        _moments, source, np.ascontiguousarray(transform[:3, :3]), np.ascontiguousarray(transform[:3, 3]),
        target, indices, distances, scale, shift, chunk_count(len(source), per_thread=1), out,
    )
    return _unpacked(out)


def _unpacked(out: np.ndarray) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
    return float(out[0]), float(out[1]), out[2:5], out[5:8], out[8:17].reshape(3, 3)


def rigid_fit(moments: tuple[float, float, np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, float]:
    """``(rotation, translation, effective_pairs)`` from :func:`pair_moments` or
    :func:`paper_moments`: the Kabsch rotation of the cross-covariance, ``t = t_bar - R s_bar``,
    and Kish's effective number of pairs ``(sum w)^2 / sum w^2``."""
    total, squares, source_mean, target_mean, cross = moments
    rotation = kabsch_rotation(cross)
    effective = total * total / squares if squares > 0 else 0.0
    return rotation, target_mean - rotation @ source_mean, effective


if numba is not None:

    @numba.njit(cache=True, nogil=True, inline="always")
    def _add_outer(h, weight, ax, ay, az, bx, by, bz):
        """``h += weight * a b^T`` (3x3, row-major in 9 entries)."""
        h[0] += weight * ax * bx
        h[1] += weight * ax * by
        h[2] += weight * ax * bz
        h[3] += weight * ay * bx
        h[4] += weight * ay * by
        h[5] += weight * ay * bz
        h[6] += weight * az * bx
        h[7] += weight * az * by
        h[8] += weight * az * bz

    @numba.njit(cache=True, parallel=True, nogil=True)
    def _paper_moments(source, rotation, translation, target, indices, distances, scale, chunks, out):
        count = source.shape[0]
        # Pass 1: the unweighted centroids of the placed source and of the matched target points,
        # and the weights' sums.
        partial = np.zeros((chunks, 8))
        for chunk in numba.prange(chunks):
            sx = sy = sz = mx = my = mz = w0 = w1 = 0.0
            for i in range(chunk * count // chunks, (chunk + 1) * count // chunks):
                x, y, z = compiled_tree.mapped(source, i, rotation, translation)
                sx += x
                sy += y
                sz += z
                j = indices[i]
                mx += target[j, 0]
                my += target[j, 1]
                mz += target[j, 2]
                w = np.exp(-distances[i] * distances[i] * scale)
                w0 += w
                w1 += w * w
            row = partial[chunk]
            row[0], row[1], row[2], row[3], row[4], row[5], row[6], row[7] = sx, sy, sz, mx, my, mz, w0, w1
        sums = np.zeros(8)
        for chunk in range(chunks):
            sums += partial[chunk]
        s_bar = np.empty(3)
        t_bar = np.empty(3)
        for a in range(3):
            s_bar[a] = sums[a] / count
            t_bar[a] = sums[3 + a] / count
        # Pass 2: H from M's entries (see esmicp.methods.esm_paper.paper_cross_covariance).
        blocks = np.zeros((chunks, 9))
        for chunk in numba.prange(chunks):
            h = np.zeros(9)
            for i in range(chunk * count // chunks, (chunk + 1) * count // chunks):
                partner = indices[i]
                if partner >= count:
                    continue  # M[c(i), i] and M[i, c(i)] have no column to act on
                w = np.exp(-distances[i] * distances[i] * scale)
                mutual = indices[partner] == i
                first = w
                if mutual and partner > i:
                    first = np.exp(-distances[partner] * distances[partner] * scale)
                # M[c(i), i] = first: source i with the target matched to c(i).
                x, y, z = compiled_tree.mapped(source, i, rotation, translation)
                k = indices[partner]
                ax, ay, az = x - s_bar[0], y - s_bar[1], z - s_bar[2]
                bx, by, bz = target[k, 0] - t_bar[0], target[k, 1] - t_bar[1], target[k, 2] - t_bar[2]
                _add_outer(h, first, ax, ay, az, bx, by, bz)
                if not mutual:
                    # M[i, c(i)] = w_i: source c(i) with the target matched to i.
                    x, y, z = compiled_tree.mapped(source, partner, rotation, translation)
                    j = indices[i]
                    ax, ay, az = x - s_bar[0], y - s_bar[1], z - s_bar[2]
                    bx, by, bz = target[j, 0] - t_bar[0], target[j, 1] - t_bar[1], target[j, 2] - t_bar[2]
                    _add_outer(h, w, ax, ay, az, bx, by, bz)
            blocks[chunk] = h
        out[:] = 0.0
        out[0], out[1] = sums[6], sums[7]
        for a in range(3):
            out[2 + a], out[5 + a] = s_bar[a], t_bar[a]
        for chunk in range(chunks):
            for a in range(9):
                out[8 + a] += blocks[chunk, a]


def paper_moments(
    source: np.ndarray, transform: np.ndarray, target: np.ndarray, indices: np.ndarray, distances: np.ndarray,
    sigma: float,
) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
    """The paper's ``(sum w, sum w^2, s_bar, t_bar, H)`` for the source placed by ``transform``
    (4x4), in two compiled passes: exactly :func:`esmicp.methods.esm_paper.paper_cross_covariance`
    on ``(T source, target[indices])`` with ``w_i = exp(-d_i^2 / (2 sigma^2))``, and the centroids
    it uses (unweighted, of all placed source points and of all matched target points)."""
    if len(source) == 0:
        raise ValueError("paper_moments needs at least one pair")
    out = np.empty(17)
    run_parallel(
        _paper_moments, source, np.ascontiguousarray(transform[:3, :3]), np.ascontiguousarray(transform[:3, 3]),
        target, indices, distances, kernel_scale(sigma), chunk_count(len(source), per_thread=1), out,
    )
    return _unpacked(out)
