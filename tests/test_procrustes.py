"""Closed-form rigid fits and SE(3) helpers in :mod:`esmicp.core.procrustes`."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.linalg import polar
from scipy.spatial.transform import Rotation

from esmicp.core.procrustes import (
    apply,
    axis_bounds,
    bounding_box_diagonal,
    project_to_rotation,
    rotation_angle,
    rotation_from_cross_covariance,
    to_matrix,
    weighted_procrustes,
)
from esmicp.types import degeneracy

# Deterministic hypothesis runs: the examples are derived from the test, not from the clock.
HYPOTHESIS = settings(
    derandomize=True,
    database=None,
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow],
)

coordinates = st.floats(min_value=-50.0, max_value=50.0, allow_nan=False, allow_infinity=False, allow_subnormal=False)


@st.composite
def clouds(draw, min_points: int = 3, max_points: int = 60) -> np.ndarray:
    count = draw(st.integers(min_points, max_points))
    points = draw(arrays(np.float64, (count, 3), elements=coordinates))
    assume(degeneracy(points) is None)
    return points


@st.composite
def rigid_motions(draw) -> tuple[np.ndarray, np.ndarray]:
    seed = draw(st.integers(0, 2**32 - 1))
    rotation = Rotation.random(random_state=seed).as_matrix()
    translation = draw(arrays(np.float64, 3, elements=st.floats(-1000.0, 1000.0, allow_subnormal=False)))
    return rotation, translation


positive_weights = st.floats(min_value=0.1, max_value=10.0, allow_nan=False, allow_infinity=False)


def well_conditioned(points: np.ndarray, weights: np.ndarray | None = None, ratio: float = 1e-3) -> bool:
    """Whether the (weighted) centred cloud's 2nd singular value is not tiny next to its 1st.

    ``degeneracy`` accepts nearly collinear clouds down to a ratio of 1e-9; for those the rotation
    about the near-line is fixed by rounding noise to only ~1e-16 / ratio, so a 1e-9 recovery bound
    is only meaningful on clouds that are not nearly collinear.
    """
    if weights is None:
        weights = np.ones(len(points))
    normalised = weights / weights.sum()
    centred = (points - normalised @ points) * np.sqrt(normalised)[:, None]
    singular = np.linalg.svd(centred, compute_uv=False)
    return singular[1] > ratio * singular[0] and singular[0] > 1e-3


def make_pair(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray):
    """``(source, target)`` with ``target = source @ R.T + t`` exactly as the convention says."""
    return points, points @ rotation.T + translation


def assert_is_rotation(matrix: np.ndarray, atol: float = 1e-12) -> None:
    np.testing.assert_allclose(matrix.T @ matrix, np.eye(3), atol=atol)
    assert np.linalg.det(matrix) == pytest.approx(1.0, abs=atol)


def objective(rotation, translation, source, target, weights) -> float:
    residual = source @ rotation.T + translation - target
    return float(weights @ np.einsum("ij,ij->i", residual, residual))


# --------------------------------------------------------------------------------------------
# weighted_procrustes: exact recovery
# --------------------------------------------------------------------------------------------


@HYPOTHESIS
@given(points=clouds(), motion=rigid_motions())
def test_procrustes_recovers_noiseless_motion(points, motion):
    assume(well_conditioned(points))
    rotation, translation = motion
    source, target = make_pair(points, rotation, translation)
    got_rotation, got_translation = weighted_procrustes(source, target)
    np.testing.assert_allclose(got_rotation, rotation, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got_translation, translation, rtol=0, atol=1e-9 * (1 + np.abs(points).max()))
    assert_is_rotation(got_rotation)


@HYPOTHESIS
@given(data=st.data(), points=clouds(), motion=rigid_motions())
def test_weighted_procrustes_recovers_noiseless_motion(data, points, motion):
    weights = data.draw(arrays(np.float64, len(points), elements=positive_weights))
    assume(well_conditioned(points, weights))
    rotation, translation = motion
    source, target = make_pair(points, rotation, translation)
    got_rotation, got_translation = weighted_procrustes(source, target, weights)
    np.testing.assert_allclose(got_rotation, rotation, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got_translation, translation, rtol=0, atol=1e-9 * (1 + np.abs(points).max()))


@HYPOTHESIS
@given(
    data=st.data(),
    points=clouds(),
    motion=rigid_motions(),
    factor=st.floats(min_value=1e-6, max_value=1e6),
    noise_seed=st.integers(0, 2**32 - 1),
)
def test_weights_scaled_by_a_constant_give_the_same_fit(data, points, motion, factor, noise_seed):
    weights = data.draw(arrays(np.float64, len(points), elements=positive_weights))
    assume(well_conditioned(points, weights))
    rotation, translation = motion
    source, target = make_pair(points, rotation, translation)
    # noisy pairs, so the fit is a genuine compromise and not just the truth
    target = target + np.random.default_rng(noise_seed).normal(scale=1.0, size=target.shape)
    r1, t1 = weighted_procrustes(source, target, weights)
    r2, t2 = weighted_procrustes(source, target, weights * factor)
    np.testing.assert_allclose(r2, r1, rtol=0, atol=1e-9)
    np.testing.assert_allclose(t2, t1, rtol=0, atol=1e-9 * (1 + np.abs(target).max()))


def test_no_weights_means_unit_weights(rng):
    source = rng.normal(size=(40, 3))
    target = source @ Rotation.random(random_state=3).as_matrix().T + rng.normal(scale=0.3, size=(40, 3))
    r1, t1 = weighted_procrustes(source, target)
    r2, t2 = weighted_procrustes(source, target, np.ones(40))
    r3, t3 = weighted_procrustes(source, target, np.full(40, 7.0))
    np.testing.assert_allclose(r1, r2, atol=1e-14)
    np.testing.assert_allclose(t1, t2, atol=1e-14)
    np.testing.assert_allclose(r1, r3, atol=1e-12)
    np.testing.assert_allclose(t1, t3, atol=1e-12)


@HYPOTHESIS
@given(data=st.data(), points=clouds(min_points=5), motion=rigid_motions(), corrupt_seed=st.integers(0, 2**32 - 1))
def test_zero_weight_ignores_a_corrupted_pair(data, points, motion, corrupt_seed):
    rotation, translation = motion
    source, target = make_pair(points, rotation, translation)
    weights = data.draw(arrays(np.float64, len(points), elements=positive_weights))
    bad = data.draw(st.integers(0, len(points) - 1))
    keep = np.arange(len(points)) != bad
    assume(degeneracy(points[keep]) is None and well_conditioned(points[keep], weights[keep]))
    target = target.copy()
    target[bad] += np.random.default_rng(corrupt_seed).normal(scale=500.0, size=3)
    weights[bad] = 0.0
    got_rotation, got_translation = weighted_procrustes(source, target, weights)
    np.testing.assert_allclose(got_rotation, rotation, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got_translation, translation, rtol=0, atol=1e-9 * (1 + np.abs(points).max()))
    # and it is the fit without that pair
    r_without, t_without = weighted_procrustes(source[keep], target[keep], weights[keep])
    np.testing.assert_allclose(got_rotation, r_without, atol=1e-9)
    np.testing.assert_allclose(got_translation, t_without, atol=1e-9 * (1 + np.abs(points).max()))


def test_corrupted_pair_with_nonzero_weight_does_change_the_fit(rng):
    # the counterpart of the zero-weight property: the corruption is not invisible by accident
    source = rng.normal(size=(20, 3))
    rotation = Rotation.random(random_state=11).as_matrix()
    target = source @ rotation.T
    target[4] += [50.0, -20.0, 10.0]
    weights = np.ones(20)
    got, _ = weighted_procrustes(source, target, weights)
    assert np.abs(got - rotation).max() > 1e-3
    weights[4] = 0.0
    got, _ = weighted_procrustes(source, target, weights)
    np.testing.assert_allclose(got, rotation, atol=1e-12)


# --------------------------------------------------------------------------------------------
# reflections
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(40))
def test_planar_cloud_gives_a_proper_rotation(seed):
    # For a planar cloud the cross-covariance has a zero singular value: the sign of the third
    # singular vectors is arbitrary, and V U^T is a reflection about half of the time. The fit
    # must still be the true rotation.
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.normal(size=(25, 2)) * [3.0, 1.0], np.zeros(25)])
    points = points @ Rotation.random(random_state=1000 + seed).as_matrix().T + rng.normal(size=3)
    rotation = Rotation.random(random_state=seed).as_matrix()
    translation = rng.uniform(-10, 10, 3)
    source, target = make_pair(points, rotation, translation)
    got_rotation, got_translation = weighted_procrustes(source, target, rng.uniform(0.5, 2.0, 25))
    assert_is_rotation(got_rotation)
    np.testing.assert_allclose(got_rotation, rotation, atol=1e-9)
    np.testing.assert_allclose(got_translation, translation, atol=1e-9)


def test_planar_clouds_exercise_the_reflection_correction():
    # guards the test above: without the det correction some of those cases WOULD be reflections
    reflections = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        points = np.column_stack([rng.normal(size=(25, 2)) * [3.0, 1.0], np.zeros(25)])
        target = points @ Rotation.random(random_state=seed).as_matrix().T
        h = (points - points.mean(0)).T @ (target - target.mean(0))
        u, _, vt = np.linalg.svd(h)
        reflections += np.linalg.det(vt.T @ u.T) < 0
    assert reflections > 0


@pytest.mark.parametrize("seed", range(10))
def test_mirrored_cloud_best_fit_is_the_best_proper_rotation(seed):
    # The target is a mirror image: the best ORTHOGONAL fit is a reflection. The fit must be a
    # rotation, and the best one: compare with scipy's independent Kabsch (align_vectors).
    rng = np.random.default_rng(seed)
    source = rng.normal(size=(30, 3)) * [4.0, 2.0, 1.0]
    mirror = Rotation.random(random_state=seed).as_matrix() @ np.diag([1.0, 1.0, -1.0])
    target = source @ mirror.T + rng.normal(size=3)
    weights = rng.uniform(0.5, 2.0, 30)
    rotation, translation = weighted_procrustes(source, target, weights)
    assert_is_rotation(rotation)

    normalised = weights / weights.sum()
    source_c = source - normalised @ source
    target_c = target - normalised @ target
    expected, _ = Rotation.align_vectors(target_c, source_c, weights=weights)
    best = objective(rotation, translation, source, target, weights)
    expected_translation = normalised @ target - expected.as_matrix() @ (normalised @ source)
    assert best == pytest.approx(
        objective(expected.as_matrix(), expected_translation, source, target, weights), rel=1e-9
    )
    np.testing.assert_allclose(rotation, expected.as_matrix(), atol=1e-8)
    # no random rotation does better
    for trial in Rotation.random(200, random_state=seed).as_matrix():
        trial_translation = normalised @ target - trial @ (normalised @ source)
        assert best <= objective(trial, trial_translation, source, target, weights) + 1e-9


# --------------------------------------------------------------------------------------------
# rotation_from_cross_covariance
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(20))
def test_rotation_from_cross_covariance_maximises_trace(seed):
    rng = np.random.default_rng(seed)
    h = rng.normal(size=(3, 3))
    rotation = rotation_from_cross_covariance(h)
    assert_is_rotation(rotation)
    best = np.trace(rotation @ h)
    for trial in Rotation.random(300, random_state=seed).as_matrix():
        assert best >= np.trace(trial @ h) - 1e-12
    # local optimality: tiny perturbations never increase trace(R H)
    for axis in np.eye(3):
        for sign in (1.0, -1.0):
            nudged = Rotation.from_rotvec(sign * 1e-4 * axis).as_matrix() @ rotation
            assert best >= np.trace(nudged @ h) - 1e-15


@pytest.mark.parametrize("seed", range(10))
def test_rotation_from_cross_covariance_of_a_pure_rotation(seed):
    # H = C R^T with C symmetric positive definite is the noiseless cross-covariance: R comes back
    rng = np.random.default_rng(seed)
    rotation = Rotation.random(random_state=seed).as_matrix()
    a = rng.normal(size=(3, 3))
    covariance = a @ a.T + 0.1 * np.eye(3)
    np.testing.assert_allclose(rotation_from_cross_covariance(covariance @ rotation.T), rotation, atol=1e-12)
    # negative determinant of H: still a rotation
    flipped = covariance @ rotation.T @ np.diag([1.0, 1.0, -1.0])
    assert_is_rotation(rotation_from_cross_covariance(flipped))


def test_rotation_from_cross_covariance_handles_rank_deficiency():
    rotation = Rotation.random(random_state=99).as_matrix()
    planar = np.diag([3.0, 1.0, 0.0]) @ rotation.T  # rank 2: planar cloud
    np.testing.assert_allclose(rotation_from_cross_covariance(planar), rotation, atol=1e-12)
    assert_is_rotation(rotation_from_cross_covariance(np.zeros((3, 3))))


# --------------------------------------------------------------------------------------------
# rotation_angle
# --------------------------------------------------------------------------------------------


def random_axis(seed: int) -> np.ndarray:
    axis = np.random.default_rng(seed).normal(size=3)
    return axis / np.linalg.norm(axis)


@pytest.mark.parametrize("angle", [1e-12, 1e-9, 1e-7, 1e-4, 0.1, 1.0, 2.0, 3.0])
@pytest.mark.parametrize("seed", range(3))
def test_rotation_angle_matches_scipy(angle, seed):
    rotation = Rotation.from_rotvec(angle * random_axis(seed))
    got = rotation_angle(rotation.as_matrix())
    assert got == pytest.approx(rotation.magnitude(), rel=1e-9, abs=0)
    assert got == pytest.approx(angle, rel=1e-9, abs=0)


@pytest.mark.parametrize("gap", [1e-3, 1e-6, 1e-9, 0.0])
@pytest.mark.parametrize("seed", range(3))
def test_rotation_angle_near_pi(gap, seed):
    angle = np.pi - gap
    rotation = Rotation.from_rotvec(angle * random_axis(seed))
    got = rotation_angle(rotation.as_matrix())
    assert 0.0 <= got <= np.pi
    assert got == pytest.approx(Rotation.from_matrix(rotation.as_matrix()).magnitude(), abs=1e-12)
    assert got == pytest.approx(angle, abs=1e-12)


def test_rotation_angle_of_identity_is_zero():
    assert rotation_angle(np.eye(3)) == 0.0


@pytest.mark.parametrize("seed", range(10))
def test_rotation_angle_of_random_rotations(seed):
    rotation = Rotation.random(random_state=seed)
    assert rotation_angle(rotation.as_matrix()) == pytest.approx(rotation.magnitude(), abs=1e-12)
    # the angle between two rotations is symmetric
    other = Rotation.random(random_state=seed + 100).as_matrix()
    a, b = rotation.as_matrix(), other
    assert rotation_angle(a.T @ b) == pytest.approx(rotation_angle(b.T @ a), abs=1e-12)


# --------------------------------------------------------------------------------------------
# project_to_rotation
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(10))
def test_project_to_rotation_removes_drift(seed):
    rng = np.random.default_rng(seed)
    rotation = Rotation.random(random_state=seed).as_matrix()
    drifted = rotation + rng.normal(scale=1e-6, size=(3, 3))
    projected = project_to_rotation(drifted)
    assert_is_rotation(projected, atol=1e-14)
    # the nearest orthogonal matrix in Frobenius norm is the polar factor
    np.testing.assert_allclose(projected, polar(drifted)[0], atol=1e-13)
    assert np.abs(projected - rotation).max() < 1e-5


def test_project_to_rotation_is_identity_on_rotations():
    for seed in range(5):
        rotation = Rotation.random(random_state=seed).as_matrix()
        np.testing.assert_allclose(project_to_rotation(rotation), rotation, atol=1e-15)


@pytest.mark.parametrize("seed", range(10))
def test_project_to_rotation_of_a_reflection_like_matrix_is_a_rotation(seed):
    rng = np.random.default_rng(seed)
    matrix = rng.normal(size=(3, 3))
    if np.linalg.det(matrix) > 0:
        matrix[:, 0] *= -1
    projected = project_to_rotation(matrix)
    assert_is_rotation(projected)
    best = np.linalg.norm(projected - matrix)
    for trial in Rotation.random(300, random_state=seed).as_matrix():
        assert best <= np.linalg.norm(trial - matrix) + 1e-12


# --------------------------------------------------------------------------------------------
# to_matrix / apply
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_to_matrix_and_apply_round_trip(seed):
    rng = np.random.default_rng(seed)
    rotation = Rotation.random(random_state=seed).as_matrix()
    translation = rng.uniform(-100, 100, 3)
    matrix = to_matrix(rotation, translation)
    assert matrix.shape == (4, 4) and matrix.dtype == np.float64
    np.testing.assert_array_equal(matrix[:3, :3], rotation)
    np.testing.assert_array_equal(matrix[:3, 3], translation)
    np.testing.assert_array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0])

    points = rng.normal(size=(50, 3))
    original = points.copy()
    moved = apply(matrix, points)
    np.testing.assert_array_equal(points, original)  # not in place
    np.testing.assert_allclose(moved, points @ rotation.T + translation, atol=1e-12)
    homogeneous = np.column_stack([points, np.ones(50)]) @ matrix.T
    np.testing.assert_allclose(moved, homogeneous[:, :3], atol=1e-12)
    np.testing.assert_allclose(apply(np.linalg.inv(matrix), moved), points, atol=1e-12)

    other = to_matrix(Rotation.random(random_state=seed + 50).as_matrix(), rng.normal(size=3))
    np.testing.assert_allclose(apply(other @ matrix, points), apply(other, apply(matrix, points)), atol=1e-12)

    # and procrustes on the pair gives the matrix back
    r, t = weighted_procrustes(points, moved)
    np.testing.assert_allclose(to_matrix(r, t), matrix, atol=1e-10)


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int64])
def test_axis_bounds_are_numpys_per_axis_min_and_max(rng, dtype):
    """Column by column, the same values as ``min(axis=0)`` / ``max(axis=0)``: floats, integers
    (voxel keys), a strided view, one row, and NaN propagating as in ``min``."""
    points = (rng.normal(size=(1001, 3)) * 1e3).astype(dtype)
    for cloud in (points, points[::3], points[:1], np.asfortranarray(points)):
        low, high = axis_bounds(cloud)
        np.testing.assert_array_equal(low, cloud.min(axis=0))
        np.testing.assert_array_equal(high, cloud.max(axis=0))
        assert low.dtype == cloud.dtype and low.shape == (3,)
    if dtype is np.float64:
        assert bounding_box_diagonal(points) == pytest.approx(np.linalg.norm(np.ptp(points, axis=0)), rel=1e-15)
        holed = points.copy()
        holed[500, 1] = np.nan
        low, high = axis_bounds(holed)
        assert np.isnan(low[1]) and np.isnan(high[1]) and np.isfinite(low[[0, 2]]).all()


def test_batched_weighted_procrustes_equals_one_fit_at_a_time(rng):
    """Every shape the global search uses (batched pairs with and without weights, a shared source
    or target with per-fit weights such as inlier masks) gives each fit :func:`weighted_procrustes`
    gives alone, and the true motion on exact data."""
    from esmicp.core.procrustes import batched_weighted_procrustes

    count, batch = 40, 7
    motions = [to_matrix(Rotation.random(random_state=k).as_matrix(), rng.normal(size=3) * 10) for k in range(batch)]
    shared = rng.normal(size=(count, 3)) * 3 + 100.0  # far from the origin: the centring matters
    paired = np.stack([apply(m, shared) for m in motions])
    noisy = paired + rng.normal(scale=0.05, size=paired.shape)
    weights = rng.uniform(0, 1, (batch, count)) * (rng.uniform(size=(batch, count)) > 0.3)
    sources = np.stack([shared + rng.normal(scale=0.01, size=shared.shape) for _ in range(batch)])
    cases = [(sources, noisy, None), (sources, noisy, weights), (shared, noisy, weights),
             (sources, paired[0], weights)]
    for source, target, weight in cases:
        rotations, translations = batched_weighted_procrustes(source, target, weight)
        assert rotations.shape == (batch, 3, 3) and translations.shape == (batch, 3)
        for b in range(batch):
            one_source = source[b] if source.ndim == 3 else source
            one_target = target[b] if target.ndim == 3 else target
            r, t = weighted_procrustes(one_source, one_target, None if weight is None else weight[b])
            np.testing.assert_allclose(rotations[b], r, atol=1e-10)
            np.testing.assert_allclose(translations[b], t, atol=1e-8)
    rotations, translations = batched_weighted_procrustes(shared, paired, (weights > 0).astype(float))
    for b, motion in enumerate(motions):
        np.testing.assert_allclose(to_matrix(rotations[b], translations[b]), motion, atol=1e-9)
