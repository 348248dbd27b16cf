"""What a local method computes each iteration."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Step:
    """One iteration's rigid increment ``T_delta`` (maps the current source placement toward the
    target: ``T_new = T_delta @ T_old``) and the weights that produced it.

    ``weights`` is None for unweighted methods (and from :meth:`StepEstimator.step_placed`, which
    forms no weight array); ``sigma`` (cloud units) is None where no kernel is used;
    ``effective_pairs`` is Kish's effective number of pairs of the weights, when known.
    """

    rotation: np.ndarray
    translation: np.ndarray
    weights: np.ndarray | None = None
    sigma: float | None = None
    effective_pairs: float | None = None


class StepEstimator(Protocol):
    """A local registration method, iterated by :func:`esmicp.methods.local.refine`."""

    name: str
    # Optional: ``order_invariant = False`` when the increment depends on the order of the source
    # points (``esm-paper``); the loop may otherwise visit them in any order.

    def step(
        self, moved_source: np.ndarray, target: np.ndarray, distances: np.ndarray, indices: np.ndarray
    ) -> Step:
        """Increment from the source as placed now (``moved_source``, target frame), the target
        cloud, and each moved source point's nearest-neighbour ``distances`` / ``indices``."""
        ...

    # Optional, for speed: ``step_placed(source, transformation, target, distances, indices)``, the
    # same increment from the unmoved ``source`` and its placement ``transformation`` (4x4), in one
    # compiled pass that builds no per-point array (:mod:`esmicp.core.moments`). The loop uses it
    # when no callback or history needs the per-point arrays.
