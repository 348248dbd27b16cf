"""How sure a registration is, and in which directions: the pose covariance and the degenerate
directions, from the final correspondences.

Convention (every array here)
-----------------------------
A pose error is a 6-vector ``delta = (omega, v)``: ``omega`` a small rotation vector (radians),
then ``v`` a translation (cloud units), applied on the LEFT of ``T_target_source``, in the target
frame: ``T_true = Exp(delta) @ T_estimated``, i.e. a target-frame point ``p`` of the placed source
moves to ``p + omega x p + v`` (rotation about the target frame's origin). :func:`left_error` gives
that vector for two poses.

The covariance
--------------
Each pair joins a source point as placed, ``p_i`` (target frame), to its nearest target point
``q_i``, with the method's weight ``w_i`` (ESM's Gaussian weight at the final sigma; 1 for ICP).
The nearest-neighbour cost of a surface behaves like the point-to-plane cost: where the target's
unit normal ``n_i`` at ``q_i`` is known, a pair constrains the pose through its residual
``r_i = n_i . (p_i - q_i)`` and gradient ``a_i = (p_i x n_i, n_i)`` only (a plane slides freely
along itself); without normals, through the three coordinates of ``p_i - q_i``.

Censi's closed form (2007) for a least-squares estimate is ``H^-1 B H^-1`` with the Hessian
``H = sum_i w_i a_i a_i^T`` and ``B`` the covariance of the gradient the estimate zeroes. Taking the
residuals as independent, with one variance estimated from them (``B = sigma^2 sum_i w_i^2 a_i
a_i^T``), is known to be over-confident, for four reasons this estimate corrects:

- the correspondences themselves are in error: a nearest neighbour lies up to a point spacing
  beside the true match, and the point-to-point cost the methods minimise feels that offset.
  ``B`` is therefore built from each pair's share of that cost's gradient,
  ``s_i = w_i (u_i x d_i, d_i)`` with ``d_i = p_i - q_i`` the whole 3-D residual, while ``H`` keeps
  the point-to-plane curvature (the cost's true stiffness once the pairs may slide);
- the residuals of neighbouring pairs are correlated (the same target points and surface patch
  serve many source points; a depth camera's smooth errors pull whole regions one way), so there
  are far fewer independent pairs than pairs. ``B`` is the cluster-robust estimate (Liang and
  Zeger's sandwich): the pairs are grouped into cubes of ``cluster_spacings`` target point
  spacings and ``B = sum_c g_c g_c^T`` with ``g_c`` the sum of the cube's ``s_i``. Within a cube
  the residuals may be correlated in any way; cubes are taken as independent;
- the residuals understate the clouds' noise where it is comparable to the spacing: each source
  point is paired with the nearest of several noisy target points, the one whose noise happens to
  bring it closest. Each cloud's noise is measured on its own, from the scatter of its points
  about their local planes (:func:`surface_noise`), and its share along the normals is added to
  ``B``: a source point's noise is its own, a target point's is shared by the pairs that matched
  it (:func:`sharing`);
- where a partial overlap ends, source points are paired with the target's border, and those
  pairs pull the pose the same way all along it, not as independent cubes: the pairs farther
  apart than ``border_spacings`` target spacings add their summed gradient to ``B`` as one more
  cluster.

The result is multiplied by ``inflation``, chosen on one set of trials and confirmed on
another (``docs/uncertainty.md``). The values named here are fields of
:class:`~esmicp.trust.policy.TrustPolicy`.

Degenerate directions
---------------------
The eigenvectors of the point-to-plane Hessian ``H`` about the overlap's weighted centroid, with
rotations scaled by the overlap's RMS radius ``L`` (so that a rotation and a translation compare
in the same units: the motion of a point at distance ``L``), whose eigenvalue is below
``degenerate_ratio`` times the largest: the overlap barely constrains the pose along them
(Zhang and Singh's degeneracy factor, 2016; X-ICP's localizability, Tuna et al. 2023). A corridor
leaves translation along its axis, a plane on a plane the two in-plane translations and the
rotation about its normal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.procrustes import skew
from ..core.sampling import evenly_strided
from .policy import DEFAULT_POLICY, TrustPolicy

AXES = ("x", "y", "z")


@dataclass(frozen=True)
class DegenerateDirection:
    """A direction of pose change the overlap barely constrains (target frame).

    ``rotation`` (3,) and ``translation`` (3,) are the parts of a unit 6-vector, the rotation part
    scaled by ``radius`` (a rotation of ``omega`` radians counts as ``omega * radius`` cloud units:
    the motion it gives a point at the overlap's RMS radius); the rotation is about ``centre``
    (the overlap's weighted centroid, target frame, cloud units). ``ratio`` is its eigenvalue
    divided by the best-constrained direction's (0-1; below ``TrustPolicy.degenerate_ratio``).
    """

    rotation: np.ndarray
    translation: np.ndarray
    ratio: float
    centre: np.ndarray
    radius: float

    @property
    def kind(self) -> str:
        """``"translation"`` or ``"rotation"``, whichever part of the direction is larger."""
        return "translation" if np.linalg.norm(self.translation) >= np.linalg.norm(self.rotation) else "rotation"

    @property
    def axis(self) -> np.ndarray:
        """The unit axis of the larger part (target frame), its sign chosen with its largest entry positive."""
        part = self.translation if self.kind == "translation" else self.rotation
        unit = part / max(float(np.linalg.norm(part)), 1e-300)
        return unit if unit[np.argmax(np.abs(unit))] >= 0 else -unit

    def describe(self) -> str:
        """In words, e.g. ``"translation along x (target frame) is poorly constrained (ratio 2.1e-05)"``."""
        axis = self.axis
        dominant = int(np.argmax(np.abs(axis)))
        if abs(axis[dominant]) > 0.9:
            where = AXES[dominant]
        else:
            where = "(" + ", ".join(f"{value:.2f}" for value in axis) + ")"
        preposition = "along" if self.kind == "translation" else "about"
        return f"{self.kind} {preposition} {where} (target frame) is poorly constrained (ratio {self.ratio:.1e})"

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "axis": self.axis.tolist(),
            "description": self.describe(),
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "ratio": self.ratio,
            "centre": self.centre.tolist(),
            "radius": self.radius,
        }


@dataclass(frozen=True)
class PoseUncertainty:
    """The uncertainty of one pose (see the module docstring for the convention).

    ``covariance`` (6, 6): of ``(omega [rad], v [cloud units])``, left perturbation, target frame.
    ``information`` (6, 6): its inverse; where the data constrain some direction not at all
    (eigenvalue below ``TrustPolicy.singular_ratio``), the pseudo-inverse, zero along it.
    ``degenerate_directions``: the poorly constrained directions (empty when none).
    ``pairs``: the number of pairs the estimate used. ``covariance`` and ``information`` are None
    when fewer than 3 pairs carry weight, or they all lie at one point.
    """

    covariance: np.ndarray | None
    information: np.ndarray | None
    degenerate_directions: tuple[DegenerateDirection, ...]
    pairs: int


def pose_uncertainty(placed: np.ndarray, matched: np.ndarray, weights: np.ndarray | None = None,
                     normals: np.ndarray | None = None, *, spacing: float, origin: np.ndarray | None = None,
                     noise: tuple[float, float] | None = None,
                     policy: TrustPolicy = DEFAULT_POLICY) -> PoseUncertainty:
    """The covariance, information and degenerate directions of a pose from its final pairs.

    Parameters
    ----------
    placed : (N, 3) array
        Source points as placed by the pose (target frame, cloud units).
    matched : (N, 3) array
        Their target points.
    weights : (N,) array, optional
        The method's weights of the pairs (>= 0; None: all 1).
    normals : (N, 3) array, optional
        Unit target normals at ``matched`` (None: point-to-point residuals). Rows of NaN: no normal
        for that pair; the Hessian then comes from the pairs that have one, scaled to the total
        weight of all of them.
    spacing : float
        The target's point spacing (cloud units): sets the cube size of the cluster-robust estimate
        and the border distance.
    origin : (3,) array, optional
        Where the frame of ``placed`` and ``matched`` has its origin in the frame the result is
        wanted in (a registration's working frame is shifted by it); default 0.
    noise : (float, float), optional
        ``(source_variance, target_variance)`` per pair along the surface normal (cloud units
        squared): each cloud's noise variance (e.g. :func:`surface_noise`), the target's times
        :func:`sharing` when several pairs share a target point. With normals, it adds the noise's
        share to the spread of the gradient (see the module docstring); None: the residuals alone.
    policy : TrustPolicy
        The estimate's values: ``cluster_spacings``, ``min_clusters``, ``border_spacings``,
        ``inflation``, ``degenerate_ratio``, ``singular_ratio`` and ``negligible_weight``.

    Returns
    -------
    PoseUncertainty
    """
    placed = np.asarray(placed, dtype=np.float64)
    matched = np.asarray(matched, dtype=np.float64)
    weights = np.ones(len(placed)) if weights is None else np.asarray(weights, dtype=np.float64)
    keep = weights > policy.negligible_weight * (float(weights.max()) if len(weights) else 0.0)
    placed, matched, weights = placed[keep], matched[keep], weights[keep]
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)[keep]
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    if len(placed) < 3:
        return _unconstrained(len(placed))
    total = float(weights.sum())
    centre = weights @ placed / total
    offsets = placed - centre
    radius = math.sqrt(float(weights @ np.einsum("ij,ij->i", offsets, offsets)) / total)
    if not radius > 0:
        return _unconstrained(len(placed))
    unit_offsets, differences = offsets / radius, placed - matched
    if normals is not None and np.isnan(normals[:, 0]).any():
        known = ~np.isnan(normals[:, 0])
        share = float(weights[known].sum())
        if not share > 0:
            return _unconstrained(len(placed))
        hessian = _hessian(unit_offsets[known], weights[known], normals[known]) * (total / share)
    else:
        hessian = _hessian(unit_offsets, weights, normals)
    # Each pair's share of the gradient of the point-to-point cost the methods minimise, J_i^T w_i d_i.
    scores = np.hstack([np.cross(unit_offsets, differences), differences]) * weights[:, None]
    inverse, groups = _clusters(placed, max(policy.cluster_spacings * spacing, 1e-300), max(spacing, 1e-300),
                               policy.min_clusters)
    sums = np.column_stack([np.bincount(inverse, weights=column, minlength=groups) for column in scores.T])
    count = len(placed)
    # Small-sample corrections of the sandwich (the usual ones of cluster-robust estimates).
    correction = groups / max(groups - 1, 1) * count / max(count - 6, 1)
    meat = correction * (sums.T @ sums)
    if noise is not None and normals is not None:
        meat = meat + _noise_meat(unit_offsets, weights, normals, noise)
    # The pairs beyond an overlap's border pull as one: their summed gradient is one more cluster.
    far = np.einsum("ij,ij->i", differences, differences) > (policy.border_spacings * spacing) ** 2
    if far.any():
        pull = scores[far].sum(axis=0)
        meat = meat + np.outer(pull, pull)

    values, vectors = np.linalg.eigh(hessian)
    largest = max(float(values[-1]), 0.0)
    ratios = np.clip(values / largest, 0.0, None) if largest > 0 else np.zeros(6)
    constrained = ratios > policy.singular_ratio
    inverse_values = np.where(constrained, 1.0 / np.where(constrained, values, 1.0), 0.0)
    pseudo = (vectors * inverse_values) @ vectors.T
    scaled = policy.inflation * pseudo @ meat @ pseudo
    # No information at all along a direction: one radian, or one overlap radius (scaled units:
    # one radius either way).
    null = vectors[:, ~constrained]
    scaled = scaled + radius * radius * (null @ null.T)
    scaled = 0.5 * (scaled + scaled.T)
    mapping, inverse_mapping = _to_frame(centre + origin, radius)
    covariance = mapping @ scaled @ mapping.T
    information = _information(scaled, null, inverse_mapping, policy.singular_ratio)
    degenerate = tuple(
        DegenerateDirection(vectors[:3, k].copy(), vectors[3:, k].copy(), float(ratios[k]), centre + origin, radius)
        for k in range(6) if ratios[k] < policy.degenerate_ratio
    )
    return PoseUncertainty(0.5 * (covariance + covariance.T), information, degenerate, count)


def _noise_meat(unit_offsets: np.ndarray, weights: np.ndarray, normals: np.ndarray,
                noise: tuple[float, float]) -> np.ndarray:
    """The spread the clouds' noise gives the gradient along the normals (6x6, scaled units),
    ``(var_s + var_t) sum_i w_i^2 a_i a_i^T`` over the pairs with a normal (not NaN rows), scaled
    to the weight of all."""
    variance = sum(max(float(value), 0.0) for value in noise)
    known = ~np.isnan(normals[:, 0])
    squares = float(np.square(weights[known]).sum())
    if not known.any() or variance <= 0 or not squares > 0:
        return np.zeros((6, 6))
    share = float(np.square(weights).sum()) / squares
    rows = np.hstack([np.cross(unit_offsets[known], normals[known]), normals[known]])
    return variance * share * ((rows * np.square(weights[known])[:, None]).T @ rows)


def sharing(indices: np.ndarray, weights: np.ndarray | None = None) -> float:
    """How many pairs share a target point's noise: ``sum_j W_j^2 / sum_i w_i^2`` with ``W_j`` the
    total weight of the pairs matched to target point ``j`` (``indices``: each pair's target
    index; 1 when no two pairs share one). A target point's noise moves every pair that matched
    it alike, so its share of the gradient's spread is this many times an independent point's."""
    indices = np.asarray(indices).ravel()
    weights = np.ones(len(indices)) if weights is None else np.asarray(weights, dtype=np.float64)
    squares = float(np.square(weights).sum())
    if not squares > 0:
        return 1.0
    return float(np.square(np.bincount(indices, weights=weights)).sum()) / squares


def surface_noise(points: np.ndarray, at: np.ndarray, tree=None, neighbours: int = 10,
                  workers: int | None = 1) -> float:
    """A cloud's noise variance along its surface normal (cloud units squared): the median, over
    the query points ``at``, of the least eigenvalue of the covariance of their ``neighbours``
    nearest points of ``points`` (the mean square distance to their best-fitting plane), times
    ``k / (k - 3)`` (a plane fitted through ``k`` noisy points absorbs 3 of their degrees of
    freedom). Curvature within a neighbourhood adds to it (the more, the more neighbours), so on
    curved, clean clouds it is an upper bound; a noise as large as the point spacing is read low
    (the nearest points are then chosen by their noise: about 2/3 of the variance at 0.7
    spacings, 1/3 at 1.1, with 10 neighbours). ``tree``: a
    :class:`~esmicp.core.compiled_tree.CompiledTree` of ``points`` (None: the neighbours from
    :func:`~esmicp.core.compiled_tree.k_nearest`, the same); ``workers``:
    threads of the neighbour search."""
    from ..core.compiled_tree import k_nearest

    points = np.asarray(points, dtype=np.float64)
    k = min(int(neighbours), len(points))
    if k < 4 or len(at) == 0:
        return 0.0
    if tree is None:  # a few hundred queries need no tree over a large cloud
        indices = k_nearest(points, np.asarray(at, dtype=np.float64), k, workers=workers)
    else:
        _, indices = tree.query_k(np.asarray(at, dtype=np.float64), k, workers=workers)
    indices = indices[np.all(indices < len(points), axis=1)]
    if not len(indices):
        return 0.0
    patches = points[indices]
    patches = patches - patches.mean(axis=1, keepdims=True)
    least = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", patches, patches) / k)[:, 0]
    return float(np.median(np.clip(least, 0.0, None))) * k / (k - 3)


def _hessian(unit_offsets: np.ndarray, weights: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
    """The 6x6 Hessian ``sum_i w_i a_i a_i^T`` (scaled rotation, translation): point-to-plane rows
    ``a_i = (u_i x n_i, n_i)`` with normals, else the three point-to-point rows of each pair."""
    if normals is not None:
        rows = np.hstack([np.cross(unit_offsets, normals), normals])
        return (rows * weights[:, None]).T @ rows
    hessian = np.zeros((6, 6))
    for axis in np.eye(3):
        axes = np.broadcast_to(axis, unit_offsets.shape)
        rows = np.hstack([np.cross(unit_offsets, axes), axes])
        hessian += (rows * weights[:, None]).T @ rows
    return hessian


def _clusters(points: np.ndarray, size: float, smallest: float, fewest: int) -> tuple[np.ndarray, int]:
    """(cluster index per point, number of clusters): cubes of side ``size``, halved while they
    make fewer than ``fewest`` clusters; below ``smallest`` (or with fewer points than that), each
    point its own cluster."""
    count = len(points)
    while count >= fewest and size >= smallest:
        _, inverse = np.unique(_cluster_ids(points, size), return_inverse=True)
        groups = int(inverse.max()) + 1
        if groups >= fewest:
            return inverse, groups
        size /= 2.0
    return np.arange(count), count


def _cluster_ids(points: np.ndarray, size: float) -> np.ndarray:
    """One integer per point naming its cube of side ``size``."""
    cells = np.floor((points - points.min(axis=0)) / size).astype(np.int64)
    extent = cells.max(axis=0) + 1
    return (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]


def _to_frame(centre: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The 6x6 map from the scaled perturbation about ``centre`` (``(omega * radius, v_c)``) to the
    perturbation about the frame's origin (``(omega, v)``, ``v = v_c + centre x omega``), and its
    inverse, written out (a numerical inverse fails on clouds of size 1e30, whose ``1 / radius``
    block is 1e-30 beside the unit one)."""
    mapping, inverse = np.zeros((6, 6)), np.zeros((6, 6))
    mapping[:3, :3] = np.eye(3) / radius
    mapping[3:, :3] = skew(centre) / radius
    mapping[3:, 3:] = np.eye(3)
    inverse[:3, :3] = np.eye(3) * radius
    inverse[3:, :3] = -skew(centre)
    inverse[3:, 3:] = np.eye(3)
    return mapping, inverse


def _information(scaled: np.ndarray, null: np.ndarray, inverse_mapping: np.ndarray,
                 singular_ratio: float) -> np.ndarray:
    """The inverse of ``mapping @ scaled @ mapping.T`` (``inverse_mapping``: the inverse of
    ``mapping``), zero along the ``null`` directions and along eigenvalues below ``singular_ratio``
    of the largest."""
    values, vectors = np.linalg.eigh(scaled)
    positive = values > singular_ratio * max(float(values[-1]), 1e-300)
    scaled_information = (vectors[:, positive] / values[positive]) @ vectors[:, positive].T
    if null.shape[1]:
        keep = np.eye(6) - null @ null.T
        scaled_information = keep @ scaled_information @ keep
    information = inverse_mapping.T @ scaled_information @ inverse_mapping
    return 0.5 * (information + information.T)


def _unconstrained(count: int) -> PoseUncertainty:
    """Too few pairs (or no spread among them) to say anything: no covariance, no information."""
    return PoseUncertainty(None, None, (), count)


def from_registration(source: np.ndarray, target_index, transformation: np.ndarray, sigma: float | None, *,
                      origin: np.ndarray | None = None, workers: int | None = None,
                      warm: np.ndarray | None = None,
                      pairs: tuple[np.ndarray, np.ndarray] | None = None,
                      sample: np.ndarray | None = None,
                      policy: TrustPolicy = DEFAULT_POLICY) -> PoseUncertainty:
    """:func:`pose_uncertainty` of a registration's final pose.

    ``source`` (N, 3) and ``transformation`` (4x4 ``T_target_source``) in the frame of
    ``target_index`` (a :class:`~esmicp.core.correspondence.NearestNeighbors`), ``origin`` that
    frame's origin in the target's own coordinates (see :func:`pose_uncertainty`). Every source
    point is paired with its nearest target point (``pairs``: their ``(distances, indices)`` at
    this pose if already known; ``warm``: optional nearest target indices of the source points
    near the final pose, where the queries start) and weighted by
    ``exp(-d^2 / (2 sigma^2))`` (all 1 when ``sigma`` is None: ICP); the target normals at the
    matches of ``policy.covariance_normals`` of them come from the
    ``policy.covariance_normal_neighbours`` nearest target points, and each cloud's noise (:func:`surface_noise`) from as many
    of its points and their ``policy.noise_neighbours`` nearest; ``policy``: the estimate's values.
    ``sample``: the indices of evenly strided source points that alone are paired (``pairs`` then
    theirs); each pair stands for ``len(source) / len(sample)`` source points (its weight and its
    gradient that many times, the clouds' noise variance along the normals that many times less),
    so that the covariance is the whole source's where neighbouring residuals are correlated and
    no smaller where they are not. Each cloud's noise is still measured on all its points.
    """
    from ..core.procrustes import apply
    from ..core.weights import relative_gaussian_weights
    from ..core.features import NormalEstimator

    stands_for = 1.0
    paired = source
    if sample is not None:
        paired = source[sample]
        stands_for = len(source) / max(len(sample), 1)
    placed = apply(transformation, paired)
    if pairs is not None:
        distances, indices = pairs
    else:
        if warm is not None and len(warm) != len(paired):
            warm = None  # another source's (a subsample's)
        distances, indices = target_index.query_near(placed, warm=warm)
    weights = None if sigma is None else relative_gaussian_weights(distances, sigma)
    if stands_for != 1.0:
        weights = np.full(len(placed), stands_for) if weights is None else weights * stands_for
    target = target_index.points
    normals, noise = None, None
    if len(target) >= 3:
        normals = np.full((len(placed), 3), np.nan)
        chosen = evenly_strided(len(placed), policy.covariance_normals)
        unique, inverse = np.unique(indices[chosen], return_inverse=True)
        estimator = NormalEstimator(target, min(policy.covariance_normal_neighbours, len(target)), tree=target_index.exact_tree(),
                                    workers=workers)
        normals[chosen] = estimator.at(target[unique])[inverse]
        noise = (surface_noise(source, source[evenly_strided(len(source), policy.covariance_normals)],
                               neighbours=policy.noise_neighbours, workers=workers),
                 surface_noise(target, target[unique], tree=target_index.exact_tree(),
                               neighbours=policy.noise_neighbours, workers=workers) * sharing(indices, weights))
        noise = (noise[0] / stands_for, noise[1] / stands_for)
    return pose_uncertainty(placed, target[indices], weights, normals, spacing=target_index.spacing(), origin=origin,
                            noise=noise, policy=policy)


def rotation_log(rotation: np.ndarray) -> np.ndarray:
    """The rotation vector (axis x angle, radians) of a 3x3 rotation."""
    cosine = min(1.0, max(-1.0, (float(np.trace(rotation)) - 1.0) / 2.0))
    angle = math.acos(cosine)
    axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    if angle < 1e-7:
        return 0.5 * axis
    if angle > math.pi - 1e-6:
        values, vectors = np.linalg.eigh(0.5 * (rotation + rotation.T))
        unit = vectors[:, -1]
        return angle * unit
    return angle / (2.0 * math.sin(angle)) * axis


def left_error(truth: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """The 6-vector ``delta`` with ``truth ~= Exp(delta) @ estimate`` (both 4x4 ``T_target_source``):
    ``(omega [rad], v [cloud units])`` in the target frame, first order in ``delta``
    (``omega`` exact, ``v`` the translation of ``truth @ inv(estimate)``)."""
    correction = truth @ np.linalg.inv(estimate)
    return np.concatenate([rotation_log(correction[:3, :3]), correction[:3, 3]])


def standard_deviations(covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rotation_deg, translation)``: the standard deviations of the rotation about x, y, z
    (degrees) and of the translation along x, y, z (cloud units) of a 6x6 covariance."""
    deviations = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    return np.degrees(deviations[:3]), deviations[3:]


def describe(covariance: np.ndarray | None, degenerate: tuple[DegenerateDirection, ...] = ()) -> list[str]:
    """Lines for a person: the standard deviations, then each degenerate direction in words."""
    lines = []
    if covariance is not None:
        rotation, translation = standard_deviations(covariance)
        lines.append("std rotation (deg, about x y z of the target frame): "
                     + " ".join(f"{value:.3g}" for value in rotation))
        lines.append("std translation (cloud units, along x y z of the target frame): "
                     + " ".join(f"{value:.3g}" for value in translation))
    lines.extend(direction.describe() for direction in degenerate)
    return lines
