"""The contract of a local method (:class:`Estimator`), what it computes each iteration
(:class:`Step`), and when the iterations stop (:class:`ConvergenceCriteria`)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..core import moments


@dataclass(frozen=True)
class Step:
    """One iteration's rigid increment ``T_delta`` (maps the current source placement toward the
    target: ``T_new = T_delta @ T_old``) and the weights that produced it.

    ``weights`` is None for unweighted methods (and from :meth:`Estimator.step_placed`, which
    forms no weight array); ``sigma`` (cloud units) is None where no kernel is used;
    ``effective_pairs`` is Kish's effective number of pairs of the weights, when known.
    """

    rotation: np.ndarray
    translation: np.ndarray
    weights: np.ndarray | None = None
    sigma: float | None = None
    effective_pairs: float | None = None


@dataclass(frozen=True)
class ConvergenceCriteria:
    """When :func:`esmicp.methods.local.refine` stops.

    At most ``max_iterations`` iterations; converged once an increment rotates by less than
    ``tolerance`` radians and translates by less than ``tolerance * scale`` (``scale``: the
    target's bounding-box diagonal, so that the test is unit-free), or once the RMS
    correspondence distance changes by less than ``tolerance`` relative to itself.
    """

    max_iterations: int = 100
    tolerance: float = 1e-8

    def reason(self, angle: float, distance: float, scale: float, previous_rmse: float | None, rmse: float) -> str | None:
        """Why the run has converged after an increment of ``angle`` radians and ``distance``
        (cloud units) that took the RMS distance from ``previous_rmse`` to ``rmse``; None if not."""
        if angle < self.tolerance and distance < self.tolerance * scale:
            return "increment below tolerance"
        if previous_rmse is not None and abs(previous_rmse - rmse) <= self.tolerance * previous_rmse:
            return "RMS distance stopped changing"
        return None


class Estimator(ABC):
    """A local registration method, iterated by :func:`esmicp.methods.local.refine`.

    Capabilities are declared, never probed: the loop reads the class attributes and properties
    below, whose defaults describe a plain method (any point order, no compiled step, no coarse
    phase, no acceleration). An estimator may hold the state of one run (``esm``'s phase): make a
    new one per registration.
    """

    #: The method's name (``method`` of :func:`esmicp.register`).
    name: ClassVar[str]
    #: False when the increment depends on the order of the source points (``esm-paper``); the
    #: loop may otherwise visit them in any order.
    order_invariant: ClassVar[bool] = True
    #: True when :meth:`step_placed` gives the increment in one compiled pass
    #: (:mod:`esmicp.core.moments`); the loop then uses it when no per-point array is needed.
    compiled_step: ClassVar[bool] = False
    #: True when :meth:`weighting` describes the weights of :meth:`step` to the compiled iteration
    #: kernel (:meth:`esmicp.core.correspondence.NearestNeighbors.step`), which then finds the
    #: pairs and computes the increment in one call; the loop hands the increment back through
    #: :meth:`took_step`.
    fused_step: ClassVar[bool] = False
    #: True when the loop may apply Anderson acceleration (:mod:`esmicp.methods.acceleration`)
    #: against :meth:`objective` while :attr:`accelerated` is True.
    accelerable: ClassVar[bool] = False

    @abstractmethod
    def step(self, moved_source: np.ndarray, target: np.ndarray, distances: np.ndarray, indices: np.ndarray) -> Step:
        """Increment from the source as placed now (``moved_source``, target frame), the target
        cloud, and each moved source point's nearest-neighbour ``distances`` / ``indices``."""

    def step_placed(self, source, transformation, target, distances, indices, workers=None) -> Step:
        """:meth:`step` from the unmoved ``source`` and its placement ``transformation`` (4x4), in
        one compiled pass that builds no per-point array (only where :attr:`compiled_step`), on
        ``workers`` threads (None: every core)."""
        raise NotImplementedError(f"{self.name} has no compiled step")

    def weighting(self) -> tuple[float, float, float, bool, bool]:
        """This iteration's weights, for the fused kernel (only where :attr:`fused_step`):
        ``(fixed sigma or 0, sigma floor, factor on the median distance, fine phase, Gaussian)``;
        the sigma is the fixed one, else the floor in the fine phase, else
        ``max(floor, factor * median distance)``; not Gaussian: every weight 1."""
        raise NotImplementedError(f"{self.name} has no fused step")

    def pair_weights(self, distances: np.ndarray, sigma: float | None) -> np.ndarray | None:
        """The weight :meth:`step` gives each pair at ``distances`` (cloud units) when its sigma is
        ``sigma``; None for an unweighted method (the default: every pair weighs 1). Used to report
        an iteration (:class:`~esmicp.methods.local.IterationState`), never to take a step."""
        return None

    def took_step(self, step: Step) -> None:
        """Called by the loop with the fused kernel's increment (the default keeps no state)."""

    @property
    def objective_sigma(self) -> float:
        """The sigma of :meth:`objective` (cloud units), for the fused kernel (only where
        :attr:`accelerable` and :attr:`fused_step`)."""
        raise NotImplementedError(f"{self.name} has no objective")

    @property
    def coarse(self) -> bool:
        """True while the method is in a coarse phase (the loop may then run on a subset of the
        source, and never stops there); the default has none."""
        return False

    def end_coarse_phase(self) -> None:
        """Leave the coarse phase: called by the loop once the coarse iterations have converged."""

    @property
    def accelerated(self) -> bool:
        """True while :meth:`objective` is fixed, so that acceleration may be tried (only read
        where :attr:`accelerable`)."""
        return False

    def objective(self, distances: np.ndarray) -> float:
        """The fit at the current pairs, higher is better (only where :attr:`accelerable`)."""
        raise NotImplementedError(f"{self.name} has no objective")


#: Whether the compiled moments (:mod:`esmicp.core.moments`) are there for :meth:`Estimator.step_placed`.
COMPILED = moments.available()
