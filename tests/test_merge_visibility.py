"""The merge's free-space check: scans placed where another scan saw empty space are doubtful, even
when every cycle agrees (wrong edges that agree with each other: repeated structure)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from esmicp.multiview import register_scans
from esmicp.trust import free_space
from esmicp.multiview.verdict import cut_off, scan_verdicts
from esmicp.trust.policy import DEFAULT_POLICY

from test_multiview import _clouds, _patch, _truth

ROOM = (np.array([-4.0, -3.0, 0.0]), np.array([4.0, 3.0, 3.0]))  # metres, a room's inside
BOXES = [(np.array([1.0, 0.5, 0.0]), np.array([2.0, 1.5, 1.0])),  # furniture: solid boxes
         (np.array([-3.0, -2.5, 0.0]), np.array([-2.2, -1.0, 2.0])),
         (np.array([-1.0, 1.8, 0.0]), np.array([0.2, 3.0, 0.8]))]


def _camera(position, yaw):
    """T_room_camera of a depth camera at ``position`` looking horizontally along ``yaw`` (rad):
    camera z forward, x right, y down."""
    T = np.eye(4)
    T[:3, 0] = [np.sin(yaw), -np.cos(yaw), 0.0]
    T[:3, 1] = [0.0, 0.0, -1.0]
    T[:3, 2] = [np.cos(yaw), np.sin(yaw), 0.0]
    T[:3, 3] = position
    return T


def _depth_frame(T_room_camera, rng):
    """A 64 x 48 depth frame (60 x 44 degrees) of the room, as points in the camera frame: along
    each ray, the first surface (a box from outside, the room's walls from inside)."""
    u, v = np.meshgrid(np.tan(np.radians(np.linspace(-30, 30, 64))), np.tan(np.radians(np.linspace(-22, 22, 48))))
    rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    direction, origin = rays @ T_room_camera[:3, :3].T, T_room_camera[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.maximum((ROOM[0] - origin) / direction, (ROOM[1] - origin) / direction).min(axis=1)
        for low, high in BOXES:
            t1, t2 = (low - origin) / direction, (high - origin) / direction
            near, far = np.minimum(t1, t2).max(axis=1), np.maximum(t1, t2).min(axis=1)
            depth = np.where((near > 0) & (near <= far) & (near < depth), near, depth)
    return rays * (depth * (1 + 0.002 * rng.standard_normal(len(depth))))[:, None]


@pytest.fixture(scope="module")
def walk():
    """Ten depth frames turning 25 degrees at a time, in scan 0's frame: (clouds, truth poses)."""
    rng = np.random.default_rng(5)
    cameras = [_camera(np.array([0.5 + 0.3 * np.cos(a), 0.3 * np.sin(a), 1.5]), a) for a in np.radians(np.arange(10) * 25.0)]
    clouds = [_depth_frame(T, rng) for T in cameras]
    return clouds, [np.linalg.inv(cameras[0]) @ T for T in cameras], cameras[0]


def _fractions(clouds, poses):
    views = {k: free_space.RangeView(c) for k, c in enumerate(clouds)}
    points = dict(enumerate(clouds))
    out = {}
    for a in range(len(clouds)):
        for b in range(a + 1, len(clouds)):
            fraction = free_space.pair_free_space(views, points, dict(enumerate(poses)), a, b, 0.15)
            if fraction is not None:
                out[(a, b)] = fraction
    return out


def _turned(poses, scans, room_to_scan0, degrees=90.0):
    """The poses with ``scans`` turned about the room's vertical axis through its centre."""
    W = np.eye(4)
    W[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.radians(degrees)]).as_matrix()
    W = np.linalg.inv(room_to_scan0) @ W @ room_to_scan0
    return [W @ T if k in scans else T for k, T in enumerate(poses)]


def test_right_poses_leave_free_space_empty_and_a_turned_scan_does_not(walk):
    clouds, truth, room_frame = walk
    right = _fractions(clouds, truth)
    assert len(right) >= 9 and max(right.values()) <= DEFAULT_POLICY.max_free_space / 4
    turned = _fractions(clouds, _turned(truth, {9}, room_frame))
    assert max(f for (a, b), f in turned.items() if 9 in (a, b)) > DEFAULT_POLICY.max_free_space
    assert all(f <= DEFAULT_POLICY.max_free_space for (a, b), f in turned.items() if 9 not in (a, b))


def test_a_conflict_cuts_off_the_side_without_the_reference():
    ring = [(k, (k + 1) % 6, 0.95) for k in range(6)] + [(0, 3, 0.95)]
    cluster = [(6, 7, 0.95), (4, 6, 0.6), (5, 7, 0.6)]  # joined to the ring by two weak edges
    cut, removed = cut_off(8, 0, ring + cluster, [(2, 7, 0.4)], trusted=DEFAULT_POLICY.trusted)
    assert set(cut) == {6, 7} and cut[7] == (2, 0.4) and removed == {(4, 6): (2, 7, 0.4), (5, 7): (2, 7, 0.4)}
    # seen from a reference inside the cluster, the ring is what the conflict cuts off
    assert set(cut_off(8, 6, ring + cluster, [(2, 7, 0.4)], trusted=DEFAULT_POLICY.trusted)[0]) == set(range(6))
    assert cut_off(8, 0, ring + cluster, [], trusted=DEFAULT_POLICY.trusted) == ({}, {})


def test_wrong_edges_that_agree_around_every_cycle_are_cut_and_their_scan_doubted(walk, monkeypatch):
    """Scan 9 is registered to the others as if turned 90 degrees, by trusted edges that agree with
    each other (views of one repeated structure, as on the kitchen walk): every cycle closes, and
    only what the frames saw tells that they are wrong. Its edges are trusted, but weaker than the
    others (0.6, as the wrong edges on the kitchen walk). The edges a conflict disproves are cut
    and scan 9 searched again; every pair with it is wrong here, so it ends doubtful."""
    clouds, truth, room_frame = walk
    _patch(monkeypatch, _turned(truth, {9}, room_frame), clouds, apart={9})
    result = register_scans(clouds, refine_rounds=0, threads=1)
    crossing = [e for e in result.edges if 9 in (e.i, e.j)]
    assert len(crossing) >= 2 and all(e.trusted for e in crossing)
    assert any(e.reason.startswith("free-space conflict") for e in crossing)  # cut, then searched again
    assert result.free_space_check == "applied"
    # the new pairs are wrong too: the last check leaves it doubtful
    assert result.status == ("placed",) * 9 + ("doubtful",)
    assert "saw empty" in result.reasons[9][0] and result.scan_confidence[9] == 0.0
    assert 9 not in set(result.merged(clouds)[1].tolist())
    assert all(e.kept for e in result.edges if 9 not in (e.i, e.j))
    # the same walk registered right: nothing is doubted
    _patch(monkeypatch, truth, clouds)
    right = register_scans(clouds, refine_rounds=0, threads=1)
    assert right.free_space_check == "applied" and right.all_placed


def test_a_scan_a_conflict_cuts_off_is_doubtful_with_the_reason():
    from esmicp.multiview.scans import Edge

    def edge(i, j):
        return Edge(i, j, np.eye(4), 0.5, 0.5, 0.5, False, True, "kept", confidence=0.9, trusted=True)

    edges = [edge(0, 1), edge(1, 2), edge(2, 0), edge(2, 3), edge(3, 0)]
    verdicts = scan_verdicts(4, 0, {0, 1, 2, 3}, edges, {3: (1, 0.4)})
    assert [v.status for v in verdicts] == ["placed", "placed", "placed", "doubtful"]
    assert verdicts[3].confidence == 0.0 and "scan 1 saw" in verdicts[3].reasons[0]
    assert "40%" in verdicts[3].reasons[0]


def test_scans_not_seen_from_their_origins_are_not_checked(monkeypatch):
    """Points filling a cube, each scan in its own frame: no scan is a range image from its origin,
    its points say so, and the check is not applied (it would doubt right scans)."""
    rng = np.random.default_rng(21)
    truth = _truth(5, rng)
    clouds = _clouds(truth, rng, points=2000)
    assert not any(free_space.range_image_test(c).range_image for c in clouds)
    _patch(monkeypatch, truth, clouds)
    result = register_scans(clouds, refine_rounds=0, threads=1, partners=4)
    assert result.free_space_check.startswith("not range images") and result.all_placed


def test_one_pair_free_space_passes_the_right_pose_and_not_one_slid_a_metre(walk):
    clouds, poses, _ = walk
    T_0_1 = poses[1]
    right = free_space.free_space_fraction(clouds[0], clouds[1], T_0_1, tolerance=0.03)
    slid = np.eye(4)
    slid[:3, 3] = [0.0, 0.0, -1.0]  # 1 m towards the target camera: its walls now stand in the empty room
    wrong = free_space.free_space_fraction(clouds[0], clouds[1], slid @ T_0_1, tolerance=0.03)
    assert right is not None and wrong is not None
    assert right <= DEFAULT_POLICY.max_free_space < wrong
    # the same pair as the merge judges it (both ways, from each origin)
    views = {k: free_space.RangeView(clouds[k]) for k in (0, 1)}
    assert right == pytest.approx(free_space.pair_free_space(views, {0: clouds[0], 1: clouds[1]},
                                                             {0: np.eye(4), 1: T_0_1}, 0, 1, 0.03), abs=0.02)


def test_one_pair_free_space_says_nothing_when_neither_sensor_sees_the_other(walk):
    clouds, poses, _ = walk
    away = np.diag([-1.0, 1.0, -1.0, 1.0])  # turned to face away, 50 m behind the target camera
    away[:3, 3] = [0.0, 0.0, -50.0]
    assert free_space.free_space_fraction(clouds[0], clouds[1], away @ poses[1], tolerance=0.03) is None
