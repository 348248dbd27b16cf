"""The similarity matrix M of one iteration, as a dense array for heat maps.

- ``esm-paper``: the paper's symmetric N x N matrix, ``M(i, c(i)) = M(c(i), i) = w_i``, written in
  the reference's order (see :func:`esmicp.methods.esm_paper.similarity_entries`).
- ``esm`` (and ``icp``, all weights 1): the rectangular N x M matrix ``M(i, c(i)) = w_i``, rows
  the source points, columns the target points.

``c(i)`` is the target point nearest to source point ``i``; ``w_i = exp(-d_i^2 / (2 sigma^2))``.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError
from ..methods.esm_paper import similarity_matrix as paper_similarity_matrix

#: Largest matrix side drawn densely (a heat map of more points is unreadable anyway).
MAX_HEATMAP_POINTS = 2000


def similarity_matrix(method: str, indices, weights, source_size: int, target_size: int) -> np.ndarray:
    """Dense M of one iteration (see the module docstring), float64."""
    if max(source_size, target_size) > MAX_HEATMAP_POINTS:
        raise InvalidInputError(
            f"points: a heat map of {max(source_size, target_size)} points is not readable (at most "
            f"{MAX_HEATMAP_POINTS}); downsample the clouds first (the paper's Fig. 3 uses about 21)"
        )
    indices = np.asarray(indices, dtype=np.int64)
    weights = np.asarray(weights, dtype=np.float64)
    if method == "esm-paper":
        return paper_similarity_matrix(indices, weights, source_size).toarray()
    matrix = np.zeros((source_size, target_size))
    matrix[np.arange(len(indices)), indices] = weights
    return matrix
