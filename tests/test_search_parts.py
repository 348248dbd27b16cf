"""Building blocks of the global search and of the fast local loop."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

import esmicp
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.nearest_grid import NearestGrid
from esmicp.globalreg import search as global_search
from esmicp.globalreg.config import DEFAULT
from esmicp.globalreg.scan import NORMALS_FROM_KEYPOINTS
from esmicp.core.procrustes import batched_rotation_from_cross_covariance
from esmicp.globalreg.rotation_search import NeighbourGraph, batched_esm, so3_grid
from esmicp.methods import ConvergenceCriteria, EsmEstimator, SigmaSchedule
from esmicp.methods.local import refine
from esmicp.metrics import random_rotation, rotation_error_deg
from esmicp_lab.bench.protocols import make_trial
from esmicp.shapes import asymmetric_shape


def test_nearest_grid_returns_an_almost_nearest_point_with_its_exact_distance():
    rng = np.random.default_rng(0)
    target = asymmetric_shape(1500, rng)
    queries = asymmetric_shape(5000, rng) @ random_rotation(rng).T * 1.3
    cell = 0.03
    grid = NearestGrid(target, cell, margin=0.5)
    distances, indices = grid.query(queries)
    np.testing.assert_allclose(distances, np.linalg.norm(queries - target[indices], axis=1))
    exact, _ = cKDTree(target).query(queries)
    assert (distances >= exact - 1e-12).all()
    inside = (queries > target.min(axis=0) - 0.5).all(axis=1) & (queries < target.max(axis=0) + 0.5).all(axis=1)
    assert (distances[inside] - exact[inside]).max() <= 2 * np.sqrt(3) * cell


def _scipy_lookup(grid: NearestGrid, target: np.ndarray) -> np.ndarray:
    """The lookup table as SciPy's Euclidean feature transform gives it: each cell's nearest occupied
    cell, and there the last target point (in input order)."""
    from scipy.ndimage import distance_transform_edt

    cells = grid._cell_index(target)
    occupied = np.zeros(int(np.prod(grid.shape)), dtype=bool)
    occupied[cells] = True
    last = np.empty(len(occupied), dtype=np.intp)
    last[cells] = np.arange(len(target))
    nearest = distance_transform_edt(~occupied.reshape(grid.shape), return_distances=False, return_indices=True)
    return last[np.ravel_multi_index(tuple(nearest), tuple(grid.shape)).ravel()]


@pytest.mark.parametrize("cloud", ["uniform", "lattice", "sphere", "shape"])
def test_nearest_grid_table_equals_scipys_feature_transform(cloud):
    """The compiled table against ``scipy.ndimage.distance_transform_edt``: the same target point
    in every cell, ties (many on a lattice) included."""
    rng = np.random.default_rng(11)
    for trial in range(12):
        count = int(rng.integers(1, 600))
        if cloud == "uniform":
            target = rng.random((count, 3)) * rng.uniform(0.5, 3.0, size=3)
        elif cloud == "lattice":
            target = rng.integers(0, 6, size=(count, 3)).astype(float)
        elif cloud == "sphere":
            target = rng.normal(size=(count, 3))
            target /= np.linalg.norm(target, axis=1, keepdims=True)
        else:
            target = asymmetric_shape(max(count, 10), rng)
        extent = float(np.ptp(target, axis=0).max()) + 1.0
        grid = NearestGrid(target, rng.uniform(0.02, 0.2) * extent, margin=rng.uniform(0.0, 0.5) * extent)
        np.testing.assert_array_equal(grid.lookup, _scipy_lookup(grid, target))


def _scipy_spacing(points: np.ndarray, max_samples: int = 5000) -> float:
    """``NearestNeighbors.spacing`` as SciPy's k-nearest query gives it (duplicates looked past)."""
    sample = points[np.linspace(0, len(points) - 1, min(len(points), max_samples)).astype(np.intp)]
    distinct = np.unique(points, axis=0)
    if len(distinct) < 2:
        return 0.0
    distances = cKDTree(distinct).query(sample, k=2)[0][:, 1]
    return float(np.median(distances))


@pytest.mark.parametrize("count", [2, 3, 50, 2000, 7000])
def test_spacing_matches_scipys_k_nearest(count):
    """The compiled spacing equals SciPy's exactly: plain clouds, a coarse lattice (exact copies and
    equidistant neighbours), half of the points on one spot; 7,000 points use a strided sample."""
    rng = np.random.default_rng(count)
    plain = rng.random((count, 3))
    lattice = np.round(plain * 4) / 4
    piled = plain.copy()
    piled[: count // 2] = piled[0]
    for points in (plain, lattice, piled):
        assert NearestNeighbors(points).spacing() == _scipy_spacing(points)
    assert NearestNeighbors(np.zeros((5, 3))).spacing() == 0.0


def test_overlap_confidence_counts_as_scipys_tree_does():
    """The confidence (compiled tree) against the same counts from SciPy's KD-tree, at the truth,
    near it and far from it."""
    from esmicp.trust.policy import DEFAULT_POLICY as trust
    from esmicp.core.features import estimate_normals
    from esmicp.core.keypoints import Keypoints
    from esmicp.trust.confidence import overlap_confidence

    def reference(transformation, keypoints):
        rotation, translation = transformation[:3, :3], transformation[:3, 3]
        sharpness, spread, shares = [], [], []
        for moved, fixed in ((keypoints.source @ rotation.T + translation, keypoints.target),
                             ((keypoints.target - translation) @ rotation, keypoints.source)):
            distances, nearest = cKDTree(fixed).query(moved)
            overlap = np.count_nonzero(distances <= trust.overlap_voxels * keypoints.voxel)
            coincide = distances <= DEFAULT.scan.keypoint.coincide_voxels * keypoints.voxel
            if overlap < 3 or np.count_nonzero(coincide) < 3:
                return 0.0
            sharpness.append(np.count_nonzero(coincide) / overlap)
            shares.append(np.count_nonzero(coincide) / len(moved))
            touched = nearest[coincide]
            if len(touched) > trust.spread_points:
                touched = touched[np.linspace(0, len(touched) - 1, trust.spread_points).astype(int)]
            normals = estimate_normals(fixed, k=trust.spread_normal_neighbours,
                                       radius=trust.spread_normal_radius_voxels * keypoints.voxel)[touched]
            spread.append(np.sort(np.linalg.eigvalsh(np.cov(normals.T, bias=True) + np.outer(*[normals.mean(axis=0)] * 2))))

        def ramp(value, bounds):
            return float(np.clip((value - bounds[0]) / (bounds[1] - bounds[0]), 0.0, 1.0))

        sharp = ramp(min(sharpness), DEFAULT.sharpness_range)
        if min(shares) >= trust.spread_below:
            return sharp
        return min(sharp, *(ramp(values[1], DEFAULT.spread_range) for values in spread),
                   *(ramp(values[0], DEFAULT.third_range) for values in spread))

    rng = np.random.default_rng(12)
    target = asymmetric_shape(2000, rng)
    values = set()
    for angle in (0.0, 2.0, 5.0, 20.0, 90.0):
        truth = esmicp.core.procrustes.to_matrix(random_rotation(rng, angle), rng.normal(size=3) * 0.01 * angle)
        source = (target - truth[:3, 3]) @ truth[:3, :3] + rng.normal(size=target.shape) * 0.002
        keypoints = Keypoints.of(source[rng.permutation(len(source))], target, NearestNeighbors(target).spacing(),
                                 DEFAULT.keypoints, DEFAULT.scan.keypoint.min_voxel_spacings)
        for shift in (0.0, 0.9, 1.05, 1.2, 30.0):  # keypoint voxels along x
            pose = esmicp.core.procrustes.to_matrix(np.eye(3), [shift * keypoints.voxel, 0.0, 0.0]) @ truth
            values.add(overlap_confidence(pose, keypoints, config=DEFAULT))
            assert overlap_confidence(pose, keypoints, config=DEFAULT) == pytest.approx(reference(pose, keypoints), abs=1e-12)
    assert len(values) > 2  # confident, unsure and wrong poses alike


def _room(rng: np.random.Generator, count: int) -> np.ndarray:
    """``3 count`` points on a 4 x 3 x 2.5 room's floor (z = 0) and two walls (y = 0, x = 0)."""
    u, v = rng.uniform(0.0, 1.0, size=(2, count))
    zero = np.zeros(count)
    return np.vstack([np.column_stack([4 * u, 3 * v, zero]), np.column_stack([4 * u, zero, 2.5 * v]),
                      np.column_stack([zero, 3 * v, 2.5 * u])])


def test_a_floor_slid_over_a_floor_is_not_confident(monkeypatch):
    """A patch of floor slid along the target's floor coincides with it as sharply as at the truth,
    and the sharpness alone read that as confident; but all its coincident normals point one way,
    which fixes 3 of the 6 degrees of freedom, so the confidence is now low
    (``SearchConfig.spread_range``). A room (floor and two walls) at the truth stays
    confident. Fails if the spread term is dropped."""
    from esmicp.core.procrustes import to_matrix
    from esmicp.globalreg import scan
    from esmicp.core.keypoints import Keypoints
    from esmicp.trust.confidence import overlap_confidence

    rng = np.random.default_rng(21)

    target, source = _room(rng, 3000), _room(rng, 3000)
    floor = source[(source[:, 2] == 0.0) & (source[:, 0] > 1.0) & (source[:, 1] > 1.0)]
    spacing = NearestNeighbors(target).spacing()
    slid = to_matrix(np.eye(3), [-0.6, -0.4, 0.0])  # stays on the target's floor
    assert overlap_confidence(np.eye(4), Keypoints.of(source, target, spacing,
                                                      DEFAULT.keypoints, DEFAULT.scan.keypoint.min_voxel_spacings), config=DEFAULT) >= DEFAULT.confident
    floor_keys = Keypoints.of(floor, target, spacing, DEFAULT.keypoints, DEFAULT.scan.keypoint.min_voxel_spacings)
    assert overlap_confidence(slid, floor_keys, config=DEFAULT) < DEFAULT.confident
    spread_off = replace(DEFAULT, spread_range=(-2.0, -1.0), third_range=(-2.0, -1.0))
    assert overlap_confidence(slid, floor_keys, config=spread_off) >= DEFAULT.confident


def test_a_corner_of_floor_and_wall_slid_along_their_line_is_not_confident(monkeypatch):
    """A floor and one wall slid along the line where they meet coincide as sharply as at the
    truth, and their normals span two directions (the middle eigenvalue is the wall's share), so
    the spread term read that as confident; but the slide along the line is free, and the smallest
    eigenvalue is 0 (``SearchConfig.third_range``; on the 3DMatch crops, two wrong
    poses 120 degrees and 1 m off). A room (floor and two walls) at the truth stays
    confident. Fails if the third-direction term is dropped."""
    from esmicp.core.procrustes import to_matrix
    from esmicp.globalreg import scan
    from esmicp.core.keypoints import Keypoints
    from esmicp.trust.confidence import overlap_confidence

    rng = np.random.default_rng(22)

    target, source = _room(rng, 3000), _room(rng, 3000)
    # The source's floor and its wall y = 0, away from the wall x = 0: two planes meeting along x.
    corner = source[(source[:, 0] > 1.5) & (source[:, 0] < 3.0) & (source[:, 1] < 1.5) & (source[:, 2] < 1.2)]
    spacing = NearestNeighbors(target).spacing()
    slid = to_matrix(np.eye(3), [-0.7, 0.0, 0.0])  # along the line: stays on the target's floor and wall
    assert overlap_confidence(np.eye(4), Keypoints.of(source, target, spacing,
                                                      DEFAULT.keypoints, DEFAULT.scan.keypoint.min_voxel_spacings), config=DEFAULT) >= DEFAULT.confident
    corner_keys = Keypoints.of(corner, target, spacing, DEFAULT.keypoints, DEFAULT.scan.keypoint.min_voxel_spacings)
    assert overlap_confidence(slid, corner_keys, config=DEFAULT) < DEFAULT.confident
    third_off = replace(DEFAULT, third_range=(-2.0, -1.0))  # the third-direction term off
    assert overlap_confidence(slid, corner_keys, config=third_off) >= DEFAULT.confident


def test_distinct_selects_what_a_loop_over_rotation_angles_selects():
    """``_distinct`` (all pairwise angles at once) against a plain loop over
    :func:`~esmicp.core.procrustes.rotation_angle`, on clustered poses (many pairs near the
    threshold)."""
    from esmicp.core.procrustes import rotation_angle, to_matrix
    from esmicp.globalreg.config import DEFAULT

    distinct_deg = DEFAULT.verification.distinct_rotation_deg

    def loop(transformations, order, limit):
        kept = []
        for index in order:
            if all(np.degrees(rotation_angle(transformations[k, :3, :3].T @ transformations[index, :3, :3]))
                   > distinct_deg for k in kept):
                kept.append(int(index))
                if len(kept) == limit:
                    break
        return kept

    rng = np.random.default_rng(13)
    for _ in range(200):
        count = int(rng.integers(1, 70))
        centres = [random_rotation(rng) for _ in range(max(1, count // 4))]
        transformations = np.stack([
            to_matrix(random_rotation(rng, float(rng.uniform(0.0, 25.0))) @ centres[rng.integers(len(centres))],
                      rng.normal(size=3))
            for _ in range(count)
        ])
        order, limit = rng.permutation(count), int(rng.integers(1, 20))
        found = global_search._distinct(transformations, order, limit, distinct_deg)
        assert found == loop(transformations, order, limit)


def test_batched_kabsch_matches_one_at_a_time():
    from esmicp.core.procrustes import rotation_from_cross_covariance

    covariances = np.random.default_rng(1).normal(size=(50, 3, 3))
    batched = batched_rotation_from_cross_covariance(covariances)
    for one, covariance in zip(batched, covariances):
        np.testing.assert_allclose(one, rotation_from_cross_covariance(covariance), atol=1e-12)


def test_batched_esm_pulls_every_nearby_start_to_the_truth():
    rng = np.random.default_rng(2)
    target = asymmetric_shape(2000, rng)
    truth = random_rotation(rng, 180.0)
    source = target @ truth  # so that R_true = truth maps source onto target
    starts = np.stack([random_rotation(rng, 25.0) @ truth for _ in range(8)])
    index = NearestNeighbors(target)
    rotations, translations, distances = batched_esm(
        source, index, starts, np.zeros((8, 3)), iterations=30, sigma_floor=2 * index.spacing()
    )
    for rotation in rotations:
        assert np.degrees(np.arccos(np.clip((np.trace(rotation.T @ truth) - 1) / 2, -1, 1))) < 0.5
    assert distances.shape == (8, len(source))


def _reference_batched_esm(source, lookup, rotations, translations, iterations, sigma_floor, fine_iterations,
                           sigma_factor=3.0):
    """Plain NumPy / SciPy batched ESM: ``lookup.query(points) -> (distances, indices)`` from scratch every
    iteration, ``numpy.median``, weights normalised to sum 1, SVD Kabsch."""
    count = len(rotations)
    for iteration in range(iterations + 1):
        moved = np.matmul(source[None], np.swapaxes(rotations, 1, 2)) + translations[:, None, :]
        distances, indices = lookup.query(moved.reshape(-1, 3))
        distances = distances.reshape(count, -1)
        if iteration == iterations:
            return rotations, translations, distances
        matched = lookup.points[indices].reshape(moved.shape)
        fine = iteration >= iterations - fine_iterations
        median = np.median(distances, axis=1)
        sigma = np.full(count, sigma_floor) if fine else np.maximum(sigma_floor, sigma_factor * median)
        squared = distances**2
        weights = np.exp(-(squared - squared.min(axis=1, keepdims=True)) / (2.0 * sigma[:, None] ** 2))
        weights = (weights / weights.sum(axis=1, keepdims=True))[:, :, None]
        moved_centroid, matched_centroid = (weights * moved).sum(axis=1), (weights * matched).sum(axis=1)
        cross = np.matmul(np.swapaxes(weights * (moved - moved_centroid[:, None]), 1, 2),
                          matched - matched_centroid[:, None])
        step = batched_rotation_from_cross_covariance(cross)
        rotations = step @ rotations
        translations = (step @ (translations - moved_centroid)[:, :, None])[:, :, 0] + matched_centroid


class _TreeLookup:
    def __init__(self, target):
        self.points, self._tree = target, cKDTree(target)

    def query(self, points):
        return self._tree.query(points)


@pytest.mark.parametrize("lookup", ["tree", "seeded tree", "grid"])
@pytest.mark.parametrize("count", [199, 200])  # odd and even: the median's two definitions
def test_compiled_batched_esm_matches_a_numpy_reference(lookup, count):
    """The compiled batched ESM (warm-started tree queries, their first ones from scratch or from
    the lookup grid's answers; or the lookup grid) against plain NumPy / SciPy: the same poses to
    1e-9 along 10 annealed then 4 fixed-sigma iterations from starts up to 60 degrees off, on one
    thread and two alike (bit for bit)."""
    rng = np.random.default_rng(6)
    target = asymmetric_shape(1500, rng)
    truth = random_rotation(rng, 180.0)
    source = asymmetric_shape(count, rng) @ truth
    starts = np.stack([random_rotation(rng, 60.0) @ truth for _ in range(12)])
    translations = rng.normal(scale=0.05, size=(12, 3))
    options = dict(iterations=14, sigma_floor=0.01, fine_iterations=4)
    if lookup == "grid":
        index = reference_lookup = NearestGrid(target, 0.02, margin=0.3)
    else:
        index, reference_lookup = NearestNeighbors(target), _TreeLookup(target)
        if lookup == "seeded tree":
            options["seeds"] = NearestGrid(target, 0.02, margin=0.3)
    rotations, moved, distances = batched_esm(source, index, starts, translations, workers=1, **options)
    two = batched_esm(source, index, starts, translations, workers=2, **options)
    for mine, theirs in zip((rotations, moved, distances), two):
        np.testing.assert_array_equal(mine, theirs)
    reference_options = {key: value for key, value in options.items() if key != "seeds"}
    expected = _reference_batched_esm(source, reference_lookup, starts, translations, **reference_options)
    np.testing.assert_allclose(rotations, expected[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(moved, expected[1], rtol=0, atol=1e-9)
    np.testing.assert_allclose(distances, expected[2], rtol=0, atol=1e-9)
    assert np.ptp(distances.mean(axis=1)) > 1e-3  # the starts did not all end at one pose


def test_seeds_over_other_points_are_refused():
    rng = np.random.default_rng(14)
    target = asymmetric_shape(300, rng)
    with pytest.raises(ValueError, match="same target points"):
        batched_esm(target, NearestNeighbors(target), np.eye(3)[None], np.zeros((1, 3)), iterations=2,
                    sigma_floor=0.01, seeds=NearestGrid(target.copy(), 0.05, margin=0.1))


def test_neighbour_graph_matches_ckdtree_with_duplicates():
    """The graph's lists are the k nearest target points (SciPy's distances), its radii the squared
    distance to the k-th, on a cloud with repeated points (ties)."""
    rng = np.random.default_rng(7)
    target = np.concatenate([asymmetric_shape(900, rng), np.repeat(rng.normal(size=(5, 3)), 20, axis=0)])
    graph = NeighbourGraph.of(NearestNeighbors(target), k=12)
    expected, _ = cKDTree(target).query(target, k=12)
    found = np.sort(np.linalg.norm(target[graph.neighbours] - target[:, None], axis=2), axis=1)
    np.testing.assert_allclose(found, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(graph.radii, expected[:, -1] ** 2, rtol=1e-12, atol=1e-15)


def test_batched_esm_without_a_graph_finds_the_same_neighbours():
    """With no neighbour graph (:meth:`NeighbourGraph.none`) the tree answers every query: the
    same poses and distances as with the graph, which only spares queries."""
    rng = np.random.default_rng(21)
    target = asymmetric_shape(2000, rng)
    source = target[rng.choice(len(target), 300, replace=False)] + rng.normal(scale=0.002, size=(300, 3))
    index = NearestNeighbors(target)
    starts = np.stack([random_rotation(rng, 20.0) for _ in range(4)])
    translations = rng.normal(scale=0.05, size=(4, 3))
    options = dict(iterations=8, sigma_floor=0.01, fine_iterations=4)
    with_graph = batched_esm(source, index, starts, translations, graph=NeighbourGraph.of(index), **options)
    without = batched_esm(source, index, starts, translations, graph=NeighbourGraph.none(), **options)
    assert NeighbourGraph.none().empty and not NeighbourGraph.of(index).empty
    for found, expected in zip(without, with_graph):
        np.testing.assert_array_equal(found, expected)
    assert np.ptp(with_graph[2].mean(axis=1)) > 1e-4  # the starts did not all end at one pose


def test_batched_esm_keeps_a_non_finite_pose_to_itself():
    """A NaN start ends as NaN distances without touching the other hypotheses (no out-of-range
    neighbour is read)."""
    target = asymmetric_shape(500, 8)
    starts = np.stack([np.eye(3), np.full((3, 3), np.nan)])
    _, _, alone = batched_esm(target[:100], NearestNeighbors(target), starts[:1], np.zeros((1, 3)), iterations=3,
                              sigma_floor=0.05)
    _, _, distances = batched_esm(target[:100], NearestNeighbors(target), starts, np.zeros((2, 3)), iterations=3,
                                  sigma_floor=0.05)
    assert np.isnan(distances[1]).all()
    np.testing.assert_array_equal(distances[0], alone[0])


class _PlainEsm(EsmEstimator):
    """ESM without Anderson acceleration, for comparison."""

    accelerable = False


def test_anderson_acceleration_reaches_an_equally_good_pose_in_fewer_iterations():
    rng = np.random.default_rng(3)
    target = asymmetric_shape(3000, rng)
    truth = random_rotation(rng, 15.0)
    source = asymmetric_shape(3000, rng) @ truth  # resampled: the optimum is flat near the truth
    index = NearestNeighbors(target)
    schedule = SigmaSchedule.constant(2 * index.spacing())
    common = dict(init=np.eye(4), criteria=ConvergenceCriteria(400, 1e-10), scale=3.0)
    fast = refine(source, index, EsmEstimator(schedule), **common)
    plain = refine(source, index, _PlainEsm(schedule), **common)
    assert fast.converged and plain.converged
    assert fast.num_iterations < plain.num_iterations, (fast.num_iterations, plain.num_iterations)
    objective = EsmEstimator(schedule).objective
    fast_objective = objective(index.query(source @ fast.transformation[:3, :3].T + fast.transformation[:3, 3])[0])
    plain_objective = objective(index.query(source @ plain.transformation[:3, :3].T + plain.transformation[:3, 3])[0])
    assert fast_objective >= plain_objective * (1 - 1e-4), (fast_objective, plain_objective)
    true_pose = np.eye(4)
    true_pose[:3, :3] = truth
    assert rotation_error_deg(fast.transformation, true_pose) < 0.5
    assert rotation_error_deg(fast.transformation, plain.transformation) < 0.2


def test_auto_stops_after_the_rotation_search_on_a_confident_full_overlap(monkeypatch):
    called = []
    monkeypatch.setattr(global_search, "_feature_candidates", lambda work: called.append(1) or [])
    rng = np.random.default_rng(4)
    target = asymmetric_shape(2000, rng)
    source = target[rng.permutation(len(target))] @ random_rotation(rng).T
    estimate = global_search.global_estimate(source, target, rng=np.random.default_rng(0))
    assert estimate.score >= DEFAULT.confident_score
    assert called == [] and set(estimate.strategies) == {"rotation-search"}


def test_features_strategy_falls_back_to_the_rotation_search_when_no_match_is_found(monkeypatch):
    monkeypatch.setattr(global_search, "_feature_candidates", lambda work: [])
    trial = make_trial("shuffled", asymmetric_shape(3000, 5), seed=1, index=0)
    result = esmicp.register(trial.source, trial.target, init="features")
    assert result.init == "global:rotation-search"
    assert rotation_error_deg(result.transformation, trial.T_target_source) < 1.0


@pytest.mark.parametrize("count", [1, 7, 64])
def test_so3_grid_is_made_of_rotations(count):
    grid = so3_grid(count)
    assert grid.shape == (count, 3, 3)
    np.testing.assert_allclose(np.linalg.det(grid), 1.0)


def _terrain(seed: int, side: int = 45) -> np.ndarray:
    """A bumpy square sheet (unit side, ``side`` x ``side`` points, a little noise)."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, 1, side), np.linspace(0, 1, side))
    z = np.zeros_like(x)
    for _ in range(25):
        cx, cy, width, height = rng.uniform(0, 1), rng.uniform(0, 1), rng.uniform(0.04, 0.15), rng.uniform(-0.1, 0.1)
        z += height * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * width * width))
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    return points + rng.normal(scale=0.001, size=points.shape)


def _searches(monkeypatch, source, target, config, scattered=None):
    """``(estimate, searches run)`` of ``scan_estimate_until_confident`` (every search counted)."""
    from esmicp.globalreg import scan

    run = []
    original = scan.scan_estimate

    def counted(*args, **kwargs):
        run.append(kwargs.get("voxel"))
        return original(*args, **kwargs)

    monkeypatch.setattr(scan, "scan_estimate", counted)
    found = scan.scan_estimate_until_confident(source, target, spacing=NearestNeighbors(target).spacing(),
                                               config=config, scattered=scattered)
    return found, len(run)


#: Keypoint counts small enough that 2,000-point clouds have voxels to search beyond the standard one.
_SMALL = replace(DEFAULT, keypoints=600, scan=replace(DEFAULT.scan, last_keypoints=(1200, 300)))


def test_a_pair_sharing_nothing_ends_after_the_standard_searches_with_its_reason(monkeypatch):
    # An object onto a bumpy sheet: no pose makes them coincide, so no search at the standard voxel
    # gives a pose with any overlap confidence, and the searches at other voxels are not run.
    source, target = 0.5 * asymmetric_shape(2000, np.random.default_rng(1)), _terrain(2)
    found, run = _searches(monkeypatch, source, target, _SMALL)
    assert found.unsupported is not None
    assert found.confidence <= _SMALL.verification.support_confidence
    assert run == len(NORMALS_FROM_KEYPOINTS)
    # Clouds carrying scattered points (their keypoint confidence is blind): every search runs.
    scattered, every = _searches(monkeypatch, source, target, _SMALL, scattered=lambda: True)
    assert scattered.unsupported is None
    assert every == len(NORMALS_FROM_KEYPOINTS) + len(_SMALL.scan.last_keypoints)


def test_a_registerable_pair_is_untouched_by_the_support_rule(monkeypatch):
    target = _terrain(3)
    source = (target - 0.5) @ random_rotation(np.random.default_rng(0)).T + 0.3
    found, run = _searches(monkeypatch, source, target, _SMALL)
    without, _ = _searches(monkeypatch, source, target, replace(_SMALL, verification=replace(
        _SMALL.verification, support_confidence=-1.0)))
    assert found.unsupported is None
    np.testing.assert_array_equal(found.transformations, without.transformations)


def test_a_search_stopped_for_want_of_support_is_never_trusted():
    from esmicp.trust.judge import Verdict

    sure = Verdict.of(converged=True, num_iterations=5, confidence=0.95)
    stopped = Verdict.of(converged=True, num_iterations=5, confidence=0.95, unsupported="no support: nothing coincided")
    assert sure.trusted and not stopped.trusted
    assert [doubt.kind for doubt in stopped.doubts] == ["no support"]
    assert [doubt.kind for doubt in stopped.at(0.0)] == ["no support"]
