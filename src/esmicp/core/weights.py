"""Gaussian similarity weights of the ESM formulation.

``w_i = exp(-d_i^2 / (2 sigma^2))`` with ``d_i`` the Euclidean distance between a source point and
its correspondence, ``sigma`` in the clouds' units.
"""

from __future__ import annotations

import numpy as np

#: Sigmas below this (cloud units) are computed as this one. ``1 / (2 sigma^2)`` overflows to inf near 1e-154
#: (and 2 sigma^2 is 0 near 1e-162); at 1e-150 every distance a representable cloud can hold
#: (clouds span at least 1e-100, see :mod:`esmicp.types`) other than 0 already weighs exactly 0,
#: so any smaller sigma gives the same weights.
SIGMA_FLOOR = 1e-150


def kernel_scale(sigma: float) -> float:
    """``1 / (2 sigma^2)``, finite for every positive sigma (see :data:`SIGMA_FLOOR`)."""
    sigma = max(float(sigma), SIGMA_FLOOR)
    return 1.0 / (2.0 * sigma * sigma)


def gaussian_weights(distances: np.ndarray, sigma: float) -> np.ndarray:
    """The paper's weights ``exp(-d^2 / (2 sigma^2))``, exactly (values in ``(0, 1]``).

    These can all underflow to 0 when every distance is much larger than ``sigma``; use
    :func:`relative_gaussian_weights` where only weight ratios matter.
    """
    with np.errstate(over="ignore"):  # d^2 * scale may be inf: weight 0
        return np.exp(-np.square(distances) * kernel_scale(sigma))


def relative_gaussian_weights(distances: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian weights divided by the largest one: ``exp(-(d^2 - d_min^2) / (2 sigma^2))``.

    A common factor cancels in weighted centroids and in the rotation of weighted Procrustes, so
    these give exactly the fit of :func:`gaussian_weights`, but never all underflow to zero: the
    closest pair always weighs 1.
    """
    squared = np.square(distances)
    with np.errstate(over="ignore"):  # (d^2 - d_min^2) * scale may be inf: weight 0
        return np.exp(-(squared - squared.min()) * kernel_scale(sigma))


def effective_count(weights: np.ndarray) -> float:
    """Kish's effective number of pairs ``(sum w)^2 / sum w^2`` (N for equal weights)."""
    total = float(weights.sum())
    squares = float(np.square(weights).sum())
    return total * total / squares if squares > 0 else 0.0
