"""Weighted first and second moments of nearest-neighbour pairs, in one compiled pass.

The Procrustes step of ``esm`` and ``icp`` needs, over the pairs ``(s_i, t_c(i))`` with the source
point as currently placed (``s_i = R0 x_i + t0``), the total weight, the weighted sums of both points
and the weighted sum of ``s_i t_c(i)^T``. :func:`pair_moments` forms them without building the
placed source, the gathered targets or the weights as arrays (one pass, on all cores, no
temporaries), and returns the weighted centroids and cross-covariance
(:func:`esmicp.core.procrustes.weighted_procrustes` on the same pairs gives the same fit).

The kernels are C++ (:mod:`esmicp._kernels`): they fill a result array the caller gives, in pieces
of fixed size summed in order, so the result does not depend on the number of threads.

Sums are taken relative to one point of each side (the first pair), so that neither clouds far
from the origin nor a source far from the target lose precision to cancellation.
"""

from __future__ import annotations

import numpy as np

from .. import _kernels
from .compiled_tree import threads
from .weights import kernel_scale
from .pose_kernels import kabsch_rotation

def available() -> bool:
    """True: the compiled kernels are built with the package."""
    return True


def pair_moments(
    source: np.ndarray,
    transform: np.ndarray,
    target: np.ndarray,
    indices: np.ndarray,
    distances: np.ndarray,
    sigma: float | None,
    workers: int | None = None,
) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
    """Moments of the pairs ``(T x_i, target[indices[i]])``, ``x_i`` = ``source[i]``.

    ``T`` is the 4x4 current placement (``T_target_source``); ``distances`` the pairs' lengths
    (cloud units). Weights: ``exp(-(d_i^2 - d_min^2) / (2 sigma^2))`` (the Gaussian weights relative
    to the closest pair, :func:`esmicp.core.weights.relative_gaussian_weights`), or 1 when
    ``sigma`` is None.

    Returns ``(total_weight, total_squared_weight, source_centroid, target_centroid,
    cross_covariance)``: weighted centroids of the placed source and of the matched target points
    (target frame), and ``H = sum_i w_i (s_i - s_bar)(t_i - t_bar)^T / sum_i w_i``. ``workers``:
    threads (None: every core); the result is bitwise the same for any number.
    """
    if len(source) == 0:
        raise ValueError("pair_moments needs at least one pair")
    if sigma is None:
        scale, shift = 0.0, 0.0
    else:
        scale, shift = kernel_scale(sigma), float(np.min(distances * distances))
    out = np.empty(17)
    _kernels.pair_moments(
        *_contiguous(source, transform, target, indices, distances), scale, shift, out, threads(workers),
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


def _contiguous(source, transform, target, indices, distances):
    return (
        np.ascontiguousarray(source, dtype=np.float64), np.ascontiguousarray(transform[:3, :3], dtype=np.float64),
        np.ascontiguousarray(transform[:3, 3], dtype=np.float64), np.ascontiguousarray(target, dtype=np.float64),
        np.ascontiguousarray(indices, dtype=np.int64), np.ascontiguousarray(distances, dtype=np.float64),
    )


def paper_moments(
    source: np.ndarray, transform: np.ndarray, target: np.ndarray, indices: np.ndarray, distances: np.ndarray,
    sigma: float, workers: int | None = None,
) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
    """The paper's ``(sum w, sum w^2, s_bar, t_bar, H)`` for the source placed by ``transform``
    (4x4), in two compiled passes: exactly :func:`esmicp.methods.esm_paper.paper_cross_covariance`
    on ``(T source, target[indices])`` with ``w_i = exp(-d_i^2 / (2 sigma^2))``, and the centroids
    it uses (unweighted, of all placed source points and of all matched target points)."""
    if len(source) == 0:
        raise ValueError("paper_moments needs at least one pair")
    out = np.empty(17)
    _kernels.paper_moments(
        *_contiguous(source, transform, target, indices, distances), kernel_scale(sigma), out, threads(workers),
    )
    return _unpacked(out)
