"""The scan search's pruning (:func:`esmicp.globalreg.scan.prune`) at 2% true correspondences, on
two views of a cluttered scene overlapping on a third: the fit agreeing with the most
correspondences is the true pose and keeps the true set, whatever rigid motion the target sits at
and whatever order the correspondences come in."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from esmicp.core.procrustes import batched_weighted_procrustes, to_matrix
from esmicp.globalreg.feature_matching import _inlier_mask
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


def _best_fit(paired_source, paired_target):
    """The pruning's fit agreeing with the most correspondences, refit twice on its own inliers
    (as the scan search does before its ICP)."""
    rotations, translations = prune(paired_source, paired_target, TOLERANCE)
    counts = _inlier_mask(rotations, translations, paired_source, paired_target, TOLERANCE).sum(axis=1)
    best = int(np.argmax(counts))
    rotation, translation = rotations[best:best + 1], translations[best:best + 1]
    for _ in range(2):
        mask = _inlier_mask(rotation, translation, paired_source, paired_target, TOLERANCE)
        rotation, translation = batched_weighted_procrustes(paired_source, paired_target, mask.astype(float))
    return rotation[0], translation[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_best_fit_at_2_percent_inliers_is_the_pose_and_keeps_the_true_set(seed):
    _, _, paired_source, paired_target, true, truth = _low_overlap_case(seed)
    rotation, translation = _best_fit(paired_source, paired_target)
    assert rotation_error_deg(rotation, truth[:3, :3]) < 2.0
    assert np.linalg.norm(translation - truth[:3, 3]) < 2 * VOXEL
    found = _inlier_mask(rotation[None], translation[None], paired_source, paired_target, TOLERANCE)[0]
    # The set the true pose aligns: the planted pairs and the random ones it happens to align.
    aligned = _inlier_mask(truth[None, :3, :3], truth[None, :3, 3], paired_source, paired_target, TOLERANCE)[0]
    assert (found & true).sum() >= 0.9 * true.sum()
    assert (found & ~aligned).sum() <= 0.1 * aligned.sum()


def test_the_fit_follows_a_rigid_motion_of_the_target_and_ignores_the_order():
    _, _, paired_source, paired_target, _, truth = _low_overlap_case(3)
    motion = to_matrix(Rotation.from_rotvec([0.4, -1.1, 2.0]).as_matrix(), np.array([20.0, -7.0, 3.0]))
    moved_paired = paired_target @ motion[:3, :3].T + motion[:3, 3]
    order = np.random.default_rng(5).permutation(len(paired_source))
    expected = motion @ truth
    for first, second in ((paired_source, moved_paired), (paired_source[order], moved_paired[order])):
        rotation, translation = _best_fit(first, second)
        assert rotation_error_deg(rotation, expected[:3, :3]) < 2.0
        assert np.linalg.norm(translation - expected[:3, 3]) < 2 * VOXEL
