"""What ``register`` promises as data: ``result.stages`` (what each stage did), the verdict it
stores (one call of :func:`esmicp.trust.judge.judge`), and the invariances of a rigid
registration (swap source and target, shuffle the points, scale by 1,000, shift by 1e6), on small
synthetic clouds."""

from __future__ import annotations

import dataclasses
import json
import pickle

import numpy as np
import pytest

import esmicp
from esmicp import InvalidInputError
from esmicp.config import RefineConfig, RegistrationConfig
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.keypoints import Keypoints
from esmicp.core.procrustes import apply, bounding_box_diagonal, rigid_inverse, to_matrix
from esmicp.globalreg.config import DEFAULT
from esmicp.metrics import random_rotation, rotation_error_deg
from esmicp.result import RegistrationResult
from esmicp.shapes import asymmetric_shape
from esmicp.trust.judge import DOUBT_KINDS, Verdict, judge
from esmicp.trust.policy import TrustPolicy


@pytest.fixture(scope="module")
def noisy_pair():
    """An asymmetric object and a moved copy, each 800 points of a 900-point cloud (700 shared),
    with independent noise: the optimum is near the truth, not at it."""
    rng = np.random.default_rng(1)
    cloud = asymmetric_shape(900, rng=np.random.default_rng(0))
    truth = to_matrix(random_rotation(rng, 60.0), [0.3, -0.2, 0.1])
    source = cloud[:800] + rng.normal(scale=0.003, size=(800, 3))
    target = apply(truth, cloud[100:] + rng.normal(scale=0.003, size=(800, 3)))
    return source, target, truth


def _names(result):
    return [stage.name for stage in result.stages]


@pytest.mark.parametrize("init", ["global", "identity", "given"])
def test_the_stages_record_what_each_did(noisy_pair, init):
    source, target, truth = noisy_pair
    start = truth if init == "given" else init
    result = esmicp.register(source, target, init=start)
    assert _names(result) == ["prepare", "start", "refine", "evaluate", "judge"]
    prepare, begun, refine, evaluate, judged = result.stages
    assert all(stage.seconds >= 0.0 for stage in result.stages)
    assert sum(stage.seconds for stage in result.stages) <= result.runtime_s
    assert prepare.points == len(source) and prepare.decided["target_points"] == len(target)
    assert not prepare.decided["shifted"]
    # the start: the given pose, the identity, or the search's winner with its candidates
    assert begun.decided["init"] == result.init
    if init == "global":
        assert begun.decided["candidates"] == result.global_candidates > 0
        assert begun.decided["ambiguous"] == result.ambiguous
        assert rotation_error_deg(begun.pose, truth[:3, :3]) < 5.0
    else:
        np.testing.assert_array_equal(begun.pose, truth if init == "given" else np.eye(4))
        assert "candidates" not in begun.decided and result.global_candidates == 0
    # the refinement passes on the result's pose, on every source point (a small source)
    np.testing.assert_array_equal(refine.pose, result.transformation)
    assert refine.points == len(source) and refine.iterations == result.num_iterations > 0
    assert refine.decided["converged"] == result.converged and refine.decided["sigma"] == result.sigma
    assert sum(stage.iterations for stage in result.stages) == result.num_iterations
    assert dict(evaluate.decided) == {"fitness": result.fitness, "inlier_rmse": result.inlier_rmse,
                                      "inlier_distance": result.inlier_distance}
    assert judged.decided["trusted"] == result.trusted and judged.decided["confidence"] == result.confidence
    assert judged.decided["doubts"] == tuple(doubt.kind for doubt in result.verdict.doubts)
    np.testing.assert_array_equal(judged.pose, result.transformation)


def test_the_stages_are_frozen_data_that_json_and_pickle_hold(noisy_pair):
    source, target, _ = noisy_pair
    result = esmicp.register(source, target, init="identity")
    stage = result.stages[2]
    with pytest.raises(dataclasses.FrozenInstanceError):
        stage.name = "other"
    with pytest.raises(TypeError):
        stage.decided["converged"] = False
    text = json.dumps([stage.to_dict() for stage in result.stages])
    assert json.loads(text)[2]["pose"] == result.transformation.tolist()
    assert json.loads(json.dumps(result.to_dict()))["stages"] == json.loads(text)
    # a result crosses process boundaries (register_many) with its stages and its verdict
    copied = pickle.loads(pickle.dumps(result))
    assert [dict(stage.decided) for stage in copied.stages] == [dict(stage.decided) for stage in result.stages]
    assert copied.verdict.doubts == result.verdict.doubts and copied.trusted == result.trusted


def test_a_fixed_sigma_refines_once_and_a_low_confidence_start_tries_twice(noisy_pair):
    """From a given start, the second try is a stage of its own, with both confidences and the run
    kept; with a fixed sigma, or with ``refine.second_try`` off, there is none."""
    source, target, truth = noisy_pair
    never = RegistrationConfig(trust=TrustPolicy(trusted=1.01))  # every run is below the bar
    tried = esmicp.register(source, target, init=truth, config=never)
    assert _names(tried) == ["prepare", "start", "refine", "second try", "evaluate", "judge"]
    first, second = tried.stages[2], tried.stages[3]
    assert second.decided["kept"] in ("first", "second")
    assert tried.confidence == max(second.decided["first_confidence"], second.decided["confidence"])
    np.testing.assert_array_equal(second.pose, tried.transformation)
    if second.decided["kept"] == "first":
        np.testing.assert_array_equal(first.pose, tried.transformation)
    fixed = esmicp.register(source, target, init=truth, sigma=0.01, config=never)
    assert "second try" not in _names(fixed)
    # the second try switched off: the first run's pose, refined once
    once = esmicp.register(source, target, init=truth,
                           config=RegistrationConfig(trust=never.trust, refine=RefineConfig(second_try=False)))
    assert _names(once) == ["prepare", "start", "refine", "evaluate", "judge"]
    np.testing.assert_array_equal(once.transformation, first.pose)


def test_the_verdict_is_one_call_of_judge_and_the_result_returns_it(noisy_pair):
    """``judge`` on the result's pose, from the clouds alone, gives the verdict ``register`` stored;
    ``trusted`` and ``doubts`` return that verdict's findings."""
    source, target, _ = noisy_pair
    result = esmicp.register(source, target, init="identity")
    index = NearestNeighbors(target)
    keypoints = Keypoints.of(source, target, index.spacing(),
                             DEFAULT.keypoints, DEFAULT.scan.keypoint.min_voxel_spacings)
    verdict = judge(result.transformation, source=source, target_index=index, keypoints=keypoints, pairs=None,
                    sigma=result.sigma, converged=result.converged, num_iterations=result.num_iterations,
                    config=DEFAULT, policy=result.policy)
    assert verdict.confidence == result.confidence and verdict.trusted == result.trusted
    np.testing.assert_array_equal(verdict.uncertainty.covariance, result.covariance)
    assert verdict.doubts == result.verdict.doubts
    assert result.trusted == result.verdict.trusted and result.doubts() == [d.words for d in result.verdict.doubts]
    # the grouped records: the stored verdict is the trust report, its uncertainty the result's
    assert result.trust is result.verdict and result.search.candidates == result.global_candidates
    assert result.uncertainty.covariance is result.covariance
    assert result.uncertainty.pairs == result.verdict.uncertainty.pairs > 0
    # a field the verdict weighed, replaced: weighed again from the fields, by the same rules
    assert result.trusted
    lowered = dataclasses.replace(result, confidence=0.0)
    assert lowered.verdict is result.verdict and not lowered.trusted
    assert not lowered.trust.trusted and lowered.trust is not result.verdict
    assert lowered.doubts() == [f"confidence 0.00 is below {result.policy.trusted:g}"]
    assert dataclasses.replace(result, converged=False).doubts(ignore=("confidence",))[0].startswith("not converged")


def test_doubts_at_another_bar_and_without_some_kinds():
    result = RegistrationResult(transformation=np.eye(4), converged=False, num_iterations=3, fitness=1.0,
                                inlier_rmse=0.0, inlier_distance=0.01, runtime_s=0.0, method="esm", sigma=None,
                                message="", confidence=0.5, ambiguous=True)
    verdict = Verdict.of(converged=False, num_iterations=3, confidence=0.5, ambiguous=True)
    judged = dataclasses.replace(result, verdict=verdict)
    for one in (result, judged):  # built by hand (judged when asked) and given its verdict: the same
        assert one.doubts() == [doubt.words for doubt in verdict.doubts]
        assert len(one.doubts(0.4)) == 2 and len(one.doubts(0.6)) == 3
        assert one.doubts(ignore=("ambiguous", "not converged")) == ["confidence 0.50 is below 0.55"]
        assert not one.trusted
    with pytest.raises(InvalidInputError, match="ignore"):
        result.doubts(ignore=("sharpness",))
    assert [doubt.kind for doubt in verdict.doubts] == ["not converged", "confidence", "ambiguous"]
    assert [kind for kind in DOUBT_KINDS if kind in ("not converged", "confidence", "ambiguous")] == \
        [doubt.kind for doubt in verdict.doubts]  # listed in the order of DOUBT_KINDS



@pytest.mark.parametrize("init", ["global", "given"])
def test_an_unjudged_pose_is_the_judged_pose_and_never_trusted(noisy_pair, init):
    source, target, truth = noisy_pair
    start = truth if init == "given" else init
    judged = esmicp.register(source, target, init=start)
    bare = esmicp.register(source, target, init=start, judge=False)
    assert judged.trusted  # the pair is one a judgement trusts
    np.testing.assert_array_equal(bare.transformation, judged.transformation)
    assert (bare.converged, bare.confidence, bare.fitness) == (judged.converged, judged.confidence, judged.fitness)
    assert not bare.trusted and bare.covariance is None and bare.information is None
    assert [doubt.kind for doubt in bare.verdict.doubts] == ["not judged"]
    assert _names(bare) == ["prepare", "start", "refine", "evaluate"]
    with pytest.raises(InvalidInputError, match="judge"):
        esmicp.register(source, target, judge="no")

def test_swapping_source_and_target_gives_the_inverse_pose():
    rng = np.random.default_rng(4)
    cloud = asymmetric_shape(700, rng=np.random.default_rng(2))
    truth = to_matrix(random_rotation(rng, 50.0), [0.2, 0.1, -0.3])
    target = apply(truth, cloud)[rng.permutation(len(cloud))]
    forward = esmicp.register(cloud, target)
    backward = esmicp.register(target, cloud)
    assert forward.trusted and backward.trusted
    np.testing.assert_allclose(backward.transformation @ forward.transformation, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(backward.transformation, rigid_inverse(forward.transformation), atol=1e-9)


@pytest.mark.parametrize("init", ["global", "identity"])
def test_shuffling_the_points_gives_the_same_pose(noisy_pair, init):
    source, target, _ = noisy_pair
    plain = esmicp.register(source, target, init=init)
    order = np.random.default_rng(7).permutation(len(source))
    shuffled = esmicp.register(source[order], target[::-1], init=init)
    np.testing.assert_allclose(shuffled.transformation, plain.transformation, atol=1e-8)
    assert shuffled.trusted == plain.trusted


@pytest.mark.parametrize("init", ["global", "identity"])
def test_scaling_by_1000_scales_the_translation_and_keeps_the_rotation(noisy_pair, init):
    source, target, _ = noisy_pair
    plain = esmicp.register(source, target, init=init)
    scaled = esmicp.register(1000.0 * source, 1000.0 * target, init=init)
    np.testing.assert_allclose(scaled.transformation[:3, :3], plain.transformation[:3, :3], atol=1e-12)
    np.testing.assert_allclose(scaled.transformation[:3, 3], 1000.0 * plain.transformation[:3, 3], rtol=1e-12,
                               atol=1e-9)
    assert scaled.trusted == plain.trusted and scaled.num_iterations == plain.num_iterations
    assert scaled.inlier_distance == pytest.approx(1000.0 * plain.inlier_distance, rel=1e-12)


@pytest.mark.parametrize("init", ["global", "identity"])
def test_shifting_by_1e6_gives_the_same_pose_up_to_the_shift(noisy_pair, init):
    """Both clouds shifted by ``s``: the pose is ``Tr(s) T Tr(-s)``; it places the shifted source
    where the plain pose places the source, shifted, to the rounding of coordinates near 1e6."""
    source, target, _ = noisy_pair
    shift = np.array([1e6, -2e6, 3e6])
    plain = esmicp.register(source, target, init=init)
    shifted = esmicp.register(source + shift, target + shift, init=init)
    assert shifted.stages[0].decided["shifted"]
    np.testing.assert_allclose(shifted.transformation[:3, :3], plain.transformation[:3, :3], atol=1e-9)
    placed = apply(shifted.transformation, source + shift) - shift
    assert np.abs(placed - apply(plain.transformation, source)).max() < 1e-7 * bounding_box_diagonal(target)
    assert shifted.trusted == plain.trusted
