"""register_scans(): many scans into one model; every scan placed, doubtful or unplaced with a reason."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from esmicp.config import MergeConfig, RegistrationConfig
from esmicp.errors import InvalidInputError
from esmicp.multiview import register_scans, scans as scans_module
from esmicp.multiview import pose_graph
from esmicp.result import RegistrationResult

from conftest import require_module, require_shared

BUNNY = ("bun000", "bun045", "bun315", "top3")


def _errors(T_estimate, T_truth):
    E = np.linalg.inv(T_truth) @ T_estimate
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(E[:3, :3]).as_rotvec()))), float(np.linalg.norm(E[:3, 3]))


@pytest.fixture(scope="module")
def bunny():
    from esmicp.io.stanford_conf import load_scans

    # 12,000 points a scan: at 4,000 the right pairs' overlap confidence falls below the trust bar
    # (the surface noise is no longer finer than the spacing), and the scans are rightly left out
    scans = load_scans(require_shared("bunny_scans"), max_points=12000, rng=7)
    return [scans[name][0] for name in BUNNY], [scans[name][1] for name in BUNNY]


@pytest.fixture(scope="module")
def bunny_result(bunny):
    clouds, _ = bunny
    return register_scans(clouds, threads=2)


def test_bunny_scans_recover_the_stanford_poses(bunny, bunny_result):
    _, truth = bunny
    result = bunny_result
    assert result.unplaced == () and result.status == ("placed",) * 4, result.reasons
    # stored in a frame near the object, not the scanner's: the free-space check must not apply
    assert result.free_space_check.startswith("not range images")
    np.testing.assert_allclose(result.poses[0], np.eye(4))
    for k in range(len(truth)):
        angle, shift = _errors(result.poses[k], np.linalg.inv(truth[0]) @ truth[k])
        # 12,000-point subsets (the docs' full-resolution run is held to 1 deg / 1 mm)
        assert angle < 1.0 and shift < 0.002, (BUNNY[k], angle, shift)
    assert all(e.reason for e in result.edges)
    assert result.to_dict()["unplaced"] == []


def test_input_order_does_not_matter(bunny, bunny_result):
    clouds, _ = bunny
    order = [2, 0, 3, 1]
    shuffled = register_scans([clouds[k] for k in order], reference=order.index(0), threads=2)
    for position, k in enumerate(order):
        np.testing.assert_allclose(shuffled.poses[position], bunny_result.poses[k], atol=1e-6)


@pytest.mark.parametrize("motion", ["shifted", "turned"])
def test_a_common_rigid_motion_of_every_scan_changes_no_verdict(bunny, bunny_result, motion):
    """Every scan moved by one rigid motion (into map coordinates 1e6 away, or turned): the same
    verdicts, and the same poses up to the motion (compared by where they put each scan's points).
    Shifted, the merge sees the same numbers but for rounding; turned, its voxel grids fall
    differently on the points."""
    clouds, _ = bunny
    M = np.eye(4)
    if motion == "shifted":
        M[:3, 3] = [1e6, -5e5, 3e4]
    else:
        M[:3, :3] = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
        M[:3, 3] = [0.2, 0.1, -0.3]
    moved = register_scans([c @ M[:3, :3].T + M[:3, 3] for c in clouds], threads=2)
    assert moved.status == bunny_result.status and moved.free_space_check.startswith("not range images")
    for k, cloud in enumerate(clouds):
        expected = M @ bunny_result.poses[k] @ np.linalg.inv(M)
        angle, _ = _errors(moved.poses[k], expected)
        at_points = cloud @ M[:3, :3].T + M[:3, 3]
        apart = np.linalg.norm((at_points @ moved.poses[k][:3, :3].T + moved.poses[k][:3, 3])
                               - (at_points @ expected[:3, :3].T + expected[:3, 3]), axis=1).max()
        if motion == "shifted":
            assert angle < 1e-4 and apart < 1e-6, (k, angle, apart)
        else:
            assert angle < 0.2 and apart < 5e-4, (k, angle, apart)


def _truth(n, rng):
    poses = [np.eye(4)]
    for _ in range(n - 1):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = rng.normal(size=3)
        poses.append(T)
    return poses


def _fake_pairwise(truth, *, wrong=(), low=(), wrong_untrusted=(), missing=(), apart=(), overlapping=None,
                   inlier_distance=0.05):
    """Stand-in for the pairwise registrations: exact, trusted relative poses, except the listed
    pairs (``wrong``: off by 40 degrees yet trusted and the most confident; ``wrong_untrusted``:
    off and below the trust bar; ``low``: every pair of these scans untrusted; ``missing``: the
    registration failed; ``apart``: pairs with one scan in this set and one outside are trusted
    at 0.6, the confidence of the wrong edges that placed kitchen frames 95 degrees off;
    ``overlapping``: when given, the only pairs that overlap, every other one untrusted);
    ``inlier_distance``: the results' (cloud units)."""

    def run(jobs, *, pairs):
        out = []
        for i, j in pairs:
            T = np.linalg.inv(truth[i]) @ truth[j]
            fitness, confidence, ambiguous = 0.9, 0.9, False
            if {(i, j), (j, i)} & set(wrong) or {(i, j), (j, i)} & set(wrong_untrusted):
                bad = np.eye(4)
                bad[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.7]).as_matrix()
                T = T @ bad
                fitness, confidence = 0.95, 0.95  # the wrong edge is the most confident one
                if {(i, j), (j, i)} & set(wrong_untrusted):
                    confidence, ambiguous = 0.33, True
            if i in low or j in low or (overlapping is not None and (min(i, j), max(i, j)) not in overlapping):
                fitness, confidence = 0.05, 0.1
            if (i in apart) != (j in apart):
                confidence = 0.6
            if {(i, j), (j, i)} & set(missing):
                out.append("pair failed")
                continue
            out.append(RegistrationResult(transformation=T, converged=True, num_iterations=1, fitness=fitness,
                                          inlier_rmse=0.0, inlier_distance=inlier_distance, runtime_s=0.0, method="esm",
                                          sigma=None, message="", ambiguous=ambiguous, confidence=confidence))
        return out

    return run


def _offset(original: np.ndarray, given: np.ndarray) -> np.ndarray:
    """The shift ``t`` with ``given + t`` among the points of ``original``: the merge may register a
    scan's subsets in a frame shifted from the one the scan was given in."""
    from scipy.spatial import cKDTree

    tree = cKDTree(original)
    scale = 1e-9 * (1.0 + np.abs(original).max())
    step = given[1] - given[0]
    distance, match = tree.query(original + step)
    for m in np.nonzero(distance <= scale)[0]:
        t = original[m] - given[0]
        if tree.query(given[:20] + t)[0].max() <= scale:
            return t
    raise AssertionError("a registered cloud is not a shifted subset of its scan")


def _patch(monkeypatch, truth, clouds, first_draw_fails=(), sparse_points=None, stalled=(), **kwargs):
    """Replace the pairwise registrations by :func:`_fake_pairwise` (relative poses from ``truth``,
    in the frames of the clouds the merge registers); the searches of the pairs in
    ``first_draw_fails`` fail on the first draw of the sparse subsets (``sparse_points`` each); the
    pairs in ``stalled``, refined from a given start, stop at their iteration cap (not converged,
    so untrusted) at the right pose with the full overlap confidence, 1.0."""
    fake = _fake_pairwise(truth, **kwargs)
    captured = {}
    offsets = {}

    def wrapper(jobs, *, progress=None, inits=None, **register_kwargs):
        # recover which (i, j) each job is from the subsampled clouds' identity: every subset drawn
        # from scan k's points (the sparse and dense subsets, a second draw) maps to k
        index = captured["scan_of"]
        pairs = [(index.get(id(t)), index.get(id(s))) for s, t in jobs]
        first = captured.get("first_sparse", set())
        known = [n for n, pair in enumerate(pairs) if None not in pair]
        for n in list(known):
            if (min(pairs[n]), max(pairs[n])) in first_draw_fails and {id(c) for c in jobs[n]} <= first:
                known.remove(n)  # "not a pair of scans": the search found nothing
        out = ["not a pair of scans"] * len(jobs)  # e.g. a piece of scans fused: no fake for it
        if register_kwargs.get("judge") is False:
            # the merge's pose-finding run on the sparse subsets; its dense check (the next call)
            # starts at the pose found, so only this call tells a refinement from a search
            captured["from_start"] = {pairs[n] for n in known if inits is not None and inits[n] is not None}
        for n, result in zip(known, fake([jobs[n] for n in known], pairs=[pairs[n] for n in known])):
            (s, t), (i, j) = jobs[n], pairs[n]
            if isinstance(result, RegistrationResult) and (min(i, j), max(i, j)) in stalled \
                    and (i, j) in captured.get("from_start", ()):
                result = replace(result, converged=False, num_iterations=30, confidence=1.0)
            if isinstance(result, RegistrationResult):
                # judged by the policy the merge asks for, as register does
                result = replace(result, policy=RegistrationConfig.of(register_kwargs.get("config")).trust)
                for cloud, k in ((t, i), (s, j)):
                    if id(cloud) not in offsets:
                        offsets[id(cloud)] = _offset(np.asarray(clouds[k], dtype=float), cloud)
                to_i, from_j = np.eye(4), np.eye(4)
                to_i[:3, 3], from_j[:3, 3] = -offsets[id(t)], offsets[id(s)]
                result = replace(result, transformation=to_i @ result.transformation @ from_j)
            out[n] = result
        return out

    real_subsample = scans_module._subsample

    def subsample(points, count, **options):
        out = real_subsample(points, count, **options)
        scans = captured.setdefault("scans", {})  # the merge first subsamples each of its scans in turn
        if id(points) not in scans and len(scans) < len(truth):
            scans[id(points)] = (len(scans), points)  # holding the points keeps their id unique
        if id(points) in scans:
            captured.setdefault("scan_of", {})[id(out)] = scans[id(points)][0]
            captured.setdefault("subsets", []).append(out)  # kept alive: ids stay unique
            if len(out) == sparse_points and options.get("draw", 0) == 0:
                captured.setdefault("first_sparse", set()).add(id(out))
        return out

    monkeypatch.setattr(scans_module, "register_many", wrapper)
    monkeypatch.setattr(scans_module, "_subsample", subsample)
    # reverse fitness comes from the clouds: make every cloud the same shape in its own frame


def _clouds(truth, rng, points=300):
    world = rng.uniform(-1, 1, size=(points, 3))
    return [(world - T[:3, 3]) @ T[:3, :3] for T in truth]  # scan k sees the world in its frame


def test_a_wrong_edge_is_rejected_by_the_robust_graph(monkeypatch):
    rng = np.random.default_rng(3)
    truth = _truth(5, rng)
    clouds = _clouds(truth, rng)
    _patch(monkeypatch, truth, clouds, wrong={(1, 3)})
    # the wrong edge is trusted (the most confident one), so only the graph can reject it; partners=4: every pair
    result = register_scans(clouds, refine_rounds=0, threads=1, partners=4)
    assert result.unplaced == ()
    assert [sorted((e.i, e.j)) for e in result.rejected_edges] == [[1, 3]]
    graph = [stage for stage in result.stages if stage.name == "pose graph"][-1]
    assert graph.decided["cycle_inconsistent"] == 1 and graph.decided["kept"] == 9
    assert len(result.kept_edges) == 9
    for k in range(5):
        angle, shift = _errors(result.poses[k], truth[k])
        assert angle < 1e-6 and shift < 1e-6


def test_an_unplaceable_scan_is_reported_not_forced_in(monkeypatch):
    rng = np.random.default_rng(4)
    truth = _truth(4, rng)
    clouds = _clouds(truth, rng)
    _patch(monkeypatch, truth, clouds, low={2})
    result = register_scans(clouds, refine_rounds=0, threads=1)
    assert result.unplaced == (2,)
    assert result.status[2] == "unplaced" and "no trusted edge" in result.reasons[2][0]
    assert result.placed == (True, True, False, True)
    assert np.isnan(result.poses[2]).all()
    assert any("scan 2" in note for note in result.notes)
    points, labels = result.merged(clouds)
    assert set(labels.tolist()) == {0, 1, 3}
    shown = repr(result)  # one line of counts, no arrays
    assert "\n" not in shown and "scans=4, placed=3, doubtful=0, unplaced=1, reference=0" in shown


def test_a_reference_left_apart_by_its_first_pairs_still_reaches_the_other_scans(monkeypatch):
    # Scans 0-2 (the reference's) and 3-14 look alike within their group and unlike across it,
    # and only neighbours overlap (2-3 and 2-4 join the groups). The first pairs join each group
    # within itself; the scans not placed must then be paired with the placed ones (pairs among
    # themselves, however similar, cannot place them).
    n = 15
    rng = np.random.default_rng(5)
    truth = _truth(n, rng)
    clouds = _clouds(truth, rng)
    overlapping = {(k, k + 1) for k in range(n - 1)} | {(k, k + 2) for k in range(n - 2)}
    group = np.array([0, 0, 0] + [1] * (n - 3))
    index = np.arange(n)
    distances = 0.01 * np.abs(index[:, None] - index[None, :]) + (group[:, None] != group[None, :])
    distances[2, 3:5] = distances[3:5, 2] = 0.9  # the views where the groups meet are the most alike across
    np.fill_diagonal(distances, 0.0)
    monkeypatch.setattr(scans_module.candidates, "matching_distances", lambda clouds, **_: distances)
    _patch(monkeypatch, truth, clouds, overlapping=overlapping)
    result = register_scans(clouds, refine_rounds=0, threads=1, partners=2)
    assert result.unplaced == (), result.reasons
    for k in range(n):
        angle, shift = _errors(result.poses[k], truth[k])
        assert angle < 1e-6 and shift < 1e-6
    # the first round alone leaves scans 3-14 apart: they were placed by pairs across the groups
    assert any(group[e.i] != group[e.j] and e.kept for e in result.edges)


def test_a_piece_that_joins_only_through_pairs_the_ranking_puts_low_is_still_placed(monkeypatch):
    """Scans 0-5 (the reference's) and 6-11 overlap within their groups, and across them only
    where the groups meet (3-5 with 6-8); the similarity ranks every pair of 0-2 with 6-11 (none
    overlapping) before those. Scans 6-11 stand apart after the first pairs, their fused piece
    finds no pose, and the pairs most like them find nothing: the pairs that join them rank after
    18 that do not, and the merge still reaches them before it stops."""
    n = 12
    rng = np.random.default_rng(21)
    truth = _truth(n, rng)
    clouds = _clouds(truth, rng)
    group = np.array([0] * 6 + [1] * 6)
    meet = {(i, j) for i in (3, 4, 5) for j in (6, 7, 8)}
    overlapping = {(i, j) for i in range(n) for j in range(i + 1, n) if group[i] == group[j]} | meet
    index = np.arange(n)
    hops = np.abs(index[:, None] - index[None, :]) % 6
    distances = 0.01 * np.minimum(hops, 6 - hops) + 2.0 * (group[:, None] != group[None, :])  # a ring in each group
    decoys = np.ix_([0, 1, 2], range(6, n))
    distances[decoys] = 0.5 + 0.01 * rng.random((3, 6))  # alike across, yet sharing nothing
    distances = np.minimum(distances, distances.T)
    np.fill_diagonal(distances, 0.0)
    monkeypatch.setattr(scans_module.candidates, "matching_distances", lambda clouds, **_: distances)
    _patch(monkeypatch, truth, clouds, overlapping=overlapping)
    result = register_scans(clouds, refine_rounds=0, threads=1, partners=2)
    assert result.status == ("placed",) * n, result.reasons
    for k in range(n):
        angle, shift = _errors(result.poses[k], truth[k])
        assert angle < 1e-6 and shift < 1e-6
    assert any(group[e.i] != group[e.j] and e.kept for e in result.edges)


def test_a_search_that_failed_on_one_draw_of_the_points_is_tried_on_another_where_the_graph_needs_it(monkeypatch):
    """The reference's pairs with scans 2-5 find nothing on the first draw of the sparse subsets
    (as the bunny's bun270 with bun180 on some draws): scans 1-5 then hang from the reference by
    its one trusted edge (with scan 1). The pairs the poses predict across that edge are searched
    again on a second draw, which puts the edge on a cycle: every scan placed."""
    n = 6
    rng = np.random.default_rng(11)
    truth = _truth(n, rng)
    clouds = _clouds(truth, rng)
    _patch(monkeypatch, truth, clouds, first_draw_fails={(0, k) for k in range(2, n)}, sparse_points=100)
    result = register_scans(clouds, refine_rounds=0, threads=1, partners=n - 1, pair_points=100, refine_points=300)
    assert result.status == ("placed",) * n, result.reasons
    assert sum(1 for e in result.kept_edges if 0 in (e.i, e.j)) >= 2
    for k in range(n):
        angle, shift = _errors(result.poses[k], truth[k])
        assert angle < 1e-6 and shift < 1e-6


def test_a_trusted_registration_of_a_pair_is_kept_over_an_untrusted_one_however_confident(monkeypatch):
    """A walk whose pairs across scans 3 and 4 (the only ones joining its two halves) stop at their
    iteration cap when refined from the identity: untrusted, yet at the full overlap confidence.
    Their global retry is trusted at a lower confidence; the merge keeps the trusted edges, and
    every scan is placed, exactly."""
    n = 8
    rng = np.random.default_rng(13)
    truth = _truth(n, rng)
    clouds = _clouds(truth, rng)
    walk = {(k, k + d) for d in (1, 2) for k in range(n - d)}
    across = {(2, 4), (3, 4), (3, 5)}
    _patch(monkeypatch, truth, clouds, overlapping=walk, stalled=across)
    result = register_scans(clouds, sequence=True, refine_rounds=0, threads=1, range_images=False)
    stored = {(min(e.i, e.j), max(e.i, e.j)): e for e in result.edges}
    for pair in sorted(across):
        assert stored[pair].trusted and stored[pair].kind == "global", (pair, stored[pair].reason)
    assert result.status == ("placed",) * n, result.reasons
    for k in range(n):
        angle, shift = _errors(result.poses[k], truth[k])
        assert angle < 1e-6 and shift < 1e-6


@pytest.mark.parametrize("half", [8, 16])
def test_a_sequence_whose_pieces_do_not_join_stops_and_names_the_piece_apart(monkeypatch, half):
    """Two pieces of a walk that share no surface: the search across them is bounded whatever the
    pieces' size (a round's pairs are counted per piece, not per scan), and the result names the
    piece that stands apart."""
    n = 2 * half
    rng = np.random.default_rng(8)
    truth = _truth(n, rng)
    clouds = _clouds(truth, rng)
    overlapping = {(i, j) for i in range(n) for j in range(i + 1, n) if (i < half) == (j < half)}
    _patch(monkeypatch, truth, clouds, overlapping=overlapping)
    result = register_scans(clouds, sequence=True, refine_rounds=0, threads=1)
    assert result.status == ("placed",) * half + ("unplaced",) * half, result.reasons
    across = [e for e in result.edges if (e.i < half) != (e.j < half)]
    rounds = 2 * MergeConfig().stalled_rounds  # none places a scan; before and after a free-space veto
    # the walk's own pairs across the cut (two neighbours each), then per round one piece's pairs
    assert len(across) <= 3 + rounds * 3 ** 2, len(across)
    assert any(f"scans {half}-{n - 1} ({half} scans) are joined to each other but not to the placed" in note
               for note in result.notes), result.notes


def test_consensus_tree_outvotes_a_confident_wrong_edge():
    rng = np.random.default_rng(5)
    truth = _truth(4, rng)
    edges = [(i, j, np.linalg.inv(truth[i]) @ truth[j], 0.5) for i in range(4) for j in range(i + 1, 4)]
    wrong = np.linalg.inv(truth[0]) @ truth[2] @ np.diag([1.0, -1.0, -1.0, 1.0])
    edges[1] = (0, 2, wrong, 1.0)
    poses = pose_graph.consensus_tree(edges, 0, max_angle_deg=2.0, max_shift=lambda m: 0.1)
    for k in range(4):
        assert _errors(poses[k], truth[k])[0] < 1e-6


def test_pose_graph_optimisation_pulls_perturbed_poses_onto_consistent_edges():
    """``pose_graph.optimise`` (every edge's residual computed at once): from poses a few degrees
    and centimetres off, exact edges of a 5-scan graph bring every pose back to the truth, with
    the reference held at the identity and a wrong edge (a half turn) outvoted by the Cauchy loss.
    Fails if a residual's frames are mixed up (T_i_j^-1 T_world_i^-1 T_world_j)."""
    rng = np.random.default_rng(7)
    truth = _truth(5, rng)
    reference = 2
    truth = [np.linalg.inv(truth[reference]) @ T for T in truth]
    edges = [(i, j, np.linalg.inv(truth[i]) @ truth[j], 1.0) for i in range(5) for j in range(i + 1, 5)]
    edges[3] = (edges[3][0], edges[3][1], edges[3][2] @ np.diag([1.0, -1.0, -1.0, 1.0]), 1.0)
    start = {}
    for k, T in enumerate(truth):
        nudge = pose_graph.pose_from_vector(np.concatenate([rng.normal(scale=0.05, size=3), rng.normal(scale=0.05, size=3)]))
        start[k] = T if k == reference else nudge @ T
    poses = pose_graph.optimise(start, edges, reference, translation_scale=0.01,
                                direct_solve_max_poses=200)
    np.testing.assert_array_equal(poses[reference], np.eye(4))
    for k in range(5):
        rotation, translation = _errors(poses[k], truth[k])
        assert rotation < 0.05 and translation < 1e-3, (k, rotation, translation)
    assert max(_errors(start[k], truth[k])[0] for k in range(5)) > 2.0  # the start was off


def _robust_cost(poses, edges, translation_scale):
    """The cost ``pose_graph.optimise`` documents: sum of log(1 + r^2) over the whitened residuals'
    components, the residual of an edge the (rotation vector, translation) of
    T_i_j^-1 T_world_i^-1 T_world_j."""
    total = 0.0
    for i, j, T_i_j, weight, information in edges:
        error = pose_graph.vector_from_pose(np.linalg.inv(T_i_j) @ np.linalg.inv(poses[i]) @ poses[j])
        W = pose_graph.whitening(weight, information, T_i_j, translation_scale=translation_scale)
        total += float(np.sum(np.log1p((W @ error) ** 2)))
    return total


def test_conjugate_gradients_solve_the_pose_graph_normal_equations():
    """The solver of large pose graphs (beyond ``MergeConfig.direct_solve_max_poses``): on a sparse symmetric
    positive definite matrix of 6x6 blocks coupled like a pose graph's, it returns the solution a
    direct solve gives."""
    from scipy.sparse import bsr_matrix
    from scipy.sparse.linalg import spsolve

    rng = np.random.default_rng(2)
    poses = 40
    dense = np.zeros((6 * poses, 6 * poses))
    for _ in range(120):  # each "edge" adds J^T J over its two poses' 12 unknowns
        a, b = rng.choice(poses, 2, replace=False)
        J = rng.normal(size=(6, 12))
        index = np.r_[6 * a: 6 * a + 6, 6 * b: 6 * b + 6]
        dense[np.ix_(index, index)] += J.T @ J
    dense += 1e-3 * np.eye(6 * poses)
    blocks = np.array([dense[6 * k: 6 * k + 6, 6 * k: 6 * k + 6] for k in range(poses)])
    right = rng.normal(size=6 * poses)
    matrix = bsr_matrix(dense, blocksize=(6, 6)).tocsr()
    solved = pose_graph._conjugate_gradients(matrix, right, blocks)
    exact = spsolve(matrix.tocsc(), right)
    assert np.linalg.norm(matrix @ solved - right) <= 1e-5 * np.linalg.norm(right)
    np.testing.assert_allclose(solved, exact, rtol=1e-3, atol=1e-6 * np.abs(exact).max())


def test_pose_graph_optimisation_ends_at_a_minimum_of_its_documented_cost():
    """On a noisy 12-scan graph with a wrong edge and mixed weights (information matrices on some
    edges), the solved poses are a minimum of the documented robust cost: no small motion of any
    free pose, rotation or translation, either sign, lowers it. Fails if the solver stops short
    (three steps do) or its closed-form Jacobian does not match the cost."""
    rng = np.random.default_rng(11)
    truth = _truth(12, rng)
    edges = []
    for i in range(12):
        for j in range(i + 1, 12):
            if j - i <= 2 or rng.random() < 0.15:
                noise = pose_graph.pose_from_vector(np.concatenate([rng.normal(scale=0.01, size=3),
                                                                    rng.normal(scale=0.01, size=3)]))
                A = rng.normal(size=(6, 6))
                information = A @ A.T * 100 + np.eye(6) * 1e3 if rng.random() < 0.5 else None
                edges.append((i, j, noise @ np.linalg.inv(truth[i]) @ truth[j], float(rng.uniform(0.3, 1.0)), information))
    edges[4] = (edges[4][0], edges[4][1], edges[4][2] @ np.diag([1.0, -1.0, -1.0, 1.0]), 1.0, None)
    start = {k: (T if k == 0 else pose_graph.pose_from_vector(rng.normal(scale=0.03, size=6)) @ T)
             for k, T in enumerate(truth)}
    poses = pose_graph.optimise(start, edges, 0, translation_scale=0.02,
                                direct_solve_max_poses=200)
    best = _robust_cost(poses, edges, 0.02)
    assert best < _robust_cost(start, edges, 0.02)
    for k in range(1, 12):
        for axis in range(6):
            for sign in (-1.0, 1.0):
                step = np.zeros(6)
                step[axis] = sign * 1e-4
                moved = dict(poses)
                moved[k] = pose_graph.pose_from_vector(step) @ poses[k]
                assert _robust_cost(moved, edges, 0.02) >= best - 1e-6 * max(best, 1.0), (k, axis, sign)


def test_merged_voxel_and_bad_arguments():
    rng = np.random.default_rng(6)
    cloud = rng.uniform(size=(500, 3))
    result = register_scans([cloud], processes=1)
    assert result.placed == (True,) and result.edges == ()
    points, labels = result.merged([cloud], voxel=0.25)
    assert len(points) <= 64 and (labels == 0).all()
    with pytest.raises(InvalidInputError, match="reference"):
        register_scans([cloud, cloud], reference=2)
    with pytest.raises(InvalidInputError, match="voxel"):
        result.merged([cloud], voxel=0)


@pytest.fixture
def bunny_files(tmp_path, bunny):
    from esmicp import write_points

    clouds, _ = bunny
    paths = []
    for name, cloud in zip(BUNNY[:3], clouds[:3]):
        path = tmp_path / f"{name}.ply"
        write_points(path, cloud[::2])
        paths.append(path)
    return paths


def test_cli_merge_end_to_end(tmp_path, bunny_files):
    from esmicp.cli import main

    require_module("plotly", "viz")  # --view writes an interactive page
    out, poses, view = tmp_path / "merged.ply", tmp_path / "poses.txt", tmp_path / "merged.html"
    argv = [*map(str, bunny_files), "-o", str(out), "--poses-out", str(poses), "--view", str(view),
            "--voxel", "0.002", "--processes", "1", "--pair-points", "800", "--no-progress"]
    assert main(["merge", *argv]) == 0
    assert out.exists() and view.exists()
    from esmicp import read_poses

    written = read_poses(poses)
    assert written.names == tuple(str(p) for p in bunny_files)  # the paths as given
    assert written.status == ("placed",) * 3 and written.reference == 0
    np.testing.assert_allclose(written.poses[0], np.eye(4))
    np.testing.assert_array_equal(np.loadtxt(poses).reshape(-1, 4, 4), written.poses)
    assert main(["merge", *argv]) == 2  # no overwrite without --force


def test_cli_merge_bad_scan_writes_nothing_unless_skip_bad(tmp_path, bunny_files, capsys):
    from esmicp.cli import main

    bad = tmp_path / "broken.ply"
    bad.write_text("not a cloud\n")
    out = tmp_path / "merged.ply"
    argv = [str(bunny_files[0]), str(bad), str(bunny_files[1]), "-o", str(out), "--processes", "1",
            "--pair-points", "500", "--no-progress"]
    assert main(["merge", *argv]) == 2
    assert "broken.ply" in capsys.readouterr().err
    assert not out.exists()
    assert main(["merge", *argv, "--skip-bad"]) == 0
    assert out.exists()


def test_cli_merge_reads_three_column_bin_scans_by_their_values(tmp_path, bunny, capsys):
    """Headerless x y z float32 .bin scans whose size also fits 4 columns are read in the layout
    their values fit, with no --bin-columns; a file whose values read as points either way (an
    isotropic blob) is refused, named, before any work, and nothing is written."""
    from esmicp.cli import main

    clouds, _ = bunny
    paths = []
    for name, cloud in zip(BUNNY[:3], clouds[:3]):
        points = cloud[::2][:6000].astype(np.float32)
        assert (points.size * 4) % 48 == 0  # ambiguous by size: fits 3 and 4 columns
        path = tmp_path / f"{name}.bin"
        points.tofile(path)
        paths.append(path)
    blob = tmp_path / "blob.bin"
    np.random.default_rng(0).normal(size=(6000, 3)).astype(np.float32).tofile(blob)
    out = tmp_path / "merged.ply"
    options = ["-o", str(out), "--processes", "1", "--pair-points", "800", "--no-progress"]
    assert main(["merge", *map(str, paths), str(blob), *options]) == 2
    assert not out.exists()
    assert "blob.bin" in capsys.readouterr().err
    assert main(["merge", *map(str, paths), *options]) == 0
    assert out.exists()


def test_bridging_pairs_join_a_piece_to_the_placed_scans_most_alike_first_each_scan_and_piece_capped():
    from esmicp.multiview.pairs import bridging_pairs

    rng = np.random.default_rng(6)
    distances = rng.random((30, 30))
    distances = distances + distances.T
    placed = [0, 4, 7, 20, 21, 22, 23, 24]
    pieces = [[1], [2, 3], list(range(8, 20))]  # a single scan, two scans, a piece of twelve
    tried = {(0, 1), (4, 8)}
    pairs = bridging_pairs(distances, placed, pieces, tried, 2)
    assert len(pairs) == len(set(pairs))
    for i, j in pairs:
        assert i < j and (i, j) not in tried
        assert (i in placed) != (j in placed)
    counts = np.bincount(np.array(pairs).ravel(), minlength=30)
    assert counts.max() <= 2
    for piece in pieces:
        across = [p for p in pairs if set(p) & set(piece)]
        # a piece costs at most what 2 of its scans asking for 2 pairs each would: not one per scan
        assert 1 <= len(across) <= 2 * min(len(piece), 2)
    gaps = [distances[i, j] for i, j in pairs]
    assert gaps == sorted(gaps)
    assert bridging_pairs(distances, [], pieces, set(), 2) == []
    assert bridging_pairs(distances, placed, [], set(), 2) == []


def _walk_twice(count, laps=2):
    """Extents of a walk going round one loop ``laps`` times: scan k at angle 2 pi k laps / count."""
    angle = 2 * np.pi * laps * np.arange(count) / count
    return {k: (np.array([np.cos(a), np.sin(a), 0.0]) * count / (2 * np.pi * laps), 1.0) for k, a in enumerate(angle)}


def test_loop_pairs_close_the_longest_bypasses_until_none_is_left():
    from esmicp.multiview.pairs import _hops, loop_pairs

    n, min_hops = 60, 6
    extents = _walk_twice(n)
    walk = [(k, k + 1) for k in range(n - 1)] + [(k, k + 2) for k in range(n - 2)]

    def overlap(a, b):  # scans at the same place of the loop see the same surface
        return float(np.linalg.norm(extents[a][0] - extents[b][0]) < 1.0)

    loops = loop_pairs(walk, extents, overlap, set(), min_overlap=0.5, min_hops=min_hops, budget=n, partners=16)
    assert loops and len(loops) == len(set(loops))
    assert all(overlap(*pair) == 1.0 and pair[0] < pair[1] for pair in loops)
    # the walk's own edges make pairs a few frames apart short paths: none of those is a loop
    assert all(j - i >= min_hops for i, j in loops)
    # the closures spread over the second lap: with them, every pair that overlaps is joined by a
    # path shorter than min_hops, so none is left worth a search
    hops = _hops(n, walk + loops)
    assert all(hops[i, j] < min_hops for i in range(n) for j in range(i + 1, n) if overlap(i, j) == 1.0)
    assert len(loops) < n // 4  # far fewer than one per scan
    # a budget caps them; the first ones are the longest bypasses
    first = loop_pairs(walk, extents, overlap, set(), min_overlap=0.5, min_hops=min_hops, budget=2, partners=16)
    assert first == loops[:2]
    assert _hops(n, walk)[first[0]] == max(_hops(n, walk)[i, j] for i, j in loops)
    assert loop_pairs(walk, extents, overlap, set(loops), min_overlap=0.5, min_hops=min_hops, budget=n,
                      partners=16) != loops


def test_closing_pairs_put_each_bridge_on_a_cycle_with_one_pair():
    from esmicp.multiview.pairs import closing_pairs, hanging_parts

    # a triangle 0-1-2 with a chain 2-3-4-5 hanging from it, and a scan 6 hanging from 0
    kept = [(0, 1), (1, 2), (0, 2), (2, 3), (3, 4), (4, 5), (0, 6)]
    parts = hanging_parts(0, kept)
    assert parts == [{5}, {6}, {4, 5}, {3, 4, 5}]
    extents = {k: (np.zeros(3), 1.0) for k in range(7)}
    likely = {(1, 5): 0.9, (1, 4): 0.8, (3, 6): 0.7, (2, 6): 0.6}

    def overlap(a, b):
        return likely.get((min(a, b), max(a, b)), 0.0)

    pairs = closing_pairs(parts, extents, overlap, set(), min_overlap=0.5, per_part=1, partners=16)
    # (1, 5) crosses the three cuts of the chain; 6 gets its own: (3, 6) is the likeliest
    assert pairs == [(1, 5), (3, 6)]
    tried = {(1, 5), (3, 6)}
    # 5 has no other likely partner: the pair across the next cut up puts it on a cycle too
    assert sorted(closing_pairs(parts, extents, overlap, tried, min_overlap=0.5, per_part=1,
                                partners=16)) == [(1, 4), (2, 6)]
    # below the predicted overlap asked for, nothing is worth a search
    assert closing_pairs(parts, extents, overlap, set(), min_overlap=0.95, per_part=1, partners=16) == []


def _check_progress_contract(calls):
    """Every stage opens at done == 0 with a total that then never changes; done never decreases
    nor exceeds the total, and the stage closes at done == total before the next one opens."""
    assert calls and calls[0][1] == 0
    stages = []
    for stage, done, total in calls:
        assert isinstance(stage, str) and stage and total >= 1 and 0 <= done <= total, (stage, done, total)
        if done == 0:
            assert not stages or stages[-1][1][-1][1] == stages[-1][1][-1][2], f"{stages[-1][0]} left unfinished"
            stages.append((stage, [(stage, done, total)]))
            continue
        name, seen = stages[-1]
        assert stage == name and total == seen[-1][2], f"{stage} {done}/{total} inside {name} of total {seen[-1][2]}"
        assert done >= seen[-1][1]
        seen.append((stage, done, total))
    assert stages[-1][1][-1][1] == stages[-1][1][-1][2], f"{stages[-1][0]} left unfinished"
    return [(name, seen[0][2]) for name, seen in stages]


def test_progress_announces_each_stage_with_a_total_that_never_grows():
    """A sequence of four scans of one shape and an intruder: the pairs, the global retries, the
    loop closures and the rounds of more pairs each announce their registrations up front; the
    pose graph, the joint refinement and the free-space check follow, each counted to its end."""
    from esmicp.shapes import asymmetric_shape

    rng = np.random.default_rng(5)
    clouds = [asymmetric_shape(1200, rng) @ Rotation.from_rotvec(rng.normal(size=3)).as_matrix().T + rng.normal(size=3)
              for _ in range(4)]
    clouds.append(rng.normal(size=(1200, 3)))  # another object: more pairs are asked for it
    calls = []
    result = register_scans(clouds, sequence=True, threads=2, pair_points=400, refine_points=1200,
                            progress=lambda *call: calls.append(call))
    stages = _check_progress_contract(calls)
    names = [name for name, _ in stages]
    # the stages announced are the stages recorded that ran registrations or steps, in order
    assert names == [stage.name for stage in result.stages if stage.name not in ("prepare", "rank pairs", "verdict")
                     and stage.decided.get("registrations", 1) > 0]
    assert names[0] == "pairs" and "pose graph" in names and names[-2:] == ["joint refinement", "free-space check"]
    pairs = [total for name, total in stages if "pairs" in name]
    assert len(pairs) >= 3  # the pairs, their retries, more: each its own stage, its total fixed at its start
    assert sum(pairs) >= result.pairs_registered  # every registration run was announced
    with pytest.raises(InvalidInputError, match="progress"):
        register_scans(clouds[:2], progress=3)


def test_progress_contract_check_catches_a_growing_total():
    with pytest.raises(AssertionError):
        _check_progress_contract([("pairs", 0, 4), ("pairs", 3, 4), ("pairs", 5, 8), ("pairs", 8, 8)])
    with pytest.raises(AssertionError):
        _check_progress_contract([("pairs", 0, 4), ("pairs", 2, 4), ("pose graph", 0, 1), ("pose graph", 1, 1)])
    assert _check_progress_contract([("pairs", 0, 4), ("pairs", 4, 4), ("pose graph", 0, 1), ("pose graph", 1, 1)]) \
        == [("pairs", 4), ("pose graph", 1)]


@pytest.mark.parametrize("search, sequence, second_try", [(None, False, False), ({"keypoints": 3000}, True, True),
                                                        (None, True, False)])
def test_the_merge_bounds_the_scan_searches_of_its_global_pair_searches_only(monkeypatch, search, sequence,
                                                                            second_try):
    """Every batch of pairs on the sparse subsets (a global search, or with ``sequence`` a
    refinement from the identity: a call not judged) runs with at most
    ``MergeConfig.pair_scan_searches`` scan-strategy searches and the second try of a refinement
    from a given start as ``MergeConfig.sparse_second_try`` says, on the merge's registration
    config otherwise; the local checks on the dense subsets keep that config as given, and
    ``register``'s default search stays unbounded."""
    from esmicp.config import MergeConfig, RegistrationConfig
    from esmicp.globalreg.config import DEFAULT

    n = 5
    rng = np.random.default_rng(4)
    truth = _truth(n, rng)
    clouds = _clouds(truth, rng)
    _patch(monkeypatch, truth, clouds, low={4})
    fake, seen = scans_module.register_many, []

    def recorder(jobs, *, inits=None, **options):
        seen.append((inits, options.get("config"), options.get("judge", True)))
        return fake(jobs, inits=inits, **options)

    monkeypatch.setattr(scans_module, "register_many", recorder)
    merge = MergeConfig(sparse_second_try=second_try) if search is None else \
        MergeConfig.from_dict({"registration": {"search": search}, "sparse_second_try": second_try})
    register_scans(clouds, refine_rounds=0, threads=1, pair_points=100, refine_points=300, config=merge,
                   sequence=sequence)
    # a batch of pairs passes one start or None per pair (a piece's placement passes none)
    sparse = [config for inits, config, judged in seen if inits is not None and not judged]
    checks = [config for inits, config, judged in seen if inits is not None and judged]
    assert sparse and checks
    refined = [inits for inits, _, judged in seen
               if inits is not None and not judged and all(init is not None for init in inits)]
    assert bool(refined) == sequence  # the sequence's first pairs, refined from the identity
    given = merge.registration
    for config in sparse:
        assert isinstance(config, RegistrationConfig)
        assert config.search == replace(given.search, scan_searches=merge.pair_scan_searches)
        assert config.trust == given.trust
        assert config.refine == replace(given.refine, second_try=second_try)
    assert all(config == given for config in checks)
    assert DEFAULT.scan_searches is None


def _bumpy_ring_views(n, rng, points=3000, window_deg=75.0):
    """``n`` views, ``360 / n`` degrees apart, of one closed surface with distinct local shapes (a
    cylinder with 80 random bumps), each view the points within ``window_deg`` of its direction,
    in a frame of its own (``truth[k]`` is ``T_world_view``): views k and k+1 overlap, k and k+3
    do not."""
    theta, z = rng.uniform(0, 2 * np.pi, points), rng.uniform(-0.5, 0.5, points)
    bumps = rng.uniform([0, -0.5, 0.02, 0.08], [2 * np.pi, 0.5, 0.08, 0.2], size=(80, 4))
    turned = np.angle(np.exp(1j * (theta[:, None] - bumps[:, 0])))
    height = np.exp(-(turned ** 2 + (z[:, None] - bumps[:, 1]) ** 2) / bumps[:, 3] ** 2)
    radius = 1 + np.sum(bumps[:, 2] * height, axis=1)
    world = np.c_[radius * np.cos(theta), radius * np.sin(theta), z]
    truth = _truth(n, rng)
    views = []
    for k in range(n):
        inside = np.abs(np.angle(np.exp(1j * (theta - 2 * np.pi * k / n)))) <= np.radians(window_deg) / 2
        views.append((world[inside] - truth[k][:3, 3]) @ truth[k][:3, :3])
    return truth, views


def _matching(views):
    from esmicp.multiview import pairs

    config = MergeConfig()
    return pairs.matching_distances(views, candidates=config.match_candidates,
                                    radius_spacings=config.match_radius_spacings,
                                    normal_neighbours=config.match_normal_neighbours, count=config.match_points)


def test_surface_matching_finds_the_overlapping_views_wherever_they_lie_and_in_any_order():
    """Views of one surface ranked by their matching surface features, with no poses: each view's
    most similar is nearly always a view it overlaps (by the shape descriptor alone, 0-3 of 10
    are); the ranking does not depend on the order the views come in, and a rigid motion of a view
    changes it by no more than rounding."""
    n = 10
    truth, views = _bumpy_ring_views(n, np.random.default_rng(0))
    distances = _matching(views)
    assert distances.shape == (n, n) and np.allclose(np.diag(distances), 0.0) and np.allclose(distances, distances.T)
    nearest = [int(np.argsort(distances[k])[1]) for k in range(n)]
    neighbours = sum((nearest[k] - k) % n in (1, n - 1) for k in range(n))
    assert neighbours >= n - 1, nearest
    order = np.random.default_rng(1).permutation(n)
    np.testing.assert_allclose(_matching([views[k] for k in order]), distances[np.ix_(order, order)], atol=1e-12)
    turn = Rotation.from_rotvec([0.4, -0.9, 1.3]).as_matrix()
    moved = _matching([v @ turn.T + [3.0, -1.0, 2.0] if k == 0 else v for k, v in enumerate(views)])
    assert np.abs(moved - distances).max() < 0.02


def test_a_bridge_the_poses_predict_no_pair_across_gets_the_most_similar_pair_across_it():
    """Scans 4-5 hang from 0-3 by one edge, 6 from 4-5 by another. For each bridge not crossed by
    a pair chosen already, the most similar untried pair with one scan on each side (never one
    inside a part, never one tried, never one of an unposed scan), smallest part first: one pair
    may cross both bridges."""
    from esmicp.multiview import pairs

    distances = np.full((8, 8), 0.9)
    distances[6, 1] = distances[1, 6] = 0.1   # crosses both bridges
    distances[4, 5] = distances[5, 4] = 0.05  # inside a part
    distances[5, 2] = distances[2, 5] = 0.2
    distances[5, 6] = distances[6, 5] = 0.3
    distances[4, 7] = distances[7, 4] = 0.01  # scan 7 is not posed
    np.fill_diagonal(distances, 0.0)
    parts = [{6}, {4, 5, 6}]
    posed = range(7)
    assert pairs.similar_crossing_pairs(parts, distances, posed, set(), [], per_part=1) == [(1, 6)]
    assert pairs.similar_crossing_pairs(parts, distances, posed, {(1, 6)}, [], per_part=1) == [(5, 6), (2, 5)]
    assert pairs.similar_crossing_pairs(parts, distances, posed, {(1, 6)}, [(3, 4)], per_part=1) == [(5, 6)]
    assert pairs.similar_crossing_pairs(parts, distances, posed, {(1, 6)}, [(3, 6)], per_part=1) == []


@pytest.mark.parametrize("n", [6, 12])
def test_a_clean_ring_costs_its_own_pairs_and_no_more(monkeypatch, n):
    """Scans on a ring, each overlapping its two neighbours only, and each the most similar to its
    neighbours: the first pairs are the ring's n pairs, every scan is on their cycle, and no pair is
    asked for beyond them (one registration of each, the search and its check)."""
    rng = np.random.default_rng(13)
    truth = _truth(n, rng)
    clouds = _clouds(truth, rng)
    ring = {(min(k, (k + 1) % n), max(k, (k + 1) % n)) for k in range(n)}
    index = np.arange(n)
    hops = np.abs(index[:, None] - index[None, :])
    distances = np.minimum(hops, n - hops) / n
    monkeypatch.setattr(scans_module.candidates, "matching_distances", lambda clouds, **_: distances)
    _patch(monkeypatch, truth, clouds, overlapping=ring)
    result = register_scans(clouds, refine_rounds=0, threads=1)
    assert result.status == ("placed",) * n, result.reasons
    assert {(min(e.i, e.j), max(e.i, e.j)) for e in result.edges} == ring
    assert result.pairs_registered == 2 * n
    assert [stage.name for stage in result.stages if "pairs" in stage.name] == ["rank pairs", "pairs"]


def _turntable_ring(n, lean_deg, wrong=(), seed=17):
    """``n`` scans on a turntable (each turned ``360 / n`` degrees about z from the last), the fake
    pairwise results of the ring's neighbouring pairs each leaning ``lean_deg`` about z the same way
    (the ring closes ``n * lean_deg`` off), every other pair untrusted, each result with a tight
    information matrix as a registration's is; ``wrong`` pairs trusted and 40 degrees off."""
    rng = np.random.default_rng(seed)
    truth = []
    for k in range(n):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", 360.0 * k / n, degrees=True).as_matrix()
        T[:3, 3] = rng.normal(scale=0.05, size=3)
        truth.append(T)
    ring = {(min(k, (k + 1) % n), max(k, (k + 1) % n)) for k in range(n)}
    return truth, _clouds(truth, rng, points=400), ring


def _leaning(monkeypatch, lean_deg):
    """Every registration the merge runs returns its pose turned ``lean_deg`` further about z in the
    sense it turns (a turn of the table measured a little too large, whichever scan is the
    target), with a tight 6x6 information matrix."""
    faked = scans_module.register_many

    def leaned(T):
        lean = np.eye(4)
        turn = np.sign(np.arctan2(T[1, 0], T[0, 0]))
        lean[:3, :3] = Rotation.from_euler("z", turn * lean_deg, degrees=True).as_matrix()
        return T @ lean

    def leaning(jobs, **options):
        return [replace(r, transformation=leaned(r.transformation), information=1e6 * np.eye(6))
                if isinstance(r, RegistrationResult) else r for r in faked(jobs, **options)]

    monkeypatch.setattr(scans_module, "register_many", leaning)


def test_small_errors_adding_up_around_a_ring_reject_no_edge_the_surfaces_agree_with(monkeypatch):
    """Twelve scans on a turntable whose neighbouring pairs each lean 0.5 degrees the same way (the
    ring closes 6 degrees off, each pair well within the graph's 2 degrees): the graph pins the sum
    on one ring edge, the surfaces (the joint refinement over the other edges) agree with it, so it
    is kept, every scan is confirmed by the ring, and no pair is asked for beyond the ring's."""
    n = 12
    truth, clouds, ring = _turntable_ring(n, 0.5)
    index = np.arange(n)
    hops = np.abs(index[:, None] - index[None, :])
    distances = np.minimum(hops, n - hops) / n
    monkeypatch.setattr(scans_module.candidates, "matching_distances", lambda clouds, **_: distances)
    _patch(monkeypatch, truth, clouds, overlapping=ring)
    _leaning(monkeypatch, 0.5)
    result = register_scans(clouds, threads=1, range_images=False)
    names = [stage.name for stage in result.stages]
    graph = [stage for stage in result.stages if stage.name == "pose graph"][0]
    assert graph.decided["cycle_inconsistent"] == 1  # the graph alone rejects one right ring edge
    assert "joint refinement (cycle check)" in names and not any(name.startswith("more pairs") for name in names)
    assert result.status == ("placed",) * n, result.reasons
    assert {(min(e.i, e.j), max(e.i, e.j)) for e in result.kept_edges} == ring
    assert result.pairs_registered == 2 * n
    for k in range(n):
        angle, _ = _errors(result.poses[k], truth[k])
        assert angle < 2.0


def test_a_wrong_edge_stays_rejected_when_the_surfaces_judge_the_rejected_edges(monkeypatch):
    """The same leaning ring with one more pair, across two of its edges, trusted and 40 degrees
    off: the graph rejects it and pins the ring's 6 degrees on a ring edge; the poses refined over
    the kept edges agree with that ring edge, not with the wrong one, which stays rejected."""
    n = 12
    truth, clouds, ring = _turntable_ring(n, 0.5)
    index = np.arange(n)
    hops = np.abs(index[:, None] - index[None, :])
    distances = np.minimum(hops, n - hops) / n
    distances[5, 7] = distances[7, 5] = 0.01  # the wrong pair is among the first pairs
    monkeypatch.setattr(scans_module.candidates, "matching_distances", lambda clouds, **_: distances)
    _patch(monkeypatch, truth, clouds, overlapping=ring | {(5, 7)}, wrong={(5, 7)}, apart={5, 6})
    _leaning(monkeypatch, 0.5)
    result = register_scans(clouds, threads=1, range_images=False)
    graph = [stage for stage in result.stages if stage.name == "pose graph"][0]
    assert graph.decided["cycle_inconsistent"] == 2  # the wrong pair and one right ring edge
    assert "joint refinement (cycle check)" in [stage.name for stage in result.stages]
    assert {(min(e.i, e.j), max(e.i, e.j)) for e in result.edges} >= ring | {(5, 7)}
    assert [(min(e.i, e.j), max(e.i, e.j)) for e in result.rejected_edges if e.trusted] == [(5, 7)]
    assert result.status == ("placed",) * n, result.reasons
    for k in range(n):
        angle, _ = _errors(result.poses[k], truth[k])
        assert angle < 2.0


def test_a_walk_joined_across_a_break_has_its_loops_sought_once_the_far_side_is_posed(monkeypatch):
    """A walk twice round one place (scan k and scan k + n/2 see the same surface), broken in the
    middle (the frames either side of the break share nothing): the first pairs pose the near side
    only, a round of more pairs joins the far side, and then the far side's loop closures are
    sought too, among every posed scan, within ``loop_searches_per_scan`` per posed scan over the
    whole merge; every scan is placed, exactly."""
    n = 20
    half = n // 2
    rng = np.random.default_rng(21)
    truth = _truth(n, rng)
    clouds = _clouds(truth, rng)
    walk = {(k, k + d) for d in (1, 2) for k in range(n - d) if (k < half) == (k + d < half)}
    laps = {(k, k + half) for k in range(half)}
    index = np.arange(n)
    distances = np.where(np.abs(index[:, None] - index[None, :]) == half, 0.1, 1.0)
    np.fill_diagonal(distances, 0.0)
    monkeypatch.setattr(scans_module.candidates, "matching_distances", lambda clouds, **_: distances)
    _patch(monkeypatch, truth, clouds, overlapping=walk | laps)
    config = MergeConfig()
    result = register_scans(clouds, sequence=True, refine_rounds=0, threads=1, range_images=False)
    assert result.status == ("placed",) * n, result.reasons
    names = [stage.name for stage in result.stages]
    joined = next(m for m, stage in enumerate(result.stages) if stage.name.startswith("more pairs"))
    loops = [stage for stage in result.stages if stage.name == "pairs (loop closures)"]
    later = [stage for stage in result.stages[joined:] if stage.name == "pairs (loop closures)"]
    assert later and later[0].decided["pairs"] >= 1, names
    assert loops[0].decided["posed"] == half and later[0].decided["posed"] == n  # the near side, then every scan
    assert sum(stage.decided["pairs"] for stage in loops) <= int(np.ceil(config.loop_searches_per_scan * n))
    for k in range(n):
        angle, shift = _errors(result.poses[k], truth[k])
        assert angle < 1e-6 and shift < 1e-6


def test_an_edge_the_surfaces_keep_stays_kept_when_the_graph_is_solved_again(monkeypatch):
    """The leaning ring of twelve scans (the graph pins its 6 degrees on one right ring edge, the
    surfaces keep it) and a thirteenth scan between scans 0 and 1 whose first pairs (with the
    scans most like it, 5 and 6) share nothing: the round of more pairs that places it solves the
    graph again, and the ring edge the surfaces kept stays kept, so the ring confirms every scan."""
    n = 12
    truth, clouds, ring = _turntable_ring(n, 0.5)
    between = np.eye(4)
    between[:3, :3] = Rotation.from_euler("z", 360.0 / n / 2, degrees=True).as_matrix()
    truth.append(between)
    clouds.append(_clouds([between], np.random.default_rng(3), points=400)[0])
    index = np.arange(n + 1)
    hops = np.abs(index[:, None] - index[None, :])
    distances = np.minimum(hops, n - hops) / n
    distances[n, :] = distances[:, n] = 0.9
    distances[n, [5, 6]] = distances[[5, 6], n] = 0.01  # its first pairs: the most alike, and apart
    distances[n, [0, 1]] = distances[[0, 1], n] = 0.5
    distances[n, n] = 0.0
    monkeypatch.setattr(scans_module.candidates, "matching_distances", lambda clouds, **_: distances)
    _patch(monkeypatch, truth, clouds, overlapping=ring | {(0, n), (1, n)})
    _leaning(monkeypatch, 0.5)
    result = register_scans(clouds, threads=1, range_images=False)
    names = [stage.name for stage in result.stages]
    assert "joint refinement (cycle check)" in names and any(name.startswith("more pairs") for name in names)
    assert result.status == ("placed",) * (n + 1), result.reasons
    kept = {(min(e.i, e.j), max(e.i, e.j)) for e in result.kept_edges}
    assert kept >= ring, sorted(ring - kept)
    assert all(result.reasons[k][0].startswith("confirmed") for k in range(1, n + 1)), result.reasons
