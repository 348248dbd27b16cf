"""Trajectory errors (ATE as the TUM benchmark computes it, relative pose errors) on synthetic walks."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from esmicp.metrics import absolute_trajectory_error, relative_pose_errors


def _pose(rotvec, translation):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = translation
    return T


def _walk(count=30, seed=0):
    """A smooth random walk of T_world_frame poses (about 3 deg and 7 cm per step)."""
    rng = np.random.default_rng(seed)
    poses = [np.eye(4)]
    for _ in range(count - 1):
        step = _pose(rng.normal(scale=np.radians(3.0) / np.sqrt(3), size=3), rng.normal(scale=0.04, size=3))
        poses.append(poses[-1] @ step)
    return np.array(poses)


def test_ate_ignores_a_rigid_change_of_world_frame():
    truth = _walk()
    moved = _pose([0.3, -1.2, 2.0], [5.0, -3.0, 1.0]) @ truth  # same walk, another world frame
    rmse, alignment = absolute_trajectory_error(moved, truth)
    assert rmse < 1e-9
    np.testing.assert_allclose(alignment @ moved, truth, atol=1e-9)


def test_ate_is_the_rmse_of_position_noise_after_alignment():
    truth = _walk(count=400, seed=1)
    rng = np.random.default_rng(2)
    noisy = truth.copy()
    noise = rng.normal(scale=0.01, size=(len(truth), 3))
    noise -= noise.mean(axis=0)
    noisy[:, :3, 3] += noise
    rmse, _ = absolute_trajectory_error(_pose([0.1, 0.2, 0.3], [1, 2, 3]) @ noisy, truth)
    expected = np.sqrt(np.mean(np.sum(noise ** 2, axis=1)))
    # The alignment absorbs a little of the noise, never adds to it.
    assert 0.95 * expected <= rmse <= expected + 1e-12


def test_ate_sees_one_frame_placed_far_off():
    truth = _walk(count=20, seed=3)
    wrong = truth.copy()
    wrong[7, :3, 3] += [0.0, 0.0, 2.0]  # one frame 2 m off
    rmse, _ = absolute_trajectory_error(wrong, truth)
    # 2 m on one of 20 frames: sqrt(4 / 20) = 0.447 m before the alignment spreads some of it.
    assert 0.3 < rmse < 0.46


def test_relative_errors_per_pair_in_degrees_and_metres():
    truth = _walk(count=10, seed=4)
    estimate = truth.copy()
    # Frame 5 turned by 2 degrees about its own z axis and moved 3 cm along its own x axis.
    estimate[5] = truth[5] @ _pose([0, 0, np.radians(2.0)], [0.03, 0, 0])
    rotation, translation = relative_pose_errors(_pose([1, 0, 0], [0, 4, 0]) @ estimate, truth)
    assert rotation.shape == translation.shape == (9,)
    untouched = [k for k in range(9) if k not in (4, 5)]
    assert np.all(rotation[untouched] < 1e-6) and np.all(translation[untouched] < 1e-9)
    assert rotation[4] == pytest.approx(2.0, abs=1e-6)  # pair (4, 5): frame 5 as seen from 4
    assert translation[4] == pytest.approx(0.03, abs=1e-9)
    assert rotation[5] == pytest.approx(2.0, abs=1e-6)  # pair (5, 6)


def test_relative_errors_of_given_pairs():
    truth = _walk(count=6, seed=5)
    estimate = truth.copy()
    estimate[5] = truth[5] @ _pose([0, np.radians(10.0), 0], [0, 0, 0])
    rotation, _ = relative_pose_errors(estimate, truth, pairs=[(0, 5), (0, 4)])
    assert rotation[0] == pytest.approx(10.0, abs=1e-6)
    assert rotation[1] < 1e-6


@pytest.mark.parametrize("bad", [np.full((4, 4, 4), np.nan), np.zeros((4, 3, 4))])
def test_trajectory_errors_refuse_bad_input(bad):
    truth = _walk(count=4)
    with pytest.raises(ValueError, match="estimate"):
        absolute_trajectory_error(bad, truth)
    with pytest.raises(ValueError, match="estimate"):
        relative_pose_errors(bad, truth)
    with pytest.raises(ValueError, match="same frames"):
        absolute_trajectory_error(truth[:3], truth)
