"""The pose covariance and the degenerate directions (``esmicp.trust.uncertainty``): their frame
convention, their shape, and what they say of corridors, planes and well-constrained objects."""

from __future__ import annotations

import json

import numpy as np
import pytest

import esmicp
from esmicp.trust import uncertainty
from esmicp.core.procrustes import apply, skew
from esmicp.metrics import random_rotation
from esmicp.shapes import asymmetric_shape
from esmicp.trust.policy import DEFAULT_POLICY, TrustPolicy

from conftest import require_shared


def corridor(count: int, rng: np.random.Generator) -> np.ndarray:
    """Two parallel walls (y = -1, y = +1, 2 high) and a floor (z = 0), 10 long along x."""
    third = count // 3
    along = rng.uniform(-5.0, 5.0, (3, third))
    walls = [np.column_stack([along[k], np.full(third, side), rng.uniform(0.0, 2.0, third)])
             for k, side in ((0, -1.0), (1, 1.0))]
    floor = np.column_stack([along[2], rng.uniform(-1.0, 1.0, third), np.zeros(third)])
    return np.vstack([*walls, floor])


def pose(rotation_axis, degrees: float, translation) -> np.ndarray:
    axis = np.asarray(rotation_axis, dtype=float) / np.linalg.norm(rotation_axis)
    angle = np.radians(degrees)
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    transform = np.eye(4)
    transform[:3, :3] = np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew
    transform[:3, 3] = translation
    return transform


def test_corridor_is_degenerate_along_its_axis(rng):
    target = corridor(15_000, rng)
    source = corridor(15_000, rng) + rng.normal(0.0, 0.005, (15_000, 3))
    result = esmicp.register(source, target, init=np.eye(4))
    directions = result.degenerate_directions
    assert len(directions) == 1, [d.describe() for d in directions]
    (direction,) = directions
    assert direction.kind == "translation"
    assert abs(direction.axis[0]) > 0.95
    assert direction.ratio < DEFAULT_POLICY.degenerate_ratio
    assert "translation along x (target frame) is poorly constrained" in direction.describe()
    # However sharply the walls coincide, a pose that may slide is not trusted, and says why.
    assert result.confidence >= 0.55 and not result.ambiguous
    assert not result.trusted and result.doubts() == [direction.describe()]
    # The covariance says so too: x translation far less certain than y and z.
    deviations = np.sqrt(np.diag(result.covariance))
    assert deviations[3] > 10 * max(deviations[4], deviations[5])


def test_plane_on_plane_leaves_three_directions(rng):
    target = np.column_stack([rng.uniform(-1, 1, (4000, 2)), np.zeros(4000)])
    source = np.column_stack([rng.uniform(-1, 1, (4000, 2)), rng.normal(0.0, 0.002, 4000)])
    result = esmicp.register(source, target, init=np.eye(4))
    directions = result.degenerate_directions
    assert len(directions) == 3, [d.describe() for d in directions]
    kinds = sorted(d.kind for d in directions)
    assert kinds == ["rotation", "translation", "translation"]
    (rotation,) = [d for d in directions if d.kind == "rotation"]
    assert abs(rotation.axis[2]) > 0.95  # about the plane's normal
    for direction in directions:
        if direction.kind == "translation":
            assert abs(direction.axis[2]) < 0.05  # in the plane
    assert not result.trusted and len(result.doubts()) >= 3
    # Nothing at all constrains them: no information along them.
    for direction in directions:
        vector = np.concatenate([direction.rotation / direction.radius, direction.translation])
        assert vector @ result.information @ vector < 1e-6 * np.trace(result.information)


def test_well_constrained_object_has_none_and_a_psd_covariance():
    path = require_shared("bunny/bun_zipper_res2.ply")
    from esmicp import io

    cloud = io.read_points(path)
    rng = np.random.default_rng(3)
    truth = pose([1, 2, 3], 25.0, [0.02, -0.01, 0.03])
    source = apply(np.linalg.inv(truth), cloud + rng.normal(0.0, 0.0005, cloud.shape))
    result = esmicp.register(source, cloud, init=truth @ pose([0, 0, 1], 2.0, [0.002, 0, 0]))
    assert result.degenerate_directions == ()
    assert result.trusted and result.doubts() == []
    covariance = result.covariance
    assert covariance.shape == (6, 6)
    assert np.allclose(covariance, covariance.T)
    assert np.linalg.eigvalsh(covariance).min() > 0
    # Information is its inverse: usable as a pose-graph edge weight.
    assert np.allclose(result.information @ covariance, np.eye(6), atol=1e-6)
    # The error lies within what the covariance allows (chi-square 6 at 99.9%: 22.5).
    error = uncertainty.left_error(truth, result.transformation)
    assert error @ result.information @ error < 22.5


def _spreads(truth_of, count: int):
    """Observed spread of three error conventions over ``count`` noisy resamples, and the mean
    predicted standard deviations."""
    errors = {"left/target": [], "right/source": [], "left, source axes": []}
    predicted = []
    for seed in range(count):
        rng = np.random.default_rng(100 + seed)
        target = asymmetric_shape(2500, rng) + [3.0, 0.0, 0.0]
        source_in_target = asymmetric_shape(2500, rng) + [3.0, 0.0, 0.0]
        source_in_target += rng.normal(0.0, 0.01, source_in_target.shape)
        truth = truth_of
        source = apply(np.linalg.inv(truth), source_in_target)
        result = esmicp.register(source, target, init=truth, workers=1)
        estimate = result.transformation
        left = uncertainty.left_error(truth, estimate)
        right = uncertainty.left_error(np.linalg.inv(estimate) @ truth, np.eye(4))  # T_true = T_est Exp(d)
        errors["left/target"].append(left)
        errors["right/source"].append(right)
        # The left error expressed along the source's axes (R^T omega, R^T v).
        rotation = truth[:3, :3]
        errors["left, source axes"].append(np.concatenate([rotation.T @ left[:3], rotation.T @ left[3:]]))
        predicted.append(np.sqrt(np.diag(result.covariance)))
    observed = {name: np.sqrt(np.mean(np.square(values), axis=0)) for name, values in errors.items()}
    return observed, np.mean(predicted, axis=0)


def test_predicted_spread_matches_observed_per_axis_in_the_stated_frame():
    """Register many noisy resamples of an elongated object lying 3 units from the target origin,
    the source turned 90 degrees: the per-axis spread the covariance predicts (left perturbation,
    target frame) matches the observed one; under the right (source-frame) perturbation or along
    the source's axes it does not."""
    truth = pose([0, 0, 1], 90.0, [0.5, -1.0, 0.2]) @ pose([1, 0, 0], 90.0, [0, 0, 0])
    observed, predicted = _spreads(truth, 24)
    ratios = {name: spread / predicted for name, spread in observed.items()}
    stated = ratios["left/target"]
    # Calibrated on every axis: never over-confident by 3x, and on these clean clouds (independent
    # noise, no cut: less correlated than the scans the inflation was fitted on) at most 4x
    # conservative...
    assert np.all(stated > 1 / 4) and np.all(stated < 3), stated
    # ... and the shape of the spread matches: the ratio is about the same on every axis.
    assert stated.max() / stated.min() < 2.5, stated
    for name in ("right/source", "left, source axes"):
        flipped = ratios[name]
        assert flipped.max() / flipped.min() > 2.5, (name, flipped)


def test_icp_gets_unit_weights_and_a_covariance(rng):
    target = asymmetric_shape(1500, rng)
    source = asymmetric_shape(1500, rng) + rng.normal(0.0, 0.005, (1500, 3))
    result = esmicp.register(source, target, init=np.eye(4), method="icp")
    assert result.covariance is not None and np.linalg.eigvalsh(result.covariance).min() > 0


def test_pose_uncertainty_ignores_the_working_frame_shift(rng):
    """Clouds far from the origin are registered in a shifted frame; the covariance is still about
    the target frame's own origin: the same as for the same clouds near the origin, moved."""
    target = asymmetric_shape(2000, rng)
    source = asymmetric_shape(2000, rng) + rng.normal(0.0, 0.01, (2000, 3))
    near = esmicp.register(source, target, init=np.eye(4))
    offset = np.array([4.0e4, -3.0e4, 1.0e4])
    far = esmicp.register(source + offset, target + offset, init=np.eye(4))
    # Moving both clouds by o maps a left perturbation (omega, v) to (omega, v - o x omega).
    mapping = np.eye(6)
    mapping[3:, :3] = skew(offset)
    expected = mapping @ near.covariance @ mapping.T
    assert np.allclose(far.covariance, expected, rtol=1e-3, atol=1e-12 * np.abs(expected).max())


def test_to_dict_carries_the_uncertainty(rng):
    target = corridor(6000, rng)
    source = corridor(6000, rng)
    data = esmicp.register(source, target, init=np.eye(4)).to_dict()
    text = json.dumps(data)
    back = json.loads(text)
    assert np.array(back["covariance"]).shape == (6, 6)
    assert np.array(back["information"]).shape == (6, 6)
    assert back["degenerate_directions"][0]["kind"] == "translation"


def test_describe_words():
    covariance = np.diag([np.radians(0.1) ** 2] * 3 + [0.01 ** 2] * 3)
    lines = uncertainty.describe(covariance)
    assert "0.1 0.1 0.1" in lines[0] and "0.01 0.01 0.01" in lines[1]


def test_left_error_is_the_left_perturbation():
    estimate = pose([1, 1, 0], 40.0, [1.0, 2.0, 3.0])
    delta = np.array([0.01, -0.02, 0.005, 0.1, -0.05, 0.02])
    exact = np.eye(4)
    exact[:3, :3] = pose(delta[:3], np.degrees(np.linalg.norm(delta[:3])), [0, 0, 0])[:3, :3]
    exact[:3, 3] = delta[3:]
    truth = exact @ estimate
    assert np.allclose(uncertainty.left_error(truth, estimate), delta, atol=1e-12)
    with pytest.raises(AssertionError):
        assert np.allclose(uncertainty.left_error(estimate @ exact, estimate), delta, atol=1e-6)


def test_cli_register_names_the_degenerate_direction_and_prints_no_deviations_beside_it(tmp_path, rng, capsys):
    """A degenerate pose is not trusted: the verdict names the free direction, and no standard
    deviation is printed beside it (-v neither); --json keeps the covariance for programs."""
    from esmicp import io
    from esmicp.cli import main

    io.write_points(tmp_path / "target.ply", corridor(6000, rng))
    io.write_points(tmp_path / "source.ply", corridor(6000, rng) + [0.03, 0.01, 0.0])
    arguments = ["register", str(tmp_path / "source.ply"), str(tmp_path / "target.ply"), "--init", "identity"]
    assert main([*arguments, "-v"]) == 0
    out = capsys.readouterr().out
    assert "std rotation" not in out and "std translation" not in out and "standard deviation" not in out
    assert "translation along x (target frame) is poorly constrained" in out
    assert "DEGENERATE" in out.splitlines()[1]  # the verdict, after the line naming the files
    # for scripts: not trusted, exit status 3, the reason on stderr
    assert main([*arguments, "--min-confidence"]) == 3
    assert "translation along x (target frame) is poorly constrained" in capsys.readouterr().err
    assert main([*arguments, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert len(report["std_rotation_deg"]) == 3 and len(report["std_translation"]) == 3
    assert report["std_translation"][0] > 10 * report["std_translation"][1]
    assert "translation along x" in report["degenerate_directions"][0]["description"]
    assert report["trusted"] is False and any("translation along x" in doubt for doubt in report["doubts"])


def test_too_few_pairs_give_no_covariance():
    placed = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    estimate = uncertainty.pose_uncertainty(placed, placed, spacing=1.0)
    assert estimate.covariance is None and estimate.information is None


def test_pose_uncertainty_is_psd_and_symmetric_on_random_pairs(rng):
    """Whatever the pairs (here random, with random normals and weights), the covariance is a
    symmetric positive semi-definite 6x6 and the information its inverse."""
    for _ in range(5):
        placed = rng.normal(size=(500, 3))
        matched = placed + rng.normal(0.0, 0.05, (500, 3))
        normals = rng.normal(size=(500, 3))
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        estimate = uncertainty.pose_uncertainty(placed, matched, rng.uniform(0, 1, 500), normals, spacing=0.1)
        covariance = estimate.covariance
        assert np.allclose(covariance, covariance.T)
        assert np.linalg.eigvalsh(covariance).min() >= -1e-12 * np.abs(covariance).max()
        assert np.allclose(estimate.information @ covariance, np.eye(6), atol=1e-6)


def test_a_few_pairs_in_one_cube_still_carry_their_noise(rng):
    """25 noisy pairs at their least-squares optimum, all inside one cluster cube: the gradient
    terms sum to zero there, so a one-cube cluster-robust estimate would claim a pose known exactly.
    The covariance must instead match the one computed with every pair its own cluster."""
    from esmicp.core.procrustes import weighted_procrustes

    source = rng.uniform(-1.0, 1.0, (25, 3))
    matched = source + rng.normal(0.0, 0.05, source.shape)
    rotation, translation = weighted_procrustes(source, matched, np.ones(len(source)))
    placed = source @ rotation.T + translation  # the optimum: the point-to-point gradient is zero
    one_cube = uncertainty.pose_uncertainty(placed, matched, spacing=1.0).covariance  # 16 spacings: one cube
    per_pair = uncertainty.pose_uncertainty(placed, matched, spacing=1e-3,
                                            policy=TrustPolicy(cluster_spacings=1.0)).covariance
    rotation_std, _ = uncertainty.standard_deviations(one_cube)
    assert rotation_std.min() > 0.5  # degrees: 25 points, 5% noise cannot fix the pose to better
    assert 0.5 < np.trace(one_cube) / np.trace(per_pair) < 2.0


def test_a_real_surface_that_slides_is_reported_along_its_slide():
    """A real sliding pair: kitchen-walk frames 300 and 310 (a depth camera's noise and edges) cut
    down to the target's dominant plane. The reported degenerate translation lies in the plane,
    the covariance is several times wider along it than along the plane's normal, and the
    registration does slide along it: a start 5 cm off along it (one way: the crop's edge holds
    the other) stays more than 3 cm off. The whole frames report no degenerate direction."""
    from esmicp_lab.bench.sequences import plane_crop_pair, read_frame, read_poses

    folder = require_shared("sequences/redkitchen_seq01_every10")
    poses = read_poses(folder)
    target, source = read_frame(folder, "frame-000300"), read_frame(folder, "frame-000310")
    truth = np.linalg.inv(poses["frame-000300"]) @ poses["frame-000310"]
    assert not esmicp.register(source, target, init=truth, workers=1).degenerate_directions

    crop_source, crop_target, normal = plane_crop_pair(target, source, truth, 0.015, np.random.default_rng(0))
    result = esmicp.register(crop_source, crop_target, init=truth, workers=1)
    slides = [d for d in result.degenerate_directions if d.kind == "translation"]
    assert slides, result.degenerate_directions
    along = slides[0].axis
    assert abs(along @ normal) < 0.1  # in the plane
    spread = result.covariance[3:, 3:]
    assert np.sqrt(along @ spread @ along) > 3 * np.sqrt(normal @ spread @ normal)

    def left_after(direction):
        start = truth.copy()
        start[:3, 3] += 0.05 * direction
        moved = esmicp.register(crop_source, crop_target, init=start, workers=1).transformation
        return abs(float((moved[:3, 3] - truth[:3, 3]) @ direction))

    assert max(left_after(along), left_after(-along)) > 0.03


# --- The covariance's contract: it means what it says, and moves with the data as it should. ---

def ellipsoid(count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``(points, unit normals)`` spread over an ellipsoid of radii 1.0 / 0.6 / 0.4: every pose
    direction constrained, the normals known exactly."""
    radii = np.array([1.0, 0.6, 0.4])
    directions = rng.normal(size=(count, 3))
    points = directions / np.linalg.norm(directions, axis=1, keepdims=True) * radii
    normals = points / radii ** 2
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def test_predicted_spread_matches_the_spread_over_noise_draws():
    """A synthetic pair with known isotropic noise (0.01, about half a point spacing, on both clouds),
    both clouds sampled afresh for each of 16 draws and registered: the observed RMS rotation and
    translation errors match the predicted standard deviations within a factor of 2 (neither far
    too sure nor far too cautious)."""
    truth = pose([1, 2, 0.5], 40.0, [0.3, -0.2, 0.1])
    rotation_errors, translation_errors, rotation_std, translation_std = [], [], [], []
    for seed in range(16):
        rng = np.random.default_rng(seed)
        target = asymmetric_shape(1500, rng) + rng.normal(0.0, 0.01, (1500, 3))
        surface = asymmetric_shape(1500, rng) + rng.normal(0.0, 0.01, (1500, 3))
        result = esmicp.register(apply(np.linalg.inv(truth), surface), target, init=truth, workers=1)
        error = uncertainty.left_error(truth, result.transformation)
        rotation_errors.append(error[:3])
        translation_errors.append(error[3:])
        deviations = np.sqrt(np.diag(result.covariance))
        rotation_std.append(deviations[:3])
        translation_std.append(deviations[3:])
    for errors, predicted in ((rotation_errors, rotation_std), (translation_errors, translation_std)):
        observed = np.sqrt(np.mean(np.square(errors)))
        ratio = observed / np.sqrt(np.mean(np.square(predicted)))
        assert 1 / 2 < ratio < 2, ratio


def test_covariance_scales_with_the_noise_variance():
    """Every residual and the clouds' noise twice as large: the covariance four times as large."""
    rng = np.random.default_rng(5)
    placed, normals = ellipsoid(3000, rng)
    offsets = rng.normal(0.0, 1.0, placed.shape)
    single, double = (uncertainty.pose_uncertainty(placed, placed - scale * 0.002 * offsets, None, normals,
                                                   spacing=0.03, noise=((scale * 0.002) ** 2,) * 2).covariance
                      for scale in (1.0, 2.0))
    assert np.allclose(double, 4.0 * single, rtol=1e-9, atol=0.0)


def test_covariance_falls_as_one_over_the_number_of_independent_pairs():
    """Four times as many pairs, each with its own independent noise, over the same surface: the
    covariance about a quarter as large. (Cubes of 2 spacings: thousands of clusters, so that the
    cluster-robust estimate is itself steady; with independent residuals its expectation does not
    depend on the cube.)"""
    rng = np.random.default_rng(8)
    policy = TrustPolicy(cluster_spacings=2.0)
    traces = []
    for count in (2000, 8000):
        placed, normals = ellipsoid(count, rng)
        matched = placed - normals * rng.normal(0.0, 0.003, (count, 1))
        spacing = 1.6 / np.sqrt(count)
        covariance = uncertainty.pose_uncertainty(placed, matched, None, normals, spacing=spacing,
                                                  policy=policy).covariance
        traces.append((np.trace(covariance[:3, :3]), np.trace(covariance[3:, 3:])))
    ratios = np.array(traces[0]) / np.array(traces[1])
    assert np.all((ratios > 4 / 1.3) & (ratios < 4 * 1.3)), ratios


def _registered_uncertainty(source, target, transformation, policy=DEFAULT_POLICY):
    from esmicp.core.correspondence import NearestNeighbors

    return uncertainty.from_registration(source, NearestNeighbors(target, workers=1), transformation, None, workers=1,
                                         policy=policy)


def test_covariance_follows_the_scene_scaled_by_1000_and_moved_rigidly():
    """The same pair in millimetres instead of metres: rotation block unchanged, cross blocks x 1e3,
    translation block x 1e6. The same pair with the whole scene (target frame) moved by ``M``: the
    covariance is ``Ad(M) Sigma Ad(M)^T`` (left perturbation, target frame), up to the cluster
    cubes, which stay aligned with the axes (small cubes here, so that their grouping matters
    little)."""
    rng = np.random.default_rng(21)
    target = asymmetric_shape(1500, rng)
    truth = pose([0, 1, 1], 30.0, [0.2, 0.1, -0.3])
    source = apply(np.linalg.inv(truth), asymmetric_shape(1500, rng) + rng.normal(0.0, 0.01, (1500, 3)))
    base = _registered_uncertainty(source, target, truth).covariance
    scaled = _registered_uncertainty(1000.0 * source, 1000.0 * target,
                                     np.block([[truth[:3, :3], 1000.0 * truth[:3, 3:]], [truth[3:]]])).covariance
    factor = np.outer([1.0] * 3 + [1000.0] * 3, [1.0] * 3 + [1000.0] * 3)
    assert np.allclose(scaled, base * factor, rtol=1e-6, atol=1e-12 * np.abs(base * factor).max())

    motion = pose([3, -1, 2], 70.0, [5.0, -2.0, 1.0])
    small_cubes = TrustPolicy(cluster_spacings=2.0)
    base = _registered_uncertainty(source, target, truth, small_cubes).covariance
    moved = _registered_uncertainty(source, apply(motion, target), motion @ truth, small_cubes).covariance
    adjoint = np.zeros((6, 6))
    adjoint[:3, :3] = adjoint[3:, 3:] = motion[:3, :3]
    adjoint[3:, :3] = skew(motion[:3, 3]) @ motion[:3, :3]
    back = np.linalg.inv(adjoint) @ moved @ np.linalg.inv(adjoint).T  # in the unmoved target frame
    assert np.allclose(np.sqrt(np.diag(back)), np.sqrt(np.diag(base)), rtol=0.1)
    # Without the adjoint (about the old origin, along the old axes) it is not the same matrix.
    assert not np.allclose(np.sqrt(np.diag(moved)), np.sqrt(np.diag(base)), rtol=0.5)


def test_surface_noise_reads_a_planes_gaussian_noise():
    """5,000 points on a unit square with Gaussian noise across it of 0.002 (about a third of the
    point spacing): the noise variance read is 4e-6 within 20%, and four times that for twice the
    noise."""
    rng = np.random.default_rng(2)
    flat = np.column_stack([rng.uniform(0, 1, 5000), rng.uniform(0, 1, 5000), np.zeros(5000)])
    across = rng.normal(0.0, 1.0, 5000)
    for deviation in (0.002, 0.004):
        points = flat + np.outer(deviation * across, [0.0, 0.0, 1.0])
        variance = uncertainty.surface_noise(points, points[::10])
        assert 0.8 < variance / deviation ** 2 < 1.2, variance / deviation ** 2


def test_sharing_counts_the_pairs_per_target_point():
    assert uncertainty.sharing(np.arange(10)) == 1.0
    assert uncertainty.sharing(np.repeat(np.arange(5), 2)) == 2.0
    assert uncertainty.sharing(np.array([0, 0, 1]), np.array([1.0, 1.0, 2.0])) == pytest.approx((4 + 4) / 6)
