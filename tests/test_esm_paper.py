"""``esm-paper``: the paper's formulation must equal a literal dense N x N reference, scale to large
clouds in O(N) memory, and warn when its index-alignment requirement cannot hold."""

from __future__ import annotations

import tracemalloc
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import esmicp
from esmicp.errors import IndexAlignmentWarning
from esmicp.methods import EsmPaperEstimator, similarity_matrix

# --------------------------------------------------------------------------------------------
# Dense reference, written literally after the paper's reference code (points as COLUMNS).
# --------------------------------------------------------------------------------------------


def brute_force_nearest(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distances, indices) of each source point's nearest target point, by exhaustive search."""
    all_distances = np.sqrt(((source[:, None, :] - target[None, :, :]) ** 2).sum(axis=2))
    indices = all_distances.argmin(axis=1)
    return all_distances[np.arange(len(source)), indices], indices


def dense_similarity(indices: np.ndarray, weights: np.ndarray, n: int) -> np.ndarray:
    """M[c_i, i] = w_i THEN M[i, c_i] = w_i, for i = 0..N-1 in order (later writes overwrite).

    Writes whose index falls outside 0..N-1 (possible only when the target has more points) have
    no column to act on and are skipped, as esmicp documents.
    """
    m = np.zeros((n, n))
    for i in range(n):
        c = indices[i]
        if c < n:
            m[c, i] = weights[i]
            m[i, c] = weights[i]
    return m


def dense_reference_step(source: np.ndarray, target: np.ndarray, sigma: float):
    """One iteration of the paper's method; returns (R, t, M, indices, distances, weights)."""
    n = len(source)
    distances, indices = brute_force_nearest(source, target)
    weights = np.exp(-(distances**2) / (2.0 * sigma**2))
    m = dense_similarity(indices, weights, n)

    src = source.T  # 3 x N
    tgt_matched = target[indices].T  # 3 x N, column i = t_c(i)
    s_bar = src.mean(axis=1, keepdims=True)  # over ALL source points
    t_bar = tgt_matched.mean(axis=1, keepdims=True)  # over the matched target points
    src_c = src - s_bar
    tgt_c = tgt_matched - t_bar
    h = src_c @ m.T @ tgt_c.T

    u, _, vt = np.linalg.svd(h)
    v = vt.T
    if np.linalg.det(u) * np.linalg.det(v) < 0:
        v[:, 2] *= -1
    rotation = v @ u.T
    translation = (t_bar - rotation @ s_bar).ravel()
    return rotation, translation, m, indices, distances, weights


def rotation_from_dense(source, target, indices, m):
    """The reference's rotation for a given similarity matrix (used to show the write order matters)."""
    src = source.T
    tgt_matched = target[indices].T
    h = (src - src.mean(axis=1, keepdims=True)) @ m.T @ (tgt_matched - tgt_matched.mean(axis=1, keepdims=True)).T
    u, _, vt = np.linalg.svd(h)
    v = vt.T
    if np.linalg.det(u) * np.linalg.det(v) < 0:
        v[:, 2] *= -1
    return v @ u.T


def dense_reference_run(source: np.ndarray, target: np.ndarray, sigma: float, iterations: int) -> np.ndarray:
    transform = np.eye(4)
    for _ in range(iterations):
        moved = source @ transform[:3, :3].T + transform[:3, 3]
        rotation, translation, *_ = dense_reference_step(moved, target, sigma)
        increment = np.eye(4)
        increment[:3, :3] = rotation
        increment[:3, 3] = translation
        transform = increment @ transform
    return transform


def random_rotation(seed: int, max_degrees: float | None = None) -> np.ndarray:
    if max_degrees is None:
        return Rotation.random(random_state=seed).as_matrix()
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(np.radians(rng.uniform(0.5, 1.0) * max_degrees) * axis).as_matrix()


def first_write_wins(indices, weights, n):
    m = np.zeros((n, n))
    written = np.zeros((n, n), dtype=bool)
    for i in range(n):
        c = indices[i]
        for r, k in ((c, i), (i, c)):
            if r < n and k < n and not written[r, k]:
                m[r, k] = weights[i]
                written[r, k] = True
    return m


# --------------------------------------------------------------------------------------------
# Cases: (source, target, sigma)
# --------------------------------------------------------------------------------------------


def case_index_aligned_noisy(seed: int, n: int):
    """N == M, a perturbed and moved copy: many mutual nearest pairs (i -> j, j -> i)."""
    rng = np.random.default_rng(seed)
    target = rng.uniform(-1.0, 1.0, (n, 3))
    rotation = random_rotation(seed, max_degrees=20.0)
    translation = rng.normal(scale=0.1, size=3)
    source = (target - translation) @ rotation + rng.normal(scale=0.05, size=(n, 3))
    return source, target, 0.5


def case_shuffled_equal_size(seed: int, n: int):
    """N == M but unrelated order: the entries pair unrelated points (and overwrite)."""
    rng = np.random.default_rng(seed)
    target = rng.normal(size=(n, 3))
    source = target[rng.permutation(n)] + rng.normal(scale=0.1, size=(n, 3))
    return source @ random_rotation(seed + 1, max_degrees=30.0).T, target, 1.0


def case_many_to_one(seed: int, n: int):
    """N == M, but the source huddles around a handful of target points: many c_i coincide, so
    entries M[c, i] / M[i, c] are written repeatedly and overwritten."""
    rng = np.random.default_rng(seed)
    target = rng.uniform(-2.0, 2.0, (n, 3))
    hubs = rng.choice(n, size=5, replace=False)
    source = target[rng.choice(hubs, size=n)] + rng.normal(scale=0.02, size=(n, 3))
    return source, target, 0.3


def case_small_target(seed: int, n: int):
    """N > M: every index is valid, the columns beyond M hold only M[i, c_i]-type entries."""
    rng = np.random.default_rng(seed)
    target = rng.normal(size=(max(4, n // 6), 3))
    source = rng.normal(size=(n, 3)) * 1.2 + 0.1
    return source, target, 0.8


def case_large_target(seed: int, n: int):
    """N < M: writes with c_i >= N are dropped."""
    rng = np.random.default_rng(seed)
    target = rng.normal(size=(3 * n, 3))
    source = target[rng.choice(3 * n, n, replace=False)] + rng.normal(scale=0.05, size=(n, 3))
    return source, target, 0.4


def case_swapped_pairs(seed: int, n: int):
    """N == M, index-aligned except that disjoint pairs of points trade places: every swapped pair
    is a mutual nearest pair, so entries are overwritten with a different weight."""
    rng = np.random.default_rng(seed)
    target = rng.uniform(-1.0, 1.0, (n, 3))
    order = np.arange(n)
    chosen = rng.choice(n, size=2 * (n // 5), replace=False).reshape(-1, 2)
    order[chosen[:, 0]], order[chosen[:, 1]] = chosen[:, 1], chosen[:, 0]
    source = target[order] + rng.normal(scale=0.01, size=(n, 3))
    return source, target, 0.05


CASES = {
    "aligned": case_index_aligned_noisy,
    "swapped-pairs": case_swapped_pairs,
    "shuffled": case_shuffled_equal_size,
    "many-to-one": case_many_to_one,
    "small-target": case_small_target,
    "large-target": case_large_target,
}


@pytest.mark.parametrize("n", [30, 97, 200])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("case", list(CASES))
def test_step_equals_dense_reference(case, seed, n):
    source, target, sigma = CASES[case](seed, n)
    rotation, translation, m, indices, distances, weights = dense_reference_step(source, target, sigma)

    step = EsmPaperEstimator(sigma).step(source, target, distances, indices)
    np.testing.assert_allclose(step.rotation, rotation, rtol=0, atol=1e-10)
    np.testing.assert_allclose(step.translation, translation, rtol=0, atol=1e-10)
    assert step.sigma == sigma
    np.testing.assert_allclose(step.weights, weights, rtol=1e-14, atol=0)

    # the sparse matrix is the dense one, entry for entry
    sparse = similarity_matrix(indices, weights, len(source))
    assert sparse.shape == (len(source), len(source))
    np.testing.assert_array_equal(sparse.toarray(), m)


@pytest.mark.parametrize("n", [30, 97, 200])
@pytest.mark.parametrize("seed", [0, 1])
def test_cases_exercise_overwrites_and_shared_targets(seed, n):
    # Guards the equality test. An entry is written twice with different values exactly when
    # c_i = j and c_j = i (mutual nearest pairs): M[j, i] and M[i, j] then end with w_j. The
    # swapped-pairs case has many, so last-write-wins differs from first-write-wins there and an
    # implementation with the wrong write order would be caught.
    source, target, sigma = CASES["swapped-pairs"](seed, n)
    rotation, _, m, indices, _, weights = dense_reference_step(source, target, sigma)
    mutual = sum(1 for i in range(n) if indices[i] != i and indices[indices[i]] == i)
    assert mutual >= n // 10
    wrong_order = first_write_wins(indices, weights, n)
    assert not np.array_equal(m, wrong_order)
    # ...by far more than the 1e-10 the equality test allows
    assert np.abs(rotation_from_dense(source, target, indices, wrong_order) - rotation).max() > 1e-6
    # and in the many-to-one case most source points share one of a few target points
    source, target, sigma = CASES["many-to-one"](seed, n)
    _, _, _, indices, _, _ = dense_reference_step(source, target, sigma)
    assert len(np.unique(indices)) <= 5


def test_step_with_kdtree_correspondences_matches_brute_force():
    # the library's own correspondences (KD-tree) give the same step as the brute-force ones
    from esmicp.core.correspondence import NearestNeighbors

    source, target, sigma = case_index_aligned_noisy(5, 150)
    rotation, translation, *_ = dense_reference_step(source, target, sigma)
    distances, indices = NearestNeighbors(target).query(source)
    step = EsmPaperEstimator(sigma).step(source, target, distances, indices)
    np.testing.assert_allclose(step.rotation, rotation, atol=1e-10)
    np.testing.assert_allclose(step.translation, translation, atol=1e-10)


def test_similarity_matrix_diagonal_and_symmetric_pairs():
    # hand-checkable: c = [0, 2, 1, 1], w = [a, b, c, d]
    indices = np.array([0, 2, 1, 1])
    weights = np.array([0.1, 0.2, 0.3, 0.4])
    m = similarity_matrix(indices, weights, 4).toarray()
    expected = np.zeros((4, 4))
    expected[0, 0] = 0.1  # i=0: M[0,0]=w0 twice
    # i=1: M[2,1]=0.2, M[1,2]=0.2 ; i=2: M[1,2]=0.3, M[2,1]=0.3 (overwrite) ; i=3: M[1,3]=0.4, M[3,1]=0.4
    expected[2, 1] = expected[1, 2] = 0.3
    expected[1, 3] = expected[3, 1] = 0.4
    np.testing.assert_array_equal(m, expected)
    np.testing.assert_array_equal(m, dense_similarity(indices, weights, 4))


# --------------------------------------------------------------------------------------------
# Full runs against the dense reference loop
# --------------------------------------------------------------------------------------------


@pytest.mark.filterwarnings("ignore::esmicp.errors.IndexAlignmentWarning")
@pytest.mark.parametrize(
    "case, seed, n",
    [
        ("aligned", 0, 60),
        ("aligned", 1, 150),
        ("swapped-pairs", 2, 100),
        ("shuffled", 3, 80),
        ("many-to-one", 4, 70),
        ("small-target", 5, 90),
        ("large-target", 6, 50),
    ],
)
@pytest.mark.parametrize("iterations", [1, 4])
def test_register_equals_dense_reference_loop(case, seed, n, iterations):
    source, target, sigma = CASES[case](seed, n)
    expected = dense_reference_run(source, target, sigma, iterations)
    result = esmicp.register(source, target, method="esm-paper", sigma=sigma, max_iterations=iterations, tolerance=0, init="identity")
    assert result.num_iterations == iterations
    assert result.method == "esm-paper"
    assert result.sigma == sigma
    np.testing.assert_allclose(result.transformation, expected, rtol=0, atol=1e-9)


def test_register_default_sigma_is_the_papers(rng):
    target = rng.uniform(-1, 1, (100, 3))
    source = target @ random_rotation(7, max_degrees=10.0)  # index-aligned copy
    expected = dense_reference_run(source, target, 1.0, 3)
    result = esmicp.register(source, target, method="esm-paper", max_iterations=3, tolerance=0, init="identity")
    assert result.sigma == 1.0
    np.testing.assert_allclose(result.transformation, expected, atol=1e-9)


# --------------------------------------------------------------------------------------------
# Memory: never N x N
# --------------------------------------------------------------------------------------------


def test_large_cloud_runs_in_linear_memory():
    n = 200_000  # an N x N float64 matrix would take 320 GB
    rng = np.random.default_rng(2024)
    target = rng.normal(size=(n, 3))
    rotation = random_rotation(3, max_degrees=5.0)
    translation = np.array([0.05, -0.02, 0.01])
    source = (target - translation) @ rotation  # index-aligned copy
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            # few iterations from an offset: the final alignment check may or may not fire
            warnings.simplefilter("ignore", IndexAlignmentWarning)
            result = esmicp.register(source, target, method="esm-paper", max_iterations=3, init="identity")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert result.num_iterations <= 3
    assert np.isfinite(result.transformation).all()
    assert peak < 200e6, f"peak traced memory {peak / 1e6:.0f} MB"


def test_a_large_index_aligned_copy_is_recovered_on_every_point():
    """Above 40,000 source points ``register`` refines on a strided subset first; ``esm-paper``
    pairs source point k with target point k, which a subset breaks (a 50k-point copy ended 141
    degrees off after the global search, 162 from the identity), so it keeps every point."""
    from esmicp.shapes import asymmetric_shape

    source = asymmetric_shape(50_000, rng=np.random.default_rng(0))
    rotation = Rotation.from_euler("xyz", [10, 5, -8], degrees=True).as_matrix()
    translation = np.array([0.05, -0.02, 0.03])
    target = source @ rotation.T + translation  # index-aligned copy
    for init in ("global", "identity"):
        result = esmicp.register(source, target, method="esm-paper", init=init)
        assert [stage.points for stage in result.stages if stage.name == "refine"] == [len(source)], init
        error = np.degrees(np.arccos(np.clip((np.trace(result.transformation[:3, :3].T @ rotation) - 1) / 2, -1, 1)))
        assert error < 1e-4, (init, error)
        np.testing.assert_allclose(result.transformation[:3, 3], translation, atol=1e-6)


# --------------------------------------------------------------------------------------------
# Index-alignment warnings
# --------------------------------------------------------------------------------------------


def aligned_pair(seed: int, n: int = 300):
    rng = np.random.default_rng(seed)
    target = rng.normal(size=(n, 3))
    rotation = random_rotation(seed, max_degrees=15.0)
    translation = rng.normal(scale=0.1, size=3)
    return (target - translation) @ rotation, target


def test_warns_when_sizes_differ():
    source, target = aligned_pair(0)
    with pytest.warns(IndexAlignmentWarning, match="300 source and 250 target"):
        esmicp.register(source, target[:250], method="esm-paper", max_iterations=5, init="identity")
    with pytest.warns(IndexAlignmentWarning, match="250 source and 300 target"):
        esmicp.register(source[:250], target, method="esm-paper", max_iterations=5, init="identity")


def test_warns_when_source_is_shuffled():
    source, target = aligned_pair(1)
    shuffled = source[np.random.default_rng(1).permutation(len(source))]
    with pytest.warns(IndexAlignmentWarning, match="not index-aligned"):
        esmicp.register(shuffled, target, method="esm-paper", init="identity")


def test_no_warning_on_an_index_aligned_copy():
    source, target = aligned_pair(2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = esmicp.register(source, target, method="esm-paper", init="identity")
    assert result.converged


@pytest.mark.parametrize("method", ["esm", "icp"])
def test_other_methods_never_warn_about_alignment(method):
    source, target = aligned_pair(3)
    shuffled = source[np.random.default_rng(3).permutation(len(source))]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        esmicp.register(shuffled, target[:250], method=method, init="identity")
        esmicp.register(shuffled, target, method=method, init="identity")
