"""``dcp``, ``rpm-net``, ``deepgmr``: learned global registration, with weights the user supplies.

No pretrained weights for these models are reachable from the project's machines, and the models
are not (yet) written in the project, so these adapters validate their inputs and then raise
:class:`~esmicp.baselines.WeightsNotAvailableError`, saying where weights would be looked for:
a benchmark shows the row as "weights not available" rather than dropping it, and never a made-up
result. (PointNetLK, whose weights are available, is :mod:`esmicp.baselines.pointnetlk`.)
"""

from __future__ import annotations

from typing import NoReturn

from .base import WeightsNotAvailableError
from ._common import checked_inputs
from .weights import find_weights

DCP = "dcp"
RPM_NET = "rpm-net"
DEEPGMR = "deepgmr"

#: The weight file each model would load, relative to a weights folder.
WEIGHT_FILES = {DCP: "dcp/model.best.t7", RPM_NET: "rpm-net/model-best.pth", DEEPGMR: "deepgmr/modelnet_clean.pth"}


def _unavailable(method, source, target, init, max_iterations, voxel_size, rng, weights_dir) -> NoReturn:
    checked_inputs(source, target, voxel_size, max_iterations, rng, init)
    path = find_weights(method, WEIGHT_FILES[method], weights_dir)
    raise WeightsNotAvailableError(
        f"{method}: found weights at {path}, but the {method} model is not implemented in esmicp yet, "
        "so it cannot be run"
    )


def dcp(source, target, *, init=None, max_iterations: int = 1, voxel_size=None, rng=None, weights_dir=None):
    """Deep Closest Point (Wang & Solomon 2019): always raises WeightsNotAvailableError here."""
    return _unavailable(DCP, source, target, init, max_iterations, voxel_size, rng, weights_dir)


def rpm_net(source, target, *, init=None, max_iterations: int = 5, voxel_size=None, rng=None, weights_dir=None):
    """RPM-Net (Yew & Lee 2020): always raises WeightsNotAvailableError here."""
    return _unavailable(RPM_NET, source, target, init, max_iterations, voxel_size, rng, weights_dir)


def deepgmr(source, target, *, init=None, max_iterations: int = 1, voxel_size=None, rng=None, weights_dir=None):
    """DeepGMR (Yuan et al. 2020): always raises WeightsNotAvailableError here."""
    return _unavailable(DEEPGMR, source, target, init, max_iterations, voxel_size, rng, weights_dir)
