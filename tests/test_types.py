"""Input validation in :mod:`esmicp.types`: as_points, as_transform, as_positive, degeneracy."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from esmicp.errors import InvalidInputError, NonFinitePointsWarning
from esmicp.types import (
    MIN_POINTS,
    as_points,
    as_positive,
    as_transform,
    check_not_degenerate,
    degeneracy,
)


def rigid(seed: int, translation_scale: float = 10.0) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    matrix[:3, 3] = np.random.default_rng(seed).uniform(-translation_scale, translation_scale, 3)
    return matrix


# --------------------------------------------------------------------------------------------
# as_points
# --------------------------------------------------------------------------------------------


def test_as_points_accepts_nested_lists():
    data = [[0, 0, 0], [1.5, 0, 0], [0, 2, 0], [0, 0, 3.25]]
    points = as_points(data)
    assert points.dtype == np.float64
    assert points.shape == (4, 3)
    assert points.flags.c_contiguous
    np.testing.assert_array_equal(points, np.array(data, dtype=float))


def test_as_points_converts_integer_dtype_exactly():
    data = np.arange(30, dtype=np.int64).reshape(10, 3) * 7 - 100
    points = as_points(data)
    assert points.dtype == np.float64
    np.testing.assert_array_equal(points, data.astype(np.float64))


def test_as_points_converts_float32_and_fortran_order():
    data = np.asfortranarray(np.random.default_rng(0).normal(size=(20, 3)).astype(np.float32))
    points = as_points(data)
    assert points.dtype == np.float64 and points.flags.c_contiguous
    np.testing.assert_array_equal(points, data.astype(np.float64))


def test_as_points_returns_a_new_array_and_leaves_input_alone():
    data = np.random.default_rng(1).normal(size=(10, 3))
    original = data.copy()
    points = as_points(data)
    assert not np.shares_memory(points, data)
    points[:] = 0.0
    np.testing.assert_array_equal(data, original)


def test_as_points_accepts_read_only_input():
    data = np.random.default_rng(2).normal(size=(10, 3))
    data.setflags(write=False)
    points = as_points(data)
    assert points.flags.writeable
    np.testing.assert_array_equal(points, data)


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros(3),  # a single (3,) vector
        [1.0, 2.0, 3.0],
        np.zeros((5, 2)),
        np.zeros((5, 4)),
        np.zeros((2, 5, 3)),
        [],
        np.float64(1.0),
    ],
    ids=["vector", "list-vector", "Nx2", "Nx4", "3d", "empty-list", "scalar"],
)
def test_as_points_rejects_wrong_shapes_naming_the_argument(bad):
    with pytest.raises(InvalidInputError, match=r"^cloudname: .*shape"):
        as_points(bad, "cloudname")


def test_as_points_rejects_empty_and_too_few_points():
    with pytest.raises(InvalidInputError, match=r"^pts: need at least 3 finite points, got 0"):
        as_points(np.empty((0, 3)), "pts")
    with pytest.raises(InvalidInputError, match=r"^pts: need at least 3 finite points, got 2"):
        as_points(np.zeros((2, 3)), "pts")
    # min_points is honoured
    assert as_points(np.zeros((2, 3)), "pts", min_points=2).shape == (2, 3)
    assert MIN_POINTS == 3


@pytest.mark.parametrize("bad", [[["a", "b", "c"]] * 3, [[1, 2, 3], [4, 5]], [[1, 2, None]] * 3])
def test_as_points_rejects_non_numeric_input(bad):
    with pytest.raises(InvalidInputError, match=r"^src: "):
        as_points(bad, "src")


def test_as_points_hints_what_to_pass_for_near_misses():
    """(N, 4) x y z intensity rows, (3, N) columns and an unreadable object each get a one-line
    error saying what to pass instead."""
    rows = np.random.default_rng(0).random((10, 4))
    with pytest.raises(InvalidInputError, match=r"source: .*shape \(10, 4\).*x y z intensity.*points\[:, :3\]"):
        as_points(rows, "source")
    with pytest.raises(InvalidInputError, match=r"points\.T"):
        as_points(rows[:, :3].T.copy())
    with pytest.raises(InvalidInputError, match=r"target: .*object.*open3d\.geometry\.PointCloud.*open3d\.t\.geometry"):
        as_points(object(), "target")


def test_method_and_init_are_typed_with_the_values_register_accepts():
    """``MethodName`` and ``InitName`` (``Literal`` types of ``register``'s ``method`` and ``init``)
    list exactly the names the library accepts, so a type checker and the library agree."""
    import typing

    import esmicp
    from esmicp.api import INIT_NAMES
    from esmicp.methods import METHODS
    from esmicp.types import InitName, MethodName

    assert typing.get_args(MethodName) == tuple(METHODS)
    assert set(typing.get_args(InitName)) == set(INIT_NAMES) and len(typing.get_args(InitName)) == len(INIT_NAMES)
    hints = typing.get_type_hints(esmicp.register)
    assert hints["method"] == MethodName
    assert InitName in typing.get_args(hints["init"])


def test_as_points_reads_any_object_holding_its_points():
    class Cloud:
        def __init__(self, points):
            self.points = points

    points = np.random.default_rng(1).random((10, 3))
    np.testing.assert_array_equal(as_points(Cloud(points.tolist())), points)
    with pytest.raises(InvalidInputError, match=r"cloud: .*shape \(10, 4\).*points\[:, :3\]"):
        as_points(Cloud(np.ones((10, 4))), "cloud")


def test_as_points_drops_non_finite_rows_with_a_warning():
    data = np.random.default_rng(3).normal(size=(8, 3))
    data[2, 1] = np.nan
    data[5, 0] = np.inf
    data[6, 2] = -np.inf
    with pytest.warns(NonFinitePointsWarning, match=r"^src: dropped 3 point\(s\).*5 left"):
        points = as_points(data, "src")
    np.testing.assert_array_equal(points, data[[0, 1, 3, 4, 7]])


def test_as_points_too_few_finite_points_raises_without_warning():
    data = np.full((5, 3), np.nan)
    data[0] = [1.0, 2.0, 3.0]
    data[1] = [4.0, 5.0, 6.0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no NonFinitePointsWarning before the error
        with pytest.raises(InvalidInputError, match=r"^src: need at least 3 finite points, got 2"):
            as_points(data, "src")


def test_as_points_no_warning_on_finite_input():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        as_points(np.random.default_rng(4).normal(size=(10, 3)))


# --------------------------------------------------------------------------------------------
# degeneracy
# --------------------------------------------------------------------------------------------


def test_degeneracy_of_a_generic_cloud_is_none(rng):
    assert degeneracy(rng.normal(size=(50, 3))) is None


@pytest.mark.parametrize("scale", [1e8, 1e-8, 1e-150, 1e150])
def test_degeneracy_is_scale_free(rng, scale):
    cloud = rng.normal(size=(50, 3))
    assert degeneracy(cloud * scale) is None
    # ...and the same degenerate shapes are still caught at that scale
    line = np.outer(rng.uniform(-1, 1, 50), [0.3, -0.4, 0.5])
    assert degeneracy(line * scale) == "all points are collinear"
    assert degeneracy(np.tile([1.0, -2.0, 0.5], (50, 1)) * scale) == "all points are identical"


def test_unit_cloud_far_from_the_origin_is_not_degenerate(rng):
    cloud = rng.normal(size=(50, 3)) + np.array([1e8, -3e7, 2e8])
    assert degeneracy(cloud) is None


def test_planar_cloud_is_not_degenerate(rng):
    planar = np.column_stack([rng.normal(size=(40, 2)), np.zeros(40)])
    assert degeneracy(planar) is None
    # a tilted plane too
    tilted = planar @ Rotation.random(random_state=5).as_matrix().T + 3.0
    assert degeneracy(tilted) is None


def test_identical_points_are_degenerate():
    assert degeneracy(np.zeros((10, 3))) == "all points are identical"
    assert degeneracy(np.tile([1e8, 1e8, 1e8], (10, 1))) == "all points are identical"


@pytest.mark.parametrize("offset", [0.0, 1e3, 1e9])
def test_a_nearly_straight_cloud_is_judged_as_by_its_exact_singular_values(rng, offset):
    """The fast scatter path only clears clouds far from the thresholds: across widths that
    straddle them (1e-14 to 1e-2 of the length), the verdict is the exact SVD's."""
    direction = rng.normal(size=3)
    for width in 10.0 ** np.arange(-14.0, -1.0):
        cloud = rng.uniform(-1, 1, (200, 1)) * direction + rng.normal(size=(200, 3)) * width + offset
        centred = cloud - cloud.mean(axis=0)
        values = np.linalg.svd(centred, compute_uv=False)
        floor = 1e-13 * np.abs(cloud).max() * np.sqrt(len(cloud))
        expected = "all points are collinear" if values[1] <= 1e-9 * values[0] + floor else None
        assert degeneracy(cloud) == expected, width


def test_collinear_points_are_degenerate(rng):
    direction = rng.normal(size=3)
    line = rng.uniform(-5, 5, (30, 1)) * direction
    assert degeneracy(line) == "all points are collinear"
    assert degeneracy(line[:3]) == "all points are collinear"
    # two distinct points (repeated) are collinear as well
    two = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]] * 5)
    assert degeneracy(two) == "all points are collinear"


def test_three_points_forming_a_triangle_are_fine():
    assert degeneracy(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])) is None


def test_check_not_degenerate_names_the_argument():
    with pytest.raises(InvalidInputError, match=r"^target: degenerate cloud, all points are identical"):
        check_not_degenerate(np.ones((5, 3)), "target")
    with pytest.raises(InvalidInputError, match=r"^source: degenerate cloud, all points are collinear"):
        check_not_degenerate(np.outer(np.arange(5.0), [1.0, 1.0, 0.0]), "source")
    check_not_degenerate(np.eye(3), "source")  # no error


# --------------------------------------------------------------------------------------------
# as_transform
# --------------------------------------------------------------------------------------------


def test_as_transform_accepts_rigid_matrices_and_lists():
    matrix = rigid(0)
    out = as_transform(matrix.tolist(), "init")
    assert out.dtype == np.float64 and out.shape == (4, 4)
    np.testing.assert_array_equal(out, matrix)
    assert not np.shares_memory(out, matrix)
    np.testing.assert_array_equal(as_transform(np.eye(4, dtype=int)), np.eye(4))


def test_as_transform_does_not_mutate_its_input():
    matrix = rigid(1)
    matrix[3] = [0.0, 0.0, 0.0, 1.0 + 1e-7]  # within tolerance: accepted and cleaned in the copy
    original = matrix.copy()
    out = as_transform(matrix)
    np.testing.assert_array_equal(matrix, original)
    np.testing.assert_array_equal(out[3], [0.0, 0.0, 0.0, 1.0])


@pytest.mark.parametrize(
    "bad, pattern",
    [
        (np.eye(3), "4x4"),
        (np.eye(4)[:3], "4x4"),
        (np.zeros(16), "4x4"),
        ("not a matrix", ""),
        ([[1, 0, 0, 0]] * 3 + [[0, 0, 1]], ""),
    ],
    ids=["3x3", "3x4", "flat", "string", "ragged"],
)
def test_as_transform_rejects_malformed_input(bad, pattern):
    with pytest.raises(InvalidInputError, match=rf"^init: .*{pattern}"):
        as_transform(bad, "init")


def test_as_transform_rejects_non_finite():
    for value in (np.nan, np.inf):
        matrix = rigid(2)
        matrix[0, 3] = value
        with pytest.raises(InvalidInputError, match=r"^init: contains NaN or infinite"):
            as_transform(matrix, "init")


def test_as_transform_rejects_bad_last_row():
    matrix = rigid(3)
    matrix[3] = [0.0, 0.1, 0.0, 1.0]
    with pytest.raises(InvalidInputError, match=r"^init: last row"):
        as_transform(matrix, "init")


def test_as_transform_rejects_scaled_and_sheared_blocks():
    scaled = rigid(4)
    scaled[:3, :3] *= 1.01
    with pytest.raises(InvalidInputError, match=r"^init: not rigid.*orthonormal"):
        as_transform(scaled, "init")
    sheared = np.eye(4)
    sheared[0, 1] = 0.05
    with pytest.raises(InvalidInputError, match=r"^init: not rigid"):
        as_transform(sheared, "init")


def test_as_transform_rejects_reflections():
    reflection = rigid(5)
    reflection[:3, :3] = reflection[:3, :3] @ np.diag([1.0, 1.0, -1.0])
    with pytest.raises(InvalidInputError, match=r"^init: not rigid.*reflection"):
        as_transform(reflection, "init")


def test_as_transform_tolerance_is_honoured():
    nearly = rigid(6)
    nearly[:3, :3] *= 1.0 + 1e-7
    as_transform(nearly)  # default tolerance 1e-5: fine
    with pytest.raises(InvalidInputError):
        as_transform(nearly, tolerance=1e-9)


# --------------------------------------------------------------------------------------------
# as_positive
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("value", [1, 0.5, 1e-300, 1e300, np.float32(2.5), np.int64(3)])
def test_as_positive_accepts_positive_numbers(value):
    out = as_positive(value, "sigma")
    assert isinstance(out, float)
    assert out == float(value)


@pytest.mark.parametrize("value", [0, 0.0, -0.0, -1, -1e-300, np.nan, np.inf, -np.inf, None, "abc", [1.0]])
def test_as_positive_rejects_the_rest_naming_the_argument(value):
    with pytest.raises(InvalidInputError, match=r"^sigma: "):
        as_positive(value, "sigma")


@pytest.mark.parametrize("offset", [0.0, 1e3, 1e6, 1e8])
def test_a_line_is_collinear_wherever_it_lies(offset):
    line = np.outer(np.linspace(0, 1, 50), [1.0, 2.0, 3.0]) + offset
    assert degeneracy(line) == "all points are collinear"
