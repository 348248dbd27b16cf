"""Local registration methods: one module each, pure numpy, no I/O.

Each method is a *step estimator*: given the source as currently placed and its nearest-neighbour
correspondences, it returns the rigid increment that moves it toward the target. The shared loop
in :mod:`esmicp.methods.local` iterates it.
"""

from .base import Step, StepEstimator
from .esm import EsmEstimator, SigmaSchedule
from .esm_paper import EsmPaperEstimator, similarity_matrix
from .icp import IcpEstimator

#: Names accepted by ``esmicp.register(method=...)``, with a one-line description each.
METHODS = {
    "esm": "ESM-ICP on true nearest-neighbour pairs: Gaussian-weighted Procrustes (any sizes, any order)",
    "esm-paper": "the paper's formulation, symmetric similarity matrix; needs index-aligned clouds",
    "icp": "classic point-to-point ICP (all weights 1)",
}

__all__ = [
    "METHODS",
    "EsmEstimator",
    "EsmPaperEstimator",
    "IcpEstimator",
    "SigmaSchedule",
    "Step",
    "StepEstimator",
    "similarity_matrix",
]
