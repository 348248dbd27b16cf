"""A mirrored input (one cloud a mirror image of the other) is never trusted: no rotation turns a
left hand into a right one, however well a nearly mirror-symmetric shape fits its best rotation;
a right pose is not doubted as mirrored (:func:`esmicp.trust.handedness.handedness`)."""

from __future__ import annotations

import numpy as np
import pytest

import esmicp
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.keypoints import Keypoints
from esmicp.globalreg.config import SearchConfig
from esmicp.metrics import random_rotation
from esmicp.trust.handedness import handedness

from conftest import require_shared


@pytest.fixture(scope="module")
def bunny():
    return esmicp.read_points(require_shared("bunny/bun_zipper_res3.ply"))


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_mirrored_bunny_is_not_trusted_and_a_turned_one_is(bunny, axis):
    rng = np.random.default_rng(axis)
    turn = random_rotation(rng)
    flip = np.ones(3)
    flip[axis] = -1.0
    mirrored = esmicp.register((bunny * flip) @ turn.T, bunny, rng=0, workers=1)
    assert not mirrored.trusted
    if mirrored.verdict.handedness is not None:  # tested: the pose was otherwise trusted
        assert mirrored.verdict.handedness.mirrored
        assert any(doubt.kind == "mirrored" for doubt in mirrored.verdict.doubts)
    turned = esmicp.register(bunny @ turn.T, bunny, rng=0, workers=1)
    assert turned.trusted and not any(doubt.kind == "mirrored" for doubt in turned.verdict.doubts)


def test_a_shape_that_is_its_own_mirror_image_is_not_doubted():
    """A box is its own mirror image: its mirror fits no better than the pose, no data tell its
    handedness, and a right pose is not doubted."""
    rng = np.random.default_rng(4)
    box = rng.uniform(-1.0, 1.0, (4000, 3))
    box[np.arange(len(box)), rng.integers(0, 3, len(box))] = rng.choice([-1.0, 1.0], len(box))
    box *= np.array([1.0, 0.6, 0.3])
    source, target = box[::2] * np.array([-1.0, 1.0, 1.0]), box[1::2]
    config = SearchConfig()
    keypoints = Keypoints.of(source, target, NearestNeighbors(target).spacing(), config.keypoints,
                             config.scan.keypoint.min_voxel_spacings)
    result = handedness(np.eye(4), keypoints, coincide_voxels=config.scan.keypoint.coincide_voxels)
    assert result is not None and not result.mirrored


def _keypoints(source, target):
    from esmicp.core.keypoints import Keypoints as Pair

    return Pair(np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64), 0.05)


def test_the_fit_recovers_a_pose_keeps_each_map_handed_and_ignores_the_thread_count():
    """The trimmed ICP of the test refines a map near the truth onto it, never turns a mirror image
    proper (its determinant keeps its sign), and gives the same maps on one thread and on two."""
    from esmicp.trust.handedness import _fit
    from esmicp.trust.policy import DEFAULT_POLICY
    from esmicp.metrics import rotation_error_deg

    rng = np.random.default_rng(7)
    target = rng.uniform(-1.0, 1.0, (1500, 3)) * np.array([1.0, 0.7, 0.4])
    turn = random_rotation(rng, 5.0)
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = turn, [0.05, -0.02, 0.03]
    source = (target - truth[:3, 3]) @ turn  # target = source @ R.T + t
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    maps = np.stack([np.eye(4), mirror, truth @ mirror])
    fitted = [_fit(maps, source[::3], _keypoints(source, target), workers, DEFAULT_POLICY, 30) for workers in (1, 2)]
    np.testing.assert_array_equal(fitted[0], fitted[1])
    assert rotation_error_deg(fitted[0][0], truth) < 0.5
    np.testing.assert_allclose(fitted[0][0][:3, 3], truth[:3, 3], atol=0.02)
    assert np.linalg.det(fitted[0][0][:3, :3]) > 0 and (np.linalg.det(fitted[0][1:, :3, :3]) < 0).all()


def test_the_bounded_distances_are_the_nearest_within_the_bound_and_infinite_beyond():
    from scipy.spatial import cKDTree

    from esmicp.core.compiled_tree import CompiledTree
    from esmicp.trust.handedness import _within

    rng = np.random.default_rng(8)
    target, points = rng.normal(size=(2000, 3)), rng.normal(size=(700, 3)) * 1.5
    maps = np.stack([np.eye(4), np.diag([1.0, -1.0, 1.0, 1.0])])
    maps[1, :3, 3] = [0.3, 0.0, -0.2]
    bound = 0.1
    for workers in (1, 2):
        distances = _within(CompiledTree(target), points, maps, bound, workers)
        for k, placed in enumerate((points, points * [1.0, -1.0, 1.0] + maps[1, :3, 3])):
            reference, _ = cKDTree(target).query(placed)
            near = reference <= bound
            assert near.any() and not near.all()
            np.testing.assert_allclose(distances[k][near], reference[near], rtol=0, atol=1e-12)
            assert np.isinf(distances[k][~near]).all()
