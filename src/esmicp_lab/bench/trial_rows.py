"""Benchmark rows (the ``esmicp bench`` row schema) from real local registrations on a few seeded
trials: a small, fast stand-in for a full benchmark, so that the plots can be tried and tested on
measured figures. The full benchmark suite writes the same rows.

The trials (:func:`angle_trial`) spread the initial rotation evenly over 0-180 degrees (a rotation
uniform on SO(3) would put most trials near 180 degrees) and rotate the source about its own
centroid with a small shift, so that local methods started from the identity are tested on the
rotation they must undo.

``benchmarks/bench_plot_rows.py OUT_DIR [--rows-out rows.jsonl]`` writes the plots from these rows
(the library holds no command line).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence

import numpy as np

from esmicp.api import register
from esmicp.errors import EsmicpError, EsmicpWarning
from esmicp.metrics import paper_errors, rotation_error_deg, strict_success, translation_error, up_to_symmetry_success
from esmicp.core.procrustes import apply, bounding_box_diagonal, rigid_inverse, to_matrix
from .protocols import Trial
from esmicp.shapes import asymmetric_shape

#: Methods, protocols and sigmas (fractions of the target's diagonal) of :func:`local_trial_rows`.
DEFAULT_METHODS = ("esm", "icp", "esm-paper")
DEFAULT_PROTOCOLS = ("copy", "resampled")
DEFAULT_SIGMA_FRACTIONS = (0.01, 0.03, 0.1, 0.3, 1.0)


#: Protocols :func:`angle_trial` builds (their meaning as in :mod:`esmicp_lab.bench.protocols`).
ANGLE_PROTOCOLS = ("copy", "shuffled", "resampled")


def angle_trial(protocol: str, cloud, angle_deg: float, rng: np.random.Generator, *, name: str = "", seed=None) -> Trial:
    """A trial of ``protocol`` whose source is rotated by exactly ``angle_deg`` degrees (random
    axis) about its centroid and shifted by up to 5% of the diagonal. ``copy``: the source is the
    cloud; ``shuffled``: the same, point order shuffled; ``resampled``: the cloud split in two
    random halves, target and source."""
    cloud = np.asarray(cloud, dtype=np.float64)
    if protocol not in ANGLE_PROTOCOLS:
        raise ValueError(f"protocol: expected one of {', '.join(ANGLE_PROTOCOLS)}, got {protocol!r}")
    target, source_object = cloud, cloud
    if protocol == "resampled":
        order = rng.permutation(len(cloud))
        half = len(cloud) // 2
        target, source_object = cloud[order[:half]], cloud[order[half : 2 * half]]
    axis = rng.normal(size=3)
    rotation = _about(axis, angle_deg)
    centroid = source_object.mean(axis=0)
    shift = rng.uniform(-0.05, 0.05, 3) * bounding_box_diagonal(target)
    moved_by = to_matrix(rotation, centroid - rotation @ centroid + shift)
    source = apply(moved_by, source_object)
    if protocol == "shuffled":
        source = source[rng.permutation(len(source))]
    target, truth = np.array(target), rigid_inverse(moved_by)
    for array in (source, target, truth):
        array.setflags(write=False)
    return Trial(protocol, name, source, target, truth, seed, bounding_box_diagonal(target))


def _about(axis, angle_deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()


def trial_row(trial, method: str, *, dataset: str, index: int, seed: int, sigma=None, max_iterations: int = 100) -> dict:
    """One schema row: ``method`` run from the identity on ``trial`` (a :class:`~esmicp_lab.bench.protocols.Trial`).

    The library's warnings (e.g. ``esm-paper`` on clouds that are not index-aligned) go to the
    extra key ``warnings`` (a list of messages) instead of the console."""
    truth = trial.T_target_source
    row = {
        "trial_id": f"{dataset}/{trial.cloud}/{trial.protocol}/{index}", "seed": seed, "protocol": trial.protocol,
        "dataset": dataset, "cloud": trial.cloud, "method": method, "method_kind": "local", "sigma": sigma,
        "max_iterations": max_iterations, "init": "identity", "status": "ok", "reason": "",
        "initial_rotation_deg": rotation_error_deg(np.eye(4), truth), "diagonal": trial.diagonal,
        "points_source": len(trial.source), "points_target": len(trial.target),
    }
    start = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", EsmicpWarning)
            result = register(trial.source, trial.target, method=method, init="identity", sigma=sigma,
                              max_iterations=max_iterations)
    except (EsmicpError, np.linalg.LinAlgError) as exc:
        row.update(status="failed", reason=str(exc), rotation_error_deg=None, translation_error=None,
                   success_strict=None, success_symmetry=None, time_s=None, iterations=None,
                   **dict.fromkeys(("mse_r", "rmse_r", "mae_r", "mse_t", "rmse_t", "mae_t")))
        return row
    elapsed = time.perf_counter() - start
    estimate = result.transformation
    pivot = trial.source.mean(axis=0)
    paper = paper_errors(estimate, truth)
    row.update(
        rotation_error_deg=rotation_error_deg(estimate, truth),
        translation_error=translation_error(estimate, truth, pivot=pivot),
        success_strict=strict_success(estimate, truth, trial.diagonal, pivot=pivot),
        success_symmetry=up_to_symmetry_success(trial.clean_source, estimate, truth, trial.diagonal),
        mse_r=paper["rotation_mse"], rmse_r=paper["rotation_rmse"], mae_r=paper["rotation_mae"],
        mse_t=paper["translation_mse"], rmse_t=paper["translation_rmse"], mae_t=paper["translation_mae"],
        time_s=elapsed, iterations=result.num_iterations,
        warnings=[str(w.message) for w in caught if issubclass(w.category, EsmicpWarning)],
    )
    return row


def local_trial_rows(
    clouds: dict | None = None,
    *,
    trials: int = 6,
    points: int = 300,
    seed: int = 0,
    methods: Sequence[str] = DEFAULT_METHODS,
    protocols: Sequence[str] = DEFAULT_PROTOCOLS,
    sweep_method: str | None = "esm",
    sigma_fractions: Sequence[float] = DEFAULT_SIGMA_FRACTIONS,
    dataset: str = "synthetic",
) -> list[dict]:
    """Rows of every method on ``trials`` trials per protocol (clouds: name -> (N, 3) points, used
    as given; default: the built-in shape at ``points`` points; resampled halves have half), the initial rotations
    spread evenly over (0, 180) degrees (:func:`angle_trial`), plus a sigma sweep of
    ``sweep_method`` on the first protocol's trials (fixed sigma = fraction x the cloud's diagonal,
    the same value on every trial of a cloud). All from the identity. Trial ``index`` of a
    protocol draws from ``SeedSequence(seed, spawn_key=(protocol number, index))``."""
    if clouds is None:
        clouds = {"built-in shape": asymmetric_shape(points, np.random.default_rng(seed))}
    names = list(clouds)
    rows = []
    for number, protocol in enumerate(protocols):
        for index in range(trials):
            name = names[index % len(names)]
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(number, index)))
            angle = (index + 0.5) * 180.0 / trials
            trial = angle_trial(protocol, clouds[name], angle, rng, name=name, seed=(seed, number, index))
            for method in methods:
                rows.append(trial_row(trial, method, dataset=dataset, index=index, seed=seed))
            if sweep_method is not None and number == 0:
                diagonal = bounding_box_diagonal(clouds[name])
                for fraction in sigma_fractions:
                    sigma = float(f"{fraction * diagonal:.4g}")
                    rows.append(trial_row(trial, sweep_method, dataset=dataset, index=index, seed=seed, sigma=sigma))
    return rows
