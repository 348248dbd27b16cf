"""Third-party and reference registration methods, wrapped behind one interface, for honest
comparisons.

Every adapter is a callable::

    adapter(source, target, *, init=None, max_iterations=..., voxel_size=None, rng=None) -> BaselineResult

with ``source`` / ``target`` ``(N, 3)`` / ``(M, 3)`` point arrays, ``init`` a 4x4
``T_target_source`` initial guess (None = identity) and the result's ``transformation`` the usual
``T_target_source`` (``target ~= source @ R.T + t``). :data:`BASELINE_KINDS` says whether a method
is ``"local"`` (it starts from ``init`` and runs at most ``max_iterations`` iterations) or
``"global"`` (it ignores both: it finds the pose from anywhere; where a refinement follows,
``max_iterations`` caps that refinement).

The libraries are optional and imported only when an adapter runs; a missing one raises
:class:`MissingDependencyError` with an install hint, missing model weights
:class:`WeightsNotAvailableError`, Go-ICP past its time limit :class:`BaselineTimeoutError`.
The library (``esmicp``) never imports this package. The methods, their settings and install
commands: ``docs/baselines.md``.
"""

from __future__ import annotations

from esmicp.errors import InvalidInputError, MissingDependencyError
from .base import INSTALL_HINT, Baseline, BaselineResult, BaselineTimeoutError, WeightsNotAvailableError

def _registry() -> tuple[dict[str, Baseline], dict[str, str]]:
    from functools import partial, update_wrapper

    from . import (
        cpd,
        dcp,
        go_icp,
        icp_nl,
        kiss_matcher,
        learned,
        ndt,
        open3d_fgr,
        open3d_local,
        open3d_ransac,
        pointnetlk,
        small_gicp,
    )

    def refined(adapter, refinement):
        return update_wrapper(partial(adapter, refinement=refinement), adapter)

    adapters: dict[str, tuple[Baseline, str]] = {
        # Global: find the pose from anywhere; init is ignored.
        open3d_ransac.NAME: (open3d_ransac.register, "global"),
        kiss_matcher.NAME: (kiss_matcher.register, "global"),
        open3d_ransac.NAME_PLANE: (refined(open3d_ransac.register, "point-to-plane"), "global"),
        kiss_matcher.NAME_PLANE: (refined(kiss_matcher.register, "point-to-plane"), "global"),
        open3d_ransac.NAME_ALONE: (refined(open3d_ransac.register, "none"), "global"),
        kiss_matcher.NAME_ALONE: (refined(kiss_matcher.register, "none"), "global"),
        kiss_matcher.NAME_GICP: (refined(kiss_matcher.register, kiss_matcher.GICP), "global"),
        open3d_fgr.NAME: (open3d_fgr.register, "global"),
        go_icp.NAME: (go_icp.register, "global"),
        dcp.NAME: (dcp.register, "global"),
        learned.RPM_NET: (learned.rpm_net, "global"),
        learned.DEEPGMR: (learned.deepgmr, "global"),
        # Local: start from init, at most max_iterations iterations.
        small_gicp.NAME: (small_gicp.register, "local"),
        small_gicp.NAME_VGICP: (
            update_wrapper(partial(small_gicp.register, registration_type="VGICP"), small_gicp.register),
            "local",
        ),
        open3d_local.NAME_ICP: (open3d_local.icp, "local"),
        open3d_local.NAME_ICP_PLANE: (open3d_local.icp_point_to_plane, "local"),
        open3d_local.NAME_GICP: (open3d_local.gicp, "local"),
        icp_nl.NAME: (icp_nl.register, "local"),
        ndt.NAME: (ndt.register, "local"),
        cpd.NAME: (cpd.register, "local"),
        pointnetlk.NAME: (pointnetlk.register, "local"),
    }
    return (
        {name: adapter for name, (adapter, _) in adapters.items()},
        {name: kind for name, (_, kind) in adapters.items()},
    )


#: name -> adapter. The adapter modules import their libraries only when called.
#: name -> "local" | "global" (see the module's docstring).
BASELINES, BASELINE_KINDS = _registry()
BASELINES: dict[str, Baseline]
BASELINE_KINDS: dict[str, str]


def get_baseline(name: str) -> Baseline:
    """The adapter called ``name``; :class:`~esmicp.errors.InvalidInputError` if there is none."""
    try:
        return BASELINES[name]
    except KeyError:
        raise InvalidInputError(
            f"baseline: unknown method {name!r}; choose one of {', '.join(BASELINES)}"
        ) from None


__all__ = [
    "BASELINES",
    "BASELINE_KINDS",
    "INSTALL_HINT",
    "Baseline",
    "BaselineResult",
    "BaselineTimeoutError",
    "MissingDependencyError",
    "WeightsNotAvailableError",
    "get_baseline",
]
