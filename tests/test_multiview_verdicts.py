"""register_scans() never silently wrong: every scan placed (confirmed), doubtful or unplaced with a
reason; one default for the CLI and the library; usable from any script; poses named by path."""

from __future__ import annotations

import argparse
import inspect
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import esmicp
from esmicp.config import MergeConfig
from esmicp.multiview import pose_graph, register_scans
from esmicp.multiview.verdict import bridges
from esmicp.shapes import asymmetric_shape
from esmicp.trust.policy import DEFAULT_POLICY

from conftest import require_shared
from test_multiview import _clouds, _errors, _patch, _truth



def test_a_scan_whose_only_edge_is_wrong_and_untrusted_is_left_out(monkeypatch):
    """Scan 3's only registration is wrong (the KITTI case: confidence 0.33, ambiguous): it must not
    be placed, and the reason says there is no trusted edge."""
    rng = np.random.default_rng(11)
    truth = _truth(4, rng)
    clouds = _clouds(truth, rng)
    _patch(monkeypatch, truth, clouds, wrong_untrusted={(0, 3)}, missing={(1, 3), (2, 3)})
    result = register_scans(clouds, refine_rounds=0, threads=1)
    assert result.status == ("placed", "placed", "placed", "unplaced")
    assert result.placed[3] is False and np.isnan(result.poses[3]).all()
    assert "no trusted edge" in result.reasons[3][0] and result.scan_confidence[3] is None
    assert 3 not in set(result.merged(clouds)[1].tolist())


def test_a_trusted_wrong_edge_contradicted_by_a_trusted_right_one_makes_the_scan_doubtful(monkeypatch):
    """Scan 3 has two trusted edges that disagree (one 40 degrees off) and no cycle to decide: it is
    doubtful, with a confidence below the trust bar, and left out of the merged cloud."""

    rng = np.random.default_rng(12)
    truth = _truth(4, rng)
    clouds = _clouds(truth, rng)
    _patch(monkeypatch, truth, clouds, wrong={(0, 3)}, missing={(2, 3)})
    result = register_scans(clouds, refine_rounds=0, threads=1)
    assert result.status[:3] == ("placed",) * 3
    assert result.status[3] == "doubtful" and result.doubtful == (3,)
    assert result.scan_confidence[3] < DEFAULT_POLICY.trusted
    assert "contradict" in result.reasons[3][0]
    assert 3 not in set(result.merged(clouds)[1].tolist())
    assert 3 in set(result.merged(clouds, include_doubtful=True)[1].tolist())


def test_a_scan_held_by_one_unchecked_trusted_edge_is_doubtful(monkeypatch):
    """Scan 3's one edge is trusted but wrong (a kitchen frame was placed 90 degrees off by one
    such edge, confidence 0.61): no cycle checks it, so the scan is doubtful, below the trust bar,
    however right or wrong the edge; in a merge of two scans the one trusted edge places it."""

    rng = np.random.default_rng(14)
    truth = _truth(4, rng)
    clouds = _clouds(truth, rng)
    _patch(monkeypatch, truth, clouds, wrong={(0, 3)}, missing={(1, 3), (2, 3)})
    result = register_scans(clouds, refine_rounds=0, threads=1)
    assert result.status == ("placed", "placed", "placed", "doubtful")
    assert result.scan_confidence[3] < DEFAULT_POLICY.trusted and "no cycle" in result.reasons[3][0]
    _patch(monkeypatch, truth[:2], clouds[:2])
    two = register_scans(clouds[:2], refine_rounds=0, threads=1)
    assert two.status == ("placed", "placed") and "only pair" in two.reasons[1][0]


def test_a_scan_confirmed_around_a_cycle_says_so(monkeypatch):
    rng = np.random.default_rng(13)
    truth = _truth(4, rng)
    clouds = _clouds(truth, rng)
    _patch(monkeypatch, truth, clouds)
    result = register_scans(clouds, refine_rounds=0, threads=1, partners=3)  # every pair
    assert result.status == ("placed",) * 4 and result.all_placed
    assert all(r[0].startswith("confirmed") for r in result.reasons[1:])
    assert result.edges_kept == (3, 3, 3, 3)
    record = json.loads(json.dumps(result.to_dict()))
    assert [s["status"] for s in record["scans"]] == ["placed"] * 4


def test_bridges_are_the_edges_on_no_cycle():
    assert bridges([(0, 1), (1, 2), (2, 0), (2, 3), (3, 4)]) == {(2, 3), (3, 4)}
    assert bridges([(0, 1), (0, 1)]) == set()  # two measurements of one pair: a cycle
    assert bridges([]) == set()


def test_information_whitening_measures_the_left_perturbation():
    """The pose graph's residual of an edge with a 6x6 information matrix is |W E|^2 =
    delta^T information delta, delta the left perturbation of T_i_j in frame i (rotation vector,
    then translation): fails if the frame or the order of the blocks is mixed up."""
    rng = np.random.default_rng(3)
    T_i_j = pose_graph.pose_from_vector(np.concatenate([rng.normal(size=3), rng.normal(size=3)]))
    A = rng.normal(size=(6, 6))
    information = A @ A.T + np.eye(6)
    W = pose_graph.whitening(1.0, information, T_i_j, translation_scale=1.0)
    delta = 1e-5 * rng.normal(size=6)
    predicted = pose_graph.pose_from_vector(delta) @ T_i_j
    error = pose_graph.vector_from_pose(np.linalg.inv(T_i_j) @ predicted)
    np.testing.assert_allclose(np.sum((W @ error) ** 2), delta @ information @ delta, rtol=1e-4)
    # no information: the weight over the units
    np.testing.assert_allclose(pose_graph.whitening(4.0, None, T_i_j, translation_scale=0.5),
                               np.diag([2 / np.radians(1.0)] * 3 + [4.0] * 3))


def test_a_tight_information_matrix_wins_over_a_loose_one():
    """Two measurements of one pair that disagree by 2 cm: the solved pose lies next to the one
    with 100x the information."""
    truth = np.eye(4)
    truth[:3, 3] = [1.0, 0.0, 0.0]
    other = truth.copy()
    other[0, 3] += 0.02
    tight, loose = 1e6 * np.eye(6), 1e2 * np.eye(6)
    poses = pose_graph.optimise({0: np.eye(4), 1: other.copy()}, [(0, 1, truth, 1.0, tight), (0, 1, other, 1.0, loose)],
                                0, translation_scale=0.01, loss="linear", direct_solve_max_poses=200)
    assert abs(poses[1][0, 3] - 1.0) < 0.001


@pytest.fixture(scope="module")
def bunny_scans():
    from esmicp.io.stanford_conf import load_scans

    scans = load_scans(require_shared("bunny_scans"), max_points=12000, rng=3)
    return scans


def _modelnet_scan(name: str, size: float, rng) -> np.ndarray:
    """The side of a ModelNet40 object facing +z (its points whose normals face the viewer), scaled
    to ``size`` across."""
    folder = require_shared(f"modelnet40/{name}")
    data = np.loadtxt(next(folder.glob("*.txt")), delimiter=",")
    points, normals = data[:, :3], data[:, 3:6]
    seen = points[normals[:, 2] > 0.1]
    seen = (seen - seen.mean(axis=0)) * size / np.ptp(seen, axis=0).max()
    return seen @ Rotation.random(random_state=rng).as_matrix().T


def test_an_intruder_among_the_bunny_scans_is_not_placed(bunny_scans):
    """Three bunny scans and one scan of a chair the bunny's size: the chair is not placed (no
    trusted edge), the bunny scans are, within 1 degree / 2 mm of bun.conf."""
    names = ("bun000", "bun045", "bun315")
    clouds = [bunny_scans[n][0] for n in names]
    intruder = _modelnet_scan("chair", 0.15, np.random.default_rng(5))
    result = register_scans([clouds[0], intruder, clouds[1], clouds[2]], threads=2)
    assert result.status[1] != "placed", result.reasons[1]
    assert not result.placed[1]
    for position, name in ((0, "bun000"), (2, "bun045"), (3, "bun315")):
        assert result.status[position] == "placed", (name, result.reasons[position])
        truth = np.linalg.inv(bunny_scans["bun000"][1]) @ bunny_scans[name][1]
        angle, shift = _errors(result.poses[position], truth)
        assert angle < 1.0 and shift < 0.002, (name, angle, shift)


def test_two_halves_of_one_scan_that_share_no_surface_are_not_merged(bunny_scans):
    points = bunny_scans["bun000"][0]
    centred = points - points.mean(axis=0)
    side = centred @ np.array([1.0, 0.0, 0.0]) > 0
    moved = points[~side] @ Rotation.from_rotvec([0.0, 0.4, 0.0]).as_matrix().T
    result = register_scans([points[side], moved], threads=2)
    assert result.status[1] != "placed", result.reasons[1]
    assert not result.all_placed


def test_no_main_guard_needed_from_stdin():
    """A script with no ``if __name__ == "__main__":`` guard, run from stdin (``python -``), merges
    scans with the default pool (a spawned process pool would re-import __main__ and die)."""
    script = (
        "import numpy as np\n"
        "from esmicp import register_scans\n"
        "from esmicp.shapes import asymmetric_shape\n"
        "from scipy.spatial.transform import Rotation\n"
        "rng = np.random.default_rng(0)\n"
        "world = asymmetric_shape(3000, rng=rng)\n"
        "clouds = [world @ Rotation.from_rotvec([0, 0, 0.3 * k]).as_matrix() for k in range(3)]\n"
        "result = register_scans(clouds, threads=2, pair_points=600, refine_points=1500)\n"
        "print('STATUS', ' '.join(result.status))\n"
    )
    # The child imports the same esmicp as this test process (installed, or a source tree with its
    # kernels built in place), not whatever src/ happens to sit beside the tests.
    package_root = str(Path(esmicp.__file__).parent.parent)
    env = {**os.environ, "PYTHONPATH": package_root + os.pathsep + os.environ.get("PYTHONPATH", "")}
    done = subprocess.run([sys.executable, "-"], input=script, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "STATUS" in done.stdout and "Traceback" not in done.stderr


def _merge_parser():
    from esmicp.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return commands.choices["merge"]


def test_cli_merge_takes_every_default_from_register_scans(monkeypatch):
    """Every option of ``esmicp merge`` that is a keyword of register_scans either has the library's
    default or (argparse.SUPPRESS) is not passed at all unless given, and --help shows the library's
    value: fails if the CLI and the library disagree (e.g. --pair-points 800 against 1500)."""
    from esmicp.cli.merge import LIBRARY_OPTIONS

    signature = inspect.signature(register_scans).parameters
    parser = _merge_parser()
    options = [a for a in parser._actions if a.dest in signature]
    assert {a.dest for a in options} >= set(LIBRARY_OPTIONS) >= {"pair_points", "refine_points", "reference", "sequence"}
    for action in options:
        assert action.default is argparse.SUPPRESS or action.default == signature[action.dest].default, action.dest
    parsed = vars(parser.parse_args(["a.ply", "b.ply"]))
    for name in LIBRARY_OPTIONS:
        assert parsed.get(name, signature[name].default) == signature[name].default, name
    # a keyword that defaults to None takes the merge configuration's field: --help shows that value
    assert signature["pair_points"].default is None
    assert f"default: {MergeConfig().pair_points})" in " ".join(parser.format_help().split())
def test_cli_pose_file_tells_two_scans_of_the_same_name_apart(tmp_path, capsys):
    """Two ``scan.npy`` in different folders: each row of --poses-out names its scan by the path
    as given; the table too, and --json gives every scan's verdict."""
    from esmicp.cli import main
    from esmicp.shapes import asymmetric_shape

    rng = np.random.default_rng(1)
    world = asymmetric_shape(3000, rng=rng)
    paths = []
    for k, folder in enumerate(("a", "b")):
        (tmp_path / folder).mkdir()
        path = tmp_path / folder / "scan.npy"
        np.save(path, world @ Rotation.from_rotvec([0.0, 0.2 * k, 0.0]).as_matrix())
        paths.append(str(path))
    poses = tmp_path / "poses.txt"
    argv = ["merge", *paths, "-o", str(tmp_path / "m.ply"), "--poses-out", str(poses), "--no-progress",
            "--threads", "1", "--pair-points", "600", "--refine-points", "1500", "--allow-partial"]
    code = main(argv)
    out = capsys.readouterr().out
    assert esmicp.read_poses(poses).names == tuple(paths)
    assert all(path in out for path in paths)
    assert code == 0
    code = main([*argv, "--json", "--force"])
    record = json.loads(capsys.readouterr().out)
    assert record["files"] == paths and len(record["scans"]) == 2 and code == 0


def test_cli_exit_status_3_when_a_scan_is_left_out_unless_allowed(tmp_path, bunny_scans, capsys):
    """A bunny scan and a chair: the chair is left out, the command says so per scan and exits 3;
    --allow-partial exits 0. The placed scan is written either way."""
    from esmicp import write_points
    from esmicp.cli import main
    from esmicp.cli.merge import EXIT_PARTIAL

    bunny = tmp_path / "bunny.ply"
    chair = tmp_path / "chair.ply"
    write_points(bunny, bunny_scans["bun000"][0])
    write_points(chair, _modelnet_scan("chair", 0.15, np.random.default_rng(2)))
    out = tmp_path / "m.ply"
    argv = ["merge", str(bunny), str(chair), "-o", str(out), "--no-progress", "--threads", "2"]
    assert main(argv) == EXIT_PARTIAL == 3
    captured = capsys.readouterr()
    assert "chair.ply" in captured.err and out.exists()
    table = [line for line in captured.out.splitlines() if str(chair) in line]
    assert table and "placed" not in table[0].split()
    assert main([*argv, "--allow-partial", "--force"]) == 0


def test_scans_too_sparse_to_resolve_a_pose_are_left_unplaced():
    """Eight scans of 40 points each, sampled independently from one shape and turned at random:
    no pair of them can certify a pose, so none but the reference is placed (they used to come back
    placed, most of them wrongly)."""
    rng = np.random.default_rng(0)
    world = asymmetric_shape(5000, rng=rng)
    clouds = [world[rng.choice(5000, 40, replace=False)] @ Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
              for _ in range(8)]
    result = register_scans(clouds, threads=2)
    assert result.status == ("placed",) + ("unplaced",) * 7
    assert all("too few points" in result.reasons[k][0] for k in range(1, 8))
