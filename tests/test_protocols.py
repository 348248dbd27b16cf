"""Evaluation protocols (esmicp_lab.bench.protocols), success metrics, and the Stanford .conf reader."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import require_shared
from scipy import stats
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from esmicp.core.procrustes import apply, rotation_angle, to_matrix
from esmicp.errors import PointCloudFileError
from esmicp.io.stanford_conf import load_scans, read_stanford_conf
from esmicp.metrics import (
    rotation_error_deg,
    strict_success,
    symmetric_placement_error,
    up_to_symmetry_success,
)
from esmicp.core.procrustes import bounding_box_diagonal
from esmicp_lab.bench.protocols import (
    PAPER_NOISE_MIXTURE,
    PROTOCOLS,
    copy_trial,
    make_trial,
    make_trials,
    outlier_trial,
    paper_noise,
    paper_noise_draw,
    random_rigid_transform,
    resampled_trial,
    scan_overlap,
    scan_pairs,
    shuffled_trial,
)
from esmicp.shapes import asymmetric_shape


@pytest.fixture(scope="module")
def cloud():
    return asymmetric_shape(1000, rng=7)


def _rows(points):
    return {tuple(row) for row in np.round(points, 9)}


# --- single-object protocols -------------------------------------------------------------------


def test_copy_trial_maps_exactly_in_the_same_order(cloud, rng):
    trial = copy_trial(cloud, rng, name="shape")
    assert trial.protocol == "copy" and trial.cloud == "shape"
    np.testing.assert_array_equal(trial.target, cloud)
    assert np.abs(trial.source - cloud).max() > 0.1  # it was moved
    np.testing.assert_allclose(apply(trial.T_target_source, trial.source), cloud, atol=1e-9)
    assert trial.diagonal == pytest.approx(bounding_box_diagonal(cloud))
    assert not trial.source.flags.writeable


def test_shuffled_trial_same_points_different_order(cloud, rng):
    trial = shuffled_trial(cloud, rng)
    placed = apply(trial.T_target_source, trial.source)
    assert np.abs(placed - cloud).max() > 0.1  # order differs
    distances, index = cKDTree(cloud).query(placed)
    assert distances.max() < 1e-9
    assert sorted(index) == list(range(len(cloud)))  # a permutation of the cloud
    assert (index != np.arange(len(cloud))).mean() > 0.9


def test_resampled_trial_halves_are_disjoint_and_map_into_the_cloud(cloud, rng):
    trial = resampled_trial(cloud, rng)
    assert len(trial.source) == len(trial.target) == len(cloud) // 2
    placed = apply(trial.T_target_source, trial.source)
    assert not _rows(placed) & _rows(trial.target)
    assert _rows(placed) | _rows(trial.target) == _rows(cloud)
    distances, _ = cKDTree(cloud).query(placed)
    assert distances.max() < 1e-9


@pytest.mark.parametrize("fraction", [0.3, 0.6])
def test_outlier_trial_corrupts_exactly_the_fraction(cloud, rng, fraction):
    trial = outlier_trial(cloud, rng, fraction)
    assert trial.protocol == f"outliers-{round(100 * fraction)}"
    placed = apply(trial.T_target_source, trial.source)
    distances, _ = cKDTree(cloud).query(placed)
    unchanged = distances < 1e-9
    assert (~unchanged).sum() == round(fraction * len(trial.source))
    assert not _rows(placed[unchanged]) & _rows(trial.target)


def test_paper_noise_bounds_and_mask(rng):
    points = rng.normal(size=(3001, 3))
    scale = 2.5
    noisy, mask = paper_noise(points, 0.3, rng, scale)
    assert mask.sum() == round(0.3 * 3001)
    np.testing.assert_array_equal(noisy[~mask], points[~mask])
    assert np.all(np.abs(noisy[mask] - points[mask]).max(axis=1) > 0)
    assert np.abs(noisy - points).max() <= 10.0 * scale


def test_paper_noise_mixture_components(rng):
    noise, component = paper_noise_draw(30000, rng)
    counts = np.bincount(component, minlength=3) / len(component)
    np.testing.assert_allclose(counts, 1 / 3, atol=0.02)
    for k, (variance, clip) in enumerate(PAPER_NOISE_MIXTURE):
        part = noise[component == k]
        assert np.abs(part).max() <= clip
        # the clip barely matters for components 2 and 3; their spread is sqrt(variance)
        if k > 0:
            assert part.std() == pytest.approx(np.sqrt(variance), rel=0.05)
    assert np.abs(noise[component == 0]).max() == pytest.approx(0.05)  # N(0, 0.01) hits its clip


# --- random transforms ------------------------------------------------------------------------


def _angles(rotations):
    return np.array([rotation_angle(r) for r in rotations])


def _uniform_euler(rng, count):
    return Rotation.from_euler("xyz", rng.uniform(-np.pi, np.pi, size=(count, 3))).as_matrix()


def test_random_rotations_are_uniform_on_so3(rng):
    count = 4000
    rotations = np.array([random_rigid_transform(rng, 1.0)[:3, :3] for _ in range(count)])
    # uniform on SO(3): E[R] = 0 (each entry has std 1/3, so the mean's std is 1/(3 sqrt(n)))
    tolerance = 5 / (3 * np.sqrt(count))
    assert np.abs(rotations.mean(axis=0)).max() < tolerance
    # angle density (1 - cos a) / pi on [0, pi]: CDF (a - sin a) / pi
    assert stats.kstest(_angles(rotations), lambda a: (a - np.sin(a)) / np.pi).pvalue > 0.01
    # and E[R_ij^2] = 1/3 for every entry (each column is a uniform unit vector)
    assert np.abs((rotations**2).mean(axis=0) - 1 / 3).max() < 0.03
    # Euler angles each uniform on the full circle are NOT uniform on SO(3). Their mean is 0 as
    # well (so a mean test alone is blind to them; their angle distribution is also close to
    # (1 - cos)/pi), but the second moments give them away: R_22 = cos a cos b has
    # E[R_22^2] = 1/4, not 1/3.
    euler = _uniform_euler(rng, count)
    assert np.abs(euler.mean(axis=0)).max() < tolerance
    assert np.abs((euler**2).mean(axis=0) - 1 / 3).max() > 0.06


def test_random_translation_box_and_bounded_rotation(rng):
    transforms = np.array([random_rigid_transform(rng, 2.0, max_angle_deg=30) for _ in range(2000)])
    translations = transforms[:, :3, 3]
    assert np.abs(translations).max() <= 10.0
    assert translations.min() < -9.5 and translations.max() > 9.5
    angles = np.degrees(_angles(transforms[:, :3, :3]))
    assert angles.max() <= 30 + 1e-9
    assert stats.kstest(angles / 30, "uniform").pvalue > 0.01


# --- make_trials determinism ------------------------------------------------------------------


@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_make_trials_is_deterministic_per_index(protocol):
    clouds = {"a": asymmetric_shape(900, rng=1), "b": asymmetric_shape(700, rng=2)}
    first = make_trials(protocol, clouds, 4, seed=11, points=200)
    again = make_trials(protocol, clouds, 6, seed=11, points=200)
    assert [t.cloud for t in first] == ["a", "b", "a", "b"]
    for one, two in zip(first, again):
        np.testing.assert_array_equal(one.source, two.source)
        np.testing.assert_array_equal(one.target, two.target)
        np.testing.assert_array_equal(one.T_target_source, two.T_target_source)
    alone = make_trial(protocol, clouds["b"], 11, 3, name="b", points=200)
    np.testing.assert_array_equal(alone.source, first[3].source)
    assert alone.seed == first[3].seed == (11, 3)
    assert not np.array_equal(first[0].T_target_source, first[2].T_target_source)
    other = make_trials(protocol, clouds, 1, seed=12, points=200)[0]
    assert not np.array_equal(other.T_target_source, first[0].T_target_source)
    assert all(len(t.source) == 200 and len(t.target) == 200 for t in first)


# --- success metrics --------------------------------------------------------------------------


def _rotated_about_axis(truth, axis, degrees, centre=(0.0, 0.0, 0.0)):
    """``truth`` followed (in the source frame) by a rotation about ``axis`` through ``centre``."""
    rotation = Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis, float)).as_matrix()
    centre = np.asarray(centre, dtype=float)
    return truth @ to_matrix(rotation, centre - rotation @ centre)


def _cylinder(rng, count, radius=0.5, height=2.0):
    side = 2 * np.pi * radius * height
    cap = np.pi * radius**2
    on_side = rng.random(count) < side / (side + 2 * cap)
    theta = rng.uniform(0, 2 * np.pi, count)
    r = np.where(on_side, radius, radius * np.sqrt(rng.random(count)))
    z = np.where(on_side, rng.uniform(-height / 2, height / 2, count), np.sign(rng.random(count) - 0.5) * height / 2)
    return np.column_stack([r * np.cos(theta), r * np.sin(theta), z])


def test_strict_success_thresholds(rng):
    truth = random_rigid_transform(rng, 1.0)
    for degrees, expected in [(1.0, True), (3.0, False)]:
        rotation = Rotation.from_rotvec(np.radians(degrees) * np.array([0.0, 0.6, 0.8])).as_matrix()
        estimate = truth @ to_matrix(rotation, np.zeros(3))  # same translation
        assert rotation_error_deg(estimate, truth) == pytest.approx(degrees)
        assert strict_success(estimate, truth, 1.0) is expected
    shifted = truth.copy()
    shifted[:3, 3] += [0.0, 0.0, 0.03]
    assert not strict_success(shifted, truth, 1.0)
    assert strict_success(shifted, truth, 2.0)


def test_up_to_symmetry_accepts_a_cylinder_turned_about_its_axis(rng):
    cylinder = _cylinder(rng, 8000)
    diagonal = bounding_box_diagonal(cylinder)
    truth = random_rigid_transform(rng, diagonal)
    estimate = _rotated_about_axis(truth, [0, 0, 1], 40)
    assert not strict_success(estimate, truth, diagonal)
    assert symmetric_placement_error(cylinder, truth, truth) == 0
    assert up_to_symmetry_success(cylinder, estimate, truth, diagonal)
    # a turn about a transverse axis is not a symmetry of the cylinder
    assert not up_to_symmetry_success(cylinder, _rotated_about_axis(truth, [1, 0, 0], 40), truth, diagonal)


def test_up_to_symmetry_rejects_an_asymmetric_cloud_off_by_40_degrees(rng):
    shape = asymmetric_shape(3000, rng=rng)
    diagonal = bounding_box_diagonal(shape)
    truth = random_rigid_transform(rng, diagonal)
    centre = shape.mean(axis=0)
    for axis in np.eye(3):
        estimate = _rotated_about_axis(truth, axis, 40, centre)
        assert not up_to_symmetry_success(shape, estimate, truth, diagonal)
    assert up_to_symmetry_success(shape, _rotated_about_axis(truth, [0, 0, 1], 0.1, centre), truth, diagonal)


# --- Stanford scans ---------------------------------------------------------------------------

SCAN_NAMES = ["bun000", "bun045", "bun090", "bun180", "bun270", "top2", "top3", "bun315", "chin", "ear_back"]


@pytest.fixture(scope="module")
def bunny_scans():
    return load_scans(require_shared("bunny_scans"), max_points=4000, rng=3)


def test_read_stanford_conf_gives_the_ten_scans():
    poses = read_stanford_conf(require_shared("bunny_scans/bun.conf"))
    assert list(poses) == SCAN_NAMES
    np.testing.assert_array_equal(poses["bun000"], np.eye(4))
    for pose in poses.values():
        np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0)


def test_conf_poses_align_bun000_and_bun045():
    folder = require_shared("bunny_scans")
    poses = read_stanford_conf(folder / "bun.conf")
    scans = load_scans(folder / "bun.conf", max_points=None)
    source, _ = scans["bun000"]
    target, _ = scans["bun045"]
    source = source[np.random.default_rng(0).choice(len(source), 5000, replace=False)]
    truth = np.linalg.inv(poses["bun045"]) @ poses["bun000"]
    distances, _ = cKDTree(target).query(apply(truth, source))
    assert np.mean(distances < 1e-3) >= 0.80
    unaligned, _ = cKDTree(target).query(source)
    assert np.mean(unaligned < 1e-3) < 0.2


def test_scan_pairs_both_directions_with_correct_truth(bunny_scans):
    trials = scan_pairs(bunny_scans, 5, max_points=2000)
    names = {trial.cloud for trial in trials}
    assert {"bun000->bun045", "bun045->bun000", "bun000->bun315", "bun315->bun000"} <= names
    assert sum(f"{b}->{a}" in names for a, b in (name.split("->") for name in names)) >= 20
    for trial in trials:
        assert trial.protocol == "scan-pairs"
        assert len(trial.source) <= 2000 and len(trial.target) <= 2000
        assert scan_overlap(trial.source, trial.target, trial.T_target_source) >= 0.3
        # the source was turned: without the truth it does not overlap as much
        assert scan_overlap(trial.source, trial.target, np.eye(4)) < 0.3
    again = scan_pairs(bunny_scans, 5, max_points=2000)
    for one, two in zip(trials, again):
        np.testing.assert_array_equal(one.T_target_source, two.T_target_source)
        np.testing.assert_array_equal(one.source, two.source)
    # exact pose check on one pair: mapped source points lie on the target scan surface
    pair = next(t for t in trials if t.cloud == "bun000->bun045")
    distances, _ = cKDTree(pair.target).query(apply(pair.T_target_source, pair.source))
    assert np.median(distances) < 2e-3


def test_scan_pairs_min_overlap_filters(bunny_scans):
    subset = {name: bunny_scans[name] for name in ("bun000", "bun045", "bun180")}
    trials = scan_pairs(subset, np.random.default_rng(1), max_points=1500)
    names = {trial.cloud for trial in trials}
    assert {"bun000->bun045", "bun045->bun000"} <= names
    assert not {"bun000->bun180", "bun180->bun000"} & names
    assert scan_pairs(subset, 1, min_overlap=1.01, max_points=1500) == []


@pytest.mark.parametrize(
    ("line", "needle"),
    [
        ("bmesh bun000.ply 0 0 0 0 0 1", "line 3"),
        ("bmesh bun000.ply 0 0 x 0 0 0 1", "line 3"),
        ("bmesh bun000.ply 0 0 0 0 0 0 2", "line 3: quaternion"),
        ("bmesh bun000.ply 0 0 nan 0 0 0 1", "line 3"),
        ("blob bun000.ply 0 0 0 0 0 0 1", "line 3: unknown keyword"),
        ("bmesh bun045.ply 0 0 0 0 0 0 1", "line 3: scan 'bun045' already listed on line 2"),
    ],
)
def test_malformed_conf_lines_name_the_line(tmp_path, line, needle):
    conf = tmp_path / "scans.conf"
    conf.write_text(f"camera 0 0 0 0 0 0 1\nbmesh bun045.ply 0 0 0 0 0 0 1\n{line}\n")
    with pytest.raises(PointCloudFileError, match=needle) as info:
        read_stanford_conf(conf)
    assert info.value.path == str(conf)


def test_conf_skips_camera_and_cybcyl(tmp_path):
    conf = tmp_path / "scans.conf"
    conf.write_text(
        "camera 0 0 0 0 0 0 1\n\nmesh calib_cybcyl.ply 0 0 0 0 0 0 1\nbmesh a.ply 1 2 3 0 0 0.7071068 0.7071068\n"
    )
    poses = read_stanford_conf(conf)
    assert list(poses) == ["a"]
    # R(q) is a +90 degree turn about z; the pose holds R(q)^T
    np.testing.assert_allclose(poses["a"][:3, :3], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-6)
    np.testing.assert_allclose(poses["a"][:3, 3], [1, 2, 3])
    with pytest.raises(PointCloudFileError, match="no bmesh lines"):
        read_stanford_conf(_write(tmp_path / "empty.conf", "camera 0 0 0 0 0 0 1\n"))
    with pytest.raises(PointCloudFileError, match="no such file"):
        read_stanford_conf(tmp_path / "missing.conf")


def _write(path, text):
    path.write_text(text)
    return path


@pytest.mark.parametrize("max_angle", [180.0, 90.0, 5.0, 0.01])
def test_random_rotation_draws_what_scipy_draws_bit_for_bit(max_angle):
    # The protocols' trials were drawn with SciPy's Rotation; the NumPy code keeps them.
    from esmicp.metrics import random_rotation

    for seed in range(200):
        ours, theirs = np.random.default_rng(seed), np.random.default_rng(seed)
        if max_angle >= 180.0:
            expected = Rotation.random(random_state=theirs).as_matrix()
        else:
            axis = theirs.normal(size=3)
            axis /= np.linalg.norm(axis)
            expected = Rotation.from_rotvec(np.radians(theirs.uniform(0.0, max_angle)) * axis).as_matrix()
        np.testing.assert_array_equal(random_rotation(ours, max_angle), expected)
        assert ours.random() == theirs.random()  # the generators stay in step
