"""Choosing among the pose fits of pruned correspondences when few of them are true.

At 10-30% overlap, 0.1-6% of the FPFH correspondences are true (a few to a few dozen of 2,500).
The second-order pruning (:func:`esmicp.globalreg.scan.prune`) still grows a right fit from a true
seed, but the fits of outlier groups are consistent with about as many correspondences as the
right one: ranked by their correspondence inliers, the right fit is often not among the few that
are verified. What separates it is the geometry: placed by the right pose, many more of the source
keypoints land on the target.

:func:`occupancy_scores` measures that for hundreds of fits at once, cheaply: the fraction of a
strided sample of the source keypoints that each fit places in a cell occupied by the target (its
keypoints' cells and their 26 neighbours, so a hit lies within about two cell edges). A sorted
array of the occupied cells' keys answers every lookup; no tree descent, whose cost grows with a
wrong pose's distance from the data. This score does not tell a fit slid along a wall or a floor
from the truth, which the correspondences do: :func:`best_of_both` keeps the best distinct fits by
each score, for the verification on the overlap to decide.

Transforms are ``T_target_source``: a fit maps ``source @ R.T + t`` into the target frame.
"""

from __future__ import annotations

import numpy as np

from .feature_matching import _distinct_order

#: The 27 cell offsets of a cell and its neighbours (a target cell is counted as occupied around it).
_NEIGHBOURS = np.stack(np.meshgrid(*(np.arange(-1, 2),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)


class _OccupiedCells:
    """The cells of edge ``cell`` (cloud units) within one cell of a ``target`` point, as sorted
    integer keys of a grid whose corner lies one cell below the target's per-axis minimum."""

    def __init__(self, target: np.ndarray, cell: float):
        self.cell = float(cell)
        self.low = target.min(axis=0) - self.cell
        cells = np.floor((target - self.low) / self.cell).astype(np.int64)
        self.shape = cells.max(axis=0) + 2  # one cell of margin above
        dilated = (cells[:, None, :] + _NEIGHBOURS[None]).reshape(-1, 3)
        self.keys = np.unique(self._key(dilated))

    def _key(self, cells: np.ndarray) -> np.ndarray:
        return (cells[:, 0] * self.shape[1] + cells[:, 1]) * self.shape[2] + cells[:, 2]

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask: each point lies in an occupied cell."""
        cells = np.floor((points - self.low) / self.cell)
        inside = np.all((cells >= 0) & (cells < self.shape), axis=-1)
        keys = self._key(np.where(inside[..., None], cells, 0).astype(np.int64).reshape(-1, 3)).reshape(inside.shape)
        where = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        return inside & (self.keys[where] == keys)


def occupancy_scores(rotations: np.ndarray, translations: np.ndarray, source: np.ndarray, target: np.ndarray,
                     cell: float, points: int) -> np.ndarray:
    """``(F,)`` fraction (0-1) of ``source`` points (at most ``points`` of them, evenly strided)
    that each fit ``(rotations[f], translations[f])`` places in a cell of edge ``cell`` (cloud
    units) occupied by ``target`` or next to one (within about ``2 cell`` of a target point).

    ``rotations`` ``(F, 3, 3)``, ``translations`` ``(F, 3)``: ``T_target_source`` fits;
    ``source`` ``(N, 3)`` and ``target`` ``(M, 3)`` in their own frames. Deterministic; invariant
    to the order of ``target``'s points."""
    rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    translations = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    source = np.asarray(source, dtype=np.float64)
    if len(rotations) == 0 or len(source) == 0 or len(target) == 0:
        return np.zeros(len(rotations))
    stride = -(-len(source) // max(int(points), 1))
    sample = source[::stride]
    occupied = _OccupiedCells(np.asarray(target, dtype=np.float64), cell)
    placed = np.matmul(sample, rotations.transpose(0, 2, 1)) + translations[:, None, :]
    return occupied.contains(placed).mean(axis=1)


def best_of_both(rotations: np.ndarray, translations: np.ndarray, first: np.ndarray, second: np.ndarray,
                 count: int, min_translation: float, min_rotation_deg: float) -> np.ndarray:
    """Indices of the fits to verify: at most ``count`` mutually distinct fits best by score
    ``first`` (e.g. correspondence inliers), then at most ``count`` best by ``second`` (e.g.
    :func:`occupancy_scores`) that are distinct from all kept before them. Two fits are distinct
    when their rotations differ by more than ``min_rotation_deg`` degrees or their translations by
    more than ``min_translation`` (cloud units)."""
    by_first = _distinct_order(rotations, translations, np.asarray(first, dtype=np.float64), count,
                               min_translation, min_rotation_deg)
    by_second = _distinct_order(rotations, translations, np.asarray(second, dtype=np.float64), count,
                                min_translation, min_rotation_deg)
    pooled = np.concatenate([by_first, by_second])
    priority = -np.arange(len(pooled), dtype=np.float64)  # the order above: first's, then second's
    kept = _distinct_order(rotations[pooled], translations[pooled], priority, len(pooled), min_translation,
                           min_rotation_deg)
    return pooled[kept]
