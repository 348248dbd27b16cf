"""The paper's ESM-ICP formulation, computed exactly as its reference code does, in O(N).

Per iteration, with ``c(i)`` the nearest target point of source point ``i``:

- ``s_bar`` is the mean of ALL source points, ``t_bar`` the mean of the matched target points
  ``t_c(i)`` (both unweighted);
- ``w_i = exp(-d_i^2 / (2 sigma^2))``, ``d_i = ||s_i - t_c(i)||``;
- the N x N similarity matrix is filled, for ``i = 0 .. N-1`` in order, with
  ``M[c(i), i] = w_i`` then ``M[i, c(i)] = w_i`` (a later write to the same entry replaces an
  earlier one, as in the reference);
- ``H = Src_c M^T TgtMatched_c^T`` with the centred source points and centred matched target points
  as the columns of ``Src_c`` and ``TgtMatched_c``;
- ``H = U S V^T``, ``R = V U^T`` (last column of ``V`` negated when ``det U det V < 0``),
  ``t = t_bar - R s_bar``.

Requirement: index-aligned clouds
---------------------------------
The entry ``M[i, c(i)]`` makes ``H`` pair source point ``c(i)`` with the target matched to point
``i``, and ``M[c(i), i]`` pairs source ``i`` with the target matched to point ``c(i)``. These are the
right pairs only when source point k and target point k are the same physical point, as in the
paper's experiments, where the target is a transformed copy of the source in the same order. On
clouds sampled independently, or merely reordered, the matrix pairs unrelated points and the
method fails (measured: see ``docs/esm-paper.md``). Use ``esm`` for real data. With clouds of
different sizes the entries whose indices fall outside ``0 .. N-1`` have no column to act on and
are left out (the reference code would index out of bounds there).

``M`` has at most 2N non-zeros and is never built densely: ``H`` is accumulated from its entries.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..core import moments
from ..core.weights import gaussian_weights
from ..core.procrustes import rotation_from_cross_covariance
from ..types import as_positive
from .base import COMPILED, Estimator, Step
from .config import EsmConfig

if TYPE_CHECKING:  # SciPy is imported where it is used: `register` with `esm` never needs it
    import scipy.sparse

def similarity_entries(
    indices: np.ndarray, weights: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Non-zero entries ``(rows, cols, values)`` of the paper's ``size x size`` matrix M.

    Follows the reference's write order (``M[c(i), i]`` then ``M[i, c(i)]`` for each i) with
    last-write-wins on repeated entries; entries with an index ``>= size`` are dropped.
    O(N log N) time (one sort) and O(N) memory.
    """
    count = len(indices)
    own = np.arange(count, dtype=np.int64)
    matched = np.asarray(indices, dtype=np.int64)
    rows = np.empty(2 * count, dtype=np.int64)
    cols = np.empty(2 * count, dtype=np.int64)
    rows[0::2], cols[0::2] = matched, own
    rows[1::2], cols[1::2] = own, matched
    values = np.repeat(weights, 2)
    inside = (rows < size) & (cols < size)
    rows, cols, values = rows[inside], cols[inside], values[inside]
    keys = rows * size + cols
    _, first_from_end = np.unique(keys[::-1], return_index=True)
    last = len(keys) - 1 - first_from_end
    return rows[last], cols[last], values[last]


def similarity_matrix(indices: np.ndarray, weights: np.ndarray, size: int) -> scipy.sparse.csr_matrix:
    """The paper's similarity matrix M as a sparse ``size x size`` matrix (for inspection and
    heat maps; the solver itself works on :func:`similarity_entries`)."""
    rows, cols, values = similarity_entries(indices, weights, size)
    import scipy.sparse

    return scipy.sparse.csr_matrix((values, (rows, cols)), shape=(size, size))


def paper_cross_covariance(
    source: np.ndarray, matched_target: np.ndarray, indices: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(H, s_bar, t_bar)`` of the paper: ``H = Src_c M^T TgtMatched_c^T`` in O(N), without a sort.

    An entry ``M[r, c] = v`` adds ``v (s_c - s_bar)(tm_r - t_bar)^T`` to ``H``. The entries of
    :func:`similarity_entries` are found without sorting: ``M[c(i), i]`` and ``M[j, c(j)]`` fall on
    the same place only when ``j = c(i)`` and ``c(j) = i`` (a mutual pair, ``i = j`` included),
    and the reference's last write there is that of ``max(i, j)``. So every first entry
    ``M[c(i), i]`` holds ``w_max(i, c(i))`` for a mutual pair and ``w_i`` otherwise, and the second
    entry ``M[i, c(i)]`` of a mutual pair is the same place, counted once.
    """
    count = len(source)
    source_centroid = source.mean(axis=0)
    target_centroid = matched_target.mean(axis=0)
    centred_source = source - source_centroid
    centred_matched = matched_target - target_centroid
    matched = np.asarray(indices, dtype=np.intp)
    valid = np.flatnonzero(matched < count)  # entries with an index >= N have no column
    partner = matched[valid]
    mutual = matched[partner] == valid
    first_values = np.where(mutual, weights[np.maximum(valid, partner)], weights[valid])
    cross_covariance = (centred_source[valid] * first_values[:, None]).T @ centred_matched[partner]
    single = valid[~mutual]
    cross_covariance += (centred_source[matched[single]] * weights[single][:, None]).T @ centred_matched[single]
    return cross_covariance, source_centroid, target_centroid


class EsmPaperEstimator(Estimator):
    """Increment of the paper's formulation (see the module docstring for its requirement)."""

    name = "esm-paper"
    #: Source point i meets target point i in M: the loop must keep the source's order.
    order_invariant = False
    compiled_step = COMPILED

    def __init__(self, sigma: float | None = None):
        """``sigma`` (cloud units): None gives the paper's
        (:attr:`~esmicp.methods.config.EsmConfig.paper_sigma`)."""
        self.sigma = as_positive(EsmConfig().paper_sigma if sigma is None else sigma, "sigma")

    def step(self, moved_source, target, distances, indices) -> Step:
        weights = gaussian_weights(distances, self.sigma)
        cross_covariance, source_centroid, target_centroid = paper_cross_covariance(
            moved_source, target[indices], indices, weights
        )
        rotation = rotation_from_cross_covariance(cross_covariance)
        return Step(rotation, target_centroid - rotation @ source_centroid, weights=weights, sigma=self.sigma)

    def pair_weights(self, distances, sigma):
        return gaussian_weights(distances, self.sigma)

    def step_placed(self, source, transformation, target, distances, indices, workers=None) -> Step:
        """:meth:`step` from the unmoved source and its placement, in two compiled passes."""
        rotation, translation, effective = moments.rigid_fit(
            moments.paper_moments(source, transformation, target, indices, distances, self.sigma, workers)
        )
        return Step(rotation, translation, sigma=self.sigma, effective_pairs=effective)
