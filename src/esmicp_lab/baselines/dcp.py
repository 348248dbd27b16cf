"""``dcp-v1``: Deep Closest Point v1 with its authors' pretrained ModelNet40 weights, in CPU torch.

One forward pass, no start needed within its training range (rotations of up to 45 degrees per
Euler angle, translations of up to 0.5 per axis on unit-sphere objects), so it is listed as a
``global`` method; far outside that range it is not expected to work, and the bench shows how it
fares there. The ESM-ICP paper's "DCP" row used DCP **v2** (the transformer pointer), whose
weights are not at hand: every result of this adapter is labelled ``dcp-v1``.

The model is :mod:`esmicp_lab.baselines.dcp_model` (written in the project). Its weights,
``dcp/dcp_v1.t7``, are looked for by :func:`esmicp_lab.baselines.weights.find_weights` (the
``weights_dir`` argument, ``$ESMICP_WEIGHTS_DIR``, ``../shared/weights`` beside the checkout) and
never shipped; missing ones raise :class:`~esmicp_lab.baselines.WeightsNotAvailableError`.

What the adapter does around the network (the authors' ModelNet40 pipeline feeds it 1,024 points
of an object inside the unit sphere, centred at the origin, and the same object moved by at most
45 degrees and 0.5):

- the source is first moved by ``init`` (the identity by default);
- each cloud is subsampled (with ``rng``) to :data:`NUM_POINTS` = 1,024 points (all points when
  it has fewer), centred on its own centroid, and both are scaled by one factor that puts the
  target inside the unit sphere; so the network never sees a translation larger than the
  centroids' residual offset (the caller's translation is recovered from the centroids);
- ``R, t`` of the network (``target_n ~= R source_n + t``) are mapped back to the caller's frames
  and units: ``T_target_source = [R | c_t - R c_s + t / s] @ init``.

``max_iterations`` passes (default 1, the authors' protocol): each pass re-runs the network on the
source moved by the previous estimate. Runs in float32 on one torch thread (restored afterwards),
as :mod:`esmicp_lab.baselines.pointnetlk` does. ``voxel_size`` is validated and unused.
"""

from __future__ import annotations

import time

import numpy as np

from esmicp.core.procrustes import apply
from ._common import TORCH_HINT, checked_inputs, require
from .base import BaselineResult
from .weights import find_weights

NAME = "dcp-v1"

#: Points per cloud the network sees (its training setting).
NUM_POINTS = 1024

#: The authors' pretrained state, relative to a weights folder.
WEIGHTS_FILE = "dcp/dcp_v1.t7"

_MODELS: dict = {}


def load_model(weights_dir=None):
    """The DCP-v1 network with the authors' state loaded (``weights_only=True``, ``strict=True``),
    in eval mode. Cached per weights file. Raises :class:`MissingDependencyError` when torch is
    missing and :class:`WeightsNotAvailableError` when the weights are not found."""
    torch = require("torch", "torch", TORCH_HINT)
    path = find_weights(NAME, WEIGHTS_FILE, weights_dir)
    key = str(path.resolve())
    if key not in _MODELS:
        from .dcp_model import DCPv1

        model = DCPv1()
        state = torch.load(path, map_location="cpu", weights_only=True)
        model.load_state_dict(state, strict=True)
        model.eval()
        _MODELS[key] = model
    return _MODELS[key]


def _subsample(points: np.ndarray, generator: np.random.Generator) -> np.ndarray:
    if len(points) <= NUM_POINTS:
        return points
    return points[generator.choice(len(points), size=NUM_POINTS, replace=False)]


def register(
    source,
    target,
    *,
    init=None,
    max_iterations: int = 1,
    voxel_size: float | None = None,
    rng=None,
    weights_dir=None,
) -> BaselineResult:
    """Register ``source`` onto ``target`` with the authors' pretrained DCP-v1.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array-like
    init : (4, 4) array-like, optional
        A ``T_target_source`` the source is moved by first; None is the identity.
    max_iterations : int
        Passes of the network (1: the authors' protocol).
    voxel_size
        Validated, unused.
    rng : None, int or numpy.random.Generator
        Draws the 1,024-point subsamples.
    weights_dir : path, optional
        A folder holding ``dcp/dcp_v1.t7``.
    """
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)
    model = load_model(weights_dir)
    import torch

    generator = np.random.default_rng(inputs.seed)
    start = time.perf_counter()
    target_sample = _subsample(inputs.target, generator)
    source_sample = _subsample(inputs.source, generator)
    target_centre = target_sample.mean(axis=0)
    scale = 1.0 / float(np.linalg.norm(target_sample - target_centre, axis=1).max())
    target_n = torch.as_tensor(((target_sample - target_centre) * scale).T, dtype=torch.float32)[None]
    estimate = np.array(inputs.init, dtype=np.float64)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for _ in range(inputs.max_iterations):
            moved = apply(estimate, source_sample)
            source_centre = moved.mean(axis=0)
            source_n = torch.as_tensor(((moved - source_centre) * scale).T, dtype=torch.float32)[None]
            rotation, translation = model(source_n, target_n)
            rotation = rotation[0].double().numpy()
            step = np.eye(4)  # target - c_t ~= R (moved - c_s) + t / s
            step[:3, :3] = rotation
            step[:3, 3] = target_centre - rotation @ source_centre + translation[0].double().numpy() / scale
            estimate = step @ estimate
    finally:
        torch.set_num_threads(threads)
    runtime = time.perf_counter() - start
    # Re-orthonormalise (the float32 SVD leaves ~1e-7 off a rotation).
    u, _, vh = np.linalg.svd(estimate[:3, :3])
    estimate[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vh)]) @ vh
    return BaselineResult(
        transformation=estimate,
        runtime_s=runtime,
        method=NAME,
        converged=None,
        notes=(
            f"weights={WEIGHTS_FILE} (DCP v1: identity pointer); points={min(NUM_POINTS, len(inputs.source))}/"
            f"{min(NUM_POINTS, len(inputs.target))}; scale={scale:.6g}; passes={inputs.max_iterations}; "
            f"max_iterations={inputs.max_iterations}; seed={inputs.seed}"
        ),
    )
