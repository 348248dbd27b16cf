"""Classic point-to-point ICP (Besl and McKay 1992): every nearest-neighbour pair weighs 1."""

from __future__ import annotations

import numpy as np

from ..core import moments
from ..core.procrustes import weighted_procrustes
from .base import COMPILED, Estimator, Step


class IcpEstimator(Estimator):
    """Point-to-point ICP increment: unweighted Procrustes on nearest-neighbour pairs."""

    name = "icp"
    compiled_step = COMPILED
    fused_step = True

    def weighting(self) -> tuple[float, float, float, bool, bool]:
        return 0.0, 0.0, 0.0, False, False

    def step(self, moved_source, target, distances, indices) -> Step:
        rotation, translation = weighted_procrustes(moved_source, target[indices], np.ones(len(indices)))
        return Step(rotation, translation)

    def step_placed(self, source, transformation, target, distances, indices, workers=None) -> Step:
        """:meth:`step` from the unmoved source and its placement, in one compiled pass."""
        rotation, translation, effective = moments.rigid_fit(
            moments.pair_moments(source, transformation, target, indices, distances, None, workers)
        )
        return Step(rotation, translation, effective_pairs=effective)
