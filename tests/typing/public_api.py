"""A user's script, checked with ``mypy --strict`` (tests/test_typing.py): the public names carry
their types (no ``Any`` behind the lazy imports), and the compiled module has its stub."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

import esmicp
from esmicp import _kernels
from esmicp.methods.local import IterationState


def stop_after_ten(state: IterationState) -> bool:
    return state.iteration >= 10


def pose(source: npt.NDArray[np.float64], target: npt.NDArray[np.float64], out: Path) -> float:
    result: esmicp.RegistrationResult = esmicp.register(
        source, target, method="esm", init="global", callback=stop_after_ten, return_correspondences=True
    )
    matrix: npt.NDArray[np.float64] = result.transformation
    pairs: esmicp.Correspondences | None = result.correspondences
    count: int = 0 if pairs is None else len(pairs)
    trusted: bool = result.trusted
    confidence: float | None = result.confidence
    esmicp.write_transform(out / "T.txt", matrix, overwrite=True)
    esmicp.write_points(out / "source.ply", source, overwrite=True)
    read: npt.NDArray[np.float64] = esmicp.read_points(out / "source.ply")
    poses: dict[str, npt.NDArray[np.float64]] = esmicp.read_stanford_conf(out / "bun.conf")
    merged: esmicp.MultiRegistrationResult = esmicp.register_scans([source, target, read])
    esmicp.write_poses(out / "poses.txt", merged.poses, format="tum", names=["a", "b", "c"], overwrite=True)
    written: esmicp.PoseFile = esmicp.read_poses(out / "poses.txt")
    stored: npt.NDArray[np.float64] = written.poses
    threads: int = _kernels.hardware_threads()
    methods: tuple[str, ...] = tuple(esmicp.METHODS)
    return float(count + trusted + len(poses) + threads + len(methods) + len(merged.poses) + len(stored)) + (confidence or 0.0)
