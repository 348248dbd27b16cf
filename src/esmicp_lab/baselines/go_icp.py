"""``go-icp``: globally optimal ICP by branch and bound (Yang, Li & Jia 2013/2016), from py-goicp
0.0.4. A GLOBAL method (``init`` and ``max_iterations`` are validated and ignored).

The adapter absorbs Go-ICP's quirks:

- **Scale.** Go-ICP expects both clouds in ``[-1, 1]^3``. Each cloud is centred on its centroid and
  both are divided by one factor, the largest centred coordinate of either, so that they fit; the
  pose found is mapped back to the original units and frames.
- **Size.** Go-ICP's cost grows with the data (source) points: the source is subsampled to
  :data:`DATA_POINTS` points (drawn with ``rng``), the target (the model, looked up through a
  distance transform) is kept whole.
- **Search space.** All rotations (the cube ``[-pi, pi]^3`` of rotation vectors), translations in
  ``[-0.5, 0.5]^3`` of the normalised units after the centring (the centroids already coincide for
  full overlap; this leaves half of the normalised half-size for partial overlap).
- **Stopping.** Branch and bound stops when the best error minus the lower bound falls below
  ``MSEThresh x data points``; ``MSEThresh`` is the squared median point spacing of the normalised
  target (an error at that level means the clouds lie on each other), no trimming (``trim_fraction``
  for outliers). Distance transform: :data:`DT_SIZE` cells a side, expansion factor 2.
- **No time limit, prints to stdout.** It runs in a child process (``python -m
  esmicp_lab.baselines._goicp_child``, stdout discarded) killed after ``timeout_s`` seconds, which
  raises :class:`~esmicp_lab.baselines.BaselineTimeoutError`.

``runtime_s`` is the time of Go-ICP's distance transform and registration measured in the child;
the process start and the transfer of the clouds (a temporary ``.npz``) are in ``notes`` as the wall
time.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .base import BaselineResult, BaselineTimeoutError
from ._common import GOICP_HINT, checked_inputs, require
from esmicp.errors import InvalidInputError
from esmicp.types import as_positive

NAME = "go-icp"

#: Source points given to Go-ICP (subsampled with ``rng`` when the source has more).
DATA_POINTS = 300
#: Distance-transform resolution (cells per side) and expansion factor around the clouds.
DT_SIZE = 150
DT_FACTOR = 2.0
#: Translation search half-width, in normalised units (the clouds fit in [-1, 1]^3).
TRANSLATION_HALF_WIDTH = 0.5
#: Default wall-time limit of one registration, in seconds. Measured: successful runs take 5-11 s
#: on a quiet machine (up to ~25 s under load); with the paper's noise Go-ICP rarely finishes at all,
#: and a 60 s limit made its time-outs 64% of a whole ``esmicp bench --paper`` run.
TIMEOUT_S = 30.0


def register(
    source,
    target,
    *,
    init=None,
    max_iterations: int = 1,
    voxel_size: float | None = None,
    rng=None,
    timeout_s: float = TIMEOUT_S,
    data_points: int = DATA_POINTS,
    trim_fraction: float = 0.0,
) -> BaselineResult:
    """Register ``source`` onto ``target`` with Go-ICP in a child process; see the module's docstring.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array-like
    init, max_iterations, voxel_size
        Validated, ignored (a global method).
    rng : None, int or numpy.random.Generator
        Draws the source subsample.
    timeout_s : float
        Wall-time limit (seconds) of the child process.
    data_points : int
        Source points given to Go-ICP.
    trim_fraction : float
        Go-ICP's trimming (fraction of the worst data points ignored), in ``[0, 1)``.

    Raises
    ------
    MissingDependencyError
        When py_goicp cannot be imported.
    BaselineTimeoutError
        When Go-ICP has not finished within ``timeout_s``.
    """
    require("py_goicp", "py-goicp", GOICP_HINT)
    inputs = checked_inputs(source, target, voxel_size, max_iterations, rng, init)
    timeout_s = as_positive(timeout_s, "timeout_s")
    if not 0.0 <= float(trim_fraction) < 1.0:
        raise InvalidInputError(f"trim_fraction: expected a value in [0, 1), got {trim_fraction!r}")
    generator = np.random.default_rng(inputs.seed)

    wall_start = time.perf_counter()
    source_centre = inputs.source.mean(axis=0)
    target_centre = inputs.target.mean(axis=0)
    source_centred = inputs.source - source_centre
    target_centred = inputs.target - target_centre
    scale = 1.0 / max(float(np.abs(source_centred).max()), float(np.abs(target_centred).max()))
    data = source_centred * scale
    if len(data) > data_points:
        data = data[generator.choice(len(data), size=int(data_points), replace=False)]
    model = target_centred * scale
    sample = model[generator.choice(len(model), size=min(len(model), 5000), replace=False)]
    spacing = float(np.median(cKDTree(model).query(sample, k=2)[0][:, 1]))
    mse_threshold = spacing**2

    with tempfile.TemporaryDirectory(prefix="esmicp-goicp-") as folder:
        inputs_path = Path(folder) / "inputs.npz"
        result_path = Path(folder) / "result.npz"
        np.savez(
            inputs_path,
            model=model,
            data=data,
            mse_threshold=mse_threshold,
            dt_size=DT_SIZE,
            dt_factor=DT_FACTOR,
            trim_fraction=float(trim_fraction),
            translation_half_width=TRANSLATION_HALF_WIDTH,
        )
        command = [sys.executable, "-m", "esmicp_lab.baselines._goicp_child", str(inputs_path), str(result_path)]
        try:
            finished = subprocess.run(
                command,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                timeout=timeout_s,
                env={**os.environ, "PYTHONPATH": _child_pythonpath()},
            )
        except subprocess.TimeoutExpired:
            raise BaselineTimeoutError(
                f"{NAME}: no result within timeout_s={timeout_s:g} s ({len(data)} data points, "
                f"{len(model)} model points); the child process was killed"
            ) from None
        if finished.returncode != 0 or not result_path.exists():
            message = finished.stderr.decode(errors="replace").strip().splitlines()
            last = message[-1] if message else f"exit status {finished.returncode}"
            raise RuntimeError(f"{NAME}: the Go-ICP child process failed: {last}")
        with np.load(result_path) as result:
            rotation = result["rotation"]
            translation = result["translation"]
            runtime = float(result["runtime_s"])
    wall = time.perf_counter() - wall_start

    # Normalised: model ~= R data + t, i.e. (y - ct) s ~= R (x - cs) s + t.
    transformation = np.eye(4)
    transformation[:3, :3] = rotation
    transformation[:3, 3] = target_centre - rotation @ source_centre + translation / scale
    return BaselineResult(
        transformation=transformation,
        runtime_s=runtime,
        method=NAME,
        converged=True,  # branch and bound finished: the optimum within its threshold
        notes=(
            f"data_points={len(data)} model_points={len(model)}; scale={scale:.6g}; MSEThresh={mse_threshold:.4g}; "
            f"dt={DT_SIZE}x{DT_FACTOR:g}; trim={float(trim_fraction):g}; translations in +-{TRANSLATION_HALF_WIDTH:g}; "
            f"seed={inputs.seed}; wall time with the child process {wall:.3g} s"
        ),
    )


def _child_pythonpath() -> str:
    """``PYTHONPATH`` for the child: the folder holding this ``esmicp_lab`` package (and the
    ``esmicp`` installed beside it) first, so that the child imports this very copy."""
    folders = [str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH", "")]
    return os.pathsep.join(folder for folder in folders if folder)
