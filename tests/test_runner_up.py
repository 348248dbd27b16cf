"""``RegistrationResult.runner_up``: the other place the source may belong, in the clouds' own
frames, whenever the global search weighed a clearly different pose; the CLI shows it when the
pose is not trusted."""

from __future__ import annotations

import json

import numpy as np
import pytest

import esmicp
from esmicp_lab.bench.protocols import random_rigid_transform
from esmicp.cli import main
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.procrustes import apply, bounding_box_diagonal
from esmicp.globalreg.config import DEFAULT as SEARCH_DEFAULT
from esmicp.metrics import rotation_error_deg
from esmicp.shapes import asymmetric_shape

DISTINCT_DEG = SEARCH_DEFAULT.verification.distinct_rotation_deg


def _box_surface(count: int, rng: np.random.Generator, size=(3.0, 2.0, 1.0)) -> np.ndarray:
    """Points on the surface of a box with three different sides: any turn by 180 degrees about
    one of its axes maps it onto itself, so a registration has four equally good answers."""
    points = rng.uniform(-0.5, 0.5, (count, 3))
    rows, face = np.arange(count), rng.integers(0, 3, count)
    points[rows, face] = np.sign(points[rows, face]) * 0.5
    return points * np.asarray(size)


def _rigid(pose: np.ndarray) -> bool:
    rotation = pose[:3, :3]
    return (pose.shape == (4, 4) and np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-9)
            and np.isclose(np.linalg.det(rotation), 1.0) and np.array_equal(pose[3], [0.0, 0.0, 0.0, 1.0]))


@pytest.mark.parametrize("offset", [0.0, 1e7])
def test_a_symmetric_box_returns_its_twin_as_the_runner_up_in_the_clouds_own_frame(offset):
    """Both poses of a box put the source on the target (within a few point spacings), the two
    are clearly different turns, and both hold far from the origin (where the search runs in a
    shifted working frame)."""
    rng = np.random.default_rng(4)
    target = _box_surface(3000, rng) + offset
    truth = random_rigid_transform(rng, bounding_box_diagonal(target))
    source = apply(np.linalg.inv(truth), _box_surface(3000, rng) + offset)
    result = esmicp.register(source, target, rng=0)
    assert result.ambiguous and not result.trusted
    runner_up = result.runner_up
    assert runner_up is not None and _rigid(runner_up)
    assert rotation_error_deg(runner_up, result.transformation) > DISTINCT_DEG
    spacing = NearestNeighbors(target).spacing()
    for pose in (result.transformation, runner_up):
        distances = NearestNeighbors(target).query(apply(pose, source))[0]
        assert np.median(distances) < 3.0 * spacing
    # In the JSON record too, as a 4x4 list.
    assert np.allclose(result.to_dict()["runner_up"], runner_up)


def test_no_runner_up_without_a_global_search_or_a_clearly_different_pose():
    rng = np.random.default_rng(2)
    target = asymmetric_shape(1500, rng)
    truth = random_rigid_transform(rng, bounding_box_diagonal(target))
    source = apply(np.linalg.inv(truth), target)
    from_start = esmicp.register(source, target, init=truth)
    assert from_start.runner_up is None and from_start.to_dict()["runner_up"] is None
    searched = esmicp.register(source, target, rng=0)
    # When the search kept a runner-up, it is clearly different and scores no better.
    assert (searched.runner_up is None) == (searched.runner_up_ratio is None)
    if searched.runner_up is not None:
        assert rotation_error_deg(searched.runner_up, searched.transformation) > DISTINCT_DEG or \
            np.linalg.norm(searched.runner_up[:3, 3] - searched.transformation[:3, 3]) > 0


def test_the_cli_prints_the_runner_up_of_an_untrusted_pose(tmp_path, capsys):
    rng = np.random.default_rng(4)
    target = _box_surface(2000, rng)
    source = apply(np.linalg.inv(random_rigid_transform(rng, bounding_box_diagonal(target))), _box_surface(2000, rng))
    np.savetxt(tmp_path / "source.xyz", source)
    np.savetxt(tmp_path / "target.xyz", target)
    assert main(["register", str(tmp_path / "source.xyz"), str(tmp_path / "target.xyz")]) == 0
    out = capsys.readouterr().out
    assert "AMBIGUOUS" in out and "runner-up T_target_source" in out
    printed = out.split("runner-up T_target_source")[1].splitlines()[1:5]
    assert main(["register", str(tmp_path / "source.xyz"), str(tmp_path / "target.xyz"), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert np.allclose(np.array([[float(v) for v in line.split()] for line in printed]), record["runner_up"], atol=1e-8)
