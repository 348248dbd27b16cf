"""Choosing among pruned pose fits at 2% true correspondences (:mod:`esmicp.globalreg.pruning`):
the right fit ranked first by the keypoints it places on the target, its inliers the true ones,
whatever rigid motion the target sits at and whatever order the correspondences come in."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from esmicp.core.procrustes import batched_weighted_procrustes, to_matrix
from esmicp.globalreg.feature_matching import _inlier_mask
from esmicp.globalreg.pruning import best_of_both, occupancy_scores
from esmicp.globalreg.scan import prune
from esmicp.metrics import rotation_error_deg

VOXEL = 0.1
TOLERANCE = 1.5 * VOXEL
OBJECTS = 30


def _scene(seed: int, count: int) -> np.ndarray:
    """Points on the faces of OBJECTS random tetrahedra (edges up to a metre) strewn over a
    10.8 x 6 x 2 m box: a cluttered place without symmetries."""
    generator = np.random.default_rng(1000 + seed)
    corners = generator.uniform([0, 0, 0], [10.8, 6, 2], (OBJECTS, 1, 3)) + generator.uniform(0, 1, (OBJECTS, 4, 3))
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    which, face = generator.integers(0, OBJECTS, count), generator.integers(0, 4, count)
    u, v = generator.uniform(size=(2, count))
    u, v = np.where(u + v > 1, 1 - u, u), np.where(u + v > 1, 1 - v, v)
    a, b, c = (corners[which, faces[face, k]] for k in range(3))
    return a + u[:, None] * (b - a) + v[:, None] * (c - a)


def _low_overlap_case(seed: int, correspondences: int = 1500, inliers: int = 30):
    """Keypoints of two views of a scene overlapping on a third of the source, and ``correspondences``
    pairs of which ``inliers`` (2%) are true: ``(source, target, paired source, paired target,
    true mask, T_target_source)``."""
    generator = np.random.default_rng(seed)
    truth = to_matrix(Rotation.random(random_state=seed).as_matrix(), generator.uniform(-3, 3, 3))
    scene = _scene(seed, 12000)
    target = scene[scene[:, 0] <= 6.0][:3000]
    part = scene[scene[:, 0] >= 3.6][:3000]  # 3.6 <= x <= 6: about a third of the source on the target
    source = (part - truth[:3, 3]) @ truth[:3, :3]
    on_both = np.flatnonzero(part[:, 0] <= 6.0)
    picked = generator.choice(on_both, inliers, replace=False)
    paired_source = source[generator.integers(0, len(source), correspondences)]
    paired_target = target[generator.integers(0, len(target), correspondences)]
    true = np.zeros(correspondences, dtype=bool)
    slots = generator.choice(correspondences, inliers, replace=False)
    true[slots] = True
    paired_source[slots] = source[picked]
    paired_target[slots] = part[picked] + generator.normal(0, 0.1 * VOXEL, (inliers, 3))
    return source, target, paired_source, paired_target, true, truth


def _best_fit(source, target, paired_source, paired_target):
    """The pruning's fit that places the most source points on the target, refit twice on its own
    inliers (as the scan strategy does before its ICP)."""
    rotations, translations = prune(paired_source, paired_target, TOLERANCE)
    scores = occupancy_scores(rotations, translations, source, target, 0.5 * VOXEL, 500)  # as the scan search
    best = int(np.argmax(scores))
    rotation, translation = rotations[best:best + 1], translations[best:best + 1]
    for _ in range(2):
        mask = _inlier_mask(rotation, translation, paired_source, paired_target, TOLERANCE)
        rotation, translation = batched_weighted_procrustes(paired_source, paired_target, mask.astype(float))
    return rotation[0], translation[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_right_fit_ranks_first_at_2_percent_inliers_and_keeps_the_true_set(seed):
    source, target, paired_source, paired_target, true, truth = _low_overlap_case(seed)
    rotation, translation = _best_fit(source, target, paired_source, paired_target)
    assert rotation_error_deg(rotation, truth[:3, :3]) < 2.0
    assert np.linalg.norm(translation - truth[:3, 3]) < 2 * VOXEL
    found = _inlier_mask(rotation[None], translation[None], paired_source, paired_target, TOLERANCE)[0]
    # The set the true pose aligns: the planted pairs and the random ones it happens to align.
    aligned = _inlier_mask(truth[None, :3, :3], truth[None, :3, 3], paired_source, paired_target, TOLERANCE)[0]
    assert (found & true).sum() >= 0.9 * true.sum()
    assert (found & ~aligned).sum() <= 0.1 * aligned.sum()


def test_the_choice_follows_a_rigid_motion_of_the_target_and_ignores_the_order():
    source, target, paired_source, paired_target, true, truth = _low_overlap_case(3)
    motion = to_matrix(Rotation.from_rotvec([0.4, -1.1, 2.0]).as_matrix(), np.array([20.0, -7.0, 3.0]))
    moved_target = target @ motion[:3, :3].T + motion[:3, 3]
    moved_paired = paired_target @ motion[:3, :3].T + motion[:3, 3]
    order = np.random.default_rng(5).permutation(len(paired_source))
    expected = motion @ truth
    for target_cloud, first, second in ((moved_target, paired_source, moved_paired),
                                        (moved_target[::-1], paired_source[order], moved_paired[order])):
        rotation, translation = _best_fit(source, target_cloud, first, second)
        assert rotation_error_deg(rotation, expected[:3, :3]) < 2.0
        assert np.linalg.norm(translation - expected[:3, 3]) < 2 * VOXEL


def test_occupancy_counts_what_lands_near_the_target_and_not_the_target_order():
    generator = np.random.default_rng(3)
    target = _scene(3, 2000)
    identity, far = np.eye(3)[None], np.array([[100.0, 0.0, 0.0]])
    assert occupancy_scores(identity, np.zeros((1, 3)), target, target, VOXEL, 400)[0] == 1.0
    assert occupancy_scores(identity, far, target, target, VOXEL, 400)[0] == 0.0
    rotations = Rotation.random(20, random_state=3).as_matrix()
    translations = generator.normal(0, 1, (20, 3))
    scores = occupancy_scores(rotations, translations, target, target, VOXEL, 400)
    shuffled = occupancy_scores(rotations, translations, target, generator.permutation(target), VOXEL, 400)
    np.testing.assert_array_equal(scores, shuffled)
    assert np.all((scores >= 0.0) & (scores < 1.0))
    assert len(occupancy_scores(np.zeros((0, 3, 3)), np.zeros((0, 3)), target, target, VOXEL, 400)) == 0


def test_the_fits_kept_are_the_best_distinct_ones_of_each_score():
    rotations = Rotation.from_rotvec(np.outer(np.arange(8), [0.0, 0.0, np.radians(30)])).as_matrix()
    translations = np.zeros((8, 3))
    rotations[1], rotations[5] = rotations[0], rotations[4]  # 1 repeats 0, 5 repeats 4
    first = np.array([9.0, 8.0, 7.0, 1.0, 2.0, 3.0, 0.0, 0.0])
    second = np.array([0.0, 0.0, 1.0, 5.0, 9.0, 8.0, 7.0, 0.0])
    kept = best_of_both(rotations, translations, first, second, 2, 0.1, 10.0)
    np.testing.assert_array_equal(kept, [0, 2, 4, 6])  # 1 and 5 repeat a better fit; 7 is best by neither
    assert set(best_of_both(rotations, translations, first, first, 2, 0.1, 10.0)) == {0, 2}
