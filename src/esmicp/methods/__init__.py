"""Local registration methods: one module each, pure numpy, no I/O.

Each method is an :class:`~esmicp.methods.base.Estimator`: given the source as currently placed and its nearest-neighbour
correspondences, it returns the rigid increment that moves it toward the target. The shared loop
in :mod:`esmicp.methods.local` iterates it.
"""

from .base import ConvergenceCriteria, Estimator, Step
from .esm import EsmEstimator, SigmaSchedule
from .esm_paper import PAPER_SIGMA, EsmPaperEstimator, similarity_matrix
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
    method: str, sigma: float | None, spacing: float, diagonal: float, *, start_fine: bool = False
) -> Estimator:
    """A fresh estimator for ``method`` (a key of :data:`METHODS`): ``sigma`` None lets ``esm``
    choose it from the data (a floor of target point spacings, ``diagonal`` as a backstop) and
    gives ``esm-paper`` the paper's 1.0 (``esm-plane``: from the overlap, above the same floor);
    ``start_fine`` starts ``esm`` in its fine phase."""
    if method == "icp":
        return IcpEstimator()
    if method == "esm-plane":
        return PlaneEstimator(SigmaSchedule.auto(spacing, diagonal).floor, diagonal, sigma)
    if method == "esm-paper":
        return EsmPaperEstimator(PAPER_SIGMA if sigma is None else sigma)
    schedule = SigmaSchedule.auto(spacing, diagonal) if sigma is None else SigmaSchedule.constant(sigma)
    return EsmEstimator(schedule, start_fine=start_fine)


__all__ = [
    "METHODS",
    "ConvergenceCriteria",
    "Estimator",
    "EsmEstimator",
    "EsmPaperEstimator",
    "IcpEstimator",
    "PlaneEstimator",
    "SigmaSchedule",
    "Step",
    "make_estimator",
    "similarity_matrix",
]
