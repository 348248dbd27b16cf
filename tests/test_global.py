"""Global registration (the default): any rotation, any order, outliers, with a confidence.

Small, fast samples of the acceptance protocols; the full figures come from
``benchmarks/global_protocols.py``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import esmicp
from conftest import require_shared
from esmicp.globalreg.config import DEFAULT
from esmicp.globalreg.rotation_search import so3_grid
from esmicp.metrics import rotation_error_deg, strict_success, up_to_symmetry_success
from esmicp_lab.bench.protocols import make_trial

ASYMMETRIC = ("airplane_0126", "chair_0848", "guitar_0165", "person_0025", "piano_0226")


def _cloud(name: str) -> np.ndarray:
    folder = name.rsplit("_", 1)[0]
    return esmicp.read_points(require_shared(f"modelnet40/{folder}/{name}.txt"))


@pytest.mark.parametrize("protocol", ["shuffled", "resampled", "outliers-30", "outliers-60"])
@pytest.mark.parametrize("name", ASYMMETRIC[:3])
def test_default_register_recovers_a_random_pose(name, protocol):
    trial = make_trial(protocol, _cloud(name), seed=11, index=ASYMMETRIC.index(name), name=name)
    result = esmicp.register(trial.source, trial.target)
    assert result.init.startswith("global:")
    pivot = trial.source.mean(axis=0)
    error = rotation_error_deg(result.transformation, trial.T_target_source)
    assert strict_success(result.transformation, trial.T_target_source, trial.diagonal, pivot=pivot), (
        f"{name} {protocol}: rotation error {error:.2f} deg"
    )
    assert not result.ambiguous
    assert result.global_candidates > 0


def test_symmetric_object_is_reported_ambiguous_but_placed_right():
    trial = make_trial("resampled", _cloud("bottle_0276"), seed=3, index=0, name="bottle")
    result = esmicp.register(trial.source, trial.target)
    assert result.ambiguous, f"runner-up ratio {result.runner_up_ratio}"
    assert up_to_symmetry_success(trial.source, result.transformation, trial.T_target_source, trial.diagonal)


def test_asymmetric_object_is_confident():
    trial = make_trial("resampled", _cloud("airplane_0126"), seed=3, index=0, name="airplane")
    result = esmicp.register(trial.source, trial.target)
    assert not result.ambiguous
    assert result.runner_up_ratio is None or result.runner_up_ratio < 0.97


def test_bunny_from_any_rotation():
    cloud = esmicp.read_points(require_shared("bunny/bun_zipper.ply"))
    trial = make_trial("resampled", cloud, seed=5, index=1, name="bunny")
    result = esmicp.register(trial.source, trial.target)
    assert strict_success(result.transformation, trial.T_target_source, trial.diagonal, pivot=trial.source.mean(axis=0))


def test_seeded_results_are_reproducible_and_seeds_matter_little():
    trial = make_trial("outliers-30", _cloud("chair_0848"), seed=8, index=0, name="chair")
    first = esmicp.register(trial.source, trial.target, rng=4)
    again = esmicp.register(trial.source, trial.target, rng=np.random.default_rng(4))
    default = esmicp.register(trial.source, trial.target)
    assert np.array_equal(first.transformation, again.transformation)
    assert np.array_equal(default.transformation, esmicp.register(trial.source, trial.target).transformation)
    other = esmicp.register(trial.source, trial.target, rng=5)
    assert rotation_error_deg(first.transformation, other.transformation) < 2.0


@pytest.mark.parametrize("init", ["global", "auto", "rotation-search", "features"])
def test_every_global_strategy_is_accepted(init):
    trial = make_trial("shuffled", _cloud("airplane_0126"), seed=2, index=0, name="airplane")
    result = esmicp.register(trial.source, trial.target, init=init)
    assert result.init.startswith("global:")
    assert rotation_error_deg(result.transformation, trial.T_target_source) < 2.0


@pytest.mark.parametrize("init", ["identity", "none"])
def test_identity_means_local_only(init):
    trial = make_trial("shuffled", _cloud("airplane_0126"), seed=2, index=0, name="airplane")
    result = esmicp.register(trial.source, trial.target, init=init, max_iterations=5)
    assert result.init == "identity" and result.global_candidates == 0 and not result.ambiguous
    assert result.num_iterations <= 5


def test_a_given_init_is_refined_without_search():
    trial = make_trial("resampled", _cloud("chair_0848"), seed=2, index=0, name="chair")
    result = esmicp.register(trial.source, trial.target, init=trial.T_target_source)
    assert result.init == "given" and result.global_candidates == 0
    assert rotation_error_deg(result.transformation, trial.T_target_source) < 1.0


def test_so3_grid_covers_every_rotation():
    grid = so3_grid(96)
    np.testing.assert_allclose(np.einsum("kij,kil->kjl", grid, grid), np.broadcast_to(np.eye(3), grid.shape), atol=1e-12)
    assert np.allclose(np.linalg.det(grid), 1.0)
    from scipy.spatial.transform import Rotation

    probes = Rotation.random(2000, random_state=0).as_matrix()
    traces = np.einsum("pij,kij->pk", probes, grid)
    worst = np.degrees(np.arccos(np.clip((traces.max(axis=1) - 1) / 2, -1, 1))).max()
    assert worst < 53.0, f"some rotation lies {worst:.1f} deg from every grid rotation"


def test_a_lidar_pose_just_short_of_confident_is_settled(monkeypatch):
    """Newer College scans 40 frames apart, with rng 9: the rotation search ends its verification
    2.6 degrees and 1.2 m short of the truth, scoring 0.597 against ``confident_score`` 0.6, and
    the scan strategy used to run too (0.29 s against 0.08 s). Settled by a few more iterations
    (``SearchConfig.settle_from``), the pose is final and right. Fails if the settling is dropped."""
    from esmicp_lab.bench.real_pairs import load_pair, pair_errors, read_pairs
    from esmicp.globalreg import search

    require_shared("real_pairs/newer_college_01")
    pair = next(p for p in read_pairs(require_shared("real_pairs")) if p.name == "newer_college_01/t00_s40")
    source, target, truth = load_pair(pair, bin_columns=3)
    result = esmicp.register(source, target, rng=9)
    assert result.init == "global:rotation-search"
    rotation, translation = pair_errors(result.transformation, truth)
    assert rotation < 5.0 and translation < 0.6
    assert result.confidence >= 0.5
    never_settle = replace(DEFAULT, settle_from=2.0)
    assert esmicp.register(source, target, rng=9, config=never_settle).init == "global:scan"


def test_a_settled_pose_must_be_confident_on_the_overlap(monkeypatch):
    """A piano cut to 70% (``esmicp bench --datasets partial-overlap``'s trial 21): the rotation
    search proposes the other half flipped end to end, and settling lifts its score (0.595 ->
    0.621 on one host, 0.585 -> 0.598 on another), while its overlap confidence is
    0.10. With ``confident_score`` between the two scores, as on the first host, the settled
    flip must not be final (the scan strategy finds the pose); without the overlap check it is.
    The bar is set from the scores measured here: a bar fixed at 0.6 is crossed on one host and
    not on another. Fails if a settled pose is final without the overlap check."""
    from esmicp.globalreg import search

    register, right = _partial_overlap_trial("piano_0226", keep_index=0, index=21)
    seen = {}
    original = search._settle

    def probe(work, estimate):
        """Measures the verified and the settled score, and settles nothing."""
        anything = replace(work, config=replace(work.config, confident_score=0.0, confident=0.0))
        seen.update(verified=estimate.score, settled=original(anything, estimate).score)
        return None

    monkeypatch.setattr(search, "_settle", probe)
    register()
    monkeypatch.setattr(search, "_settle", original)
    assert seen["settled"] > seen["verified"]
    bar = 0.5 * (seen["verified"] + seen["settled"])
    assert seen["verified"] >= DEFAULT.settle_from * bar
    result = register(config=replace(DEFAULT, confident_score=bar))
    assert right(result) and result.init != "global:rotation-search"
    result = register(config=replace(DEFAULT, confident_score=bar, confident=0.0))  # no overlap check
    assert result.init == "global:rotation-search" and not right(result)


def _partial_overlap_trial(name: str, *, keep_index: int, index: int, bench_seed: int = 0):
    """Trial ``index`` of ``esmicp bench --datasets partial-overlap --seed bench_seed`` at keep
    fraction ``(0.7, 0.5)[keep_index]`` on ModelNet40 object ``name``: a callable running the
    default ``register`` on it with the bench's seed, and one judging a result up to symmetry (on
    the kept points, stricter than the bench's whole half)."""
    from esmicp_lab.bench.real_pairs import partial_trial
    from esmicp_lab.bench.scans import _seed_of

    rng = np.random.default_rng(np.random.SeedSequence(bench_seed, spawn_key=(1, keep_index, index)))
    trial = partial_trial(_cloud(name), (0.7, 0.5)[keep_index], rng, 2000)
    seed = _seed_of(bench_seed, 1, keep_index, index)
    diagonal = float(np.linalg.norm(trial.target.max(axis=0) - trial.target.min(axis=0)))

    def register(**options):
        return esmicp.register(trial.source, trial.target, rng=seed, **options)

    def right(result):
        return up_to_symmetry_success(trial.source, result.transformation, trial.T_target_source, diagonal)

    return register, right


def test_the_rotation_searchs_pose_is_final_at_once_only_when_confident_on_the_overlap(monkeypatch):
    """A stool cut to 50% (``esmicp bench --datasets partial-overlap``'s trial 10 of
    ``partial-50``): the rotation search's pose, 89 degrees off, lays enough of the source on the
    target to be final at once, but it is not confident on the overlap; the scan strategy's first
    search then finds the truth. Fails if that pose is final on the rotation search's score alone."""
    from dataclasses import replace

    from esmicp.globalreg import search

    register, right = _partial_overlap_trial("stool_0072", keep_index=1, index=10)
    result = register()
    assert right(result) and result.init == "global:scan"
    monkeypatch.setattr(search, "_on_the_overlap", lambda work, estimate: replace(estimate, confidence=1.0))
    wrong = register()
    assert not right(wrong) and wrong.init == "global:rotation-search"


def test_a_pose_covering_the_whole_target_is_final_without_the_scan_search(monkeypatch):
    """A chair under 30% outliers (``benchmarks/global_protocols.py``'s trial 2 of outliers-30):
    the rotation search's pose is right and covers the whole target, so it is final without the
    scan strategy even when its confidence on the overlap is held below the bar (here by
    replacing the measured confidence with 0: the rule under test is the coverage). Fails if the
    coverage is not checked: the scan search then runs."""
    from dataclasses import replace

    from esmicp.globalreg import search

    trial = make_trial("outliers-30", _cloud("chair_0848"), seed=0, index=2, name="chair_0848")
    searched, decided = [], []
    scan, on_the_overlap = search._scan, search._on_the_overlap
    monkeypatch.setattr(search, "_scan", lambda *args, **kwargs: searched.append(1) or scan(*args, **kwargs))
    monkeypatch.setattr(search, "_on_the_overlap", lambda work, estimate: decided.append(
        replace(on_the_overlap(work, estimate), confidence=0.0)) or decided[-1])
    result = esmicp.register(trial.source, trial.target, rng=3141116543)
    assert strict_success(result.transformation, trial.T_target_source, trial.diagonal, pivot=trial.source.mean(axis=0))
    assert result.init == "global:rotation-search" and not searched
    assert decided and decided[0].confidence < DEFAULT.confident  # final on the coverage, not on the confidence
    monkeypatch.setattr(search, "_covers_the_target", lambda work, transformation: False)
    esmicp.register(trial.source, trial.target, rng=3141116543)
    assert searched


def test_the_scan_strategys_unconfident_poses_join_the_verification(monkeypatch):
    """A stool cut to 50% (``esmicp bench --datasets partial-overlap``'s trial 22 of
    ``partial-50``): the scan strategy's best pose is right but not confident on the overlap (a
    few hundred keypoints), so it does not win at once; the rotation search and the feature
    strategy end 158 degrees off. Joining the verification (``SearchConfig.scan_candidates``), the scan
    pose wins on the clouds' points. Left out of it, it still wins at the very end, over the
    feature strategy's unconfident pose (``SearchConfig.sharper_than_chosen``). Fails if both are off."""
    from esmicp.globalreg import search

    register, right = _partial_overlap_trial("stool_0072", keep_index=1, index=22)
    result = register()
    assert right(result) and result.init == "global:scan"
    assert result.confidence < DEFAULT.confident  # it did not win on its own confidence
    assert right(register(config=replace(DEFAULT, scan_candidates=0)))
    assert not right(register(config=replace(DEFAULT, scan_candidates=0, sharper_than_chosen=2.0)))


def test_an_unconfident_choice_gives_way_to_a_sharper_scan_pose(monkeypatch):
    """A guitar cut to 50% (``esmicp bench --datasets partial-overlap --seed 1``'s trial 17 of
    ``partial-50``): the rotation search's pose, 100 degrees off, lays as much of the source on the
    target as any, but the overlap does not coincide (confidence 0); one of the scan strategy's
    poses is right and confident. Fails if the chosen pose is kept whatever its confidence."""
    from esmicp.globalreg import search

    register, right = _partial_overlap_trial("guitar_0165", keep_index=1, index=17, bench_seed=1)
    result = register()
    assert right(result) and result.init == "global:scan" and result.confidence >= DEFAULT.confident
    kept = register(config=replace(DEFAULT, sharper_than_chosen=2.0))  # never sharper enough
    assert not right(kept) and kept.init == "global:rotation-search" and kept.confidence < DEFAULT.confident


def test_sharper_on_the_overlap_replaces_only_an_unconfident_choice(monkeypatch):
    """``_sharper_on_the_overlap`` on an asymmetric object's keypoints: a pose turned 180 degrees
    (not confident) gives way to the scan strategy's right pose, ranked second by overlap, and
    stays as its runner-up; a confident choice, a scan search with no sharper pose or one that
    found nothing (score 0), or a margin no pose reaches, change nothing."""
    from scipy.spatial.transform import Rotation

    from esmicp.core.correspondence import NearestNeighbors
    from esmicp.globalreg import search
    from esmicp.core.keypoints import Keypoints

    cloud = _cloud("chair_0848")
    keypoints = Keypoints.of(cloud, cloud, NearestNeighbors(cloud).spacing(),
                             DEFAULT.keypoints, DEFAULT.scan.keypoint.min_voxel_spacings)
    right, wrong = np.eye(4), np.eye(4)
    wrong[:3, :3] = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    wrong[:3, 3] = cloud.mean(axis=0) - wrong[:3, :3] @ cloud.mean(axis=0)

    def estimate(poses, scores):
        return search.GlobalEstimate(np.stack(poses), np.asarray(scores, float), ("rotation-search",) * len(poses),
                                     candidates=len(poses), keypoints=keypoints)

    def choice(chosen, scanned):
        return search._sharper_on_the_overlap(chosen, scanned).transformations

    chosen, scanned = estimate([wrong], [0.7]), estimate([wrong, right], [0.6, 0.5])
    better = search._sharper_on_the_overlap(chosen, scanned)
    assert better.strategies == ("scan", "rotation-search") and better.confidence >= DEFAULT.confident
    assert np.array_equal(better.transformations, np.stack([right, wrong]))
    kept = search._sharper_on_the_overlap(chosen, estimate([wrong], [0.6]))
    assert np.array_equal(kept.transformations, np.stack([wrong])) and kept.confidence < DEFAULT.confident
    assert np.array_equal(choice(chosen, estimate([right], [0.0])), np.stack([wrong]))
    assert np.array_equal(choice(estimate([right], [0.7]), scanned), np.stack([right]))
    never = replace(DEFAULT, sharper_than_chosen=2.0)
    assert np.array_equal(search._sharper_on_the_overlap(chosen, scanned, config=never).transformations,
                          np.stack([wrong]))


def test_only_an_unconfident_scan_search_sends_its_poses_to_the_verification():
    """A confident scan pose keeps its own way to win (``_scan_leads``) and sends nothing; an
    unconfident one sends its best ``SearchConfig.scan_candidates`` poses, never the identity that stands for
    "found nothing" (score 0)."""
    from esmicp.globalreg.search import GlobalEstimate, _unconfident_scan_poses

    poses = np.stack([np.eye(4)] * 5)
    poses[:, 0, 3] = np.arange(5)  # tell them apart

    def scanned(scores, confidence):
        return GlobalEstimate(poses[: len(scores)], np.asarray(scores, float), ("scan",) * len(scores),
                              candidates=len(scores), confidence=confidence)

    sent = _unconfident_scan_poses(scanned([0.4, 0.3, 0.2, 0.1, 0.05], 0.3))
    assert len(sent) == DEFAULT.scan_candidates == 3
    assert [pose[0, 3] for pose in sent] == [0.0, 1.0, 2.0]  # best first
    assert _unconfident_scan_poses(scanned([0.4, 0.3, 0.2], 0.5)) == []
    assert _unconfident_scan_poses(scanned([0.0], 0.0)) == []
