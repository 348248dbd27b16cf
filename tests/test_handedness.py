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
