"""Anderson acceleration of a local registration loop (as in AA-ICP, Pavlov et al. 2018).

With a fixed, narrow sigma, ESM behaves like an EM algorithm: every step goes the right way but
covers only part of the distance, so the last stretch to convergence takes many small steps. The
loop is a fixed-point iteration ``x_{k+1} = G(x_k)`` on the pose; Anderson acceleration replaces
``G(x_k)`` by the combination of the last few ``G`` values whose residuals ``G(x) - x`` cancel best
in least squares. A proposal that lowers the method's objective is rejected by the caller (which
then takes the plain step and calls :meth:`AndersonAccelerator.reset`).

Poses are parametrised relative to the pose where acceleration started, as a rotation vector
(radians) and a translation divided by ``scale`` (so both parts are unit-free).
"""

from __future__ import annotations

import numpy as np
from ..core.pose_kernels import anderson_mix, pose_from_parameters, pose_parameters

#: Past residuals combined by each proposal.
WINDOW = 5


class AndersonAccelerator:
    """Proposes accelerated poses from the plain iteration's poses (4x4 ``T_target_source``)."""

    def __init__(self, scale: float, window: int = WINDOW):
        self.scale = scale if scale > 0 else 1.0
        self.window = window
        self.reset()

    def reset(self) -> None:
        """Forget the history (after a rejected proposal or when the objective changes)."""
        self._reference: np.ndarray | None = None
        self._residuals: list[np.ndarray] = []
        self._images: list[np.ndarray] = []

    def _params(self, transform: np.ndarray) -> np.ndarray:
        return pose_parameters(transform, self._reference, self.scale)

    def _transform(self, params: np.ndarray) -> np.ndarray:
        return pose_from_parameters(params, self._reference, self.scale)

    def propose(self, current: np.ndarray, plain: np.ndarray) -> np.ndarray:
        """The next pose: ``plain`` (= G(current)) itself until two steps are known, then the
        Anderson combination of the last ``window`` steps."""
        if self._reference is None:
            self._reference = np.ascontiguousarray(current, dtype=np.float64)
        image = self._params(plain)
        self._residuals.append(image - self._params(current))
        self._images.append(image)
        del self._residuals[: -self.window - 1], self._images[: -self.window - 1]
        if len(self._residuals) < 2:
            return plain
        residuals, images = np.array(self._residuals), np.array(self._images)
        if not (np.isfinite(residuals).all() and np.isfinite(images).all()):
            self.reset()
            return plain
        proposal = anderson_mix(residuals, images)
        if not np.isfinite(proposal).all():
            self.reset()
            return plain
        return self._transform(proposal)
