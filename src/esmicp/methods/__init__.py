"""Local registration methods: one module each, pure numpy, no I/O.

Each method is an :class:`~esmicp.methods.base.Estimator`: given the source as currently placed and its nearest-neighbour
correspondences, it returns the rigid increment that moves it toward the target. The shared loop
in :mod:`esmicp.methods.local` iterates it.
"""

from .base import ConvergenceCriteria, Estimator, Step
from .config import EsmConfig, LoopConfig, PlaneConfig
from .esm import EsmEstimator, SigmaSchedule
from .esm_paper import EsmPaperEstimator, similarity_matrix
from .icp import IcpEstimator
from .plane import PlaneEstimator

#: Names accepted by ``esmicp.register(method=...)``, with a one-line description each.
METHODS = {
    "esm": "ESM-ICP on true nearest-neighbour pairs: Gaussian-weighted Procrustes (any sizes, any order)",
    "esm-paper": "the paper's formulation, symmetric similarity matrix; needs index-aligned clouds",
    "icp": "classic point-to-point ICP (all weights 1)",
    "esm-plane": "ESM's Gaussian weights on point-to-plane residuals (target normals), sigma from the overlap: for scans",
}



def make_estimator(
    method: str, sigma: float | None, spacing: float, diagonal: float, *, start_fine: bool = False,
    esm: EsmConfig | None = None, plane: PlaneConfig | None = None,
) -> Estimator:
    """A fresh estimator for ``method`` (a key of :data:`METHODS`): ``sigma`` None lets ``esm``
    choose it from the data (a floor of target point spacings, ``diagonal`` as a backstop) and
    gives ``esm-paper`` the paper's (``esm.paper_sigma``; ``esm-plane``: from the overlap, above
    the same floor); ``start_fine`` starts ``esm`` in its fine phase. ``esm`` and ``plane``: the
    methods' values (:mod:`esmicp.methods.config`; None: the defaults)."""
    esm = EsmConfig() if esm is None else esm
    if method == "icp":
        return IcpEstimator()
    if method == "esm-plane":
        return PlaneEstimator(SigmaSchedule.auto(spacing, diagonal, esm).floor, diagonal, sigma, config=plane,
                              fine_phase_step=esm.fine_phase_step)
    if method == "esm-paper":
        return EsmPaperEstimator(esm.paper_sigma if sigma is None else sigma)
    schedule = SigmaSchedule.auto(spacing, diagonal, esm) if sigma is None else SigmaSchedule.constant(sigma)
    return EsmEstimator(schedule, start_fine=start_fine)


__all__ = [
    "METHODS",
    "ConvergenceCriteria",
    "EsmConfig",
    "Estimator",
    "EsmEstimator",
    "EsmPaperEstimator",
    "IcpEstimator",
    "LoopConfig",
    "PlaneConfig",
    "PlaneEstimator",
    "SigmaSchedule",
    "Step",
    "make_estimator",
    "similarity_matrix",
]
