"""The local methods' tuned values: frozen records of the configuration tree.

:class:`EsmConfig` (``esm``'s sigma schedule and ``esm-paper``'s sigma), :class:`PlaneConfig`
(``esm-plane``) and :class:`LoopConfig` (the loop every method runs in,
:func:`esmicp.methods.local.refine`). :class:`esmicp.config.RefineConfig` holds one of each
(``refine.esm``, ``refine.plane``, ``refine.loop``); a method made without one takes the defaults.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..core.config import Config, count, fraction, number


@dataclass(frozen=True)
class EsmConfig(Config):
    """``esm``'s automatic sigma (:class:`esmicp.methods.esm.SigmaSchedule`) and ``esm-paper``'s
    sigma.

    Attributes
    ----------
    sigma_floor_spacings : float
        The automatic sigma never falls below this many target point spacings (gain).
    sigma_median_factor : float
        The automatic sigma is this many times the median correspondence distance, above the
        floor (gain).
    fine_phase_step : float
        Below this increment (radians, and this times the target's bounding-box diagonal in
        translation) the automatic schedule enters its fine phase, sigma at the floor; ``esm-plane``
        then leaves its strided subset.
    start_quantile : float
        From a given start, the coarse sigma is ``sigma_median_factor`` times this quantile of the
        start's correspondence distances (0-1; above the floor, never above the median rule).
    tight_start_quantile : float
        ... and on :func:`esmicp.register`'s second try, when the first ends unconfident, this
        quantile (0-1): where less than a quarter of the source overlaps, the ``start_quantile``
        distance already measures the part that does not.
    coarse_points : int
        A larger source runs its coarse phase on this many evenly strided points, the fine phase
        on all (count; ``coarse_points`` of :func:`esmicp.methods.local.refine`).
    paper_sigma : float
        ``esm-paper``'s sigma when none is given (cloud units): the paper's, for unit-size objects.

    References
    ----------
    ``sigma_median_factor``: ``docs/measured-global.md``, "Why these choices".
    ``start_quantile`` and ``tight_start_quantile``: ``docs/scans-start-drift.md``.
    ``coarse_points``: ``docs/speed.md``.
    """

    sigma_floor_spacings: float = number(2.0, above=0.0)
    sigma_median_factor: float = number(3.0, above=0.0)
    fine_phase_step: float = number(1e-3, least=0.0)
    start_quantile: float = fraction(0.25)
    tight_start_quantile: float = fraction(0.05)
    coarse_points: int = count(20_000)
    paper_sigma: float = number(1.0, above=0.0)


@dataclass(frozen=True)
class PlaneConfig(Config):
    """``esm-plane``'s values (:class:`esmicp.methods.plane.PlaneEstimator`).

    Attributes
    ----------
    normal_neighbours : int
        Nearest target points whose PCA gives a target point's normal (count; 3 to 64).
    overlap_sigmas : float
        Pairs farther than this many sigmas are not part of the overlap when sigma is re-estimated
        (gain).
    sigma_mad_factor : float
        Sigma is this many robust standard deviations (1.4826 times the median) of the overlap's
        distances (gain).
    sigma_rounds : int
        At most this many rounds of the sigma fixed point per iteration (count).
    singular_fraction : float
        Eigenvalues of the step's 6x6 normal matrix below this fraction of the largest are taken
        as zero: directions a plane-like target leaves unconstrained get no motion (ratio).

    References
    ----------
    The choice of sigma from the overlap: ``docs/scans-refinement.md``.
    """

    normal_neighbours: int = count(20, least=3)
    overlap_sigmas: float = number(3.0, above=0.0)
    sigma_mad_factor: float = number(2.0, above=0.0)
    sigma_rounds: int = count(30)
    singular_fraction: float = fraction(1e-9)


@dataclass(frozen=True)
class LoopConfig(Config):
    """The local loop's values (:func:`esmicp.methods.local.refine`,
    :func:`esmicp.methods.guard.guarded_refine`).

    Attributes
    ----------
    acceleration_window : int
        Past residuals each Anderson-accelerated proposal combines
        (:class:`esmicp.methods.acceleration.AndersonAccelerator`; count).
    spatial_order_min : int
        From this many source points on, the source is queried in the target's spatial order
        (count; only the speed changes).
    min_effective_pairs : float
        A run whose last step had fewer effective pairs (Kish's count of the weights) than this
        did not fit the data: it is reported as not converged (count; 3 points fix a rotation).

    References
    ----------
    Anderson acceleration of ICP: Pavlov, Ovchinnikov, Shabanov, Kachurin, "AA-ICP: Iterative
    Closest Point with Anderson Acceleration", ICRA 2018.
    """

    acceleration_window: int = count(5)
    spatial_order_min: int = count(2048, least=0)
    min_effective_pairs: float = number(3.0, least=0.0)
