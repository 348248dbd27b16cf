"""Clouds from the Python point-cloud ecosystem: an ``open3d.geometry.PointCloud`` (or Open3D's
tensor cloud) is accepted wherever an (N, 3) array is (:func:`esmicp.register`,
:func:`esmicp.register_scans`, the writers)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import require_module

import esmicp
import esmicp.types
from esmicp.core.procrustes import apply, to_matrix
from esmicp.metrics import rotation_error_deg
from esmicp.shapes import asymmetric_shape


def test_open3d_point_clouds_are_registered_merged_and_written(tmp_path):
    o3d = require_module("open3d", "baselines")
    target = asymmetric_shape(1500, rng=3)
    truth = to_matrix(np.array([[0.96, -0.28, 0.0], [0.28, 0.96, 0.0], [0.0, 0.0, 1.0]]), np.array([0.02, 0.0, 0.01]))
    source = apply(np.linalg.inv(truth), target)

    def cloud(points):
        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(points)
        return pcd

    from_open3d = esmicp.register(cloud(source), cloud(target))
    from_arrays = esmicp.register(source, target)
    np.testing.assert_array_equal(from_open3d.transformation, from_arrays.transformation)
    assert rotation_error_deg(from_open3d.transformation, truth[:3, :3]) < 0.1
    merged = esmicp.register_scans([cloud(source), cloud(target)], reference=1)
    assert rotation_error_deg(merged.poses[0], truth[:3, :3]) < 0.1
    esmicp.write_points(tmp_path / "source.ply", cloud(source))
    np.testing.assert_array_equal(esmicp.read_points(tmp_path / "source.ply"), source)


def test_open3d_tensor_point_clouds_are_accepted_as_the_legacy_ones_are(tmp_path):
    """``open3d.t.geometry.PointCloud`` (positions float32 or float64) goes wherever an array goes;
    an empty one is refused in one line naming the argument."""
    o3d = require_module("open3d", "baselines")
    target = asymmetric_shape(1500, rng=3)
    truth = to_matrix(np.array([[0.96, -0.28, 0.0], [0.28, 0.96, 0.0], [0.0, 0.0, 1.0]]), np.array([0.02, 0.0, 0.01]))
    source = apply(np.linalg.inv(truth), target)

    def tensor_cloud(points, dtype):
        return o3d.t.geometry.PointCloud(o3d.core.Tensor(points.astype(dtype)))

    np.testing.assert_array_equal(esmicp.types.as_points(tensor_cloud(source, np.float64)), source)
    np.testing.assert_array_equal(esmicp.types.as_points(tensor_cloud(source, np.float32)),
                                  source.astype(np.float32).astype(np.float64))
    from_tensors = esmicp.register(tensor_cloud(source, np.float64), tensor_cloud(target, np.float64), init=truth)
    from_arrays = esmicp.register(source, target, init=truth)
    np.testing.assert_array_equal(from_tensors.transformation, from_arrays.transformation)
    esmicp.write_points(tmp_path / "source.ply", tensor_cloud(source, np.float64))
    np.testing.assert_array_equal(esmicp.read_points(tmp_path / "source.ply"), source)
    with pytest.raises(esmicp.InvalidInputError, match=r"^source: .*open3d\.t\.geometry\.PointCloud has no positions"):
        esmicp.register(o3d.t.geometry.PointCloud(), target)


def test_the_stanford_conf_reader_is_public():
    from conftest import require_shared

    poses = esmicp.read_stanford_conf(require_shared("bunny_scans/bun.conf"))
    assert "read_stanford_conf" in esmicp.__all__
    assert {"bun000", "bun045"} <= set(poses)
    for pose in poses.values():
        np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
