"""``esm-plane``: point-to-plane ESM refinement (exact recovery, the real 3DMatch pair whose
overlap ``esm`` pulls apart, scale invariance, the method listing and the command line, bad input)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

import esmicp
from esmicp.cli import main
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.procrustes import apply, rigid_inverse, to_matrix
from esmicp.errors import InvalidInputError
from esmicp.methods import METHODS, ConvergenceCriteria, PlaneEstimator, make_estimator
from esmicp.methods.local import refine
from esmicp.methods.plane import plane_step
from esmicp.metrics import random_rotation, rotation_error_deg
from conftest import require_shared


def room(points_per_face: int, rng: np.random.Generator) -> np.ndarray:
    """Points on a floor, two walls and a tilted box: a planar scene with every direction fixed."""
    u, v = rng.uniform(0.0, 1.0, size=(2, points_per_face))
    zero = np.zeros(points_per_face)
    faces = [np.column_stack([4 * u, 3 * v, zero]), np.column_stack([4 * u, zero, 2.5 * v]),
             np.column_stack([zero, 3 * v, 2.5 * u])]
    box = rng.uniform(-0.5, 0.5, size=(3 * points_per_face, 3))
    side = rng.integers(0, 3, len(box))
    box[np.arange(len(box)), side] = np.sign(box[np.arange(len(box)), side]) * 0.5
    tilt = to_matrix(random_rotation(np.random.default_rng(3), 40.0), [2.0, 1.5, 0.8])
    return np.vstack([*faces, apply(tilt, box)])


@pytest.fixture
def scene():
    rng = np.random.default_rng(11)
    target = room(1500, rng)
    offset = to_matrix(random_rotation(rng, 4.0), [0.08, -0.05, 0.06])
    source = apply(rigid_inverse(offset), target)[rng.permutation(len(target))]
    return source, target


def test_exact_recovery_of_a_planar_scene_from_a_small_offset(scene):
    source, target = scene
    result = esmicp.register(source, target, method="esm-plane", init=np.eye(4))
    assert result.converged and result.method == "esm-plane"
    # The copy lands on itself: every source point on its own target point.
    gap, _ = cKDTree(target).query(apply(result.transformation, source))
    assert gap.max() < 1e-7


def test_a_pair_scaled_by_1000_gives_the_same_pose(scene):
    source, target = scene
    metres = esmicp.register(source, target, method="esm-plane", init=np.eye(4), max_iterations=5)
    millimetres = esmicp.register(1000 * source, 1000 * target, method="esm-plane", init=np.eye(4), max_iterations=5)
    assert rotation_error_deg(metres.transformation, millimetres.transformation) < 1e-7
    assert np.allclose(1000 * metres.transformation[:3, 3], millimetres.transformation[:3, 3], atol=1e-6)
    assert millimetres.sigma == pytest.approx(1000 * metres.sigma, rel=1e-9)


def test_a_plane_does_not_slide_along_itself():
    """A flat target constrains only its normal, the tilt about it and no in-plane motion: the
    step moves the source onto the plane and nowhere along it."""
    rng = np.random.default_rng(5)
    target = np.column_stack([rng.uniform(0, 2, 2000), rng.uniform(0, 2, 2000), np.zeros(2000)])
    source = target[:1000] + [0.3, -0.2, 0.05]
    normals = np.tile([0.0, 0.0, 1.0], (1000, 1))
    rotation, translation = plane_step(source, target[:1000], normals, np.ones(1000))
    assert np.allclose(rotation, np.eye(3), atol=1e-12)
    assert np.allclose(translation, [0.0, 0.0, -0.05], atol=1e-12)


def test_the_overlap_sets_sigma_not_the_pairs_off_it():
    """Pairs off the overlap (far, many) must not widen sigma: it follows the close ones."""
    estimator = PlaneEstimator(floor=0.01, diameter=5.0)
    rng = np.random.default_rng(2)
    distances = np.concatenate([np.abs(rng.normal(0.0, 0.02, 400)), rng.uniform(0.5, 3.0, 600)])
    sigma = estimator._sigma(distances)
    assert 0.01 <= sigma < 0.1
    assert PlaneEstimator(floor=0.01, diameter=5.0, sigma=0.7)._sigma(distances) == 0.7


def test_real_3dmatch_pair_keeps_its_overlap_and_recovers_the_truth():
    """3DMatch redkitchen t00_s06 (about 40% overlap): ``esm`` started at the ground truth drifted
    0.77 m (its sigma measured the whole source); ``esm-plane`` stays, and comes back from 5 deg and
    0.1 m away."""
    folder = require_shared("real_pairs")
    source = esmicp.read_points(folder / "3dmatch_redkitchen" / "geotransformer_src.npy")
    target = esmicp.read_points(folder / "3dmatch_redkitchen" / "geotransformer_ref.npy")
    truth = esmicp.read_transform(folder / "3dmatch_redkitchen" / "t00_s06" / "T_target_source.txt")
    at_truth = esmicp.register(source, target, method="esm-plane", init=truth, max_iterations=50)
    assert np.linalg.norm(at_truth.transformation[:3, 3] - truth[:3, 3]) < 0.2
    centre = apply(truth, source).mean(axis=0)
    turn = random_rotation(np.random.default_rng(0), 5.0)
    offset = to_matrix(turn, centre - turn @ centre + [0.06, -0.06, 0.05])
    result = esmicp.register(source, target, method="esm-plane", init=offset @ truth, max_iterations=50)
    assert rotation_error_deg(result.transformation, truth) < 3.0
    assert np.linalg.norm(result.transformation[:3, 3] - truth[:3, 3]) < 0.2


def test_esm_plane_is_listed_and_made():
    assert "esm-plane" in METHODS
    assert isinstance(make_estimator("esm-plane", None, 0.01, 1.0), PlaneEstimator)
    assert make_estimator("esm-plane", None, 0.01, 1.0).floor == pytest.approx(0.02)


def test_command_line_method_choice(scene, tmp_path, capsys):
    source, target = scene
    np.savetxt(tmp_path / "source.xyz", source)
    np.savetxt(tmp_path / "target.xyz", target)
    code = main(["register", str(tmp_path / "source.xyz"), str(tmp_path / "target.xyz"), "--method", "esm-plane",
                 "--init", "identity", "--json"])
    out = capsys.readouterr().out
    assert code == 0
    report = json.loads(out)
    assert report["method"] == "esm-plane"
    with pytest.raises(SystemExit) as exit_:
        main(["register", "--help"])
    assert exit_.value.code == 0
    assert "esm-plane" in capsys.readouterr().out


@pytest.mark.parametrize("kwargs, words", [
    (dict(method="esm_plane"), ("method", "esm-plane")),
    (dict(method="esm-plane", sigma=-1.0), ("sigma",)),
    (dict(method="esm-plane", max_iterations=0), ("max_iterations",)),
])
def test_bad_input_is_refused_by_name(scene, kwargs, words):
    source, target = scene
    with pytest.raises(InvalidInputError) as error:
        esmicp.register(source, target, init=np.eye(4), **kwargs)
    assert all(word in str(error.value) for word in words)


def test_bad_clouds_are_refused_by_name():
    with pytest.raises(InvalidInputError, match="source"):
        esmicp.register(np.zeros((5, 2)), np.zeros((5, 3)), method="esm-plane", init=np.eye(4))
    with pytest.raises(InvalidInputError, match="target"):
        esmicp.register(np.random.default_rng(0).normal(size=(50, 3)), np.full((50, 3), np.nan),
                        method="esm-plane", init=np.eye(4))


def test_a_large_source_ends_on_the_whole_source(scene):
    """The subset phase (a strided subset of a large source) ends once the steps are small, so the
    pose comes from every point."""
    source, target = scene
    estimator = PlaneEstimator(floor=0.02, diameter=6.0)
    assert estimator.coarse
    outcome = refine(source, NearestNeighbors(target), estimator, init=np.eye(4), criteria=ConvergenceCriteria(),
                     scale=6.0, coarse_points=len(source) // 4)
    assert not estimator.coarse and outcome.converged
    gap, _ = cKDTree(target).query(apply(outcome.transformation, source))
    assert gap.max() < 1e-7


def test_normals_come_from_the_offered_tree_only_when_it_holds_the_target(scene, monkeypatch):
    """``use_target_tree``: the target index's own tree serves the normals (no second tree) when
    its points are the target's; a tree over other points is refused and the normals stay right."""
    from esmicp.core.compiled_tree import CompiledTree
    from esmicp.core.features import estimate_normals
    from esmicp.methods import plane

    _, target = scene
    indices = np.arange(0, len(target), 7)
    expected = estimate_normals(target, plane.PlaneConfig().normal_neighbours, at=target[indices])
    built = []
    monkeypatch.setattr(plane, "CompiledTree", lambda points: built.append(len(points)) or CompiledTree(points))
    for offered, builds in [(NearestNeighbors(target).exact_tree(), 0), (CompiledTree(target.copy()), 0),
                            (CompiledTree(target[::-1].copy()), 1)]:
        built.clear()
        estimator = PlaneEstimator(floor=0.02, diameter=6.0)
        estimator.use_target_tree(offered, workers=2)
        normals = estimator._normals_at(target, indices)
        assert len(built) == builds
        assert np.allclose(np.abs(np.einsum("ij,ij->i", normals, expected)), 1.0, atol=1e-9)


def test_normals_asked_again_are_the_ones_estimated_first(scene):
    """The normals of target points asked for over several steps (each point estimated once, then
    kept) are bit for bit those of one estimate at all of them, in the order asked."""
    from esmicp.core.features import estimate_normals
    from esmicp.methods import plane

    _, target = scene
    rng = np.random.default_rng(3)
    estimator = PlaneEstimator(floor=0.02, diameter=6.0)
    for _ in range(3):
        indices = rng.integers(0, len(target), 300)
        expected = estimate_normals(target, plane.PlaneConfig().normal_neighbours, at=target[indices])
        assert np.array_equal(estimator._normals_at(target, indices), expected)


@pytest.mark.parametrize("plane_moves_by_deg, kept", [(0.5, True), (40.0, False)])
def test_the_plane_stage_is_undone_when_it_loses_the_overlap(monkeypatch, plane_moves_by_deg, kept):
    """After a global search on a large source, ``register`` runs ``esm-plane`` first; a stage that
    lowers the overlap confidence by more than ``RefineConfig.plane_confidence_drop`` (as on a 15%-overlap
    scan pair, where its sigma grew with the pairs off the overlap) is undone, and its stage record
    says so. Here the stage is replaced by one that turns the pose by a set angle."""
    import esmicp.api as api
    from esmicp.working_frame import WorkingFrame
    from esmicp.core.keypoints import Keypoints
    from esmicp.globalreg.config import DEFAULT
    from esmicp.trust.confidence import overlap_confidence
    from esmicp.methods.local import RefinementOutcome

    rng = np.random.default_rng(5)
    target = room(1500, rng)
    truth = to_matrix(random_rotation(rng, 4.0), [0.08, -0.05, 0.06])
    source = apply(rigid_inverse(truth), target)
    keypoints = Keypoints.of(source, target, NearestNeighbors(target).spacing(),
                             DEFAULT.keypoints, DEFAULT.scan.keypoint.min_voxel_spacings)
    turned = to_matrix(random_rotation(np.random.default_rng(2), plane_moves_by_deg), [0.0, 0.0, 0.0]) @ truth

    def fake_stage(points, index, estimator, *, init, criteria, scale, **_):
        return RefinementOutcome(turned, True, 7, None, "moved", None)

    monkeypatch.setattr(api, "guarded_refine", fake_stage)
    request = api._validate(source, target, "esm", truth, None, 100, 1e-8, None, None, None)
    index = NearestNeighbors(target)
    clouds = api._Clouds(WorkingFrame(None), source, target, index, 1.0)
    stages = []
    pose, iterations, _ = api._plane_start(source, clouds, truth, request, keypoints, None, None, stages)
    (stage,) = stages
    assert iterations == stage.iterations == 7 and stage.name == "plane" and stage.points == len(source)
    before, after = overlap_confidence(truth, keypoints, config=DEFAULT), overlap_confidence(turned, keypoints, config=DEFAULT)
    assert (stage.decided["confidence_before"], stage.decided["confidence_after"]) == (before, after)
    assert stage.decided["undone"] == (not kept) == (before - after > request.refine.plane_confidence_drop)
    assert pose is (turned if kept else truth)
    np.testing.assert_array_equal(stage.pose, pose)
