"""The compiled kernels (esmicp._kernels): exact against SciPy / NumPy references, fork-safe, and
near-linear on coincident points."""

from __future__ import annotations

import functools
import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
from scipy.spatial import cKDTree

import esmicp
from esmicp.core import compiled_tree, voxel_hash
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.moments import pair_moments, rigid_fit


def _cloud(count, seed):
    return np.random.default_rng(seed).normal(size=(count, 3))


@pytest.mark.parametrize("workers", [1, 2, None])
def test_tree_and_hash_match_ckdtree(workers):
    target, source = _cloud(5000, 1), _cloud(4000, 2) * 1.1
    reference_distances, _ = cKDTree(target).query(source)
    tree = compiled_tree.CompiledTree(target)
    distances, indices = tree.query(source, workers=workers)
    np.testing.assert_allclose(distances, reference_distances, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(target[indices] - source, axis=1), reference_distances, atol=1e-12)
    near = voxel_hash.VoxelHash(target, 0.2)
    distances, indices, _ = near.query(source, tree, workers=workers)
    np.testing.assert_allclose(distances, reference_distances, rtol=0, atol=1e-12)


@pytest.mark.parametrize("cloud", ["spread", "ties"])
def test_a_tree_is_the_same_built_on_one_or_more_threads(cloud):
    """A large tree is built in subtrees on several threads: every array is the one a single thread
    builds (on a cloud of many equal coordinates too), and it answers as SciPy's tree does."""
    points = _cloud(40_001, 4)  # above the size from which the build runs in parallel; odd, so halves differ
    if cloud == "ties":
        points = points.round(1)
    one = compiled_tree.CompiledTree(points, workers=1)
    for workers in (2, 3, None):
        other = compiled_tree.CompiledTree(points, workers=workers)
        for name in ("points", "order", "starts", "ends", "lefts", "boxes", "rank"):
            assert np.array_equal(getattr(one, name), getattr(other, name)), name
    queries = _cloud(2000, 5) * 1.2
    distances, indices = one.query(queries, workers=2)
    reference, _ = cKDTree(points).query(queries)
    np.testing.assert_allclose(distances, reference, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(points[indices] - queries, axis=1), reference, atol=1e-12)


@pytest.mark.parametrize("count", [1, 2, 1000, 100_003])
def test_the_compiled_centroid_is_numpys_mean_to_the_last_bit(count):
    """``centroid`` sums the columns in the order NumPy does: the same bits as ``mean(axis=0)``,
    on clouds far from the origin (where the order of the additions shows) and on a strided view."""
    from esmicp.core.procrustes import centroid

    rng = np.random.default_rng(count)
    points = rng.normal(size=(count, 3)) * np.array([1e-3, 1.0, 1e3]) + rng.normal(size=3) * 1e6
    assert np.array_equal(centroid(points), points.mean(axis=0))
    assert np.array_equal(centroid(points[::2]), points[::2].mean(axis=0))
    assert np.array_equal(centroid(points.astype(np.float32)), points.astype(np.float32).mean(axis=0))


@pytest.mark.parametrize("cell", [0.05, 0.4])
def test_the_voxel_hash_orders_its_points_as_a_stable_sort_of_their_cells(cell):
    """The points in the order of a stable NumPy argsort of their cell keys (many points share a
    cell: ties keep the points' order), each point's rank in it, and the cells' starts."""
    points = _cloud(30_000, 6).round(1) * 0.5  # a coarse grid: many equal coordinates
    near = voxel_hash.VoxelHash(points, cell)
    ijk = np.floor((points - near.low) / near.cell).astype(np.int64)
    keys = ijk[:, 0] + near.dims[0] * (ijk[:, 1] + near.dims[1] * ijk[:, 2])
    order = np.argsort(keys, kind="stable")
    assert np.array_equal(near.sorted_index, order)
    assert np.array_equal(near.sorted_points, points[order])
    assert np.array_equal(near.rank[order], np.arange(len(points)))
    starts = np.concatenate([[0], np.flatnonzero(np.diff(keys[order])) + 1, [len(points)]])
    assert np.array_equal(near.cell_starts, starts)


def test_moments_match_numpy_kabsch():
    rng = np.random.default_rng(3)
    source = rng.normal(size=(20000, 3))
    angle = 0.3
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    target = source @ rotation.T + [0.5, -0.2, 0.1]
    indices = np.arange(len(source), dtype=np.int64)
    distances = np.linalg.norm(target - source, axis=1)
    fitted_rotation, fitted_translation, _ = rigid_fit(pair_moments(source, np.eye(4), target, indices, distances, None))
    # Plain NumPy Kabsch.
    s_bar, t_bar = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((source - s_bar).T @ (target - t_bar))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    reference = vt.T @ np.diag([1, 1, d]) @ u.T
    np.testing.assert_allclose(fitted_rotation, reference, atol=1e-9)
    np.testing.assert_allclose(fitted_translation, t_bar - reference @ s_bar, atol=1e-9)


def test_coincident_points_stay_near_linear():
    """Three points repeated 100,000 times each (a cell of 100k coincident points): a query that
    scanned its whole cell would be quadratic (minutes). The bound here is generous
    (no timing): the answer must be exact, and the run must finish at all within the suite."""
    base = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    target = np.repeat(base, 100000, axis=0)
    source = target + 0.01
    index = NearestNeighbors(target)
    index._spacing = 0.5  # a realistic cell: coincident points all land in one cell
    distances, indices = index.query_near(source)
    np.testing.assert_allclose(distances, np.sqrt(3) * 0.01, atol=1e-12)
    np.testing.assert_array_equal(target[indices], np.repeat(base, 100000, axis=0))


def _register_small(seed, count=3000):
    rng = np.random.default_rng(seed)
    target = rng.normal(size=(count, 3))
    return esmicp.register(target + 0.01, target, method="icp", init="identity").transformation


@pytest.mark.parametrize("count", [3000, 800])
@pytest.mark.parametrize("executor", ["pool", "process_pool_executor"])
def test_fork_after_register_works(executor, count):
    """A forked pool after a registration in the parent (no OpenMP runtime).
    Below 32,768 points the step runs on the kernels' persistent helper threads, which the child
    does not inherit: it starts its own."""
    _register_small(0, count)
    context = multiprocessing.get_context("fork")
    register = functools.partial(_register_small, count=count)
    if executor == "pool":
        with context.Pool(2) as pool:
            results = pool.map_async(register, [1, 2]).get(timeout=120)
    else:
        with ProcessPoolExecutor(2, mp_context=context) as pool:
            results = list(pool.map(register, [1, 2], timeout=120))
    for transform in results:
        np.testing.assert_allclose(transform[:3, 3], [-0.01, -0.01, -0.01], atol=1e-6)


def _bunny_like(count, seed):
    """A smooth closed surface (an ellipsoid with bumps), so that the registration has work to do."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radius = 1.0 + 0.2 * np.sin(3 * directions[:, 0]) * np.cos(2 * directions[:, 1])
    return directions * radius[:, None] * [1.0, 0.7, 0.5]


@pytest.mark.parametrize("sizes", [(40000, 35000), (1500, 1200)])
@pytest.mark.parametrize("init", ["identity", None])
def test_register_is_the_same_on_one_and_two_threads(init, sizes):
    """``workers=`` reaches every kernel call (global search and refinement), and the kernels sum
    in pieces of fixed size: one thread and two give the same pose, to the last bit (threads
    started per call, and below 32,768 points the persistent helper threads)."""
    target = _bunny_like(sizes[0], 1)
    angle = 0.15
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    source = _bunny_like(sizes[1], 2) @ rotation.T + [0.05, 0.0, -0.02]
    one = esmicp.register(source, target, init=init, workers=1)
    two = esmicp.register(source, target, init=init, workers=2)
    assert one.num_iterations == two.num_iterations > 1
    np.testing.assert_allclose(two.transformation, one.transformation, rtol=0, atol=1e-12)
    assert one.fitness == two.fitness


def test_workers_reach_the_kernels(monkeypatch):
    """Every compiled call of a registration gets the thread count given to ``register``."""
    from esmicp import _kernels

    seen = []
    for name in ("tree_query", "hash_query", "pair_moments"):
        original = getattr(_kernels, name)

        def spy(*args, _original=original):
            seen.append(args[-1])
            return _original(*args)

        monkeypatch.setattr(_kernels, name, spy)
    target = _bunny_like(5000, 3)
    esmicp.register(target[::2] + 0.01, target, workers=1)
    assert seen and set(seen) == {1}
    seen.clear()
    esmicp.register(target[::2] + 0.01, target, init="identity")
    assert set(seen) == {0}  # 0: every core, as the kernels read it


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2", True])
def test_a_bad_workers_value_is_a_clear_error(bad):
    target = _bunny_like(500, 4)
    with pytest.raises(ValueError, match=r"^workers: expected a whole number of threads from 1 to \d+, or None"):
        esmicp.register(target, target, workers=bad)


def test_register_many_runs_one_thread_per_process():
    from esmicp.batch import per_process_kwargs

    assert per_process_kwargs({"init": "identity"}) == {"init": "identity", "workers": 1}
    assert per_process_kwargs({"workers": 2}) == {"workers": 2}


def test_compiled_kabsch_matches_numpy_svd():
    """The compiled rotation (Horn's quaternion method) against the SVD formula, on random
    cross-covariances over ten orders of magnitude, a third of them of rank 2 (planar clouds)."""
    from esmicp import _kernels

    def kabsch_rotation(cross):
        rotation = np.empty((3, 3))
        _kernels.kabsch(np.ascontiguousarray(cross), rotation)
        return rotation

    def nearest_rotation(matrix):
        rotation = np.empty((3, 3))
        _kernels.nearest_rotation(np.ascontiguousarray(matrix), rotation)
        return rotation

    rng = np.random.default_rng(7)
    for trial in range(500):
        cross = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-5, 5)
        if trial % 3 == 0:
            cross[:, 2] = 0.0
        u, _, vt = np.linalg.svd(cross)
        d = np.sign(np.linalg.det(vt.T @ u.T))
        np.testing.assert_allclose(kabsch_rotation(cross), vt.T @ np.diag([1.0, 1.0, d]) @ u.T, rtol=0, atol=1e-9)
    drifted = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    drifted *= np.sign(np.linalg.det(drifted))
    drifted += 1e-9 * rng.normal(size=(3, 3))
    u, _, vt = np.linalg.svd(drifted)
    np.testing.assert_allclose(nearest_rotation(drifted), u @ vt, rtol=0, atol=1e-12)


@pytest.mark.parametrize("method", ["esm", "icp"])
@pytest.mark.parametrize("count", [1000, 30000])
def test_the_one_call_iteration_gives_the_pose_of_the_numpy_step(method, count):
    """The fused compiled iteration (query, weights, moments, Kabsch, composition in one call)
    against the loop's NumPy path (an estimator that declares no compiled step: weighted
    Procrustes on the gathered pairs, NumPy SVD): the same pose to 1e-9, the same number of iterations.

    The 1,000-point case runs to its own stop. The 30,000-point one creeps slowly in the fine
    phase, where after about 45 iterations a round-off difference (1e-16) can flip one of Anderson
    acceleration's accept/reject decisions and the two paths stop at different, equally converged
    poses (1e-5 apart): it compares a fixed budget of 30 iterations, where every step of the
    two paths must agree."""
    target = _bunny_like(count, 5)
    angle = 0.2
    rotation = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    source = _bunny_like(count, 6) @ rotation.T + [0.02, 0.01, 0.0]
    budget = {} if count <= 1000 else {"max_iterations": 30, "tolerance": 1e-300}
    from esmicp.methods import ConvergenceCriteria, make_estimator
    from esmicp.methods.config import EsmConfig
    from esmicp.methods.local import refine

    index = NearestNeighbors(target)
    scale = float(np.linalg.norm(np.ptp(target, axis=0)))
    criteria = ConvergenceCriteria(budget.get("max_iterations", 100), budget.get("tolerance", 1e-8))

    def run(compiled):
        estimator = make_estimator(method, None, index.spacing(), scale)
        if not compiled:
            estimator.compiled_step = estimator.fused_step = False
        return refine(source, index, estimator, init=np.eye(4), criteria=criteria, scale=scale,
                      coarse_points=EsmConfig().coarse_points)

    fused, plain = run(True), run(False)
    assert fused.num_iterations == plain.num_iterations > 2
    np.testing.assert_allclose(fused.transformation, plain.transformation, rtol=0, atol=1e-9)


@pytest.mark.parametrize("count", [1000, 40000])
def test_a_step_below_reject_below_stops_after_its_queries(count):
    """``reject_below`` (the trial of an accelerated pose that fits worse): above the objective the
    step stops after its queries, with the same neighbours, RMS distance and objective as the
    whole step; at or below it the whole step runs (the helper threads and threads per call)."""
    from esmicp import _kernels

    target = _bunny_like(count, 8)
    source = np.ascontiguousarray(_bunny_like(count, 9))
    pose = np.eye(4)
    pose[:3, 3] = [0.01, -0.02, 0.005]
    weighting = np.array([0.0, 0.02, 3.0, 1.0, 1.0])  # the fine phase: sigma = the floor, 0.02

    def step(reject_below):
        index = NearestNeighbors(target, workers=2)
        indices, distances, out = np.empty(count, dtype=np.int64), np.empty(count), np.full(_kernels.STEP_OUT, -7.0)
        index.step(source, pose, indices, distances, out, warm=False, weighting=weighting, objective_sigma=0.02,
                   reject_below=reject_below)
        return indices, distances, out

    whole_indices, whole_distances, whole = step(-np.inf)
    assert whole[39] == 0.0 and 0.0 < whole[2] < 1.0
    stopped_indices, stopped_distances, stopped = step(np.nextafter(whole[2], np.inf))
    assert stopped[39] == 1.0
    np.testing.assert_array_equal(stopped_indices, whole_indices)
    np.testing.assert_array_equal(stopped_distances, whole_distances)
    np.testing.assert_array_equal(stopped[1:4], whole[1:4])
    assert np.all(stopped[4:39] == -7.0)  # nothing past the queries was computed
    _, _, again = step(whole[2])
    assert again[39] == 0.0
    np.testing.assert_array_equal(again[:39], whole[:39])


def test_coincident_points_are_counted_exactly():
    from esmicp.core.correspondence import coincident_points

    rng = np.random.default_rng(8)
    points = np.round(rng.normal(size=(20000, 3)), 1)  # many exact repeats
    points[:5] = [-0.0, 0.0, 0.0]  # -0.0 and 0.0 are the same point
    repeats, most, most_count, first = coincident_points(points)
    unique, counts = np.unique(points + 0.0, axis=0, return_counts=True)
    assert repeats == len(points) - len(unique) == len(points) - first.sum()
    assert most_count == counts.max()
    np.testing.assert_array_equal(np.unique(points[first] + 0.0, axis=0), unique)


def test_a_cloud_full_of_zero_points_warns_and_says_what_to_do():
    """A depth sensor's invalid pixels stored as (0, 0, 0); the registration
    runs (near-linear) and warns, naming the share, the place and the fix."""
    cloud = _bunny_like(4000, 9)
    zeros = np.zeros((1000, 3))
    with pytest.warns(esmicp.CoincidentPointsWarning) as caught:
        result = esmicp.register(np.vstack([cloud + 0.01, zeros]), np.vstack([zeros, cloud]), init="identity")
    messages = [str(w.message) for w in caught]
    assert len(messages) == 2
    assert messages[0].startswith("source: 999 of its 5,000 points (20.0%) are copies of other points (the most repeated: 1,000 at (0, 0, 0))")
    assert "deduplicate" in messages[0] and "(0, 0, 0) points: depth sensors store invalid pixels" in messages[0]
    assert messages[1].startswith("target: 999 of its 5,000 points")
    assert np.isfinite(result.transformation).all()


def test_few_coincident_points_do_not_warn(recwarn):
    cloud = _bunny_like(4000, 10)
    repeated = np.vstack([cloud, cloud[:300]])  # 7% copies: below the 10% of the warning
    esmicp.register(repeated + 0.01, repeated, init="identity")
    assert not [w for w in recwarn if issubclass(w.category, esmicp.CoincidentPointsWarning)]
    assert len(repeated) * 0.1 > 300


def test_repeated_points_warn_without_the_zero_advice():
    cloud = _bunny_like(3000, 11)
    doubled = np.vstack([cloud, cloud])
    with pytest.warns(esmicp.CoincidentPointsWarning, match=r"^target: 3,000 of its 6,000 points \(50\.0%\)") as caught:
        esmicp.register(cloud + 0.01, doubled, init="identity")
    assert "depth sensors" not in str(caught[0].message)


def _reference_anderson(poses, plains, scale, window):
    """Anderson's proposal after the steps ``plains[k] = G(poses[k])`` in NumPy and SciPy: poses
    relative to ``poses[0]`` as (rotation vector, translation / scale), ``gamma`` from
    ``numpy.linalg.lstsq`` on the residuals' differences, the combination mapped back."""
    from scipy.spatial.transform import Rotation

    reference = poses[0]

    def parameters(pose):
        rotation = pose[:3, :3] @ reference[:3, :3].T
        return np.concatenate([Rotation.from_matrix(rotation).as_rotvec(),
                               (pose[:3, 3] - rotation @ reference[:3, 3]) / scale])

    images = np.array([parameters(p) for p in plains])[-window - 1:]
    residuals = images - np.array([parameters(p) for p in poses])[-window - 1:]
    gamma = np.linalg.lstsq(np.diff(residuals, axis=0).T, residuals[-1])[0]
    mixed = images[-1] - np.diff(images, axis=0).T @ gamma
    pose = np.eye(4)
    rotation = Rotation.from_rotvec(mixed[:3]).as_matrix()
    pose[:3, :3] = rotation @ reference[:3, :3]
    pose[:3, 3] = rotation @ reference[:3, 3] + mixed[3:] * scale
    return pose


@pytest.mark.parametrize("start_angle", [0.3, 3.0])
def test_compiled_anderson_proposals_match_numpy_and_scipy(start_angle):
    """The compiled proposal (rotation log and exp, Jacobi-SVD least squares) against SciPy's
    rotation vectors and NumPy's lstsq, to 1e-9, along a contracting fixed-point iteration that
    starts ``start_angle`` radians from its fixed point (relative rotations of up to 2.4 rad)."""
    from scipy.spatial.transform import Rotation

    from esmicp.core.procrustes import to_matrix
    from esmicp.methods.acceleration import AndersonAccelerator

    rng = np.random.default_rng(11)
    scale = 2.5
    axis = rng.normal(size=3)
    fixed = to_matrix(Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), [1.0, -2.0, 0.5])
    accelerator = AndersonAccelerator(scale)
    start = Rotation.from_rotvec(start_angle * axis / np.linalg.norm(axis)).as_matrix()
    pose = to_matrix(start, rng.normal(size=3)) @ fixed
    poses, plains = [], []
    for step in range(12):
        # G moves part of the way to `fixed`, each coordinate at its own rate: a linear rate is what
        # Anderson removes, and the poses differ enough for a well-posed least squares.
        rate = np.array([0.6, 0.3, 0.5, 0.4, 0.7, 0.2])
        offset = Rotation.from_matrix(pose[:3, :3] @ fixed[:3, :3].T).as_rotvec()
        shift = pose[:3, 3] - (pose[:3, :3] @ fixed[:3, :3].T) @ fixed[:3, 3]
        plain = to_matrix(Rotation.from_rotvec(rate[:3] * offset).as_matrix(), rate[3:] * shift) @ fixed
        poses.append(pose)
        plains.append(plain)
        proposed = accelerator.propose(pose, plain)
        if step == 0:
            assert proposed is plain
            continue
        expected = _reference_anderson(poses, plains, scale, accelerator.window)
        np.testing.assert_allclose(proposed, expected, rtol=0, atol=1e-9)
        motion = proposed[:3, :3] @ pose[:3, :3].T
        np.testing.assert_allclose(accelerator.motion[0], Rotation.from_matrix(motion).magnitude(), atol=1e-9)
        np.testing.assert_allclose(accelerator.motion[1], np.linalg.norm(proposed[:3, 3] - motion @ pose[:3, 3]),
                                   atol=1e-9)
        pose = proposed if step % 3 else plain  # both kinds of continuation, as the loop's fallback makes
    accelerator.reset()
    assert accelerator.propose(pose, plains[-1]) is plains[-1]


def test_anderson_forgets_a_non_finite_step():
    from esmicp.methods.acceleration import AndersonAccelerator

    accelerator = AndersonAccelerator(1.0)
    first, second = np.eye(4), np.eye(4)
    second[:3, 3] = [0.1, 0.0, 0.0]
    accelerator.propose(first, second)
    broken = second.copy()
    broken[0, 3] = np.nan
    assert accelerator.propose(second, broken) is broken  # cleared: the next step starts afresh
    assert accelerator.propose(first, second) is second


def _walk_case(case):
    """(target, source, second pose) of a graph-walk case of the step's queries."""
    rng = np.random.default_rng(11)
    if case == "near":  # warm starts close to the answer: the walk certifies most queries
        target = _bunny_like(6000, 12)
        return target, _bunny_like(3000, 13), _pose(0.01, [0.003, -0.002, 0.001])
    if case == "far":  # a third of the source far from the target: those must fall back
        target = _bunny_like(6000, 12)
        source = _bunny_like(3000, 13)
        source[::3] += [4.0, -3.0, 2.0]
        return target, source, _pose(0.01, [0.003, -0.002, 0.001])
    if case == "duplicates":  # every target point 1-12 times: radii of 0, ties between copies
        base = _bunny_like(800, 14)
        target = np.repeat(base, rng.integers(1, 13, size=len(base)), axis=0)
        return target, _bunny_like(2000, 15), _pose(0.02, [0.01, 0.0, 0.0])
    # "plane": a flat target (no spread along z), the source just above and below it
    target = np.column_stack([rng.uniform(-1, 1, size=(5000, 2)), np.zeros(5000)])
    source = np.column_stack([rng.uniform(-1.1, 1.1, size=(3000, 2)), rng.normal(scale=0.01, size=3000)])
    return target, source, _pose(0.05, [0.02, -0.01, 0.0])


def _pose(angle, translation):
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    pose[:3, 3] = translation
    return pose


@pytest.mark.parametrize("case", ["near", "far", "duplicates", "plane"])
def test_the_steps_graph_walk_matches_ckdtree(case):
    """The step's warm-started queries walk the target's neighbour graph first (certified answers)
    and hand the rest to the hash or the tree: every answer is the exact nearest distance of
    scipy's KD-tree, on 1 and 2 threads alike, where the walk certifies most queries ("near") and
    where many must fall back (far source points, copies of target points, a flat target). The
    walk runs whatever the RMS distance here (the far points would otherwise switch it off)."""
    from esmicp import _kernels
    from esmicp.core.config import NeighbourIndexConfig

    always_walk = NeighbourIndexConfig(graph_rms_spacings=1e300)

    target, source, pose = _walk_case(case)
    source = np.ascontiguousarray(source)
    reference = cKDTree(target)
    weighting = np.array([0.0, 0.01, 3.0, 1.0, 1.0])
    results = []
    for workers in (1, 2):
        index = NearestNeighbors(target, workers=workers, config=always_walk)
        indices, distances, out = np.empty(len(source), dtype=np.int64), np.empty(len(source)), np.empty(_kernels.STEP_OUT)
        index.step(source, np.eye(4), indices, distances, out, warm=False, weighting=weighting, objective_sigma=0.0)
        assert out[40] == 0  # no warm start: nothing to walk from
        index.step(source, pose, indices, distances, out, warm=True, weighting=weighting, objective_sigma=0.0)
        placed = source @ pose[:3, :3].T + pose[:3, 3]
        expected, _ = reference.query(placed)
        np.testing.assert_allclose(distances, expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(target[indices] - placed, axis=1), expected, rtol=0, atol=1e-12)
        results.append((indices, distances, out[40]))
        certified = out[40] / len(source)
        if case == "near":
            assert certified > 0.8
        elif case == "far":
            assert 0.1 < certified < 2 / 3 + 1e-9
        else:
            assert 0.05 < certified < 0.95
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[0][1], results[1][1])
    assert results[0][2] == results[1][2]


def test_k_nearest_finds_the_k_nearest_distances_of_a_tree():
    # A large cloud (answered from voxels) with dense and sparse parts and far queries (the voxel
    # doubled, then a tree): every query's k nearest at the distances a tree finds.
    rng = np.random.default_rng(11)
    dense = np.column_stack([rng.uniform(0, 1, size=(60_000, 2)), rng.normal(scale=1e-3, size=60_000)])
    sparse = rng.uniform(-5, 5, size=(300, 3))
    points = np.vstack([dense, sparse])
    queries = np.vstack([dense[::600], sparse[::10], [[40.0, 40.0, 40.0]]])
    k = 10
    indices = compiled_tree.k_nearest(points, queries, k, workers=2)
    expected, _ = compiled_tree.CompiledTree(points).query_k(queries, k)
    found = np.sqrt(np.square(points[indices] - queries[:, None]).sum(axis=2))
    assert indices.shape == (len(queries), k) and len(np.unique(indices[0])) == k
    np.testing.assert_array_equal(found, expected)
    # Monotone: nearest first.
    assert (np.diff(found, axis=1) >= 0).all()
