"""``rpm-net``, ``deepgmr``: learned global registration, with weights the user supplies.

No pretrained weights for these models are reachable from the project's machines, and the models
are not (yet) written in the project, so these adapters validate their inputs and then raise
:class:`~esmicp_lab.baselines.WeightsNotAvailableError`, saying where weights would be looked for:
a benchmark shows the row as "weights not available" rather than dropping it, and never a made-up
result. (PointNetLK and DCP-v1, whose weights are available, are :mod:`esmicp_lab.baselines.pointnetlk` and
:mod:`esmicp_lab.baselines.dcp`; DCP-v2, the transformer-pointer model, has no weights at hand and no adapter.)
"""

from __future__ import annotations

from typing import NoReturn

from .base import WeightsNotAvailableError
from ._common import checked_inputs
from .weights import find_weights

RPM_NET = "rpm-net"
DEEPGMR = "deepgmr"

#: The weight file each model would load, relative to a weights folder.
WEIGHT_FILES = {RPM_NET: "rpm-net/model-best.pth", DEEPGMR: "deepgmr/modelnet_clean.pth"}


def _unavailable(method, source, target, init, max_iterations, voxel_size, rng, weights_dir) -> NoReturn:
    checked_inputs(source, target, voxel_size, max_iterations, rng, init)
    path = find_weights(method, WEIGHT_FILES[method], weights_dir)
    raise WeightsNotAvailableError(
        f"{method}: found weights at {path}, but the {method} model is not implemented in esmicp yet, "
        "so it cannot be run"
    )


def rpm_net(source, target, *, init=None, max_iterations: int = 5, voxel_size=None, rng=None, weights_dir=None):
    """RPM-Net (Yew & Lee 2020): always raises WeightsNotAvailableError here."""
    return _unavailable(RPM_NET, source, target, init, max_iterations, voxel_size, rng, weights_dir)


def deepgmr(source, target, *, init=None, max_iterations: int = 1, voxel_size=None, rng=None, weights_dir=None):
    """DeepGMR (Yuan et al. 2020): always raises WeightsNotAvailableError here."""
    return _unavailable(DEEPGMR, source, target, init, max_iterations, voxel_size, rng, weights_dir)
