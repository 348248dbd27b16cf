"""``register(..., range_images=True)``: the pose of a pair of range images is checked against the
space each sensor saw empty, and a pose that contradicts it is not trusted (``result.free_space``).
At the default (``range_images=None``) the premise is established from each cloud's own points."""

from __future__ import annotations

import json

import numpy as np
import pytest

import esmicp
from esmicp import InvalidInputError
from esmicp_lab.bench.real_pairs import pair_errors
from esmicp_lab.bench.sequences import read_frame, read_poses
from esmicp.cli import main
from esmicp.trust import free_space
from esmicp.result import RegistrationResult
from esmicp.trust.policy import DEFAULT_POLICY, TrustPolicy

from conftest import require_shared
from test_merge_visibility import _turned, walk  # noqa: F401  (walk: ray-cast depth frames of a room)


def _result(**fields) -> RegistrationResult:
    return RegistrationResult(transformation=np.eye(4), converged=True, num_iterations=1, fitness=1.0,
                              inlier_rmse=0.0, inlier_distance=0.01, runtime_s=0.0, method="esm", sigma=None,
                              message="", **fields)


def test_trusted_requires_the_free_space_test_when_it_was_measured():
    assert _result(confidence=0.9).trusted  # not measured: confidence alone
    assert _result(confidence=0.9, free_space=0.0).trusted
    assert _result(confidence=0.9, free_space=DEFAULT_POLICY.max_free_space_pair).trusted
    assert not _result(confidence=0.9, free_space=DEFAULT_POLICY.max_free_space_pair + 0.01).trusted
    assert not _result(confidence=0.1, free_space=0.0).trusted
    # the bars are the result's policy's
    assert _result(confidence=0.9, free_space=0.1, policy=TrustPolicy(max_free_space_pair=0.2)).trusted
    assert not _result(confidence=0.9, policy=TrustPolicy(trusted=0.95)).trusted
    assert _result(confidence=0.9, free_space=0.3).to_dict()["free_space"] == 0.3


def _turned_90(walk) -> np.ndarray:
    """Scan 1's pose turned 90 degrees about the room's vertical axis: its walls now stand where
    scan 0 saw an empty room."""
    clouds, poses, room_frame = walk
    return _turned(poses, {1}, room_frame)[1]


def test_a_right_pose_passes_and_a_turned_one_fails(walk):  # noqa: F811
    """Two ray-cast depth frames of a room, refined from the truth and from the truth turned 90 degrees
    (one step: the pose stays wrong). The test is measured on the clouds' own frames, at the
    result's pose; the pose itself is the one ``register`` gives without it."""
    clouds, poses, _ = walk
    right = esmicp.register(clouds[1], clouds[0], init=poses[1], range_images=True, workers=1)
    assert right.free_space is not None and right.free_space <= DEFAULT_POLICY.max_free_space_pair
    assert "free-space test passed" in right.message
    assert right.free_space == free_space.free_space_fraction(
        clouds[0], clouds[1], right.transformation, DEFAULT_POLICY.free_space_tolerance_inliers * right.inlier_distance)
    plain = esmicp.register(clouds[1], clouds[0], init=poses[1], range_images=False, workers=1)
    np.testing.assert_array_equal(plain.transformation, right.transformation)
    assert plain.free_space is None and "free-space" not in plain.message

    wrong = esmicp.register(clouds[1], clouds[0], init=_turned_90(walk), max_iterations=1,
                            range_images=True, workers=1)
    assert pair_errors(wrong.transformation, poses[1])[1] > 0.5
    assert wrong.free_space > DEFAULT_POLICY.max_free_space_pair and not wrong.trusted
    assert "free-space test failed" in wrong.message


@pytest.mark.parametrize("bad", ["yes", 1, "auto"])
def test_range_images_must_be_a_bool(walk, bad):  # noqa: F811
    clouds, _, _ = walk
    with pytest.raises(InvalidInputError, match="range_images"):
        esmicp.register(clouds[1], clouds[0], range_images=bad)


# Kitchen frames 70-140 frames apart, the source turned about its camera (as in
# benchmarks/global_regression.py --sets kitchen-far): some share no surface, and the global search
# can match a repeated structure in the wrong place with a high confidence. The contract: with
# range_images=True, a pose 0.8 m or more off is never trusted; a right pose passes the test.
FAR_PAIRS = [("frame-000680", "frame-000820"), ("frame-000700", "frame-000810"), ("frame-000000", "frame-000070")]


@pytest.mark.parametrize("target_name, source_name", FAR_PAIRS)
def test_far_kitchen_pairs_wrong_poses_are_never_trusted(target_name, source_name):
    folder = require_shared("sequences/redkitchen_seq01_every10")
    poses = read_poses(folder)
    source, target = read_frame(folder, source_name), read_frame(folder, target_name)
    truth = np.linalg.inv(poses[target_name]) @ poses[source_name]
    result = esmicp.register(source, target, range_images=True, rng=0, workers=1)
    rotation, translation = pair_errors(result.transformation, truth)
    if rotation < 5.0 and translation < 0.1:
        assert result.free_space is not None and result.free_space <= DEFAULT_POLICY.max_free_space_pair
    elif translation >= 0.8:
        assert not result.trusted, (rotation, translation, result.confidence, result.free_space)


def test_cli_range_images(walk, tmp_path, capsys):  # noqa: F811
    clouds, poses, _ = walk
    source, target, init, turned = tmp_path / "b.npy", tmp_path / "a.npy", tmp_path / "T.txt", tmp_path / "turned.txt"
    np.save(source, clouds[1])
    np.save(target, clouds[0])
    np.savetxt(init, poses[1])
    np.savetxt(turned, _turned_90(walk))
    common = ["register", str(source), str(target), "--init"]
    assert main(common + [str(init), "--range-images", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["free_space"] <= DEFAULT_POLICY.max_free_space_pair
    assert main(common + [str(init), "--no-range-images", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["free_space"] is None
    # a pose the sensors contradict: the summary says so, and --min-confidence refuses it even at 0
    code = main(common + [str(turned), "--max-iterations", "1", "--range-images", "--min-confidence", "0"])
    out, err = capsys.readouterr()
    assert code == 3 and "free-space test" in err and "free-space test failed" in out


def test_by_default_the_premise_comes_from_the_clouds_own_points(in_scanner_frames, stored):
    """The bunny's scans in their scanner's frame are range images: at the default the free-space
    test runs, as declared. As stored (a frame near the object, as a turntable's), they are not:
    the test does not run, unless declared. Moved 0.1-0.3 m and 5-20 degrees off the scanner
    (a few percent of the 1.3 m range: still nearly the same range image), the right pose stays
    trusted whether the test runs or not."""
    from esmicp_lab.bench.off_sensor import moved_off

    clouds, truth = in_scanner_frames
    pose = np.linalg.inv(truth[0]) @ truth[1]
    found = esmicp.register(clouds[1], clouds[0], init=pose, workers=1)
    declared = esmicp.register(clouds[1], clouds[0], init=pose, range_images=True, workers=1)
    assert found.trusted and found.free_space is not None and found.free_space == declared.free_space

    clouds, truth = stored
    pose = np.linalg.inv(truth[0]) @ truth[1]
    found = esmicp.register(clouds[1], clouds[0], init=pose, workers=1)
    assert found.trusted and found.free_space is None
    assert esmicp.register(clouds[1], clouds[0], init=pose, range_images=True, workers=1).free_space is not None

    clouds, truth = moved_off(*in_scanner_frames, rng=5)
    assert esmicp.register(clouds[1], clouds[0], init=np.linalg.inv(truth[0]) @ truth[1], workers=1).trusted


@pytest.fixture(scope="module")
def in_scanner_frames():
    from esmicp_lab.bench.off_sensor import bunny_in_scanner_frames

    _, clouds, truth = bunny_in_scanner_frames(require_shared("bunny_scans"), ("bun000", "bun045"), max_points=6000,
                                               rng=3)
    return clouds, truth


@pytest.fixture(scope="module")
def stored():
    """The bunny's raw scans as stored: a frame near the object, not the scanner's."""
    from esmicp.io.stanford_conf import load_scans

    scans = load_scans(require_shared("bunny_scans"), max_points=6000, rng=3)
    return [scans[n][0] for n in ("bun000", "bun045")], [scans[n][1] for n in ("bun000", "bun045")]


def test_bunny_scans_are_range_images_in_their_scanner_frames_and_not_as_stored(in_scanner_frames, stored):
    """The pair verdict's premise (:meth:`SensorClouds.premise`) on real scans: the bunny's scans in
    their scanner's frame are range images; as stored, they are not; declared, they are."""
    from esmicp.trust.judge import SensorClouds

    clouds, _ = in_scanner_frames
    assert SensorClouds(clouds[1], clouds[0], 0.001, None).premise(DEFAULT_POLICY) is None
    clouds, _ = stored
    assert "not a range image" in SensorClouds(clouds[1], clouds[0], 0.001, None).premise(DEFAULT_POLICY)
    assert SensorClouds(clouds[1], clouds[0], 0.001, True).premise(DEFAULT_POLICY) is None  # declared wins
