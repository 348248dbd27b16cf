"""ESM-ICP on true correspondences: the honest generalisation of the paper's method.

Each iteration pairs every source point ``s_i`` with its nearest target point ``t_c(i)``, weighs the
pair by ``w_i = exp(-||s_i - t_c(i)||^2 / (2 sigma^2))`` and solves the weighted Procrustes problem
``min sum_i w_i ||R s_i + t - t_c(i)||^2`` (weighted centroids, weighted cross-covariance, SVD,
``R = V U^T``, ``t = t_bar - R s_bar``). Unlike the paper's symmetric matrix, no pair ever joins
source point k to target point k, so the clouds may differ in size and order.

Choosing sigma (the paper leaves it open)
-----------------------------------------
``sigma`` is in the clouds' units. A fixed value can be given. By default
(:meth:`SigmaSchedule.auto`) it is re-chosen every iteration as

    sigma_k = max(sigma_floor, 3 * median_i d_i)

with ``d_i`` the current correspondence distances and ``sigma_floor = 2 x`` the target's median
point spacing (distance from a target point to its nearest neighbour). Far from the solution most
pairs are wrong by about the median distance, so weights stay broad (a typical pair weighs about
0.95) and the step behaves like ICP; as the clouds close in, sigma shrinks with the residuals (a
coarse-to-fine annealing that needs no tuning), down to the floor, where sampling noise still
weighs about 0.9 and pairs several spacings off (outliers, non-overlapping parts) weigh almost
nothing. When many points are outliers the median stays large, so the schedule has a second,
fine phase: once an increment rotates by less than ``fine_phase_step`` radians and translates by
less than ``fine_phase_step`` times the target's diagonal, sigma drops to the floor and stays there
until convergence. The factor 3 on the median is the best of those measured
(``docs/measured-global.md``, "Why these choices"). The floor makes the choice unit-free:
the same default serves a unit-size object, a scan in millimetres and a LiDAR scan in metres.

From a start the user gives (``init``), the median is the wrong scale on partial overlap: it
measures how far the non-overlapping part lies, and a coarse sigma that wide pulls a good start
apart. There the coarse sigma is held at ``sigma_median_factor`` times the ``start_quantile``
quantile of the start's distances (the overlap's residuals; at least the floor, at most the
median rule), then the fine phase follows as above (:meth:`SigmaSchedule.from_start`). When that
run ends unconfident, :func:`esmicp.register` tries once more from the ``tight_start_quantile``
quantile and keeps the more confident run (less than a quarter of the source may overlap). After
a global search the refinement starts in the fine phase. The values named here are the fields of
:class:`esmicp.methods.config.EsmConfig` (``RefineConfig.esm``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..core import moments
from ..core.weights import kernel_scale, relative_gaussian_weights
from ..core.procrustes import rotation_angle, weighted_procrustes
from ..types import as_positive
from .base import COMPILED, Estimator, Step
from .config import EsmConfig

@dataclass(frozen=True)
class SigmaSchedule:
    """How sigma (cloud units) is chosen each iteration.

    ``fixed`` set: that value every iteration. Otherwise ``start`` in the coarse phase when it
    is set (a given start, :meth:`from_start`), else ``max(floor, config.sigma_median_factor *
    median distance)``; the floor in the fine phase. ``config``: the schedule's values
    (:class:`~esmicp.methods.config.EsmConfig`).
    """

    fixed: float | None = None
    floor: float = 0.0
    diameter: float = 1.0
    start: float | None = None
    config: EsmConfig = field(default_factory=EsmConfig)

    @classmethod
    def constant(cls, sigma: float) -> "SigmaSchedule":
        return cls(fixed=as_positive(sigma, "sigma"))

    @classmethod
    def auto(cls, target_spacing: float, diameter: float, config: EsmConfig | None = None) -> "SigmaSchedule":
        """Schedule with a floor of ``config.sigma_floor_spacings`` point spacings (``config``: an
        :class:`~esmicp.methods.config.EsmConfig`, None for the defaults).

        ``diameter`` (cloud units) backs the floor for clouds with no measurable spacing (all
        target points duplicated): then one millionth of the diameter.
        """
        config = EsmConfig() if config is None else config
        floor = config.sigma_floor_spacings * target_spacing
        if not floor > 0:
            floor = 1e-6 * diameter
        return cls(fixed=None, floor=floor, diameter=diameter, config=config)

    def from_start(self, distances: np.ndarray, quantile: float | None = None) -> "SigmaSchedule":
        """This schedule with its coarse sigma held at the scale of the overlap at a given start.

        ``distances``: each source point's distance (cloud units) to its nearest target point
        under the start. On a partial overlap the median of all of them measures how far the
        non-overlapping part lies, not how far off the start is: a coarse sigma that wide pulls
        a good start apart. The overlap's residuals are the small ones, so the coarse sigma is
        ``config.sigma_median_factor`` times their ``quantile`` quantile (default
        ``config.start_quantile``; at
        least the floor, at most what the median rule gives at the start), held until the coarse
        phase converges.
        """
        if self.fixed is not None or len(distances) == 0:
            return self
        quantile = self.config.start_quantile if quantile is None else quantile
        overlap = self.config.sigma_median_factor * float(np.quantile(distances, quantile))
        return replace(self, start=min(max(self.floor, overlap), self(distances)))

    def __call__(self, distances: np.ndarray, *, fine: bool = False) -> float:
        """Sigma for this iteration; ``fine`` selects the fine phase (the floor)."""
        if self.fixed is not None:
            return self.fixed
        if fine:
            return self.floor
        if self.start is not None:
            return self.start
        return max(self.floor, self.config.sigma_median_factor * float(np.median(distances)))


class EsmEstimator(Estimator):
    """ESM-ICP increment on nearest-neighbour pairs with Gaussian weights.

    Weights are computed relative to the closest pair (see
    :func:`esmicp.core.weights.relative_gaussian_weights`): the fit is exactly the one the
    paper's weights give, but it never breaks down when all of them would underflow to zero.
    """

    name = "esm"
    compiled_step = COMPILED
    fused_step = True
    accelerable = True

    def __init__(self, sigma: SigmaSchedule, *, start_fine: bool = False):
        self.sigma = sigma
        #: The phase of the automatic schedule: True once sigma has dropped to its floor.
        self.fine = start_fine

    @property
    def coarse(self) -> bool:
        """True in the coarse phase of the automatic sigma (not with a fixed sigma)."""
        return not self.fine and self.sigma.fixed is None

    def start_from(self, distances: np.ndarray, quantile: float | None = None) -> None:
        """Refine from a given start whose correspondence distances are ``distances`` (cloud
        units): the coarse sigma is held at the overlap's scale, measured by their ``quantile``
        quantile (default the schedule's ``config.start_quantile``; :meth:`SigmaSchedule.from_start`)."""
        self.sigma = self.sigma.from_start(distances, quantile)

    def end_coarse_phase(self) -> None:
        self.fine = True

    @property
    def accelerated(self) -> bool:
        """True once sigma is fixed (a user's sigma, or the fine phase): the loop may then apply
        Anderson acceleration (:mod:`esmicp.methods.acceleration`) against :meth:`objective`."""
        return self.fine or self.sigma.fixed is not None

    def objective(self, distances: np.ndarray) -> float:
        """The ESM similarity at the current sigma: mean of ``exp(-d^2 / (2 sigma^2))`` (higher is
        better); meaningful only while :attr:`accelerated` (sigma fixed)."""
        sigma = self.sigma(distances, fine=True)
        with np.errstate(over="ignore"):
            return float(np.mean(np.exp(-np.square(distances) * kernel_scale(sigma))))

    def step(self, moved_source, target, distances, indices) -> Step:
        sigma = self.sigma(distances, fine=self.fine)
        weights = relative_gaussian_weights(distances, sigma)
        rotation, translation = weighted_procrustes(moved_source, target[indices], weights)
        self._update_phase(rotation, translation)
        return Step(rotation, translation, weights=weights, sigma=sigma)

    def step_placed(self, source, transformation, target, distances, indices, workers=None) -> Step:
        """:meth:`step` from the unmoved source and its placement, in one compiled pass."""
        sigma = self.sigma(distances, fine=self.fine)
        rotation, translation, effective = moments.rigid_fit(
            moments.pair_moments(source, transformation, target, indices, distances, sigma, workers)
        )
        self._update_phase(rotation, translation)
        return Step(rotation, translation, sigma=sigma, effective_pairs=effective)

    def weighting(self) -> tuple[float, float, float, bool, bool]:
        fixed = self.sigma.fixed
        if fixed is None and not self.fine:
            fixed = self.sigma.start
        return (0.0 if fixed is None else fixed), self.sigma.floor, self.sigma.config.sigma_median_factor, self.fine, True

    def pair_weights(self, distances, sigma):
        return None if sigma is None else relative_gaussian_weights(distances, sigma)

    def took_step(self, step: Step) -> None:
        self._update_phase(step.rotation, step.translation)

    @property
    def objective_sigma(self) -> float:
        return self.sigma.fixed if self.sigma.fixed is not None else self.sigma.floor

    def _update_phase(self, rotation, translation) -> None:
        if self.coarse:
            self.fine = (
                rotation_angle(rotation) < self.sigma.config.fine_phase_step
                and np.linalg.norm(translation) < self.sigma.config.fine_phase_step * self.sigma.diameter
            )
