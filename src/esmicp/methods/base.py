"""What a local method computes each iteration."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Step:
    """One iteration's rigid increment ``T_delta`` (maps the current source placement toward the
    target: ``T_new = T_delta @ T_old``) and the weights that produced it.

    ``weights`` is None for unweighted methods; ``sigma`` (cloud units) is None where no kernel
    is used.
    """

    rotation: np.ndarray
    translation: np.ndarray
    weights: np.ndarray | None = None
    sigma: float | None = None


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
