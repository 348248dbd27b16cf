"""What ``register_scans`` promises as data: ``result.stages`` (what each stage of the merge did),
and verdicts that do not depend on the order the scans come in or on where they lie (every scan
moved by one rigid motion, or shifted by 1e6), on small synthetic scans with the pairwise
registrations faked (:func:`test_multiview._patch`), so that only the merge's own decisions are
tested."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from esmicp.multiview import register_scans
from esmicp.result import Stage

from test_multiview import _errors, _patch, _truth

N = 7
WRONG = {(1, 3)}  # trusted, the most confident, and wrong by 40 degrees: only the graph can reject it
LOW = {5}  # every pair of this scan untrusted: it cannot be placed


def _windows(truth, rng, points=1500):
    """Scan k sees the world points in its own window along x (neighbours' windows overlap, so
    each scan has a shape of its own), in its own frame (``truth[k]`` is ``T_world_scan``)."""
    world = rng.uniform(-1, 1, size=(points, 3))
    world[:, 0] *= 2.0
    out = []
    for k, T in enumerate(truth):
        low = -2.0 + 3.2 * k / len(truth)
        seen = world[(world[:, 0] >= low) & (world[:, 0] <= low + 1.2)]
        out.append((seen - T[:3, 3]) @ T[:3, :3])
    return out


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(21)
    truth = _truth(N, rng)
    return truth, _windows(truth, rng)


def _merge(monkeypatch, truth, clouds, *, wrong=WRONG, low=LOW, **options):
    _patch(monkeypatch, truth, clouds, wrong=wrong, low=low)
    return register_scans(clouds, threads=1, pair_points=150, refine_points=300, **options)


@pytest.fixture
def plain(monkeypatch, scene):
    truth, clouds = scene
    return _merge(monkeypatch, truth, clouds)


def _decided(result, leave_out=("check", "rmse")):
    """Each stage's name and counts (the free-space check's words and the refinement's RMS left out)."""
    return [(stage.name, {key: value for key, value in stage.decided.items() if key not in leave_out})
            for stage in result.stages]


def test_the_stages_record_what_each_did(plain):
    result = plain
    names = [stage.name for stage in result.stages]
    assert names[:3] == ["prepare", "rank pairs", "pairs"] and names[3] == "pose graph"
    assert names[-3:] == ["joint refinement", "free-space check", "verdict"]
    assert all(isinstance(stage, Stage) and stage.seconds >= 0.0 for stage in result.stages)
    assert sum(stage.seconds for stage in result.stages) <= result.runtime_s
    prepare, ranked, first = result.stages[:3]
    assert prepare.decided["scans"] == N and prepare.decided["duplicates"] == 0
    assert first.decided["pairs"] == ranked.decided["pairs"] == first.decided["searched"] > 0
    assert first.decided["refined"] == 0 and first.decided["registrations"] == 2 * first.decided["pairs"]
    # every registration run is counted by one stage: two a pair, one a piece placed as a whole
    registered = sum(stage.decided["registrations"] for stage in result.stages if "registrations" in stage.decided)
    pieces = sum(stage.decided["searched"] for stage in result.stages if stage.name.startswith("piece pairs"))
    assert registered + pieces == result.pairs_registered
    # each pair tried is one edge of the result (a pair tried again keeps its more confident edge)
    tried = sum(stage.decided["pairs"] for stage in result.stages if "registrations" in stage.decided)
    assert tried >= len(result.edges) == len({(min(e.i, e.j), max(e.i, e.j)) for e in result.edges})
    # the last pose graph is the one the result holds: the wrong edge rejected, scan 5 left out
    graph = [stage for stage in result.stages if stage.name == "pose graph"][-1]
    assert graph.decided["edges"] == len(result.edges) and graph.decided["kept"] == len(result.kept_edges)
    assert graph.decided["cycle_inconsistent"] == 1 == len([e for e in result.rejected_edges if e.trusted])
    assert graph.decided["posed"] == N - 1
    assert {(min(e.i, e.j), max(e.i, e.j)) for e in result.rejected_edges if e.trusted} == WRONG
    verdict = result.stages[-1].decided
    assert (verdict["placed"], verdict["doubtful"], verdict["unplaced"]) == \
        tuple(result.status.count(s) for s in ("placed", "doubtful", "unplaced")) == (N - 1, 0, 1)
    assert result.unplaced == tuple(LOW) and verdict["edges_kept"] == len(result.kept_edges)
    refined = result.stages[-3].decided
    assert refined["scans"] == N - 1 and refined["edges"] == len(result.kept_edges)
    assert refined["rmse"] == result.refinement_rmse


def test_the_stages_are_frozen_and_json_holds_them(plain):
    stage = plain.stages[0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        stage.name = "other"
    with pytest.raises(TypeError):
        stage.decided["scans"] = 0
    data = json.loads(json.dumps(plain.to_dict()))
    assert [s["name"] for s in data["stages"]] == [s.name for s in plain.stages]
    assert data["stages"][-1]["decided"]["unplaced"] == 1


def test_a_sequence_records_its_own_stages_and_an_exact_duplicate(monkeypatch, scene):
    """With the capture order, the pairs are refined from the identity, the untrusted ones the walk
    needs retried globally, and loop closures sought: each its stage, even when it finds no pair to
    ask for. An exact duplicate is set aside by the preparation and given its twin's verdict."""
    truth, clouds = scene
    copy = clouds[2][::-1].copy()
    result = _merge(monkeypatch, truth, [*clouds, copy], sequence=True, refine_rounds=0)
    names = [stage.name for stage in result.stages]
    assert names[:4] == ["prepare", "pairs", "pairs (global retry)", "pose graph"]
    assert names[4:6] == ["pairs (loop closures)", "pose graph"] and "joint refinement" not in names
    prepare, walk = result.stages[0], result.stages[1]
    assert prepare.decided["scans"] == N + 1 and prepare.decided["duplicates"] == 1
    assert walk.decided["refined"] == walk.decided["pairs"] > 0 and walk.decided["searched"] == 0
    assert result.stages[2].decided["refined"] == 0
    assert result.status[N] == result.status[2] and result.stages[-1].decided["placed"] == result.status.count("placed")


def test_the_input_order_changes_no_verdict_and_no_stage(monkeypatch, scene, plain):
    """The same scans in another order: the same verdicts and poses for each scan, and every stage
    decides the same counts."""
    truth, clouds = scene
    order = list(np.random.default_rng(3).permutation(N))
    at = {k: position for position, k in enumerate(order)}
    shuffled = _merge(monkeypatch, [truth[k] for k in order], [clouds[k] for k in order], reference=at[0],
                      wrong={(at[i], at[j]) for i, j in WRONG}, low={at[k] for k in LOW})
    for k in range(N):
        assert shuffled.status[at[k]] == plain.status[k] and shuffled.edges_kept[at[k]] == plain.edges_kept[k]
        assert shuffled.scan_confidence[at[k]] == plain.scan_confidence[k]
        if plain.status[k] != "unplaced":
            np.testing.assert_allclose(shuffled.poses[at[k]], plain.poses[k], atol=1e-9)
    assert _decided(shuffled) == _decided(plain)


@pytest.mark.parametrize("motion", ["shifted by 1e6", "turned and moved"])
def test_a_common_rigid_motion_of_every_scan_changes_no_verdict_and_no_stage(monkeypatch, scene, plain, motion):
    """Every scan moved by one rigid motion ``M`` in its own frame: the same verdicts and the poses
    ``M T M^-1`` (compared where they put each scan's points). Shifted, every stage decides the
    same counts; turned, the voxel grids of the surface matching fall differently on the points,
    and the first pairs chosen may differ."""
    truth, clouds = scene
    M = np.eye(4)
    M[:3, 3] = [1e6, -2e6, 3e6]
    if motion != "shifted by 1e6":
        M[:3, :3] = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
        M[:3, 3] = [0.2, 0.1, -0.3]
    moved = _merge(monkeypatch, [T @ np.linalg.inv(M) for T in truth],
                   [c @ M[:3, :3].T + M[:3, 3] for c in clouds])
    assert moved.status == plain.status and moved.edges_kept == plain.edges_kept
    assert moved.scan_confidence == plain.scan_confidence and moved.reasons == plain.reasons
    if motion == "shifted by 1e6":
        assert _decided(moved) == _decided(plain)
    for k, cloud in enumerate(clouds):
        if plain.status[k] == "unplaced":
            continue
        expected = M @ plain.poses[k] @ np.linalg.inv(M)
        at_points = cloud @ M[:3, :3].T + M[:3, 3]
        apart = np.linalg.norm((at_points @ moved.poses[k][:3, :3].T + moved.poses[k][:3, 3])
                               - (at_points @ expected[:3, :3].T + expected[:3, 3]), axis=1).max()
        assert _errors(moved.poses[k], expected)[0] < 1e-6 and apart < 1e-6, (k, apart)
