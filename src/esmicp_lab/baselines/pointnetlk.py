"""``pointnetlk``: PointNetLK with learning3d's pretrained ModelNet40 weights, in CPU torch. A LOCAL
method (it refines from ``init``; the network was trained on perturbations of up to 45 degrees).

The model is :mod:`esmicp_lab.baselines.pointnetlk_model` (written in the project; learning3d's PyPI
wheel is unusable). Its weights, ``pointnetlk/best_model.t7``, are looked for by
:func:`esmicp_lab.baselines.weights.find_weights` (the ``weights_dir`` argument, ``$ESMICP_WEIGHTS_DIR``,
``../shared/weights`` beside the checkout) and never shipped; missing ones raise
:class:`~esmicp_lab.baselines.WeightsNotAvailableError`.

The adapter absorbs the network's training conditions:

- both clouds are subsampled (with ``rng``) to :data:`NUM_POINTS` = 1,024 points, as in training;
- both are expressed in one normalised frame, centred on the target's centroid and scaled so that
  the target fits the unit sphere (ModelNet40 as trained: ``modelnet40`` objects are already in it);
  the source is first moved by ``init``;
- inside, each cloud is centred on its own centroid (PointNetLK's protocol), the LK iterations run
  (at most ``max_iterations``, stopping when the twist increment falls below 1e-7), and the pose is
  mapped back to the original frames and units and composed with ``init``.

Runs in float32 on one torch thread (restored afterwards), like the other single-threaded
adapters: on this 2-core machine shared with other jobs one thread ran PointNet 12x faster than
two (0.05 s against 0.63 s per 1,024-point forward pass, measured). ``voxel_size`` is validated and unused.
"""

from __future__ import annotations

import time

import numpy as np

from .base import BaselineResult
from esmicp.core.procrustes import apply
from ._common import TORCH_HINT, checked_inputs, require
from .weights import find_weights

NAME = "pointnetlk"

#: Default iteration cap of the local methods (the same for every local adapter).
MAX_ITERATIONS = 50

#: Points per cloud the network sees (its training setting).
NUM_POINTS = 1024

#: The pretrained state, relative to a weights folder.
WEIGHTS_FILE = "pointnetlk/best_model.t7"

_MODELS: dict = {}


def load_model(weights_dir=None):
    """The PointNetLK network with its pretrained state loaded (``strict=True``), in eval mode.

    Cached per weights file. Raises :class:`MissingDependencyError` when torch is missing and
    :class:`WeightsNotAvailableError` when the weights are not found.
    """
    torch = require("torch", "torch", TORCH_HINT)
    path = find_weights(NAME, WEIGHTS_FILE, weights_dir)
    key = str(path.resolve())
    if key not in _MODELS:
        from .pointnetlk_model import PointNetLK

        model = PointNetLK()
        state = torch.load(path, map_location="cpu", weights_only=True)
        model.load_state_dict(state, strict=True)
        model.eval()
        _MODELS[key] = model
    return _MODELS[key]


def _subsample(points: np.ndarray, generator: np.random.Generator) -> np.ndarray:
    replace = len(points) < NUM_POINTS
    return points[generator.choice(len(points), size=NUM_POINTS, replace=replace)]


def register(
    source,
    target,
    *,
    init=None,
    max_iterations: int = MAX_ITERATIONS,
    voxel_size: float | None = None,
    rng=None,
    weights_dir=None,
) -> BaselineResult:
    """Register ``source`` onto ``target`` with pretrained PointNetLK from ``init``.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array-like
    init : (4, 4) array-like, optional
        Initial ``T_target_source``; None is the identity.
    max_iterations : int
        LK iterations, at most.
    voxel_size
        Validated, unused.
    rng : None, int or numpy.random.Generator
        Draws the 1,024-point subsamples.
    weights_dir : path, optional
        A folder holding ``pointnetlk/best_model.t7``.
    """
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)
    model = load_model(weights_dir)
    import torch

    generator = np.random.default_rng(inputs.seed)
    start = time.perf_counter()
    centre = inputs.target.mean(axis=0)
    scale = 1.0 / float(np.linalg.norm(inputs.target - centre, axis=1).max())
    template = _subsample((inputs.target - centre) * scale, generator)
    moved = _subsample((apply(inputs.init, inputs.source) - centre) * scale, generator)
    template_mean, moved_mean = template.mean(axis=0), moved.mean(axis=0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        g, iterations, converged = model.register(
            torch.as_tensor(template - template_mean, dtype=torch.float32)[None],
            torch.as_tensor(moved - moved_mean, dtype=torch.float32)[None],
            inputs.max_iterations,
        )
    finally:
        torch.set_num_threads(threads)
    g = g.double().numpy()
    runtime = time.perf_counter() - start

    # In the normalised frame: template ~= R (moved - m1) + t + m0.
    rotation = g[:3, :3]
    normalised_t = g[:3, 3] + template_mean - rotation @ moved_mean
    step = np.eye(4)  # the same motion in the original frame: x -> R x + t / s + c - R c
    step[:3, :3] = rotation
    step[:3, 3] = normalised_t / scale + centre - rotation @ centre
    return BaselineResult(
        transformation=step @ inputs.init,
        runtime_s=runtime,
        method=NAME,
        converged=bool(converged),
        notes=(
            f"weights={WEIGHTS_FILE}; points={NUM_POINTS}; scale={scale:.6g}; "
            f"max_iterations={inputs.max_iterations}; iterations={iterations}; seed={inputs.seed}"
        ),
    )
