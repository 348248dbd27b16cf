"""Local shape features: voxel downsampling, PCA normals and FPFH (the global search, the
plane method, the pose covariance and the merge use them).

No Python loop over points: the normals and FPFH are compiled passes (:mod:`esmicp._kernels`),
deterministic whatever the number of threads. Lengths
(``voxel``, ``radius``) are in the clouds' units; angles inside FPFH are in radians.

Normal orientation
------------------
PCA gives a normal only up to sign, and FPFH's angle features change when a normal flips, so the
sign must be chosen the same way on both clouds. :func:`estimate_normals` orients each normal
*away from the cloud's centroid* (``n . (p - centroid) >= 0``) by default. That rule is
equivariant under rigid motions (rotate and translate the cloud: the normals rotate with it), so
FPFH stays invariant; it is right for roughly convex objects and consistent between two views of
the same object as long as their centroids are close. Where the normal is perpendicular to
``p - centroid`` (a plane through the centroid) the rule cannot decide and the sign is the
eigen-solver's. A ``viewpoint`` (a sensor position) may be given instead; that rule is *not*
equivariant (the viewpoint is fixed in the cloud's frame).

Open3D, for comparison, does not orient estimated normals at all (the sign is whatever its
3x3 eigen-solver returns, unless the cloud already had normals, which are then used to pick the
sign); orientation toward +z or a camera are separate, explicit calls there
(``orient_normals_to_align_with_direction``, ``orient_normals_towards_camera_location``).

FPFH
----
Rusu, Blodow and Beetz, "Fast Point Feature Histograms (FPFH) for 3D registration", ICRA 2009.
For a pair of points ``(p_s, n_s)``, ``(p_t, n_t)`` at distance ``d``, the *source* of the pair is
the point whose normal is closer to the connecting line (larger ``|n . (p_t - p_s)| / d``), which
makes the pair's features independent of the order. With ``e = (p_t - p_s) / d`` and the Darboux
frame ``u = n_s``, ``v = e x u / |e x u|``, ``w = u x v``:

* ``alpha = v . n_t`` in ``[-1, 1]``,
* ``phi = u . e`` in ``[-1, 1]``,
* ``theta = atan2(w . n_t, u . n_t)`` in ``[-pi, pi]`` (radians).

(``v = e x u`` rather than the paper's ``u x e`` flips the signs of ``alpha`` and ``theta``: that
is Open3D's convention, kept so that the features can be compared with Open3D's directly.) When
both normals make the same angle with the line (to 1e-9 in cosine, e.g. two points with the same
normal) the source is the point that gives the larger ``phi``, so that the result depends neither
on the order of the points nor on the pose (Open3D's choice then depends on rounding).

Each feature is binned into 11 equal bins over its range. The SPFH of a point is the histogram of
the triplets of its pairs with every other point within ``radius``: three 11-bin blocks
``[theta | alpha | phi]``, each normalised to sum to 100. The FPFH is
``FPFH_i = SPFH_i + 100 * S_i / |S_i|`` per block, with ``S_i = sum_j SPFH_j / d_ij^2`` over the
neighbours ``j`` of ``i`` and ``|S_i|`` the block's sum. The paper writes a plain ``1/k`` mean
weighted by ``1 / d_ij``; the inverse *squared* distance and the per-block renormalisation are
Open3D's, and make the result independent of the cloud's units and density. Each 11-bin block of
an FPFH therefore sums to 200 (the whole row is 0 for a point without neighbours). With a radius
search, :func:`fpfh` agrees with Open3D 0.20's ``compute_fpfh_feature`` to rounding (measured:
4e-14 on random points and normals) apart from the tie rule above.
"""

from __future__ import annotations

import numpy as np

from .. import _kernels
from .compiled_tree import K_MAX, CompiledTree, threads
from .procrustes import axis_bounds, centroid
from ..errors import InvalidInputError
from ..types import as_positive

#: Bins per FPFH angle feature, and the feature length (three blocks: theta, alpha, phi): the
#: compiled kernel's layout.
FPFH_BINS = _kernels.FPFH_BINS
FPFH_DIMENSION = _kernels.FPFH_DIMENSION

#: Value each block of an SPFH sums to (a point with at least one neighbour).
SPFH_BLOCK_SUM = _kernels.SPFH_BLOCK_SUM

#: Value each block of an FPFH sums to (a point with at least one neighbour): its own SPFH block
#: plus its neighbours' weighted blocks renormalised to one SPFH block's sum.
FPFH_BLOCK_SUM = _kernels.FPFH_BLOCK_SUM


def _as_cloud(points, name: str = "points", *, min_points: int = 1) -> np.ndarray:
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidInputError(f"{name}: expected (N, 3) points, got shape {array.shape}")
    if len(array) < min_points:
        raise InvalidInputError(f"{name}: need at least {min_points} point(s), got {len(array)}")
    if not np.isfinite(array).all():
        raise InvalidInputError(f"{name}: contains NaN or infinite coordinates")
    return array


def voxel_downsample(points, voxel: float) -> np.ndarray:
    """Replace the points of every occupied voxel by their centroid.

    The grid is anchored at the cloud's minimum corner (so the result moves with the cloud under
    translations; no voxel grid is invariant under rotations).

    Parameters
    ----------
    points : (N, 3) array
        The cloud (any units).
    voxel : float
        Edge length of the cubic voxels, in the cloud's units (> 0).

    Returns
    -------
    (K, 3) float64 array
        One centroid per occupied voxel, ``K <= N``, ordered by voxel index (x-major).
    """
    centroids, _ = voxel_grid(points, voxel)
    return centroids


def voxel_grid(points, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`voxel_downsample`, also returning which centroid each input point went to.

    Returns
    -------
    centroids : (K, 3) float64 array
    owner : (N,) intp array
        ``centroids[owner[i]]`` is the centroid of the voxel of ``points[i]``.
    """
    points = np.ascontiguousarray(_as_cloud(points), dtype=np.float64)
    voxel = as_positive(voxel, "voxel")
    # One compiled pass with a hash of the cells (no sort of every point's key), the occupied
    # cells then sorted: the centroids and owners of a sort of the keys, sums in point order.
    owner = np.empty(len(points), dtype=np.intp)
    sums = np.empty((len(points), 3))
    counts = np.empty(len(points), dtype=np.int64)
    occupied = _kernels.voxel_cells(points, np.ascontiguousarray(axis_bounds(points)[0], dtype=np.float64),
                                    float(voxel), owner, sums, counts)
    if occupied < 0:
        raise InvalidInputError(f"voxel: {voxel!r} is too small for the cloud's extent (over 2^62 voxels per axis)")
    return sums[:occupied] / counts[:occupied, None], owner


def dense_point_mask(
    points, radius: float, *, fraction: float = 0.3, quantile: float = 0.75, tree: CompiledTree | None = None,
    workers: int | None = 1,
) -> np.ndarray:
    """Mask of the points that are not isolated: a radius outlier filter with a relative threshold.

    A point is kept when its number of neighbours within ``radius`` (itself included) is at least
    ``fraction`` times the ``quantile`` of that number over the cloud. The threshold adapts to the
    sampling density, so the same call suits sparse and dense clouds; on a clean surface almost
    every point is kept, while scattered outliers (far from the surface, hence with few
    neighbours) are dropped.

    Parameters
    ----------
    points : (N, 3) array
    radius : float
        Neighbourhood radius, in the cloud's units (> 0); a few sampling spacings.
    fraction : float
        Relative threshold in ``[0, 1]``; 0 keeps everything.
    quantile : float
        Which quantile of the neighbour counts is the reference density, in ``[0, 1]``.
    tree : esmicp.core.compiled_tree.CompiledTree, optional
        The compiled tree over ``points``, to reuse (the counts are compiled: no SciPy import).
    workers : int or None
        Threads of the counts (None: every core).

    Returns
    -------
    (N,) bool array
    """
    points = _as_cloud(points)
    radius = as_positive(radius, "radius")
    tree = CompiledTree(points, workers=workers) if tree is None else tree
    counts = np.empty(len(points), dtype=np.int64)
    _kernels.count_within(np.ascontiguousarray(points, dtype=np.float64), tree.points, tree.order, tree.starts,
                          tree.ends, tree.lefts, tree.boxes, float(radius), counts, threads(workers))
    return counts >= fraction * np.quantile(counts, quantile)


def estimate_normals(
    points,
    k: int = 30,
    radius: float | None = None,
    *,
    at=None,
    viewpoint=None,
    tree: CompiledTree | None = None,
    workers: int | None = 1,
) -> np.ndarray:
    """Unit surface normals by PCA of each point's neighbourhood.

    The normal is the eigenvector of the smallest eigenvalue of the covariance of the
    neighbourhood (compiled: the k nearest, the 3 x 3 covariance and its Jacobi eigen-decomposition,
    one pass per query on ``workers`` threads).

    Parameters
    ----------
    points : (N, 3) array
        The surface samples the neighbourhoods are taken from (any units).
    k : int
        At most this many nearest neighbours (the query point itself included when it belongs to
        ``points``).
    radius : float, optional
        If given, only neighbours within ``radius`` (cloud units) are used, among the ``k``
        nearest (Open3D's "hybrid" search). None: the ``k`` nearest, whatever their distance.
    at : (M, 3) array, optional
        Where normals are wanted (default: at ``points``). E.g. the centroids of a downsampled
        cloud, with neighbourhoods from the dense cloud.
    viewpoint : (3,) array, optional
        Orient each normal toward this position (a sensor). Default: away from the centroid of
        ``points`` (see the module docstring; this default is equivariant under rigid motions).
    tree : esmicp.core.compiled_tree.CompiledTree, optional
        The compiled KD-tree over ``points``, to reuse (its exact k nearest; no SciPy import).
    workers : int or None
        Threads of the neighbour queries and the decompositions (None: every core).

    Returns
    -------
    (M, 3) float64 array of unit vectors
        Where fewer than 3 neighbours are found, the normal falls back to the unit direction from
        the centroid of ``points`` to the query point (or ``+z`` if they coincide).
    """
    estimator = NormalEstimator(points, k, radius, tree=tree, workers=workers)
    return estimator.at(estimator.points if at is None else at, viewpoint)


class NormalEstimator:
    """:func:`estimate_normals` of one cloud, asked many times: what depends only on the cloud
    (its tree and its centroid) is made once, so that each call
    costs in proportion to the points asked about (``esm-plane`` asks for a few thousand new
    normals of a 300k-point target at each iteration). Same parameters and results as
    :func:`estimate_normals`; ``points`` must not change while it is in use."""

    def __init__(self, points, k: int = 30, radius: float | None = None, *, tree: CompiledTree | None = None,
                 workers: int | None = 1):
        self.points = _as_cloud(points)
        if not 3 <= int(k) <= K_MAX:
            raise InvalidInputError(f"k: need 3 to {K_MAX} neighbours for a normal, got {k!r}")
        self.k = min(int(k), len(self.points))
        self.upper = np.inf if radius is None else as_positive(radius, "radius")
        self.tree = CompiledTree(self.points, workers=workers) if tree is None else tree
        self.workers = workers
        # Covariances are taken of coordinates relative to the cloud's centroid (for accuracy).
        self.centroid = centroid(self.points)

    def at(self, query, viewpoint=None) -> np.ndarray:
        """Unit normals at ``query`` ((M, 3), cloud units), oriented as :func:`estimate_normals`
        orients them (toward ``viewpoint`` if given)."""
        query = query if query is self.points else _as_cloud(query, "at")
        tree = self.tree
        normals = np.empty((len(query), 3))
        counts = np.empty(len(query), dtype=np.int64)
        # The k nearest within the radius, their covariance and its least eigenvector, compiled
        # (NumPy's gather and batched eigh cost more than the neighbour search itself).
        _kernels.knn_normals(np.ascontiguousarray(query, dtype=np.float64), tree.points, tree.order, tree.starts,
                             tree.ends, tree.lefts, tree.boxes, self.k, float(self.upper), self.centroid, normals,
                             counts, threads(self.workers))

        outward = query - self.centroid
        few = counts < 3
        if few.any():
            fallback = outward[few]
            lengths = np.linalg.norm(fallback, axis=1)
            unit = fallback / np.where(lengths > 0, lengths, 1.0)[:, None]
            fallback = np.where(lengths[:, None] > 0, unit, [0.0, 0.0, 1.0])
            normals[few] = fallback
        reference = outward if viewpoint is None else np.asarray(viewpoint, dtype=np.float64).reshape(3) - query
        flip = np.einsum("ij,ij->i", normals, reference) < 0
        normals[flip] *= -1.0
        return normals


def fpfh(points, normals, radius: float, tree: CompiledTree | None = None, workers: int | None = 1) -> np.ndarray:
    """Fast Point Feature Histograms of every point (see the module docstring for the definition).

    Compiled: each point's neighbours within ``radius`` from the KD-tree, its SPFH from the bins of
    its pairs, then the weighted sum of its neighbours' SPFHs; every pair's features are computed
    with the same operands from both of its ends, so both see the same bins.

    Parameters
    ----------
    points : (N, 3) array
        The cloud (any units).
    normals : (N, 3) array
        Unit normals, consistently oriented (e.g. :func:`estimate_normals`).
    radius : float
        Neighbourhood radius in the cloud's units (> 0); typically 5x the sampling spacing.
    tree : esmicp.core.compiled_tree.CompiledTree, optional
        The compiled KD-tree over ``points``, to reuse.
    workers : int or None
        Threads (None: every core).

    Returns
    -------
    (N, 33) float64 array
        Blocks ``[theta (11) | alpha (11) | phi (11)]``; each block sums to
        :data:`FPFH_BLOCK_SUM` (200) for a point with at least one neighbour within ``radius``,
        and the whole row is 0 for an isolated point. Invariant under rigid motions of the cloud
        (with the normals moved along).
    """
    points = _as_cloud(points)
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != points.shape:
        raise InvalidInputError(f"normals: expected shape {points.shape}, got {normals.shape}")
    radius = as_positive(radius, "radius")
    tree = CompiledTree(points, workers=workers) if tree is None else tree
    features = np.empty((len(points), FPFH_DIMENSION))
    _kernels.fpfh(np.ascontiguousarray(normals), tree.points, tree.order, tree.starts, tree.ends, tree.lefts,
                  tree.boxes, float(radius), features, threads(workers))
    return features
