"""The overlap confidence of a whole object whose source carries scattered outliers: it is measured
on the surface of the cloud that carries them (:func:`esmicp.trust.confidence.surface_part`, read
from the cloud alone, before any pose), so a right pose is trusted and a pose a few voxels off or
turned is not, and a cloud without scattered points is measured as before; the search ends after
the rotation search on such a whole object when its pose is unambiguous and confident there."""

from __future__ import annotations

import numpy as np
import pytest

from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.keypoints import Keypoints
from esmicp.core.procrustes import bounding_box_diagonal
from esmicp.globalreg.config import DEFAULT
from esmicp.trust.confidence import surface_part
from esmicp.trust.judge import judge, scattered_keypoints

SIDES = np.array([1.0, 0.6, 0.3])


def box_surface(count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points uniform on the surface of a box of sides ``SIDES``, centred at 0."""
    areas = np.array([SIDES[1] * SIDES[2], SIDES[0] * SIDES[2], SIDES[0] * SIDES[1]])
    axis = rng.choice(3, size=count, p=areas / areas.sum())
    points = (rng.random((count, 3)) - 0.5) * SIDES
    points[np.arange(count), axis] = np.where(rng.random(count) < 0.5, -0.5, 0.5) * SIDES[axis]
    return points


def with_outliers(points: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """``points`` with ``fraction`` of them moved by clipped Gaussian offsets of three widths (0.1,
    0.2 and 0.32 of the half-diagonal, clipped at 0.05, 1 and 10 of it): a shell near the surface
    and a cloud scattered through and around the object."""
    noisy = points.copy()
    chosen = rng.choice(len(points), size=round(fraction * len(points)), replace=False)
    component = rng.integers(0, 3, size=len(chosen))
    half = 0.5 * bounding_box_diagonal(points)
    width, clip = np.array([0.1, 0.2, 0.32])[component], np.array([0.05, 1.0, 10.0])[component]
    offsets = np.clip(rng.normal(size=(len(chosen), 3)) * width[:, None], -clip[:, None], clip[:, None])
    noisy[chosen] += half * offsets
    return noisy


def turn(degrees: float, axis) -> np.ndarray:
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    angle = np.radians(degrees)
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew


def verdict(transformation, source, target):
    index = NearestNeighbors(target, workers=1)
    keypoints = Keypoints.of(source, target, index.spacing(), DEFAULT.keypoints,
                             DEFAULT.scan.keypoint.min_voxel_spacings)
    return judge(transformation, source=source, target_index=index, keypoints=keypoints, pairs=None, sigma=None,
                 converged=True, num_iterations=1, config=DEFAULT, workers=1), keypoints.voxel


@pytest.fixture(scope="module")
def pair():
    rng = np.random.default_rng(7)
    target = box_surface(2000, rng)
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = turn(40.0, [1, 2, 3]), [0.3, -0.2, 0.1]
    clean = box_surface(2000, rng)
    source_object = with_outliers(clean, 0.6, rng)
    # the source in its own frame: target ~= source @ R.T + t
    source = (source_object - truth[:3, 3]) @ truth[:3, :3]
    return source, target, truth, (clean - truth[:3, 3]) @ truth[:3, :3]


def test_a_right_pose_under_heavy_outliers_is_trusted(pair):
    source, target, truth, _ = pair
    judged, _ = verdict(truth, source, target)
    assert judged.trusted, judged.doubts


@pytest.mark.parametrize("wrong", ["shifted", "turned"])
def test_a_wrong_pose_under_the_same_outliers_is_not_trusted(pair, wrong):
    source, target, truth, _ = pair
    _, voxel = verdict(truth, source, target)
    pose = truth.copy()
    if wrong == "shifted":  # a few keypoint voxels off
        pose[:3, 3] += 3.0 * voxel * np.array([1.0, 0.0, 0.0])
    else:
        pose[:3, :3] = turn(10.0, [0, 0, 1]) @ truth[:3, :3]
    judged, _ = verdict(pose, source, target)
    right, _ = verdict(truth, source, target)
    assert not judged.trusted
    assert judged.confidence < right.confidence


def test_a_clean_cloud_is_measured_on_every_keypoint(pair):
    """Without scattered points the surface part changes nothing: every keypoint counts, at the
    keypoint voxel; with them, the scattered share is what the premise reads."""
    source, target, _, clean = pair
    index = NearestNeighbors(target, workers=1)
    for cloud, scattered in ((clean, False), (target, False), (source, True)):
        keypoints = Keypoints.of(cloud, target, index.spacing(), DEFAULT.keypoints,
                                 DEFAULT.scan.keypoint.min_voxel_spacings)
        part = surface_part(keypoints.source, keypoints.source_tree, keypoints.voxel,
                            DEFAULT.scan.keypoint.min_voxel_spacings)
        assert (part.surface is not None) == scattered, part.scattered
        if not scattered:
            assert part.scale == 1.0


@pytest.mark.parametrize("cloud", ["scattered", "clean"])
def test_the_keypoints_a_caller_already_made_judge_as_keypoints_made_again(pair, cloud):
    """The judge reads the clouds' scatter from the whole clouds' keypoints; given those keypoints
    (``made``, as :func:`esmicp.register` passes its own), or its caller's reading of that scatter
    (``scatter``, the search's), it decides the same as when it makes them itself: a confidence handed in is replaced by one measured on the surface where a cloud
    carries scattered points, and kept where none does."""
    source, target, truth, clean = pair
    source = source if cloud == "scattered" else clean
    pose = truth.copy()
    pose[:3, :3] = turn(10.0, [0, 0, 1]) @ truth[:3, :3]
    index = NearestNeighbors(target, workers=1)
    keypoints = Keypoints.of(source, target, index.spacing(), DEFAULT.keypoints,
                             DEFAULT.scan.keypoint.min_voxel_spacings)
    # The caller's own reading of the scatter (the search's), handed in with what it returned.
    found = scattered_keypoints(source, index, DEFAULT, workers=1, made=keypoints)
    assert (found is not None) == (cloud == "scattered")
    verdicts = [judge(pose, source=source, target_index=index, keypoints=keypoints, pairs=None, sigma=None,
                      converged=True, num_iterations=1, config=DEFAULT, workers=1, confidence=1.0, made=made,
                      scatter=scatter)
                for made, scatter in ((None, None), (keypoints, None), (found, found is not None))]
    for verdict in verdicts[1:]:
        assert verdict.confidence == verdicts[0].confidence
        assert verdict.doubts == verdicts[0].doubts
    assert (verdicts[1].confidence < 1.0) == (cloud == "scattered")


def test_a_whole_object_under_scattered_outliers_ends_after_the_rotation_search(monkeypatch):
    """A whole asymmetric object whose source carries 60% scattered outliers: its rotation-search
    score cannot reach ``confident_score`` (the outliers never lie on the target), yet the pose,
    unambiguous and confident on the surface, is final there: no scan-strategy search runs, and
    the result is right and trusted."""
    import esmicp
    from esmicp.core.procrustes import to_matrix
    from esmicp.globalreg import scan
    from esmicp.metrics import rotation_error_deg
    from esmicp.shapes import asymmetric_shape
    from scipy.spatial.transform import Rotation

    searches = []
    real = scan.scan_estimate
    monkeypatch.setattr(scan, "scan_estimate", lambda *args, **kwargs: searches.append(1) or real(*args, **kwargs))
    rng = np.random.default_rng(0)
    shape = asymmetric_shape(1500, rng)
    truth = to_matrix(Rotation.random(random_state=0).as_matrix(), rng.normal(size=3))
    source = with_outliers(shape[rng.permutation(len(shape))[:1000]], 0.6, rng)
    target = shape @ truth[:3, :3].T + truth[:3, 3]
    result = esmicp.register(source, target, rng=0, workers=1)
    assert not searches
    assert rotation_error_deg(result.transformation, truth) < 1.0
    assert result.trusted
