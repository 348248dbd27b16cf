"""The joint refinement (:func:`esmicp.multiview.refine.refine`): each pair of scans counts with the
inverse of its own residual variance, so a pair whose surfaces agree less pulls a scan less; and a
pair queries the points of its overlap, so a pair sharing a small part of its scans is refined as
well as one sharing all."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from esmicp.core.features import estimate_normals
from esmicp.multiview import pose_graph
from esmicp.multiview.refine import refine


def _terrain(rng, count, noise):
    """``count`` points of one smooth bumpy surface over [-1, 1]^2 (world frame), with Gaussian noise
    of standard deviation ``noise`` on each coordinate."""
    xy = rng.uniform(-1.0, 1.0, (count, 2))
    z = 0.15 * np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1]) + 0.1 * np.cos(4 * xy[:, 0] + xy[:, 1])
    return np.column_stack([xy, z]) + rng.normal(0.0, noise, (count, 3))


def _scans(seed, noises, count=2000):
    """(true ``T_world_scan``, clouds in their centroid frames, normals, starting poses) of scans of
    the same surface with the given noises; scan 0 is the reference (the identity)."""
    rng = np.random.default_rng(seed)
    truth, clouds, normals, start = {}, {}, {}, {}
    for k, noise in enumerate(noises):
        T = np.eye(4)
        if k:
            T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
            T[:3, 3] = rng.normal(0.0, 1.0, 3)
        local = (_terrain(rng, count, noise) - T[:3, 3]) @ T[:3, :3]
        centre = local.mean(axis=0)
        T[:3, 3] += T[:3, :3] @ centre
        truth[k], clouds[k] = T, local - centre
        normals[k] = estimate_normals(clouds[k], k=12)
        # a start about 0.6 degrees and 1% of the surface's size off the truth
        start[k] = T if k == 0 else pose_graph.pose_from_vector(rng.normal(0.0, 0.01, 6)) @ T
    return truth, clouds, normals, start


def _refined(clouds, normals, start, edges):
    poses = {k: start[k].copy() for k in {k for edge in edges for k in edge}}
    poses, _, _ = refine(poses, clouds, normals, edges, 0, np.geomspace(0.2, 0.02, 4), query_points=1000,
                         rounds_per_distance=2, huber_ratio=3.0, min_pairs=10)
    return poses


@pytest.mark.parametrize("seed", [0, 1])
def test_a_noisy_pair_does_not_pull_a_scan_off_where_its_clean_pair_puts_it(seed):
    # scans 0 and 1 carry 0.5 thousandths of the surface's size of noise, scan 2 sixty times as much;
    # all three see the same surface, so each pair shares it all
    _, clouds, normals, start = _scans(seed, (0.0005, 0.0005, 0.03))
    alone = _refined(clouds, normals, start, [(0, 1)])[1]
    joined = _refined(clouds, normals, start, [(0, 1), (0, 2), (1, 2)])[1]
    angle, shift = pose_graph.edge_error(alone, joined, np.eye(4))
    # the noisy pair weighs (1/60)^2 of the clean one: scan 1 stays within a few thousandths of a
    # degree and a ten-thousandth of the size of where the clean pair alone puts it (with every
    # correspondence weighing the same, the noisy pair moves it 0.02-0.14 degrees)
    assert angle < 0.005 and shift < 1e-4, (angle, shift)


def test_pairs_of_equal_noise_weigh_the_same_and_the_refinement_reaches_the_truth():
    truth, clouds, normals, start = _scans(2, (0.0005, 0.0005, 0.0005))
    poses = _refined(clouds, normals, start, [(0, 1), (0, 2), (1, 2)])
    for k in (1, 2):
        angle, shift = pose_graph.edge_error(truth[k], poses[k], np.eye(4))
        assert angle < 0.05 and shift < 1e-3, (k, angle, shift)


def _corner_pair(seed, count=6000):
    """Two scans of one bumpy surface, each over a 2 x 2 square, overlapping in a 0.4 x 0.4 corner (4%
    of each scan): (true poses, clouds in their centroid frames, normals, the second scan's start,
    about 1.5 degrees and 0.05 off the truth)."""
    rng = np.random.default_rng(seed)
    truth, clouds, normals = {}, {}, {}
    for k, corner in enumerate((0.0, 1.6)):
        xy = rng.uniform(-1.0, 1.0, (count, 2)) + corner
        world = np.column_stack([xy, 0.3 * np.sin(5 * xy[:, 0]) * np.cos(4 * xy[:, 1])
                                 + 0.2 * np.cos(7 * xy[:, 0] + 3 * xy[:, 1])])
        T = np.eye(4)
        if k:
            T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
            T[:3, 3] = rng.normal(0.0, 1.0, 3)
        local = (world - T[:3, 3]) @ T[:3, :3]
        centre = local.mean(axis=0)
        T[:3, 3] += T[:3, :3] @ centre
        truth[k], clouds[k] = T, local - centre
        normals[k] = estimate_normals(clouds[k], k=12)
    start = {0: truth[0], 1: pose_graph.pose_from_vector(rng.normal(0.0, 0.02, 6)) @ truth[1]}
    return truth, clouds, normals, start


@pytest.mark.parametrize("seed", [0, 1])
def test_a_pair_sharing_a_small_part_of_its_scans_is_refined_on_its_overlap(seed):
    truth, clouds, normals, start = _corner_pair(seed)
    poses = {k: start[k].copy() for k in start}
    # 200 queried points a direction: evenly strided over a whole scan, 8 of them would lie in the
    # overlap (under min_pairs: the pair could not move); strided over the overlap, all 200
    poses, _, _ = refine(poses, clouds, normals, [(0, 1)], 0, np.geomspace(0.1, 0.02, 4), query_points=200,
                         rounds_per_distance=2, huber_ratio=3.0, min_pairs=10)
    angle, shift = pose_graph.edge_error(truth[1], poses[1], np.eye(4))
    start_angle, start_shift = pose_graph.edge_error(truth[1], start[1], np.eye(4))
    assert start_angle > 0.5
    assert angle < 0.15 and shift < 0.004, (angle, shift)
