"""Classic point-to-point ICP (Besl and McKay 1992): every nearest-neighbour pair weighs 1."""

from __future__ import annotations

import numpy as np

from ..core import moments
from ..core.procrustes import rotation_from_cross_covariance, weighted_procrustes
from .base import Step


class IcpEstimator:
    """Point-to-point ICP increment: unweighted Procrustes on nearest-neighbour pairs."""

    name = "icp"

    def step(self, moved_source, target, distances, indices) -> Step:
        rotation, translation = weighted_procrustes(moved_source, target[indices], np.ones(len(indices)))
        return Step(rotation, translation)

    if moments.available():

        def step_placed(self, source, transformation, target, distances, indices) -> Step:
            total, squares, source_mean, target_mean, cross = moments.pair_moments(
                source, transformation, target, indices, distances, None
            )
            rotation = rotation_from_cross_covariance(cross)
            return Step(rotation, target_mean - rotation @ source_mean, effective_pairs=float(len(indices)))
