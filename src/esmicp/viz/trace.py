"""Run a registration and keep what every iteration of its local refinement did, for the pictures.

The solver knows nothing of plots: this module only listens to its ``callback`` and keeps copies
of what it reports (:class:`~esmicp.methods.local.IterationState`); the callback never changes
the run, so the pictures show the pose :func:`esmicp.register` gives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..api import register
from ..core.procrustes import apply
from ..result import RegistrationResult
from ..types import as_points, as_transform


@dataclass(frozen=True, eq=False)
class Step:
    """One iteration of a traced run (copies of the solver's arrays).

    ``indices[i]`` is the target point nearest to source point ``i`` as placed before the
    iteration, ``distances[i]`` its distance (cloud units), ``weights[i]`` the weight the method
    gave the pair (all 1 for ``icp``): None when the trace keeps no per-point arrays;
    ``transformation`` the ``T_target_source`` after it, ``rmse`` the RMS correspondence distance
    before it (cloud units).
    """

    iteration: int
    transformation: np.ndarray
    indices: np.ndarray | None
    distances: np.ndarray | None
    weights: np.ndarray | None
    sigma: float | None
    rmse: float


@dataclass(frozen=True, eq=False)
class RegistrationTrace:
    """A registration's local refinement, iteration by iteration, or one pose to show.

    ``poses[k]`` is ``T_target_source`` after ``k`` iterations (``poses[0]`` the start: the
    identity, a given pose, or the global search's pose), so there are ``iterations + 1`` poses;
    ``steps[k - 1]`` is what iteration ``k`` did. A trace of no step holds one pose, shown as it is
    (:func:`fixed_trace`). ``result`` is the :class:`~esmicp.result.RegistrationResult` whose pose
    ``poses[-1]`` is (its verdict goes in the captions), or None for a bare pose.
    """

    method: str
    start: str
    source: np.ndarray
    target: np.ndarray
    poses: tuple[np.ndarray, ...]
    steps: tuple[Step, ...]
    result: RegistrationResult | None

    @property
    def iterations(self) -> int:
        return len(self.steps)

    def aligned(self, k: int) -> np.ndarray:
        """The source placed by ``poses[k]`` (target frame)."""
        return apply(self.poses[k], self.source)

    @property
    def label(self) -> str:
        if self.result is None:
            return self.start
        state = "converged" if self.result.converged else "not converged"
        text = f"{self.method} from {self.start}: {self.result.num_iterations} iterations, {state}"
        if self.result.confidence is not None:
            doubts = self.result.doubts()
            verdict = "trusted" if not doubts else "LOW" if self.result.confidence < self.result.policy.trusted else (
                "ambiguous" if self.result.ambiguous else "not trusted: " + "; ".join(doubts))
            text += f"; confidence {self.result.confidence:.2f} ({verdict})"
        return text


def fixed_trace(source, target, pose, label: str, result: RegistrationResult | None = None) -> RegistrationTrace:
    """A trace of no iteration that shows ``source`` placed by ``pose`` (4x4 ``T_target_source``;
    the identity for clouds already aligned), captioned ``label`` (with ``result``, the
    registration the pose comes from, its method and verdict instead)."""
    pose = as_transform(pose, "pose")
    source, target = as_points(source, "source"), as_points(target, "target")
    if result is None:
        return RegistrationTrace("", label, source, target, (pose,), (), None)
    return RegistrationTrace(result.method, start_name(result), source, target, (pose,), (), result)


def start_name(result: RegistrationResult) -> str:
    """How the run started, for captions."""
    if result.init.startswith("global:"):
        return f"global search ({result.init.split(':', 1)[1]})"
    return "given pose" if result.init == "given" else result.init


def trace_registration(
    source,
    target,
    *,
    method: str = "esm",
    init="identity",
    sigma: float | None = None,
    max_iterations: int = 100,
    tolerance: float = 1e-8,
    per_point: bool = True,
) -> RegistrationTrace:
    """Run :func:`esmicp.register` from ``init`` (any of its values: ``"identity"``, a 4x4
    ``T_target_source``, ``None`` / ``"global"`` or a strategy) and keep every iteration of its
    local refinement; after a global search, ``poses[0]`` is the search's pose. The pose is the
    one :func:`esmicp.register` gives with these arguments (the callback changes nothing). When
    it tries a second run from the same start, the trace is the run whose pose it returns.
    ``per_point``: keep each iteration's per-point arrays (heat maps, animations need them; the
    viewer does not).
    """
    source_points = as_points(source, "source")
    target_points = as_points(target, "target")
    runs: list[list[tuple[np.ndarray, Step]]] = []

    def keep(state) -> None:
        if state.iteration == 1:
            runs.append([])
        distances = np.array(state.distances, dtype=np.float64)
        rmse = float(np.sqrt(np.mean(np.square(distances))))
        arrays = (None, None, None)
        if per_point:
            weights = np.ones(len(distances)) if state.weights is None else np.array(state.weights, dtype=np.float64)
            arrays = (np.array(state.indices, dtype=np.int64), distances, weights)
        step = Step(state.iteration, np.array(state.transformation, dtype=np.float64), *arrays, state.sigma, rmse)
        runs[-1].append((np.array(state.placement, dtype=np.float64), step))

    result = register(
        source_points, target_points, method=method, init=init, sigma=sigma,
        max_iterations=max_iterations, tolerance=tolerance, callback=keep,
    )
    kept = next((run for run in reversed(runs) if np.array_equal(run[-1][1].transformation, result.transformation)),
                runs[-1] if runs else [])
    start = kept[0][0] if kept else result.transformation
    steps = tuple(step for _, step in kept)
    poses = (start, *(step.transformation for step in steps))
    return RegistrationTrace(method, start_name(result), source_points, target_points, poses, steps, result)
