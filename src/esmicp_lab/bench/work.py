"""One unit of work, the same function on every executor: a trial and the methods to run on it,
in, one row per method out (the row schema of ``docs/bench.md``)."""

from __future__ import annotations

import math
import subprocess
from dataclasses import dataclass

import numpy as np

from esmicp.core.procrustes import rotation_angle
from esmicp.metrics import (
    paper_errors,
    rotation_error_deg,
    strict_success,
    symmetric_placement_error,
    translation_error,
    up_to_symmetry_success,
)
from .protocols import Trial
from .methods import Unavailable, method_kind, run_method
from .results import row_key  # noqa: F401  (re-exported: where the runner looks for it)
from .trials import TrialSpec

#: The processes' methods already called once (their first call, untimed, pays the imports).
_WARM: set[str] = set()


@dataclass(frozen=True, eq=False)
class WorkItem:
    """A trial and the (method, sigma) runs still to do on it.

    ``init`` is the start every local method gets (4x4 ``T_target_source``); ``init_label`` what
    rows say about it (``identity`` or ``given``).
    """

    spec: TrialSpec
    trial: Trial
    runs: tuple[tuple[str, float | None], ...]
    max_iterations: int
    init: np.ndarray
    init_label: str
    #: Threads of esmicp's own compiled kernels (``register(workers=...)``); None: every core.
    #: One inside a Dask worker, whose cluster already runs one process per core.
    threads: int | None = None


def run_item(item: WorkItem) -> list[dict]:
    """Every run of ``item``, one row each (never raises for a method's own failure)."""
    return [run_one(item, method, sigma) for method, sigma in item.runs]


def _finite_or_none(value):
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def run_one(item: WorkItem, method: str, sigma: float | None) -> dict:
    trial, spec = item.trial, item.spec
    kind = method_kind(method)
    row = {
        "trial_id": spec.trial_id,
        "seed": spec.seed,
        "protocol": spec.protocol,
        "dataset": spec.dataset,
        "cloud": spec.cloud,
        "method": method,
        "method_kind": kind,
        "sigma": sigma,
        "max_iterations": item.max_iterations if kind == "local" else None,
        "init": item.init_label if kind == "local" else "none (global)",
        "status": "ok",
        "reason": "",
        "initial_rotation_deg": float(np.degrees(rotation_angle(trial.T_target_source[:3, :3]))),
        "diagonal": float(trial.diagonal),
        "points_source": int(len(trial.source)),
        "points_target": int(len(trial.target)),
        "trial_index": spec.index,
        "points": spec.points,
        "translation_range": spec.translation_range,
        "case": spec.case,
    }
    metrics = dict.fromkeys(
        ("rotation_error_deg", "translation_error", "success_strict", "success_symmetry", "mse_r", "rmse_r",
         "mae_r", "mse_t", "rmse_t", "mae_t", "time_s", "iterations", "converged", "ambiguous"), None)
    row.update(metrics, notes="")
    call = dict(init=item.init, max_iterations=item.max_iterations, sigma=sigma, seed=spec.seed, workers=item.threads)
    try:
        if method not in _WARM:
            run_method(method, trial.source, trial.target, **call)  # untimed: imports, first-call caches
            _WARM.add(method)
        outcome = run_method(method, trial.source, trial.target, **call)
        estimate = np.asarray(outcome.transformation, dtype=np.float64)
        if estimate.shape != (4, 4) or not np.all(np.isfinite(estimate)):
            raise ValueError(f"returned a non-finite or malformed transform (shape {estimate.shape})")
    except Unavailable as exc:
        row.update(status="unavailable", reason=str(exc))
        return row
    except (TimeoutError, subprocess.TimeoutExpired) as exc:  # e.g. an adapter's child process ran out of time
        row.update(status="timeout", reason=f"{type(exc).__name__}: {exc}")
        return row
    except Exception as exc:  # noqa: BLE001 - a method's own crash is a row, not the end of the run
        row.update(status="failed", reason=f"{type(exc).__name__}: {exc}")
        return row
    truth = trial.T_target_source
    pivot = trial.source.mean(axis=0)
    errors = paper_errors(estimate, truth)
    row.update(
        rotation_error_deg=rotation_error_deg(estimate, truth),
        translation_error=translation_error(estimate, truth, pivot),
        success_strict=strict_success(estimate, truth, trial.diagonal, pivot=pivot),
        success_symmetry=up_to_symmetry_success(trial.clean_source, estimate, truth, trial.diagonal),
        placement_error=symmetric_placement_error(trial.clean_source, estimate, truth),
        mse_r=errors["rotation_mse"], rmse_r=errors["rotation_rmse"], mae_r=errors["rotation_mae"],
        mse_t=errors["translation_mse"], rmse_t=errors["translation_rmse"], mae_t=errors["translation_mae"],
        time_s=outcome.time_s, iterations=outcome.iterations, converged=outcome.converged,
        ambiguous=outcome.ambiguous, notes=outcome.notes, transformation=estimate.tolist(),
    )
    for key in ("rotation_error_deg", "translation_error", "placement_error", "mse_r", "rmse_r", "mae_r",
                "mse_t", "rmse_t", "mae_t"):
        row[key] = _finite_or_none(row[key])
    return row
