"""Validation of the library's inputs, in one place.

Clouds are ``(N, 3)`` float64 arrays; transforms are 4x4 float64 homogeneous matrices
``T_target_source`` (they map source coordinates into the target frame). Inputs are never mutated:
every validator returns a new array.
"""

from __future__ import annotations

import numbers
import warnings
from typing import Any, Literal, Protocol, Sequence, Union

import numpy as np
import numpy.typing as npt

from . import _kernels
from .core.procrustes import axis_bounds, centroid
from .errors import InvalidInputError, NonFinitePointsWarning

class HasPoints(Protocol):
    """A cloud object holding its ``(N, 3)`` coordinates in ``points`` (an
    ``open3d.geometry.PointCloud``, ...)."""

    @property
    def points(self) -> Any: ...


class HasPointAttributes(Protocol):
    """A cloud object holding its attributes by name in ``point``, the coordinates under
    ``"positions"`` (Open3D's tensor cloud, ``open3d.t.geometry.PointCloud``)."""

    @property
    def point(self) -> Any: ...


#: What a cloud argument accepts (:func:`as_points`): an ``(N, 3)`` array-like or a cloud object.
PointsLike = Union[npt.ArrayLike, HasPoints, HasPointAttributes]

#: The names of :data:`esmicp.methods.METHODS`, for ``method=`` of :func:`esmicp.register`.
MethodName = Literal["esm", "esm-paper", "icp", "esm-plane"]

#: The strategies ``init=`` of :func:`esmicp.register` accepts by name (:data:`esmicp.api.INIT_NAMES`):
#: ``"global"`` (also ``"auto"``), ``"rotation-search"``, ``"features"``, ``"scan"``, ``"identity"``
#: (also ``"none"``).
InitName = Literal["global", "auto", "rotation-search", "features", "scan", "identity", "none"]

#: A 4x4 matrix argument (``init=``): a NumPy array or nested sequences of numbers (not any
#: array-like: NumPy counts a string as one, and ``init`` takes strings by name).
TransformLike = Union[npt.NDArray[Any], Sequence[Sequence[float]]]

#: What an unsupported cloud argument should be instead (the end of :func:`as_points`'s message).
_CLOUD_HINT = ("pass an (N, 3) array, or a point-cloud object: open3d.geometry.PointCloud, "
               "open3d.t.geometry.PointCloud")

#: Minimum number of points a cloud must have for a rigid fit.
MIN_POINTS = 3

#: Tolerance on ``R^T R = I`` and ``det R = 1`` when a 4x4 transform is checked for rigidity.
RIGID_TOLERANCE = 1e-5


def as_points(points: PointsLike, name: str = "points", *, min_points: int = MIN_POINTS) -> np.ndarray:
    """Return ``points`` as a new C-contiguous ``(N, 3)`` float64 array.

    ``points`` is an ``(N, 3)`` array-like (NumPy array, nested lists, a CPU tensor...), an
    object holding one in its ``points`` attribute (an ``open3d.geometry.PointCloud``, ...) or an
    ``open3d.t.geometry.PointCloud`` (its ``positions``, on any device): the
    one adapter every entry point (:func:`esmicp.register`, :func:`esmicp.register_scans`, the
    writers) reads clouds through. Rows with NaN or infinite coordinates are dropped with a
    :class:`NonFinitePointsWarning`.

    Raises
    ------
    InvalidInputError
        If the input is not numeric, not of shape ``(N, 3)``, or fewer than ``min_points`` finite
        points remain. The message starts with ``name`` and, where it can, says what to pass
        instead (``points[:, :3]`` for ``(N, 4)`` x y z intensity rows, an array or a point-cloud object
        for anything else).
    """
    array = _coordinate_array(points, name)
    # One pass over the coordinates first: the rows are sorted out only when some are not finite
    # (a per-row reduction of three values costs a 300k-point cloud several milliseconds).
    if not np.isfinite(array).all():
        finite = np.isfinite(array).all(axis=1)
        dropped = int((~finite).sum())
        array = array[finite]
        if len(array) >= min_points:
            warnings.warn(
                f"{name}: dropped {dropped} point(s) with NaN or infinite coordinates, {len(array)} left",
                NonFinitePointsWarning,
                stacklevel=2,
            )
    if len(array) < min_points:
        raise InvalidInputError(
            f"{name}: need at least {min_points} finite points, got {len(array)}"
        )
    return np.ascontiguousarray(array)


def _coordinate_array(points, name: str) -> np.ndarray:
    """A new ``(N, 3)`` float64 array of ``points`` (or of their ``.points``, or of an Open3D
    tensor cloud's positions), or a one-line :class:`InvalidInputError` saying what to pass instead."""
    source = points
    if not isinstance(points, np.ndarray):
        if hasattr(points, "points"):
            source = points.points  # an Open3D PointCloud (a Vector3dVector), or any cloud object holding its array
        elif _is_open3d_tensor_cloud(points):
            source = _tensor_cloud_positions(points, name)
    try:
        array = np.array(_real_numbers(source, name), dtype=np.float64, copy=True)
    except InvalidInputError:
        raise
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(
            f"{name}: expected (N, 3) numeric points, could not convert a {type(points).__name__} ({exc}); "
            f"{_CLOUD_HINT}"
        ) from None
    if array.ndim == 2 and array.shape[1] == 3:
        return array
    shape = f"got shape {array.shape}"
    if array.ndim == 2 and array.shape[0] == 3 and array.shape[1] > 3:
        hint = "; this looks like one point a column: pass points.T"
    elif array.ndim == 2 and array.shape[1] == 4:
        hint = "; this looks like x y z intensity (or x y z w) rows: pass points[:, :3]"
    elif array.ndim == 2 and array.shape[1] > 4:
        hint = f"; if its first 3 columns are x y z (then {array.shape[1] - 3} more values a point): pass points[:, :3]"
    elif array.ndim == 0:
        hint = f" (a {type(points).__name__}); {_CLOUD_HINT}"
    else:
        hint = ""
    raise InvalidInputError(f"{name}: expected (N, 3) points, {shape}{hint}")


def _is_open3d_tensor_cloud(points) -> bool:
    """True for an ``open3d.t.geometry.PointCloud`` (told by its type's module and its ``point``
    attribute map, so that Open3D is never imported here)."""
    return type(points).__module__.startswith("open3d") and hasattr(points, "point")


def _tensor_cloud_positions(cloud, name: str):
    """The positions of an ``open3d.t.geometry.PointCloud`` as a NumPy array (copied to the host
    from a GPU device), or one clear error for a cloud without positions."""
    attributes = cloud.point
    if "positions" not in attributes:
        raise InvalidInputError(f"{name}: the open3d.t.geometry.PointCloud has no positions (an empty cloud)")
    positions = attributes["positions"]
    if hasattr(positions, "cpu"):
        positions = positions.cpu()
    return positions.numpy() if hasattr(positions, "numpy") else positions


def _real_numbers(points, name: str):
    """``points`` as an array, refused when its numbers are complex (NumPy would drop the imaginary
    parts with a warning) or booleans (they would become points at 0 and 1)."""
    array = np.asarray(points)
    if array.dtype.kind == "c":
        raise InvalidInputError(f"{name}: expected real coordinates, got complex numbers ({array.dtype})")
    if array.dtype.kind == "b":
        raise InvalidInputError(f"{name}: expected coordinates, got booleans ({array.dtype})")
    return array


def degeneracy(points: np.ndarray) -> str | None:
    """Describe why ``points`` cannot fix a rigid transform, or return None if they can.

    A cloud whose points all coincide, or all lie on one line, leaves a rotation about that line
    (or every rotation) undetermined. Planar clouds are fine. Thresholds are relative to the
    cloud's extent, so the check is unit-free.
    """
    centre = centroid(points)
    # Coordinates of magnitude m carry rounding noise of about m * 1e-16, which spreads even an
    # exact line; anything below this floor is indistinguishable from that noise.
    magnitude = max(float(np.abs(points).max()), 1e-300)
    rounding_floor = 1e-13 * magnitude * np.sqrt(len(points))
    # The eigenvalues of the 3x3 scatter are the squared singular values, cheaper than the SVD of
    # the whole cloud. Squaring halves their precision (they resolve to about 1e-16 of the
    # largest), so they only clear a cloud whose second direction lies far above both thresholds
    # below; a cloud anywhere near one is decided by the exact SVD. Coordinates are scaled by
    # their magnitude first, so that no square overflows or underflows. The scatter is one
    # compiled pass (no centred copy; not BLAS, whose threads keep spinning after the product and
    # take the cores from the kernels that follow).
    scatter = np.empty((3, 3))
    _kernels.centred_scatter(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(centre),
                             float(magnitude), scatter)
    squared = np.linalg.eigvalsh(scatter)
    if squared[1] > 1e-12 * squared[2] and np.sqrt(squared[1]) * magnitude > 2.0 * rounding_floor:
        return None
    singular_values = np.linalg.svd(points - centre, compute_uv=False)
    if singular_values[0] <= rounding_floor:
        return "all points are identical"
    if singular_values[1] <= 1e-9 * singular_values[0] + rounding_floor:
        return "all points are collinear"
    return None


#: Largest coordinate magnitude a registration accepts: squared distances and their sums must stay
#: far from float64's overflow (1.8e308).
MAX_COORDINATE = 1e100

#: Smallest extent (longest side of the bounding box) a registration accepts: squared point spacings must stay
#: far from float64's underflow (2.2e-308), where precision is lost (measured: a 1e-160 cloud is
#: registered 0.1 degrees off, a 1e-200 one not at all).
MIN_EXTENT = 1e-100


def check_representable(points: np.ndarray, name: str = "points") -> None:
    """Raise :class:`InvalidInputError` if ``points`` are too large or too small for float64 geometry.

    Within ``|x| <= 1e100`` and an extent of at least ``1e-100`` (any physical unit, from
    femtometres to light years, is far inside), registration is exact to rounding; outside, squared
    distances overflow or underflow. The message says to rescale (change units).
    """
    magnitude = float(np.abs(points).max())
    if magnitude > MAX_COORDINATE:
        raise InvalidInputError(
            f"{name}: coordinates up to {magnitude:.3g} in magnitude, beyond the {MAX_COORDINATE:g} that "
            f"float64 squared distances allow; rescale the cloud (other units) or drop the points that far out"
        )
    low, high = axis_bounds(points)
    extent = float(np.max(high - low))  # no squares: they would underflow
    if extent < MIN_EXTENT and degeneracy(points) is None:  # a degenerate cloud is named so by check_not_degenerate
        raise InvalidInputError(
            f"{name}: the cloud spans only {extent:.3g} units, below the {MIN_EXTENT:g} that float64 "
            f"squared distances resolve; rescale the cloud (other units)"
        )


#: Largest ratio :func:`check_scales` accepts between the largest extent of the clouds and the
#: smallest spread of their points (unitless). At 1e15 the smaller spans about 5 rounding steps of
#: float64 coordinates as large as the larger (2.2e-16 relative): measured, a source 1e20 times
#: its target ended in the voxel grid's overflow ("voxel ... too small for the cloud's extent").
MAX_SCALE_RATIO = 1e15

#: Points :func:`check_scales` takes the spread of (evenly strided), so that it costs microseconds.
SCALE_SAMPLE = 10_000


def _spread(points: np.ndarray) -> float:
    """Where most points lie: the largest per-axis median absolute deviation (from a strided sample),
    or the extent when more than half of the points coincide (the deviation is then 0)."""
    sample = points[:: max(1, len(points) // SCALE_SAMPLE)]
    deviation = float(np.max(np.median(np.abs(sample - np.median(sample, axis=0)), axis=0)))
    if deviation > 0:
        return deviation
    low, high = axis_bounds(points)
    return float(np.max(high - low))


def check_scales(clouds) -> None:
    """Raise :class:`InvalidInputError` if float64 coordinates cannot resolve all ``clouds`` at once.

    ``clouds`` maps a name (``"source"``, or a file's path) to its ``(N, 3)`` points. The largest
    extent among them must stay within :data:`MAX_SCALE_RATIO` of the smallest spread of points
    (median absolute deviation): beyond, the points of one cloud lie within a few rounding steps
    of the coordinates of another (clouds in different units), or a few points lie so far from
    the others that those others collapse (outliers; a file read in the wrong layout, such as the
    columns of a ``.bin``). Every later check would blame the wrong thing. Degenerate clouds (no
    spread) are left to :func:`check_not_degenerate`.
    """
    extents, spreads = {}, {}
    for name, points in clouds.items():
        low, high = axis_bounds(points)
        extents[name] = float(np.max(high - low))
        spreads[name] = _spread(points)
    spreads = {name: spread for name, spread in spreads.items() if spread > 0}
    for name, spread in spreads.items():
        ratio = extents[name] / spread
        if ratio > MAX_SCALE_RATIO:
            raise InvalidInputError(
                f"{name}: its points span {extents[name]:.3g} units, but half of them lie within {spread:.3g} of "
                f"their median, {ratio:.2g} times less: beyond what float64 coordinates resolve "
                f"({MAX_SCALE_RATIO:g}); outliers far from the other points, or a file read in the wrong layout "
                "(such as the columns of a .bin)"
            )
    if not spreads:
        return
    widest = max(extents, key=extents.get)
    tightest = min(spreads, key=spreads.get)
    ratio = extents[widest] / spreads[tightest]
    if ratio > MAX_SCALE_RATIO:
        raise InvalidInputError(
            f"{widest}: spans {extents[widest]:.3g} units, {ratio:.2g} times the spread of the {tightest}'s "
            f"points ({spreads[tightest]:.3g}): beyond what float64 coordinates resolve at once "
            f"({MAX_SCALE_RATIO:g}); the clouds may be in different units: rescale one"
        )


def check_geometry(clouds) -> None:
    """The checks of numbers float64 geometry cannot use, in the order that blames the right thing:
    :func:`check_representable` for each cloud, then :func:`check_scales` across them (before
    :func:`check_not_degenerate`, whose verdict those numbers would distort). ``clouds`` maps a
    name (``"source"``, or a file's path) to its points."""
    for name, points in clouds.items():
        check_representable(points, name)
    check_scales(clouds)


def check_not_degenerate(points: np.ndarray, name: str = "points") -> None:
    """Raise :class:`InvalidInputError` if ``points`` is degenerate (see :func:`degeneracy`)."""
    problem = degeneracy(points)
    if problem is not None:
        raise InvalidInputError(f"{name}: degenerate cloud, {problem}")


def as_transform(transform, name: str = "transform", *, tolerance: float = RIGID_TOLERANCE) -> np.ndarray:
    """Return ``transform`` as a new 4x4 float64 rigid transform.

    Raises
    ------
    InvalidInputError
        If it is not 4x4, not finite, its last row is not ``[0, 0, 0, 1]``, or its 3x3 block is not
        a rotation (orthonormal with determinant +1, to ``tolerance``).
    """
    try:
        matrix = np.array(transform, dtype=np.float64, copy=True)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name}: expected a 4x4 numeric matrix, could not convert: {exc}") from None
    if matrix.shape != (4, 4):
        raise InvalidInputError(f"{name}: expected a 4x4 matrix, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise InvalidInputError(f"{name}: contains NaN or infinite entries")
    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], atol=tolerance):
        raise InvalidInputError(f"{name}: last row must be [0 0 0 1], got {matrix[3].tolist()}")
    rotation = matrix[:3, :3]
    orthogonality = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if orthogonality > tolerance:
        raise InvalidInputError(
            f"{name}: not rigid, its 3x3 block is not orthonormal (max |R^T R - I| = {orthogonality:.3g})"
        )
    determinant = float(np.linalg.det(rotation))
    if determinant < 0:
        raise InvalidInputError(f"{name}: not rigid, its 3x3 block is a reflection (det = {determinant:.3g})")
    matrix[3] = [0.0, 0.0, 0.0, 1.0]
    return matrix


def as_real(value, name: str) -> float:
    """Return a real number (Python or NumPy; not a bool or a string) as a float, or raise
    :class:`InvalidInputError`."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Real, np.floating, np.integer)):
        raise InvalidInputError(f"{name}: expected a number, got {value!r}")
    return float(value)


def as_count(value, name: str, minimum: int = 1) -> int:
    """Return a whole number (Python or NumPy int; not a bool, float or string) >= ``minimum``, or
    raise :class:`InvalidInputError`."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise InvalidInputError(f"{name}: expected a whole number >= {minimum}, got {value!r}")
    return int(value)


#: Most threads ``workers=`` may ask for: the compiled kernels take a C ``int`` (each call then
#: uses at most one thread per piece of its work).
MAX_WORKERS = 2**31 - 1


def as_workers(value, name: str = "workers") -> int | None:
    """Return the number of threads ``value`` asks for: None (every core) or a whole number from 1
    to :data:`MAX_WORKERS`, or raise :class:`InvalidInputError`."""
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or not 1 <= value <= MAX_WORKERS:
        raise InvalidInputError(
            f"{name}: expected a whole number of threads from 1 to {MAX_WORKERS}, or None for every core, got {value!r}"
        )
    return int(value)


def as_positive(value, name: str) -> float:
    """Return ``value`` as a finite float > 0, or raise :class:`InvalidInputError`."""
    number = as_real(value, name)
    if not np.isfinite(number) or number <= 0:
        raise InvalidInputError(f"{name}: must be a finite number > 0, got {value!r}")
    return number


def as_generator(rng, name: str = "rng", *, default_seed: int | None = None) -> np.random.Generator:
    """``rng`` as a :class:`numpy.random.Generator` (the one place randomness is coerced, like
    scikit-learn's ``check_random_state``): a Generator is used as is, an int (or a
    :class:`numpy.random.SeedSequence`) seeds a new one, None seeds one from ``default_seed`` (None:
    fresh entropy)."""
    try:
        return np.random.default_rng(default_seed if rng is None else rng)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(
            f"{name}: expected None, a seed >= 0 or a numpy Generator, got {rng!r} ({exc})"
        ) from None
