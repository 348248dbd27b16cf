"""``esmicp.register`` end to end, on real clouds (ModelNet40, Stanford bunny) with known motions,
plus its result record, options and argument checking."""

from __future__ import annotations

import itertools
import json
import warnings

import numpy as np
import pytest
from conftest import require_shared
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import esmicp
from esmicp import IndexAlignmentWarning, InvalidInputError, NonFinitePointsWarning, RegistrationResult
from esmicp.config import RefineConfig, RegistrationConfig
from esmicp.core.procrustes import apply, rotation_angle, to_matrix, weighted_procrustes
from esmicp.methods.local import IterationState

#: The refinement's defaults (:class:`esmicp.config.RefineConfig`).
REFINE = RefineConfig()


def refined_on(points: int, **changes) -> RegistrationConfig:
    """A registration config whose strided stages run on ``points`` strided source points."""
    return RegistrationConfig(refine=RefineConfig(strided_points=points, **changes))


MODELNET = {
    "airplane": "modelnet40/airplane/airplane_0126.txt",
    "chair": "modelnet40/chair/chair_0848.txt",
    "guitar": "modelnet40/guitar/guitar_0165.txt",
}
BUNNY = "bunny/bun_zipper_res2.ply"

_CACHE: dict[str, np.ndarray] = {}


def load(name: str) -> np.ndarray:
    """Full cloud by short name (read once per session)."""
    if name not in _CACHE:
        if name == "bunny":
            import plyfile

            vertex = plyfile.PlyData.read(str(require_shared(BUNNY)))["vertex"]
            _CACHE[name] = np.column_stack([vertex["x"], vertex["y"], vertex["z"]]).astype(np.float64)
        else:
            _CACHE[name] = np.loadtxt(require_shared(MODELNET[name]), delimiter=",")[:, :3]
    return _CACHE[name]


def subsample(name: str, count: int, seed: int = 0) -> np.ndarray:
    cloud = load(name)
    return cloud[np.random.default_rng(seed).choice(len(cloud), count, replace=False)]


def diagonal(cloud: np.ndarray) -> float:
    return float(np.linalg.norm(cloud.max(axis=0) - cloud.min(axis=0)))


def small_motion(seed: int, scale: float, low_deg: float = 10.0, high_deg: float = 20.0):
    """A rotation of low..high degrees about a random axis and a translation of ~5% of ``scale``."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rotation = Rotation.from_rotvec(np.radians(rng.uniform(low_deg, high_deg)) * axis).as_matrix()
    translation = rng.normal(size=3) * 0.05 * scale / np.sqrt(3)
    return rotation, translation


def move_to_source(target_points: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Source such that ``T_true = [R | t]`` maps it onto ``target_points``."""
    return (target_points - translation) @ rotation


def rotation_error_deg(transformation: np.ndarray, rotation: np.ndarray) -> float:
    return float(np.degrees(rotation_angle(transformation[:3, :3].T @ rotation)))


def halves(cloud: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    order = np.random.default_rng(seed).permutation(len(cloud))
    half = len(cloud) // 2
    return cloud[order[:half]], cloud[order[half:]]


def with_outliers(points: np.ndarray, fraction: float, seed: int) -> np.ndarray:
    """Replace ``fraction`` of the points by uniform samples in their bounding box."""
    rng = np.random.default_rng(seed)
    out = points.copy()
    count = round(fraction * len(points))
    chosen = rng.choice(len(points), count, replace=False)
    out[chosen] = rng.uniform(points.min(axis=0), points.max(axis=0), (count, 3))
    return out


@pytest.fixture(scope="module")
def chair() -> np.ndarray:
    return subsample("chair", 1500, seed=1)


@pytest.fixture(scope="module")
def easy_pair(chair):
    """A shuffled, moved copy of the chair with its true transform."""
    rotation, translation = small_motion(42, diagonal(chair))
    source = move_to_source(chair, rotation, translation)[np.random.default_rng(42).permutation(len(chair))]
    return source, chair, to_matrix(rotation, translation)


# --------------------------------------------------------------------------------------------
# Accuracy on real data
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("shape", ["chair", "airplane", "bunny"])
@pytest.mark.parametrize("method", ["esm", "icp"])
def test_small_rotation_on_a_shuffled_copy(method, shape, seed):
    target = subsample(shape, 2000, seed)
    rotation, translation = small_motion(seed, diagonal(target))
    source = move_to_source(target, rotation, translation)[np.random.default_rng(seed).permutation(len(target))]
    result = esmicp.register(source, target, method=method, init="identity")
    error = rotation_error_deg(result.transformation, rotation)
    assert error < 0.5, f"{method} on {shape}: {error:.3f} deg"
    assert np.linalg.norm(result.translation - translation) < 1e-3 * diagonal(target)
    assert result.converged
    assert result.fitness == 1.0


# The bunny is left out of the disjoint-halves checks on purpose: for random halves of
# bun_zipper_res2 the nearest-neighbour objective itself has its minimum 2-3 degrees away from the
# truth (measured: ICP and ESM started AT the true pose drift to 2.4-2.9 degrees, at a lower RMS than
# the truth), a property of the data and not of the solver.
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("shape", ["chair", "airplane", "guitar"])
@pytest.mark.parametrize("method", ["esm", "icp"])
def test_small_rotation_on_disjoint_halves(method, shape, seed):
    cloud = subsample(shape, 4000, seed)
    target_half, source_half = halves(cloud, seed)
    rotation, translation = small_motion(100 + seed, diagonal(cloud))
    source = move_to_source(source_half, rotation, translation)
    result = esmicp.register(source, target_half, method=method, init="identity")
    error = rotation_error_deg(result.transformation, rotation)
    assert error < 2.0, f"{method} on {shape} halves: {error:.3f} deg"
    assert np.linalg.norm(result.translation - translation) < 0.02 * diagonal(cloud)


def test_esm_paper_recovers_any_pose_on_an_index_aligned_copy():
    target = subsample("chair", 2000, seed=3)
    errors = []
    for seed in range(20):
        rotation = Rotation.random(random_state=seed).as_matrix()
        translation = np.random.default_rng(seed).uniform(-1000.0, 1000.0, 3)
        source = move_to_source(target, rotation, translation)  # same order as the target
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # in particular: no IndexAlignmentWarning
            result = esmicp.register(source, target, method="esm-paper", init="identity")
        errors.append(rotation_error_deg(result.transformation, rotation))
        assert np.linalg.norm(result.translation - translation) < 1e-6, f"seed {seed}"
        assert result.converged, f"seed {seed}: {result.message}"
    assert max(errors) < 1e-4, f"rotation errors (deg): {np.round(errors, 6).tolist()}"


def test_esm_paper_fails_once_the_source_is_shuffled():
    # documents the method's limitation: the same problem as above, the source merely reordered
    target = subsample("chair", 2000, seed=3)
    errors = []
    for seed in range(10):
        rotation = Rotation.random(random_state=seed).as_matrix()
        translation = np.random.default_rng(seed).uniform(-1000.0, 1000.0, 3)
        source = move_to_source(target, rotation, translation)
        source = source[np.random.default_rng(50 + seed).permutation(len(source))]
        with pytest.warns(IndexAlignmentWarning):
            result = esmicp.register(source, target, method="esm-paper", init="identity")
        errors.append(rotation_error_deg(result.transformation, rotation))
    failures = sum(error > 2.0 for error in errors)
    assert failures >= 8, f"esm-paper failed on only {failures}/10 shuffled copies: {np.round(errors, 2).tolist()}"
    # ...while esm on the same shuffled clouds is fine from a small offset (sanity of the setup)
    rotation, translation = small_motion(7, diagonal(target))
    source = move_to_source(target, rotation, translation)[np.random.default_rng(7).permutation(len(target))]
    assert rotation_error_deg(esmicp.register(source, target, method="esm", init="identity").transformation, rotation) < 0.5


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("shape", ["airplane", "guitar"])
def test_esm_is_robust_to_outliers_where_icp_is_not(shape, seed):
    cloud = subsample(shape, 4000, seed)
    target_half, source_half = halves(cloud, seed)
    rotation, translation = small_motion(200 + seed, diagonal(cloud))
    source = with_outliers(move_to_source(source_half, rotation, translation), 0.3, seed)
    esm_error = rotation_error_deg(esmicp.register(source, target_half, method="esm", init="identity").transformation, rotation)
    icp_error = rotation_error_deg(esmicp.register(source, target_half, method="icp", init="identity").transformation, rotation)
    assert esm_error < 1.0, f"esm {esm_error:.3f} deg (icp {icp_error:.3f} deg)"
    assert esm_error < icp_error, f"esm {esm_error:.3f} deg, icp {icp_error:.3f} deg"


def test_a_large_source_is_refined_on_a_subsample_where_every_point_takes_it():
    """After a global search, a source above twice ``RefineConfig.strided_points`` is refined on a
    strided subsample: the pose is where a refinement of every point started from it stays, and
    ``max_iterations`` bounds every stage together. (A smaller subsample than the default, so that
    the bunny's 8k points take that path.)"""
    strided = refined_on(2000)
    target = load("bunny")
    assert len(target) > 2 * 2000
    rotation, translation = small_motion(5, diagonal(target), 30.0, 60.0)
    source = move_to_source(target, rotation, translation)[np.random.default_rng(5).permutation(len(target))]
    result = esmicp.register(source, target, config=strided)
    refine = next(stage for stage in result.stages if stage.name == "refine")
    assert refine.points == 2000 and refine.decided["tolerance"] == strided.refine.strided_tolerance
    np.testing.assert_array_equal(refine.pose, result.transformation)
    assert rotation_error_deg(result.transformation, rotation) < 0.05
    spacing = float(np.median(cKDTree(target).query(target, k=2)[0][:, 1]))
    # Every point from the start: a subsample as large as the source.
    full = esmicp.register(source, target, init=result.transformation, config=refined_on(len(source)))
    assert next(stage for stage in full.stages if stage.name == "refine").points == len(source)
    assert rotation_error_deg(full.transformation, result.transformation[:3, :3]) < 0.05
    assert np.linalg.norm(full.transformation[:3, 3] - result.transformation[:3, 3]) < 0.1 * spacing
    capped = esmicp.register(source, target, max_iterations=3, config=strided)
    assert capped.num_iterations == sum(stage.iterations for stage in capped.stages) <= 3


def test_a_large_source_from_a_given_start_is_refined_on_a_subsample():
    """From a given start, a source above twice ``strided_points`` takes the same strided run as
    after a global search (no ``esm-plane`` stage, the caller's tolerance kept on the
    subsample): it ends where a refinement of every point from that start ends, and each
    ``method`` but ``esm-paper`` (whose pairs are by index) takes that path. (A smaller
    subsample than the default, so that the bunny's 8k points take it; on a 313k-point 3DMatch
    fragment the strided run made a given start 4-5x faster, ``docs/speed.md``.)"""
    target = load("bunny")
    rotation, translation = small_motion(5, diagonal(target), 30.0, 60.0)
    source = move_to_source(target, rotation, translation)[np.random.default_rng(5).permutation(len(target))]
    start = to_matrix(Rotation.from_rotvec([0.0, 0.0, np.radians(4.0)]).as_matrix() @ rotation, translation)
    spacing = float(np.median(cKDTree(target).query(target, k=2)[0][:, 1]))
    for method in ("esm", "icp", "esm-plane"):
        given = esmicp.register(source, target, init=start, method=method, config=refined_on(2000))
        names = [stage.name for stage in given.stages]
        assert names == ["prepare", "start", "refine", "evaluate", "judge"], (method, names)  # no plane stage
        assert given.stages[2].points == 2000 and given.stages[2].decided["tolerance"] == 1e-8, method
        # every point from the start
        full = esmicp.register(source, target, init=start, method=method, config=refined_on(len(source)))
        assert rotation_error_deg(given.transformation, full.transformation[:3, :3]) < 0.05, method
        assert np.linalg.norm(given.transformation[:3, 3] - full.transformation[:3, 3]) < 0.1 * spacing, method
        assert rotation_error_deg(given.transformation, rotation) < 0.1, method


def test_a_street_scan_slid_along_the_road_by_the_global_search_is_pulled_back():
    """The shared KITTI pair (124k points, 3-column ``.bin``): with seed 1 the global search places
    the scan about a metre along the road, which ``esm`` alone kept (0.90 m, over the 0.6 m
    criterion); the ``esm-plane`` iterations that now precede it on the subsample pull it back."""
    from esmicp_lab.bench.real_pairs import load_pair, pair_errors, read_pairs

    pair = next(p for p in read_pairs(require_shared("real_pairs")) if p.dataset == "kitti_00")
    source, target, truth = load_pair(pair, bin_columns=3)
    result = esmicp.register(source, target, rng=1)
    rotation_deg, translation_m = pair_errors(result.transformation, truth)
    plane = next(stage for stage in result.stages if stage.name == "plane")
    assert plane.points == REFINE.plane_points and plane.iterations > 0 and not plane.decided["undone"], plane
    assert rotation_deg < 5.0 and translation_m < 0.6, (rotation_deg, translation_m, result.message)


def test_different_sizes_work(chair):
    rotation, translation = small_motion(5, diagonal(chair))
    source = move_to_source(chair[:900], rotation, translation)  # a 900-point part of the 1500
    for method in ("esm", "icp"):
        result = esmicp.register(source, chair, method=method, init="identity")
        assert rotation_error_deg(result.transformation, rotation) < 0.5, method
    # and the other way round: fewer target than source points
    result = esmicp.register(move_to_source(chair, rotation, translation), chair[:1200], method="esm", init="identity")
    assert rotation_error_deg(result.transformation, rotation) < 2.0


# --------------------------------------------------------------------------------------------
# sigma
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method, sigma", [("esm", 0.05), ("esm", 3.0), ("esm-paper", 0.2), ("esm-paper", 1.5)])
def test_fixed_sigma_is_respected(easy_pair, method, sigma):
    source, target, _ = easy_pair
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IndexAlignmentWarning)  # esm-paper on a shuffled pair
        result = esmicp.register(source, target, method=method, sigma=sigma, record_history=True, max_iterations=10, init="identity")
    assert result.sigma == sigma
    assert all(record.sigma == sigma for record in result.history)


def test_automatic_sigma_and_icp_sigma(easy_pair):
    source, target, _ = easy_pair
    result = esmicp.register(source, target, method="esm", record_history=True, init="identity")
    spacing = float(np.median(cKDTree(target).query(target, k=2)[0][:, 1]))
    sigmas = [record.sigma for record in result.history]
    assert all(sigma >= 2.0 * spacing * (1 - 1e-12) for sigma in sigmas)
    assert sigmas[0] > sigmas[-1]  # anneals from broad to the floor
    assert result.sigma == sigmas[-1]
    icp = esmicp.register(source, target, method="icp", record_history=True, init="identity")
    assert icp.sigma is None
    assert all(record.sigma is None for record in icp.history)


# --------------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["esm", "icp", "esm-paper"])
def test_inputs_are_never_mutated(easy_pair, method):
    source, target, _ = easy_pair
    source, target = source.copy(), target.copy()
    init = to_matrix(Rotation.from_rotvec([0.0, 0.0, 0.01]).as_matrix(), np.zeros(3))
    copies = source.copy(), target.copy(), init.copy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IndexAlignmentWarning)
        result = esmicp.register(source, target, method=method, init=init, max_iterations=20)
    np.testing.assert_array_equal(source, copies[0])
    np.testing.assert_array_equal(target, copies[1])
    np.testing.assert_array_equal(init, copies[2])
    assert not np.shares_memory(result.transformation, init)


def test_read_only_inputs_work(easy_pair):
    source, target, truth = easy_pair
    source, target = source.copy(), target.copy()
    init = np.eye(4)
    for array in (source, target, init):
        array.setflags(write=False)
    result = esmicp.register(source, target, init=init)
    assert rotation_error_deg(result.transformation, truth[:3, :3]) < 0.5
    writable = esmicp.register(source.copy(), target.copy(), init="identity")
    np.testing.assert_array_equal(result.transformation, writable.transformation)


def test_list_and_float32_inputs(easy_pair):
    source, target, truth = easy_pair
    from_lists = esmicp.register(source.tolist(), target.tolist(), init="identity")
    reference = esmicp.register(source, target, init="identity")
    np.testing.assert_array_equal(from_lists.transformation, reference.transformation)
    single = esmicp.register(source.astype(np.float32), target.astype(np.float32), init="identity")
    assert single.transformation.dtype == np.float64
    assert rotation_error_deg(single.transformation, truth[:3, :3]) < 0.5


def test_nan_rows_are_dropped_with_a_warning(easy_pair):
    source, target, _ = easy_pair
    dirty = source.copy()
    dirty[[3, 10, 500]] = np.nan
    dirty[700, 1] = np.inf
    keep = np.isfinite(dirty).all(axis=1)
    with pytest.warns(NonFinitePointsWarning, match=r"^source: dropped 4 point"):
        result = esmicp.register(dirty, target, init="identity")
    clean = esmicp.register(dirty[keep], target, init="identity")
    np.testing.assert_array_equal(result.transformation, clean.transformation)
    assert result.fitness == clean.fitness
    dirty_target = target.copy()
    dirty_target[0] = [np.nan, 0.0, 0.0]
    with pytest.warns(NonFinitePointsWarning, match=r"^target: dropped 1 point"):
        esmicp.register(source, dirty_target, init="identity")


# --------------------------------------------------------------------------------------------
# the result record
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["esm", "icp"])
def test_result_fields(easy_pair, method):
    source, target, truth = easy_pair
    result = esmicp.register(source, target, method=method, max_iterations=60, init="identity")
    assert isinstance(result, RegistrationResult)
    assert result.method == method
    assert result.transformation.shape == (4, 4)
    assert result.transformation.dtype == np.float64
    np.testing.assert_array_equal(result.transformation[3], [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(result.rotation, result.transformation[:3, :3])
    np.testing.assert_array_equal(result.translation, result.transformation[:3, 3])
    result.rotation[0, 0] = 99.0  # properties hand out copies
    assert result.transformation[0, 0] != 99.0
    np.testing.assert_allclose(result.rotation.T @ result.rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(result.rotation) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(result.transformation, truth, atol=1e-6)
    assert result.converged is True
    assert "converged" in result.message
    assert isinstance(result.num_iterations, int)
    assert 1 <= result.num_iterations <= 60
    assert 0.0 <= result.fitness <= 1.0
    assert result.inlier_rmse >= 0.0
    assert result.inlier_distance > 0.0
    assert result.runtime_s > 0.0
    assert result.history is None

    data = result.to_dict()
    text = json.dumps(data)
    loaded = json.loads(text)
    np.testing.assert_array_equal(np.array(loaded["transformation"]), result.transformation)
    for key in (
        "method",
        "converged",
        "num_iterations",
        "fitness",
        "inlier_rmse",
        "inlier_distance",
        "sigma",
        "message",
    ):
        assert loaded[key] == getattr(result, key), key
    assert "history" not in loaded


def test_result_is_frozen(easy_pair):
    source, target, _ = easy_pair
    result = esmicp.register(source, target, max_iterations=3, init="identity")
    with pytest.raises(AttributeError):
        result.converged = True  # type: ignore[misc]


@pytest.mark.parametrize("method", ["esm", "icp", "esm-paper"])
def test_history_records_every_iteration(easy_pair, method):
    source, target, _ = easy_pair
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IndexAlignmentWarning)
        result = esmicp.register(source, target, method=method, record_history=True, max_iterations=25, init="identity")
    history = result.history
    assert isinstance(history, tuple)
    assert len(history) == result.num_iterations
    assert [record.iteration for record in history] == list(range(1, result.num_iterations + 1))
    np.testing.assert_array_equal(history[-1].transformation, result.transformation)
    for record in history:
        assert record.rmse >= 0.0
        assert 0.0 <= record.weight_min <= record.weight_mean <= record.weight_max <= 1.0
        assert 0.0 <= record.effective_pairs <= len(source) * (1 + 1e-12)
    if method == "icp":
        assert all(record.effective_pairs == len(source) for record in history)
    data = json.loads(json.dumps(result.to_dict(include_history=True)))
    assert len(data["history"]) == result.num_iterations
    np.testing.assert_array_equal(np.array(data["history"][-1]["transformation"]), result.transformation)


def test_history_rmse_is_the_rms_distance_before_each_step(easy_pair):
    source, target, _ = easy_pair
    result = esmicp.register(source, target, method="icp", record_history=True, max_iterations=5, init="identity")
    tree = cKDTree(target)
    previous = np.eye(4)
    for record in result.history:
        distances, _ = tree.query(apply(previous, source))
        assert record.rmse == pytest.approx(np.sqrt(np.mean(distances**2)), rel=1e-12)
        previous = record.transformation
    # ICP never increases the RMS distance
    rmses = [record.rmse for record in result.history]
    assert all(later <= earlier * (1 + 1e-12) for earlier, later in itertools.pairwise(rmses))


# --------------------------------------------------------------------------------------------
# callback, init, max_iterations
# --------------------------------------------------------------------------------------------


def test_callback_sees_every_iteration(easy_pair):
    source, target, _ = easy_pair
    states: list[IterationState] = []
    result = esmicp.register(source, target, method="esm", callback=states.append, record_history=True, init="identity")
    assert len(states) == result.num_iterations
    assert all(isinstance(state, IterationState) for state in states)
    assert [state.iteration for state in states] == list(range(1, result.num_iterations + 1))
    for state, record in zip(states, result.history):
        np.testing.assert_array_equal(state.transformation, record.transformation)
        assert state.sigma == record.sigma
        assert state.moved_source.shape == source.shape
        assert state.indices.shape == state.distances.shape == state.weights.shape == (len(source),)
        # the record summarises the weights the callback saw
        weights = state.weights
        assert record.weight_mean == pytest.approx(weights.mean(), rel=1e-12)
        assert record.weight_min == weights.min() and record.weight_max == weights.max()
        assert record.effective_pairs == pytest.approx(weights.sum() ** 2 / np.square(weights).sum(), rel=1e-12)
        assert record.rmse == pytest.approx(np.sqrt(np.mean(state.distances**2)), rel=1e-12)
    # moved_source is the placement BEFORE the increment: the first is the source itself (init = I)
    np.testing.assert_allclose(states[0].moved_source, source, atol=1e-15)
    np.testing.assert_allclose(states[1].moved_source, apply(states[0].transformation, source), atol=1e-12)
    np.testing.assert_array_equal(states[-1].transformation, result.transformation)


@pytest.mark.parametrize("method", ["esm", "icp"])
@pytest.mark.parametrize("size", ["small", "large"])
def test_a_callback_or_a_history_never_changes_the_pose(method, size):
    """Callbacks and histories observe the run: the same pose, bitwise, and the same iterations,
    with or without them, after the global search and from a given start, and on a bunny scan of
    more than twice ``RefineConfig.strided_points`` (the ``esm-plane`` and strided stages)."""
    from esmicp import io

    if size == "small":
        target = load("bunny")[::4]
        source = move_to_source(target, *small_motion(11, diagonal(target), 20.0, 30.0))
    else:
        source = io.read_points(require_shared("bunny_scans/bun000.ply"))
        target = io.read_points(require_shared("bunny_scans/bun045.ply"))
        assert len(source) > 2 * REFINE.strided_points
    for init in (None, "identity") if size == "small" else (None,):
        plain = esmicp.register(source, target, method=method, init=init)
        states: list[IterationState] = []
        watched = esmicp.register(source, target, method=method, init=init, callback=states.append,
                                  record_history=True)
        np.testing.assert_array_equal(watched.transformation, plain.transformation)
        assert watched.num_iterations == plain.num_iterations == len(states) == len(watched.history)
        assert watched.message == plain.message
        assert all(state.moved_source.shape == source.shape for state in states)
        np.testing.assert_array_equal(states[-1].transformation, plain.transformation)


@pytest.mark.parametrize("method", ["esm", "icp"])
def test_correspondences_are_the_final_inlier_pairs(easy_pair, method):
    """``return_correspondences``: valid indices into the clouds as given, weights in [0, 1],
    distances those of the transformed source to the target, and as many pairs as ``fitness``
    counts; none unless asked for, and the pose the same either way."""
    source, target, _ = easy_pair
    result = esmicp.register(source, target, method=method, return_correspondences=True)
    pairs = result.correspondences
    assert esmicp.register(source, target, method=method).correspondences is None
    assert len(pairs) == round(result.fitness * len(source)) > 0
    assert pairs.source_index.dtype == pairs.target_index.dtype == np.int64
    assert np.all(np.diff(pairs.source_index) > 0) and pairs.source_index[-1] < len(source)
    assert pairs.target_index.min() >= 0 and pairs.target_index.max() < len(target)
    assert np.all((pairs.weight >= 0) & (pairs.weight <= 1)) and pairs.weight.max() > 0
    if method == "icp":
        assert np.all(pairs.weight == 1.0)
    moved = apply(result.transformation, source[pairs.source_index])
    np.testing.assert_allclose(pairs.distance, np.linalg.norm(moved - target[pairs.target_index], axis=1), atol=1e-12)
    np.testing.assert_allclose(pairs.distance, cKDTree(target).query(moved)[0], atol=1e-12)
    assert np.all(pairs.distance <= result.inlier_distance)
    np.testing.assert_array_equal(pairs.pairs, np.column_stack([pairs.source_index, pairs.target_index]))


def test_callback_returning_true_stops(easy_pair):
    source, target, _ = easy_pair
    seen: list[int] = []

    def stop_at_three(state: IterationState) -> bool:
        seen.append(state.iteration)
        return state.iteration == 3

    result = esmicp.register(source, target, method="icp", callback=stop_at_three, init="identity")
    assert seen == [1, 2, 3]
    assert result.num_iterations == 3
    assert result.converged is False
    assert "callback" in result.message


def test_callback_returning_none_or_false_does_not_stop(easy_pair):
    source, target, _ = easy_pair
    reference = esmicp.register(source, target, method="icp", init="identity")
    for value in (None, False, 0):
        result = esmicp.register(source, target, method="icp", callback=lambda state, v=value: v, init="identity")
        assert result.num_iterations == reference.num_iterations
        np.testing.assert_array_equal(result.transformation, reference.transformation)


@pytest.mark.parametrize("method", ["esm", "icp", "esm-paper"])
def test_init_at_the_truth_converges_at_once(method, chair):
    rotation, translation = small_motion(9, diagonal(chair))
    source = move_to_source(chair, rotation, translation)  # index-aligned, so esm-paper applies
    truth = to_matrix(rotation, translation)
    result = esmicp.register(source, chair, method=method, init=truth)
    assert result.converged
    assert result.num_iterations == 1
    np.testing.assert_allclose(result.transformation, truth, atol=1e-10)
    assert rotation_error_deg(result.transformation, rotation) < 1e-6


def test_init_is_honoured_far_from_the_identity(chair):
    # 120 degrees: out of reach from the identity, trivial from a nearby init
    rotation = Rotation.from_rotvec(np.radians(120.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
    translation = np.array([0.3, -0.2, 0.1])
    source = move_to_source(chair, rotation, translation)[np.random.default_rng(0).permutation(len(chair))]
    nearby = to_matrix(
        Rotation.from_rotvec(np.radians(5.0) * np.array([1.0, 0.0, 0.0])).as_matrix() @ rotation, translation
    )
    from_init = esmicp.register(source, chair, method="esm", init=nearby)
    assert rotation_error_deg(from_init.transformation, rotation) < 0.5
    from_identity = esmicp.register(source, chair, method="esm", init="identity")
    assert rotation_error_deg(from_identity.transformation, rotation) > 5.0


def test_max_iterations_one_performs_exactly_one_icp_step(easy_pair):
    source, target, _ = easy_pair
    result = esmicp.register(source, target, method="icp", max_iterations=1, record_history=True, init="identity")
    assert result.num_iterations == 1
    assert len(result.history) == 1
    assert result.converged is False
    assert "max_iterations=1" in result.message
    _, indices = cKDTree(target).query(source)
    rotation, translation = weighted_procrustes(source, target[indices])
    np.testing.assert_allclose(result.transformation, to_matrix(rotation, translation), atol=1e-12)


def test_max_iterations_bounds_the_run(easy_pair):
    source, target, _ = easy_pair
    for limit in (2, 5):
        result = esmicp.register(source, target, method="esm", max_iterations=limit, tolerance=0, init="identity")
        assert result.num_iterations == limit
        assert result.converged is False


def test_rng_does_not_change_local_methods(easy_pair):
    source, target, _ = easy_pair
    a = esmicp.register(source, target, rng=1, init="identity")
    b = esmicp.register(source, target, rng=np.random.default_rng(2), init="identity")
    np.testing.assert_array_equal(a.transformation, b.transformation)


# --------------------------------------------------------------------------------------------
# fitness / inlier_rmse
# --------------------------------------------------------------------------------------------


def expected_fitness(result, source, target, inlier_distance):
    distances, _ = cKDTree(target).query(apply(result.transformation, source))
    inliers = distances <= inlier_distance
    rmse = float(np.sqrt(np.mean(distances[inliers] ** 2))) if inliers.any() else 0.0
    return float(inliers.mean()), rmse


def test_fitness_and_inlier_rmse_default_distance():
    cloud = subsample("airplane", 4000, seed=5)
    target, source_half = halves(cloud, 5)
    rotation, translation = small_motion(5, diagonal(cloud))
    source = with_outliers(move_to_source(source_half, rotation, translation), 0.3, 5)
    result = esmicp.register(source, target, method="esm", init="identity")
    spacing = float(np.median(cKDTree(target).query(target, k=2)[0][:, 1]))
    assert result.inlier_distance == pytest.approx(3.0 * spacing, rel=1e-12)
    fitness, rmse = expected_fitness(result, source, target, result.inlier_distance)
    assert result.fitness == pytest.approx(fitness, abs=1e-15)
    assert result.inlier_rmse == pytest.approx(rmse, rel=1e-12)
    assert 0.6 < result.fitness < 0.9  # ~70% genuine points, 30% outliers (a few land near the surface)
    assert 0.0 < result.inlier_rmse <= result.inlier_distance


@pytest.mark.parametrize("inlier_distance", [1e-9, 0.005, 0.02, 10.0])
def test_fitness_with_explicit_inlier_distance(inlier_distance):
    cloud = subsample("guitar", 3000, seed=6)
    target, source_half = halves(cloud, 6)
    rotation, translation = small_motion(6, diagonal(cloud))
    source = with_outliers(move_to_source(source_half, rotation, translation), 0.2, 6)
    result = esmicp.register(source, target, inlier_distance=inlier_distance, init="identity")
    assert result.inlier_distance == inlier_distance
    fitness, rmse = expected_fitness(result, source, target, inlier_distance)
    assert result.fitness == pytest.approx(fitness, abs=1e-15)
    assert result.inlier_rmse == pytest.approx(rmse, rel=1e-12, abs=0)
    if inlier_distance == 1e-9:
        assert result.fitness == 0.0 and result.inlier_rmse == 0.0
    if inlier_distance == 10.0:
        assert result.fitness == 1.0


# --------------------------------------------------------------------------------------------
# argument checking
# --------------------------------------------------------------------------------------------


def _pair():
    rng = np.random.default_rng(0)
    target = rng.normal(size=(50, 3))
    return target + 0.01, target


def _scaled():
    matrix = np.eye(4)
    matrix[:3, :3] *= 1.5
    return matrix


def _reflection():
    matrix = np.eye(4)
    matrix[2, 2] = -1.0
    return matrix


def _nan_init():
    matrix = np.eye(4)
    matrix[1, 3] = np.nan
    return matrix


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"method": "ransac"}, "method"),
        ({"method": "ESM"}, "method"),
        ({"sigma": 0.0}, "sigma"),
        ({"sigma": -1.0}, "sigma"),
        ({"sigma": float("nan")}, "sigma"),
        ({"sigma": float("inf")}, "sigma"),
        ({"sigma": "wide"}, "sigma"),
        ({"max_iterations": 0}, "max_iterations"),
        ({"max_iterations": -5}, "max_iterations"),
        ({"max_iterations": 2.5}, "max_iterations"),
        ({"max_iterations": 10.0}, "max_iterations"),
        ({"max_iterations": True}, "max_iterations"),
        ({"max_iterations": "10"}, "max_iterations"),
        ({"tolerance": -1e-9}, "tolerance"),
        ({"tolerance": float("nan")}, "tolerance"),
        ({"tolerance": "small"}, "tolerance"),
        ({"init": np.eye(3)}, "init"),
        ({"init": _nan_init()}, "init"),
        ({"init": _scaled()}, "init"),
        ({"init": _reflection()}, "init"),
        ({"init": "sideways"}, "init"),
        ({"inlier_distance": 0.0}, "inlier_distance"),
        ({"inlier_distance": -0.1}, "inlier_distance"),
        ({"sigma": True}, "sigma"),
        ({"sigma": "2.5"}, "sigma"),
        ({"tolerance": True}, "tolerance"),
        ({"rng": "abc"}, "rng"),
        ({"rng": -1}, "rng"),
    ],
    ids=lambda value: repr(value) if not isinstance(value, dict) else ",".join(f"{k}" for k in value),
)
def test_bad_arguments_raise_naming_the_argument(kwargs, name):
    source, target = _pair()
    with pytest.raises(InvalidInputError, match=rf"^{name}: "):
        esmicp.register(source, target, **kwargs)


@pytest.mark.parametrize("method", ["esm", "icp", "esm-paper"])
def test_invalid_input_error_is_a_value_error(method):
    source, target = _pair()
    with pytest.raises(ValueError):
        esmicp.register(source, target, method=method, sigma=-1.0, init="identity")


def _collinear(count: int = 20) -> np.ndarray:
    return np.outer(np.linspace(-1.0, 1.0, count), [0.2, -0.7, 0.4]) + [1.0, 2.0, 3.0]


@pytest.mark.parametrize(
    "which, points, pattern",
    [
        ("source", np.random.default_rng(1).normal(size=(2, 3)), "need at least 3"),
        ("source", np.random.default_rng(1).normal(size=(40, 2)), r"\(N, 3\)"),
        ("target", np.random.default_rng(1).normal(size=(40, 4)), r"\(N, 3\)"),
        ("target", np.random.default_rng(1).normal(size=3), r"\(N, 3\)"),
        ("source", np.empty((0, 3)), "need at least 3"),
        ("source", np.tile([0.5, 0.5, 0.5], (30, 1)), "identical"),
        ("target", np.zeros((30, 3)), "identical"),
        ("source", _collinear(), "collinear"),
        ("target", _collinear(30), "collinear"),
        ("source", np.full((10, 3), np.nan), "need at least 3"),
    ],
    ids=[
        "2-points",
        "Nx2",
        "Nx4",
        "vector",
        "empty",
        "identical",
        "identical-target",
        "collinear",
        "collinear-target",
        "all-nan",
    ],
)
def test_bad_clouds_raise_naming_the_argument(which, points, pattern):
    source, target = _pair()
    arguments = {"source": source, "target": target, which: points}
    with pytest.raises(InvalidInputError, match=rf"^{which}: .*{pattern}"):
        esmicp.register(arguments["source"], arguments["target"], init="identity")


def test_planar_clouds_are_accepted():
    rng = np.random.default_rng(3)
    target = np.column_stack([rng.normal(size=(200, 2)), np.zeros(200)])
    rotation = Rotation.from_rotvec([0.0, 0.0, np.radians(10.0)]).as_matrix()
    source = move_to_source(target, rotation, np.zeros(3))
    result = esmicp.register(source, target, method="icp", init="identity")
    assert rotation_error_deg(result.transformation, rotation) < 0.5


def test_duplicated_target_points_do_not_break_the_default_inlier_distance():
    source, target = _pair()
    single = esmicp.register(source, target, init="identity")
    doubled = esmicp.register(source, np.vstack([target, target]), init="identity")
    assert doubled.inlier_distance == pytest.approx(single.inlier_distance)
    assert doubled.fitness == pytest.approx(single.fitness)
    assert single.fitness > 0.5


def test_the_strided_stages_stop_at_their_own_tolerance_without_moving_the_pose():
    """After a global search on a source of more than 40k points, the strided stages stop at
    ``RefineConfig.strided_tolerance``: the pose is the one that
    following the caller's 1e-8 on the subsample too gives, in fewer iterations."""
    source = esmicp.read_points(require_shared("bunny_scans/bun180.ply"))
    target = esmicp.read_points(require_shared("bunny_scans/bun090.ply"))
    assert len(source) > 2 * REFINE.strided_points
    default = esmicp.register(source, target)
    followed = esmicp.register(source, target, config=refined_on(REFINE.strided_points, strided_tolerance=0.0))
    assert default.num_iterations < followed.num_iterations
    assert rotation_error_deg(default.transformation, followed.transformation[:3, :3]) < 0.05
    diagonal = np.linalg.norm(np.ptp(target, axis=0))
    assert np.linalg.norm(default.transformation[:3, 3] - followed.transformation[:3, 3]) < 1e-3 * diagonal


def test_a_small_source_after_a_global_search_stops_at_the_whole_tolerance():
    """After a global search, a source too small for the strided stages (the 3DMatch pair
    ``t04_s06``: 16k source points) is refined whole at ``whole_tolerance``: following the
    caller's 1e-8 there creeps on for many more iterations and moves the pose by hundredths of a
    degree. Fails if the small-source path ignores that tolerance. A given ``init`` keeps
    the caller's tolerance."""
    from esmicp_lab.bench.real_pairs import load_pair, read_pairs

    pair = next(p for p in read_pairs(require_shared("real_pairs")) if p.pair == "t04_s06")
    source, target, _ = load_pair(pair)
    assert len(source) <= 2 * REFINE.strided_points
    default = esmicp.register(source, target)
    followed = esmicp.register(source, target, config=refined_on(REFINE.strided_points, whole_tolerance=0.0))
    assert default.num_iterations < followed.num_iterations
    assert rotation_error_deg(default.transformation, followed.transformation[:3, :3]) < 0.05
    assert np.linalg.norm(default.transformation[:3, 3] - followed.transformation[:3, 3]) < 0.01  # metres
    # a tolerance of 1 would stop a tolerance-driven run at once
    given = esmicp.register(source, target, init=default.transformation, max_iterations=5,
                            config=refined_on(REFINE.strided_points, whole_tolerance=1.0, strided_tolerance=1.0))
    assert given.num_iterations > 1  # one iteration would mean it stopped at the strided tolerance


def test_a_small_object_after_a_global_search_keeps_the_callers_tolerance():
    """Below ``RefineConfig.looser_from_points`` source points the refinement after a global search
    keeps the caller's tolerance: on 2,000-point objects with 60% outliers it can still be sliding
    steadily at the looser tolerances (measured: a cup 0.8 -> 5.1 degrees). Fails if the floor is
    dropped."""
    from esmicp.shapes import asymmetric_shape

    rng = np.random.default_rng(3)
    target = asymmetric_shape(2000, rng)
    source = apply(to_matrix(Rotation.random(random_state=4).as_matrix(), [0.3, -0.2, 0.1]), asymmetric_shape(2000, rng))
    assert len(source) <= REFINE.looser_from_points
    # a tolerance of 1 would stop a tolerance-driven run at once
    result = esmicp.register(source, target, config=refined_on(REFINE.strided_points, strided_tolerance=1.0,
                                                                whole_tolerance=1.0))
    assert result.init.startswith("global") and result.num_iterations > 1
