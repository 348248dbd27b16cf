"""The global search's contract: every candidate generator returns rigid ``T_target_source``
poses (checked against a known transform), the verifier scores on one 0-1 scale, and a result's
``runner_up_ratio`` is never above 1."""

from __future__ import annotations

import numpy as np
import pytest

import esmicp
from esmicp_lab.bench.protocols import PROTOCOLS, make_trial, random_rigid_transform
from esmicp_lab.bench.real_pairs import partial_trial
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.procrustes import apply, bounding_box_diagonal
from esmicp.globalreg import search
from esmicp.globalreg.config import DEFAULT
from esmicp.globalreg.scan import scan_estimate
from esmicp.metrics import rotation_error_deg
from esmicp.shapes import asymmetric_shape


def _rigid(pose: np.ndarray) -> bool:
    rotation = pose[:3, :3]
    return (pose.shape == (4, 4) and np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-9)
            and np.isclose(np.linalg.det(rotation), 1.0) and np.array_equal(pose[3], [0.0, 0.0, 0.0, 1.0]))


def _pair(seed: int, count: int = 1500):
    """A copy of an asymmetric shape moved by a known ``T_target_source``: (source, target, truth)."""
    rng = np.random.default_rng(seed)
    target = asymmetric_shape(count, rng)
    truth = random_rigid_transform(rng, bounding_box_diagonal(target))
    source = apply(np.linalg.inv(truth), target)[rng.permutation(count)]
    return source, target, truth


def _workspace(source, target, seed=0):
    index = NearestNeighbors(target)
    spacing = index.spacing()
    return search._Workspace(source, target, np.random.default_rng(seed), index, index, spacing,
                             DEFAULT.verification.score_width_spacings * spacing)


def _near(pose, truth, source, diagonal, fraction=0.02) -> bool:
    return float(np.abs(apply(pose, source) - apply(truth, source)).max()) < fraction * diagonal


def test_every_generator_returns_rigid_poses_in_target_from_source():
    source, target, truth = _pair(1)
    diagonal = bounding_box_diagonal(target)
    work = _workspace(source, target)
    rotations = search._rotation_candidates(work)
    features = search._feature_candidates(work)
    scanned = scan_estimate(source, target, spacing=work.spacing).transformations
    twins = search._twins(target, truth)
    for poses in (rotations, features, scanned, twins):
        assert len(poses) and all(_rigid(pose) for pose in poses)
    # Each generator proposes the known pose (the rotation search's from a short ESM on a
    # subsample: verified, it lands on it).
    verified = search._verify(work, rotations, ["rotation-search"] * len(rotations))
    assert _near(verified.transformation, truth, source, diagonal)
    assert any(_near(pose, truth, source, diagonal) for pose in features)
    assert _near(scanned[0], truth, source, diagonal)


def test_a_twin_turned_twice_is_the_pose():
    source, target, truth = _pair(2)
    for axis, twin in enumerate(search._twins(target, truth)):
        assert np.allclose(search._twins(target, twin)[axis], truth, atol=1e-9)


def test_the_verifier_scores_on_one_scale():
    """Any pose, whatever proposed it, gets a soft fraction in [0, 1]: 1 at the truth on an exact
    copy, the same for the same pose given twice, and lower for a twin of an asymmetric shape."""
    source, target, truth = _pair(3)
    work = _workspace(source, target)
    twins = search._twins(target, truth)
    poses = np.stack([truth, truth, *twins])
    _, scores = search._batched_verification(work, work.index, source, poses, 6, work.width)
    assert np.all((scores >= 0.0) & (scores <= 1.0))
    assert scores[0] > 0.99 and scores[0] == scores[1]
    assert scores[2:].max() < scores[0]


def test_the_runner_up_ratio_is_the_lower_score_over_the_higher():
    poses = np.stack([np.eye(4)] * 2)

    def estimate(scores):
        return search.GlobalEstimate(poses, np.asarray(scores, float), ("scan", "scan"), candidates=2)

    assert estimate([0.8, 0.5]).runner_up_ratio == pytest.approx(0.625) and not estimate([0.8, 0.5]).ambiguous
    # The returned pose won on a tie-break the score does not see: ambiguous, ratio still <= 1.
    assert estimate([0.5, 0.8]).runner_up_ratio == pytest.approx(0.625) and estimate([0.5, 0.8]).ambiguous
    assert estimate([0.0, 0.0]).runner_up_ratio == 1.0 and estimate([0.0, 0.0]).ambiguous
    single = search.GlobalEstimate(poses[:1], np.array([0.7]), ("scan",), candidates=1)
    assert single.runner_up_ratio is None and not single.ambiguous


@pytest.mark.parametrize("protocol", [*PROTOCOLS, "half-70", "half-50"])
def test_runner_up_ratio_is_at_most_one_on_every_protocol(protocol):
    rng = np.random.default_rng(7)
    cloud = asymmetric_shape(3000, rng)
    for index in range(2):
        if protocol.startswith("half"):
            trial = partial_trial(cloud, int(protocol[-2:]) / 100, np.random.default_rng(index), 1000)
        else:
            trial = make_trial(protocol, cloud, seed=0, index=index, points=1000)
        result = esmicp.register(trial.source, trial.target, rng=index)
        ratio = result.runner_up_ratio
        assert ratio is None or 0.0 <= ratio <= 1.0
        assert 0.0 <= result.confidence <= 1.0


@pytest.mark.parametrize("scale", [1e-100, 1e-90, 1e-30, 1e30, 1e90, 1e98])
def test_the_confidence_is_scale_free_over_the_range_register_accepts(scale):
    """An exact fit is confident at any scale register accepts (a cloud scaled by 1e-90 used to
    report confidence 0); a partial overlap gets the confidence it gets at scale 1."""
    rng = np.random.default_rng(11)
    cloud = asymmetric_shape(1500, rng)
    exact = esmicp.register(cloud * scale, cloud * scale, init="identity")
    assert exact.confidence == 1.0 and exact.trusted
    trial = partial_trial(cloud, 0.7, np.random.default_rng(3), 700)
    at_one = esmicp.register(trial.source, trial.target, rng=0)
    scaled = esmicp.register(trial.source * scale, trial.target * scale, rng=0)
    assert scaled.confidence == pytest.approx(at_one.confidence, abs=0.02)
    assert rotation_error_deg(scaled.transformation, at_one.transformation) < 1.0


@pytest.mark.parametrize("count", [21, 40])
@pytest.mark.parametrize("init", ["identity", None])
def test_too_few_points_to_resolve_the_pose_are_never_trusted(count, init):
    """Two independent samples of a few dozen points of one shape, turned 30 degrees: at the
    keypoint voxel such clouds "coincide" under poses tens of degrees off, so whatever pose comes
    back, the result is not trusted (too few coinciding keypoints: ``TrustPolicy.min_coincident``)."""
    from esmicp.trust.policy import DEFAULT_POLICY

    assert count < DEFAULT_POLICY.min_coincident
    rng = np.random.default_rng(count)
    shape = asymmetric_shape(3000, rng)
    turn = np.eye(4)
    turn[:3, :3] = random_rigid_transform(rng, 1.0)[:3, :3]
    source = shape[rng.choice(3000, count, replace=False)]
    target = apply(turn, shape[rng.choice(3000, count, replace=False)])
    result = esmicp.register(source, target, init=init, rng=0)
    assert result.confidence == 0.0 and not result.trusted


def test_a_dense_exact_copy_is_still_trusted():
    """The evidence floor leaves well-sampled clouds alone: 300 points onto their own copy."""
    cloud = asymmetric_shape(300, np.random.default_rng(2))
    result = esmicp.register(cloud, cloud, init="identity")
    assert result.trusted
