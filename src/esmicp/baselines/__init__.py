"""Third-party registration methods, wrapped behind one interface, for honest comparisons.

Every adapter is a callable::

    register(source, target, *, voxel_size=None, rng=None, max_iterations=...) -> BaselineResult

with ``source`` / ``target`` ``(N, 3)`` / ``(M, 3)`` point arrays and the result's
``transformation`` the usual ``T_target_source`` (``target ~= source @ R.T + t``).

The libraries are optional (``pip install 'esmicp[baselines]'``) and imported only when an adapter
runs; a missing one raises :class:`MissingDependencyError` with an install hint. Nothing here is
imported by ``import esmicp``.

Adapters (:data:`BASELINES`):

``open3d-ransac-fpfh-icp``
    Open3D: voxel downsampling, FPFH features, RANSAC on feature matches, then point-to-point ICP
    on the full clouds (:mod:`esmicp.baselines.open3d_ransac`). Global.
``kiss-matcher-icp``
    KISS-Matcher (faster-PFH + ROBIN + GNC) as the global step, then the same Open3D ICP
    (:mod:`esmicp.baselines.kiss_matcher`). Global.
``open3d-ransac-fpfh-p2l``, ``kiss-matcher-p2l``
    The same two pipelines refined by point-to-plane ICP (target normals) instead. On resampled
    surfaces (two different samplings of one shape) point-to-point ICP keeps a bias of a few tenths
    of a degree that point-to-plane mostly removes.
``small-gicp``
    small_gicp's GICP from the identity (:mod:`esmicp.baselines.small_gicp`). Local only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..errors import EsmicpError, InvalidInputError

#: What to tell a user whose baseline library is missing.
INSTALL_HINT = (
    "pip install 'esmicp[baselines]' (and on Debian/Ubuntu: apt-get install libusb-1.0-0, "
    "which open3d-cpu needs at import)"
)


class MissingDependencyError(EsmicpError):
    """A baseline's optional library is not installed (or fails to import)."""


@dataclass(frozen=True)
class BaselineResult:
    """Outcome of a baseline adapter.

    Attributes
    ----------
    transformation : (4, 4) float64 array
        ``T_target_source``: ``target ~= source @ R.T + t``.
    runtime_s : float
        Wall time (``time.perf_counter``) of the registration itself: downsampling, features,
        global step and refinement; not the library import nor input validation.
    method : str
        The adapter's name (a key of :data:`BASELINES`).
    converged : bool or None
        The library's own success flag where it gives one (RANSAC found a model, KISS-Matcher's
        ``valid``, GICP's ``converged``); None when unknown.
    notes : str
        Settings used and the library's figures (voxel size, fitness, inliers, ...).
    """

    transformation: np.ndarray
    runtime_s: float
    method: str
    converged: bool | None
    notes: str = ""


class Baseline(Protocol):
    def __call__(
        self, source, target, *, voxel_size: float | None = None, rng=None, max_iterations: int = ...
    ) -> BaselineResult: ...


def _registry() -> dict[str, Baseline]:
    from functools import partial, update_wrapper

    from . import kiss_matcher, open3d_ransac, small_gicp

    def plane(adapter):
        return update_wrapper(partial(adapter, refinement="point-to-plane"), adapter)

    return {
        open3d_ransac.NAME: open3d_ransac.register,
        kiss_matcher.NAME: kiss_matcher.register,
        open3d_ransac.NAME_PLANE: plane(open3d_ransac.register),
        kiss_matcher.NAME_PLANE: plane(kiss_matcher.register),
        small_gicp.NAME: small_gicp.register,
    }


#: name -> adapter. The adapter modules import their libraries only when called.
BASELINES: dict[str, Baseline] = _registry()


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
    "INSTALL_HINT",
    "Baseline",
    "BaselineResult",
    "MissingDependencyError",
    "get_baseline",
]
