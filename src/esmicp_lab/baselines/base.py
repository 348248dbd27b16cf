"""The contract of a baseline adapter: its result record, its call signature, its errors."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from esmicp.errors import EsmicpError, MissingDependencyError

#: What to tell a user whose baseline library is missing.
INSTALL_HINT = (
    "pip install 'esmicp[baselines]' (and on Debian/Ubuntu: apt-get install libusb-1.0-0, "
    "which open3d-cpu needs at import)"
)


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


class WeightsNotAvailableError(MissingDependencyError):
    """A learned baseline's pretrained weights are not found (the message says where they were
    looked for, and how to supply them)."""


class BaselineTimeoutError(EsmicpError, TimeoutError):
    """A baseline did not finish within its time limit (Go-ICP's ``timeout_s``). Also a
    :class:`TimeoutError`, which is what ``esmicp bench`` records as status ``timeout``."""


class Baseline(Protocol):
    def __call__(
        self,
        source,
        target,
        *,
        init=None,
        max_iterations: int = ...,
        voxel_size: float | None = None,
        rng=None,
    ) -> BaselineResult: ...
