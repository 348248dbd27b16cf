"""The premise of the merge's free-space check (each scan a range image seen from its own origin) is
established per scan from the scan's own points, or declared; the check never cuts right edges of
scans stored off their sensors' frames (a turntable's or an object's frame, moved off the sensor,
crops of a map)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from esmicp_lab.bench.off_sensor import bunny_in_scanner_frames, map_crops, moved_off, turntable_scans
from esmicp.io import read_points
from esmicp.io.stanford_conf import load_scans
from esmicp.multiview import register_scans
from esmicp.multiview.scans import _subsample
from esmicp.trust import free_space
from esmicp.trust.policy import DEFAULT_POLICY

from conftest import require_shared
from test_multiview import _patch

#: The bunny's scans used here: their neighbouring pairs overlap.
NAMES = ("bun000", "bun045", "bun315", "top3", "chin")


def _as_checked(points):
    """The subset of a scan the merge's free-space check judges (and tests the premise on)."""
    points = np.asarray(points, dtype=np.float64)
    return _subsample(_subsample(points, 8000), DEFAULT_POLICY.free_space_points)


@pytest.fixture(scope="module")
def stored():
    """The bunny's raw scans as stored: a frame near the object (a turntable's), not the scanner's."""
    scans = load_scans(require_shared("bunny_scans"), max_points=6000, rng=3)
    return [scans[n][0] for n in NAMES], [scans[n][1] for n in NAMES]


@pytest.fixture(scope="module")
def in_scanner_frames():
    _, clouds, truth = bunny_in_scanner_frames(require_shared("bunny_scans"), NAMES, max_points=6000, rng=3)
    return clouds, truth


@pytest.fixture(scope="module")
def crops():
    """Balls of 0.4 m cut along a path from one fused 3DMatch fragment, each moved at random."""
    fragment = read_points(require_shared("real_pairs/3dmatch_redkitchen/cloud_bin_0.ply"))
    clouds, truth = map_crops(fragment, 6, rng=1)
    return [_subsample(c, 6000) for c in clouds], truth


@pytest.fixture(scope="module")
def turntable():
    """15 range scans of the bunny's mesh on a turntable turning 24 degrees at a time: stored in the
    turntable's frame, and in the sensor's."""
    return turntable_scans(read_points(require_shared("bunny/bun_zipper.ply")), 15)


@pytest.fixture(scope="module")
def depth_frames():
    folder = require_shared("sequences/redkitchen_seq01_every10/frames")
    return [np.load(f).astype(np.float64) for f in sorted(folder.glob("frame-*.npy"))[:40:10]]


def test_depth_frames_and_scans_in_their_scanners_frame_are_range_images(depth_frames, in_scanner_frames,
                                                                         turntable):
    for cloud in [*depth_frames, *in_scanner_frames[0], *turntable[1][0][:3]]:
        test = free_space.range_image_test(_as_checked(cloud))
        assert test.range_image, test
        assert abs(test.sampling_slope) < DEFAULT_POLICY.max_sampling_slope / 2 and test.hidden <= DEFAULT_POLICY.max_hidden


def test_scans_not_seen_from_their_origin_are_not_range_images(stored, turntable, crops, depth_frames):
    # as stored (a frame near the object, a turntable's): points spread evenly over the surface, seen from there
    for cloud in [*stored[0], *turntable[0][0][:3]]:
        test = free_space.range_image_test(_as_checked(cloud))
        assert not test.range_image and test.sampling_slope > DEFAULT_POLICY.max_sampling_slope, test
    # crops of a fused map, each moved by a random rigid transform
    assert not any(free_space.range_image_test(_as_checked(c)).range_image for c in crops[0])
    # a depth frame in map coordinates: far from its origin for its size
    far = free_space.range_image_test(_as_checked(depth_frames[0] + [451234.5, 5741234.25, 61.0]))
    assert not far.range_image and "far from the origin" in far.reason
    # too few points to tell
    assert not free_space.range_image_test(depth_frames[0][:500]).range_image


def test_the_premise_is_the_points_not_the_frame_rotation(depth_frames):
    """Turning a scan about its origin changes nothing a sensor there saw: same verdict, and the
    same measures up to the normals' rounding."""
    from scipy.spatial.transform import Rotation

    cloud = _as_checked(depth_frames[1])
    turned = cloud @ Rotation.from_rotvec([0.4, -1.2, 2.0]).as_matrix().T
    a, b = free_space.range_image_test(cloud), free_space.range_image_test(turned)
    assert a.range_image and b.range_image
    assert b.sampling_slope == pytest.approx(a.sampling_slope, abs=1e-4) and b.hidden == a.hidden


def _merge_right_edges(monkeypatch, clouds, truth, **options):
    """The merge with every pair registered right (trusted, exact relative poses, an inlier
    distance of 3 point spacings as the merge's registrations report)."""
    spacing = np.median([np.median(cKDTree(c).query(c, k=2)[0][:, 1]) for c in clouds])
    _patch(monkeypatch, list(truth), clouds, inlier_distance=3.0 * spacing)
    return register_scans(clouds, refine_rounds=0, threads=1, **options)


def _cut(result):
    return [e for e in result.edges if e.reason.startswith("free-space")]


@pytest.mark.parametrize("kind", ["turntable", "stored", "moved off the scanner", "map crops"])
def test_right_edges_are_never_cut_on_scans_stored_off_their_sensors(monkeypatch, kind, turntable, stored,
                                                                     in_scanner_frames, crops):
    """Every pair registered right: the free-space check, left on auto, cuts no edge and leaves
    every scan placed. Judged from their frames' origins as range images, the turntable's scans
    and the crops put surfaces where the other saw empty space (the check would cut right edges
    and leave scans out), as do pairs of the bunny's raw scans (up to 14% of a surface)."""
    if kind == "turntable":
        clouds, truth = turntable[0]
    elif kind == "stored":
        clouds, truth = stored
    elif kind == "moved off the scanner":
        clouds, truth = moved_off(*in_scanner_frames, rng=5)  # 0.1-0.3 m and 5-20 degrees off
    else:
        clouds, truth = crops
    result = _merge_right_edges(monkeypatch, clouds, truth)
    assert _cut(result) == [] and result.all_placed, (result.free_space_check, result.reasons)
    if kind != "moved off the scanner":  # a few cm off a 1.3 m range image is still one, and harmless
        assert result.free_space_check.startswith("not range images")


def test_the_same_scans_in_their_sensors_frame_are_checked(monkeypatch, turntable):
    """The turntable's scans in the sensor's frame are range images: the check applies to them and
    passes the right poses."""
    clouds, truth = turntable[1]
    right = _merge_right_edges(monkeypatch, clouds, truth)
    assert right.free_space_check == "applied" and _cut(right) == [] and right.all_placed


def test_a_declared_premise_is_obeyed(monkeypatch, turntable, in_scanner_frames):
    # declared range images: checked even where the points say otherwise (here wrongly: it cuts)
    declared = _merge_right_edges(monkeypatch, *turntable[0], range_images=True)
    assert declared.free_space_check == "applied" and _cut(declared)
    off = _merge_right_edges(monkeypatch, *turntable[0], range_images=False)
    assert off.free_space_check == "declared off" and _cut(off) == [] and off.all_placed
    # established from the points: the bunny's scans in their scanner's frame are checked, and pass
    auto = _merge_right_edges(monkeypatch, *in_scanner_frames)
    assert auto.free_space_check == "applied" and _cut(auto) == [] and auto.all_placed
    with pytest.raises(Exception, match="range_images"):
        register_scans(turntable[0][0][:2], range_images="yes")


def test_an_exact_duplicate_confirms_nothing():
    """bun000 and bun045 overlap, bun270 overlaps neither: bun045 hangs on one unchecked edge and is
    doubtful. A copy of bun045 (its points in another order) would close a triangle with it, but
    confirms nothing: both stay doubtful, with the same pose."""
    scans = load_scans(require_shared("bunny_scans"), max_points=12000, rng=7)
    clouds = [scans[n][0] for n in ("bun000", "bun045", "bun270")]
    copy = clouds[1][np.random.default_rng(0).permutation(len(clouds[1]))]
    result = register_scans([*clouds, copy], threads=2)
    assert result.status == ("placed", "doubtful", "unplaced", "doubtful"), result.reasons
    assert "on no cycle" in result.reasons[1][0]
    assert "duplicate of scan 1" in result.reasons[3][0] and "on no cycle" in result.reasons[3][1]
    np.testing.assert_array_equal(result.poses[3], result.poses[1])
    assert {(e.i, e.j) for e in result.edges if 3 in (e.i, e.j)} == set()  # never registered


def test_cli_declares_the_premise_or_leaves_it_to_the_scans(tmp_path, capsys):
    """``esmicp merge --range-images / --no-range-images``: the free-space check applied or declared
    off; neither: judged from the points (two views of a shape sampled evenly over its surface:
    not range images)."""
    import json

    from esmicp.cli import main
    from esmicp.shapes import asymmetric_shape
    from scipy.spatial.transform import Rotation

    world = asymmetric_shape(3000, rng=np.random.default_rng(1))
    paths = []
    for k in range(2):
        paths.append(str(tmp_path / f"scan{k}.npy"))
        np.save(paths[-1], world @ Rotation.from_rotvec([0.0, 0.2 * k, 0.0]).as_matrix())
    argv = ["merge", *paths, "-o", str(tmp_path / "m.ply"), "--no-progress", "--threads", "1", "--pair-points", "600",
            "--refine-points", "1500", "--allow-partial", "--json", "--force"]
    checks = {}
    for flag in ("--range-images", "--no-range-images", None):
        assert main([*argv, flag] if flag else argv) == 0
        checks[flag] = json.loads(capsys.readouterr().out)["free_space_check"]
    assert checks["--range-images"] == "applied" and checks["--no-range-images"] == "declared off"
    assert checks[None].startswith("not range images")
