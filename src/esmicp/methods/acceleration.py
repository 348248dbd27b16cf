"""Anderson acceleration of a local registration loop (as in AA-ICP, Pavlov et al. 2018).

With a fixed, narrow sigma, ESM behaves like an EM algorithm: every step goes the right way but
covers only part of the distance, so the last stretch to convergence takes many small steps. The
loop is a fixed-point iteration ``x_{k+1} = G(x_k)`` on the pose; Anderson acceleration replaces
``G(x_k)`` by the combination of the last few ``G`` values whose residuals ``G(x) - x`` cancel best
in least squares. A proposal that lowers the method's objective is rejected by the caller (which
then takes the plain step and calls :meth:`AndersonAccelerator.reset`).

Poses are parametrised relative to the pose where acceleration started, as a rotation vector
(radians) and a translation divided by ``scale`` (so both parts are unit-free). Each proposal is
one compiled call (``esmicp._kernels.anderson_propose``: the rotation log and exp, the minimum-norm
least squares by a Jacobi SVD with NumPy's ``lstsq`` cutoff): in NumPy it cost 50-80 us per
iteration, about a third of a 1,000-point iteration.
"""

from __future__ import annotations

import numpy as np

from .. import _kernels
from .config import LoopConfig

class AndersonAccelerator:
    """Proposes accelerated poses from the plain iteration's poses (4x4 ``T_target_source``), each
    combining the last ``window`` residuals (count; None:
    :attr:`~esmicp.methods.config.LoopConfig.acceleration_window`)."""

    def __init__(self, scale: float, window: int | None = None):
        window = LoopConfig().acceleration_window if window is None else window
        self.scale = scale if scale > 0 else 1.0
        self.window = window
        # The compiled state: steps stored, the reference pose, the residual and image rows.
        self._state = np.zeros(_kernels.anderson_state_size(window))
        self._out = np.empty(18)
        #: ``(angle, translation norm)`` (radians, cloud units) from ``current`` to the last
        #: proposal :meth:`propose` returned (not to ``plain``).
        self.motion = (0.0, 0.0)

    def reset(self) -> None:
        """Forget the history (after a rejected proposal or when the objective changes)."""
        self._state[0] = 0.0

    def propose(self, current: np.ndarray, plain: np.ndarray) -> np.ndarray:
        """The next pose: ``plain`` (= G(current), returned as is) until two steps are known,
        then the Anderson combination of the last ``window`` steps (a new array)."""
        current = np.ascontiguousarray(current, dtype=np.float64)
        plain_c = np.ascontiguousarray(plain, dtype=np.float64)
        if not _kernels.anderson_propose(current, plain_c, self._state, float(self.scale), self.window, self._out):
            return plain
        self.motion = (float(self._out[16]), float(self._out[17]))
        return self._out[:16].reshape(4, 4).copy()
