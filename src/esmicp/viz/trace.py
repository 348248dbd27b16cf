"""Run a local registration and keep what every iteration did, for the pictures.

The solver knows nothing of plots: this module only listens to its ``callback`` and keeps copies
of what it reports (:class:`~esmicp.methods.local.IterationState`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..api import register
from ..core.procrustes import apply
from ..errors import InvalidInputError
from ..result import RegistrationResult
from ..types import as_points, as_transform


@dataclass(frozen=True, eq=False)
class Step:
    """One iteration of a traced run (copies of the solver's arrays).

    ``indices[i]`` is the target point nearest to source point ``i`` as placed before the
    iteration, ``distances[i]`` its distance (cloud units), ``weights[i]`` the weight the method
    gave the pair (all 1 for ``icp``), ``transformation`` the ``T_target_source`` after it.
    """

    iteration: int
    transformation: np.ndarray
    indices: np.ndarray
    distances: np.ndarray
    weights: np.ndarray
    sigma: float | None

    @property
    def rmse(self) -> float:
        """RMS correspondence distance before the iteration (cloud units)."""
        return float(np.sqrt(np.mean(np.square(self.distances))))


@dataclass(frozen=True, eq=False)
class RegistrationTrace:
    """A local registration, iteration by iteration.

    ``poses[k]`` is ``T_target_source`` after ``k`` iterations (``poses[0]`` the start), so there
    are ``iterations + 1`` poses; ``steps[k - 1]`` is what iteration ``k`` did.
    """

    method: str
    start: str
    source: np.ndarray
    target: np.ndarray
    poses: tuple[np.ndarray, ...]
    steps: tuple[Step, ...]
    result: RegistrationResult

    @property
    def iterations(self) -> int:
        return len(self.steps)

    def aligned(self, k: int) -> np.ndarray:
        """The source placed by ``poses[k]`` (target frame)."""
        return apply(self.poses[k], self.source)

    @property
    def label(self) -> str:
        state = "converged" if self.result.converged else "not converged"
        return f"{self.method} from {self.start}: {self.iterations} iterations, {state}"


def _start(init) -> tuple[str, np.ndarray]:
    if isinstance(init, str):
        if init in ("identity", "none"):
            return "identity", np.eye(4)
        raise InvalidInputError(
            f"init: the pictures show the local iterations, so init must be 'identity' or a 4x4 "
            f"T_target_source (for instance a global register() result's transformation), got {init!r}"
        )
    if init is None:
        return "identity", np.eye(4)
    return "given pose", as_transform(init, "init")


def trace_registration(
    source,
    target,
    *,
    method: str = "esm",
    init="identity",
    sigma: float | None = None,
    max_iterations: int = 100,
    tolerance: float = 1e-8,
) -> RegistrationTrace:
    """Run :func:`esmicp.register` locally from ``init`` and keep every iteration.

    ``init`` is ``"identity"`` or a 4x4 ``T_target_source``: a global search's own iterations are
    not the local history, so it is not run here (start from its result instead).
    """
    source_points = as_points(source, "source")
    target_points = as_points(target, "target")
    start, initial = _start(init)
    steps: list[Step] = []

    def keep(state) -> None:
        weights = (
            np.ones(len(state.indices)) if state.weights is None else np.array(state.weights, dtype=np.float64)
        )
        steps.append(
            Step(
                state.iteration,
                np.array(state.transformation, dtype=np.float64),
                np.array(state.indices, dtype=np.int64),
                np.array(state.distances, dtype=np.float64),
                weights,
                state.sigma,
            )
        )

    result = register(
        source_points, target_points, method=method, init=initial, sigma=sigma,
        max_iterations=max_iterations, tolerance=tolerance, callback=keep,
    )
    poses = (initial, *(step.transformation for step in steps))
    return RegistrationTrace(method, start, source_points, target_points, poses, tuple(steps), result)
