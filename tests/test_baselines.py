"""Baseline adapters (esmicp_lab.baselines): the common interface, recovery on an easy real pair,
determinism, and the error raised when an optional library is missing.

The baseline libraries are optional: locally a test that needs a missing one is skipped; in CI
(``CI=true``), where .ci/run installs them, it fails.
"""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
from conftest import require_module, require_shared
from scipy.spatial.transform import Rotation

from esmicp_lab.baselines import (
    BASELINES,
    BaselineResult,
    MissingDependencyError,
    get_baseline,
)
from esmicp.errors import EsmicpError, InvalidInputError
from esmicp.metrics import rotation_error_deg, translation_error

#: Adapters that find the pose from any start, and the module each one imports.
GLOBAL = {
    "open3d-ransac-fpfh-icp": ("open3d",),
    "open3d-ransac-fpfh-p2l": ("open3d",),
    "kiss-matcher-icp": ("kiss_matcher", "open3d"),
    "kiss-matcher-p2l": ("kiss_matcher", "open3d"),
    "kiss-matcher-gicp": ("kiss_matcher", "small_gicp"),
}
LOCAL = {"small-gicp": ("small_gicp",)}
MODULES = {**GLOBAL, **LOCAL}


def _require_all(method: str) -> None:
    for module in MODULES[method]:
        require_module(module, "baselines")


def _read_only(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=np.float64)
    array.setflags(write=False)
    return array


def _pair(max_angle_deg: float | None, seed: int, scale: float = 1.0):
    """Chair, 2,000 + 2,000 points: disjoint random halves; the source half moved by a random
    rotation (uniform on SO(3) if ``max_angle_deg`` is None) and translation. Read-only arrays."""
    path = require_shared("modelnet40/chair/chair_0848.txt")
    cloud = scale * np.loadtxt(path, delimiter=",")[:, :3]
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(cloud))[:4000]
    target, source_object = cloud[order[:2000]], cloud[order[2000:]]
    if max_angle_deg is None:
        rotation = Rotation.random(random_state=rng).as_matrix()
    else:
        axis = rng.normal(size=3)
        rotation = Rotation.from_rotvec(np.radians(max_angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
    diagonal = float(np.linalg.norm(target.max(axis=0) - target.min(axis=0)))
    shift = rng.uniform(-diagonal, diagonal, size=3) if max_angle_deg is None else 0.02 * diagonal * np.ones(3)
    source = source_object @ rotation.T + shift
    truth = np.eye(4)  # T_target_source = inverse of the motion applied to the source
    truth[:3, :3] = rotation.T
    truth[:3, 3] = -rotation.T @ shift
    return _read_only(source), _read_only(target), truth, diagonal


@pytest.fixture(scope="module")
def chair_pair():
    return _pair(None, seed=11)


@pytest.mark.parametrize("method", sorted(GLOBAL))
def test_global_adapter_recovers_a_random_rotation(method, chair_pair):
    _require_all(method)
    source, target, truth, diagonal = chair_pair
    before = (source.copy(), target.copy())
    result = get_baseline(method)(source, target, rng=5)

    assert isinstance(result, BaselineResult)
    assert result.method == method
    assert result.transformation.shape == (4, 4) and result.transformation.dtype == np.float64
    assert np.allclose(result.transformation[3], [0, 0, 0, 1])
    assert result.runtime_s > 0
    assert result.converged in (True, False, None)
    assert "voxel=" in result.notes
    assert rotation_error_deg(result.transformation, truth) < 5.0
    assert translation_error(result.transformation, truth) < 0.05 * diagonal
    np.testing.assert_array_equal(source, before[0])
    np.testing.assert_array_equal(target, before[1])


def test_small_gicp_is_local_and_refines_a_nearby_pose():
    _require_all("small-gicp")
    source, target, truth, diagonal = _pair(10.0, seed=12)
    result = get_baseline("small-gicp")(source, target)
    assert result.method == "small-gicp"
    assert isinstance(result.converged, bool)
    assert rotation_error_deg(result.transformation, truth) < 5.0
    assert translation_error(result.transformation, truth) < 0.05 * diagonal


@pytest.mark.parametrize("method", ["kiss-matcher-icp", "kiss-matcher-gicp"])
def test_kiss_matcher_works_in_any_units(method):
    # KISS-Matcher itself refuses voxels below 5 mm; the adapter works in voxel units, and the
    # refinement's distances follow the voxel.
    _require_all(method)
    source, target, truth, diagonal = _pair(None, seed=11, scale=0.01)
    result = get_baseline(method)(source, target)
    assert rotation_error_deg(result.transformation, truth) < 5.0
    assert translation_error(result.transformation, truth) < 0.05 * diagonal


def test_open3d_ransac_is_deterministic_for_a_seed(chair_pair):
    _require_all("open3d-ransac-fpfh-icp")
    source, target, _, _ = chair_pair
    register = get_baseline("open3d-ransac-fpfh-icp")
    first = register(source, target, rng=2024).transformation
    again = register(source, target, rng=2024).transformation
    from_generator = register(source, target, rng=np.random.default_rng(2024)).transformation
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(first, from_generator)


def test_registry_and_bad_arguments(chair_pair):
    assert set(MODULES) <= set(BASELINES)  # every adapter: tests/test_baselines_methods.py
    with pytest.raises(InvalidInputError, match="unknown method 'nope'"):
        get_baseline("nope")
    _require_all("open3d-ransac-fpfh-icp")
    source, target, _, _ = chair_pair
    register = get_baseline("open3d-ransac-fpfh-icp")
    with pytest.raises(InvalidInputError, match="voxel_size"):
        register(source, target, voxel_size=-1.0)
    with pytest.raises(InvalidInputError, match="max_iterations"):
        register(source, target, max_iterations=0)
    with pytest.raises(InvalidInputError, match="source"):
        register(source[:, :2], target)
    with pytest.raises(InvalidInputError, match="rng"):
        register(source, target, rng="seed")


@pytest.mark.parametrize("method", sorted(MODULES))
def test_missing_library_raises_with_an_install_hint(method, monkeypatch):
    missing = MODULES[method][0]
    monkeypatch.setitem(sys.modules, missing, None)  # import of it now raises ImportError
    points = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(MissingDependencyError) as caught:
        get_baseline(method)(points, points)
    assert isinstance(caught.value, EsmicpError)
    message = str(caught.value)
    assert "pip install 'esmicp[baselines]'" in message
    assert "libusb-1.0-0" in message


def test_broken_shared_library_is_a_missing_dependency(monkeypatch):
    # open3d-cpu without libusb-1.0 fails at import with an OSError-like error, not ImportError.
    from esmicp_lab.baselines import _common

    def broken(name):
        raise OSError("libusb-1.0.so.0: cannot open shared object file")

    monkeypatch.setattr(_common, "importlib", types.SimpleNamespace(import_module=broken))
    points = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(MissingDependencyError, match="libusb-1.0.so.0"):
        get_baseline("open3d-ransac-fpfh-icp")(points, points)
