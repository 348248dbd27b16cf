"""``esm-plane``: ESM's Gaussian weights on point-to-plane residuals, for scans.

Each iteration pairs every source point ``s_i`` (as currently placed, target frame) with its
nearest target point ``t_c(i)``, whose unit normal ``n_c(i)`` comes from a PCA of the target
around it (:func:`esmicp.core.features.estimate_normals`, the ``normal_neighbours`` nearest
target points: a scale the sampling chooses, so the method is unit-free). The residual is the
distance of the point to the target's tangent plane,

    r_i = n_c(i) . (R s_i + t - t_c(i)),

and the increment minimises ``sum_i w_i r_i^2`` linearised at ``R = I, t = 0`` (one Gauss-Newton
step, a 6x6 system solved in closed form) with ESM's Gaussian weights
``w_i = exp(-d_i^2 / (2 sigma^2))``, ``d_i`` the pair's point distance (see
``docs/scans-refinement.md``, for why the point distance and not the plane
residual). A plane slides freely along itself, so a flat target leaves directions unconstrained:
the solve moves along none of them (a pseudo-inverse), where point-to-point ICP would pull the
overlap's borders toward each other.

Choosing sigma: from the overlap, not from every pair
-----------------------------------------------------
``esm``'s schedule (``3 x`` the median distance) measures every pair; on scans that overlap by
40% most pairs join points the other scan never saw, the median is theirs, and a wide sigma pulls
the overlap apart (a scan pair started at its ground truth drifts off it, see
``docs/scans-refinement.md``). Here sigma is the robust scale of the distances *of the overlap*:
``sigma_mad_factor x 1.4826 x`` the median of the distances below ``overlap_sigmas`` sigmas, at
its least fixed point above ``esm``'s floor of ``sigma_floor_spacings`` target point spacings
(iterated up from the floor, each iteration anew): sigma widens only as far as the close pairs'
own spread carries it, so the pairs off the overlap are discounted from the first step on. The
price: a start further off than a few sigmas of the overlap's spread finds too few close pairs
(this is a refinement, for after a global search). Units: sigma, distances and residuals in the clouds' units.
The values named here are the fields of :class:`esmicp.methods.config.PlaneConfig`
(``RefineConfig.plane``) and :class:`esmicp.methods.config.EsmConfig` (``RefineConfig.esm``).
"""

from __future__ import annotations

import math

import numpy as np

from ..core.compiled_tree import CompiledTree
from ..core.features import NormalEstimator
from ..core.pose_kernels import rotation_exp
from ..core.procrustes import rotation_angle
from ..core.weights import relative_gaussian_weights
from .base import Estimator, Step
from .config import EsmConfig, PlaneConfig

#: 1.4826 (about 1 / the normal distribution's 0.75 quantile) times the median absolute value
#: estimates a Gaussian's standard deviation (dimensionless).
_MAD_SCALE = 1.4826


class PlaneEstimator(Estimator):
    """Point-to-plane Gauss-Newton increment with Gaussian weights on the pair distances.

    ``floor`` (cloud units, > 0) is the smallest sigma; ``sigma`` a fixed sigma (cloud units) in
    place of the schedule of the module docstring; ``diameter`` (cloud units, the target's
    bounding-box diagonal) scales the increment that ends the subset phase, below
    ``fine_phase_step`` (radians; times ``diameter`` in translation; None: ``esm``'s default,
    :attr:`~esmicp.methods.config.EsmConfig.fine_phase_step`); ``config``: the method's values
    (:class:`~esmicp.methods.config.PlaneConfig`, None: the defaults). The target's normals
    are estimated the first time a target point is paired (only where needed), then kept: make a
    new estimator per registration. The same steps run on a subset of a large source first
    (:attr:`coarse`): the subset brings the clouds together, the whole source decides the pose.
    """

    name = "esm-plane"

    def __init__(self, floor: float, diameter: float, sigma: float | None = None, *,
                 config: PlaneConfig | None = None, fine_phase_step: float | None = None):
        self.config = PlaneConfig() if config is None else config
        self.fine_phase_step = EsmConfig().fine_phase_step if fine_phase_step is None else float(fine_phase_step)
        self.floor = float(floor)
        self.diameter = float(diameter)
        self.fixed = sigma
        self._whole = False
        self._target: np.ndarray | None = None
        self._estimator: NormalEstimator | None = None
        # The normals estimated so far (rows in the order they were estimated) and each target
        # point's row among them (-1: not estimated yet).
        self._normals: np.ndarray | None = None
        self._row: np.ndarray | None = None
        self._offered: CompiledTree | None = None
        self._workers: int | None = 1

    def use_target_tree(self, tree: CompiledTree, workers: int | None = None) -> None:
        """Take the normals' neighbours from ``tree`` (the compiled KD-tree of the target the steps
        will see, e.g. :meth:`~esmicp.core.correspondence.NearestNeighbors.exact_tree`) on
        ``workers`` threads (None: every core), instead of building a second tree over the same
        points on one thread. Used only if its points are the target's (checked once)."""
        self._offered, self._workers = tree, workers

    @property
    def coarse(self) -> bool:
        """True until the first increment below ``fine_phase_step`` (or the loop's
        convergence): the loop may iterate on a strided subset of a large source (``coarse_points``
        of :func:`esmicp.methods.local.refine`) until then, then on all of it."""
        return not self._whole

    def end_coarse_phase(self) -> None:
        self._whole = True

    def step(self, moved_source, target, distances, indices) -> Step:
        sigma = self._sigma(distances)
        weights = relative_gaussian_weights(distances, sigma)
        normals = self._normals_at(target, indices)
        rotation, translation = plane_step(moved_source, target[indices], normals, weights,
                                           self.config.singular_fraction)
        small = rotation_angle(rotation) < self.fine_phase_step
        self._whole = self._whole or (small and np.linalg.norm(translation) < self.fine_phase_step * self.diameter)
        return Step(rotation, translation, weights=weights, sigma=sigma)

    def pair_weights(self, distances, sigma):
        return None if sigma is None else relative_gaussian_weights(distances, sigma)

    def _sigma(self, distances: np.ndarray) -> float:
        """This iteration's sigma: the least fixed point above the floor of the overlap's scale."""
        if self.fixed is not None:
            return self.fixed
        sigma = self.floor
        config = self.config
        for _ in range(config.sigma_rounds):
            overlap = distances[distances <= config.overlap_sigmas * sigma]
            scale = config.sigma_mad_factor * _MAD_SCALE * float(np.median(overlap)) if len(overlap) else 0.0
            if scale <= (1.0 + 1e-3) * sigma:
                break
            sigma = scale
        return sigma

    def _normals_at(self, target: np.ndarray, indices: np.ndarray) -> np.ndarray:
        """Unit normals at ``target[indices]``, estimated once per target point."""
        if self._target is not target:
            offered = self._offered
            same = offered is not None and offered.is_over(target)
            self._target = target
            self._estimator = NormalEstimator(target, self.config.normal_neighbours, tree=offered if same else CompiledTree(target),
                                              workers=self._workers)
            self._normals = np.empty((0, 3))
            self._row = np.full(len(target), -1, dtype=np.intp)
        rows = self._row[indices]
        needed = np.unique(indices[rows < 0])
        if len(needed):
            self._row[needed] = np.arange(len(self._normals), len(self._normals) + len(needed))
            self._normals = np.concatenate([self._normals, self._estimator.at(target[needed])])
            rows = self._row[indices]
        return self._normals[rows]


def plane_step(source: np.ndarray, target: np.ndarray, normals: np.ndarray, weights: np.ndarray,
               singular_fraction: float | None = None):
    """``(R, t)`` minimising ``sum_i w_i (n_i . (R s_i + t - t_i))^2`` to first order in the rotation.

    ``source``, ``target``, ``normals`` are ``(N, 3)`` (target frame, unit normals), ``weights``
    ``(N,)``. The rotation is linearised about the weighted centroid ``c`` of the source and its
    columns scaled by the source's weighted RMS radius ``L`` about it, so that the 6x6 system is
    unit-free (a cloud in millimetres gives the same step); the solution ``(omega L, tau)`` gives
    ``R = exp(omega)``, ``t = c + tau - R c``. Unconstrained directions (eigenvalues of the normal
    matrix below ``singular_fraction`` of the largest; None:
    :attr:`~esmicp.methods.config.PlaneConfig.singular_fraction`) get no motion.
    """
    if singular_fraction is None:
        singular_fraction = PlaneConfig().singular_fraction
    total = float(weights.sum())
    centre = np.einsum("i,ij->j", weights, source) / total
    offsets = source - centre
    radius = math.sqrt(max(float(np.einsum("i,ij,ij->", weights, offsets, offsets)) / total, 0.0))
    if not radius > 0:
        return np.eye(3), np.zeros(3)
    jacobian = np.hstack([np.cross(offsets / radius, normals), normals])
    residuals = np.einsum("ij,ij->i", normals, source - target)
    weighted = jacobian * weights[:, None]
    normal_matrix = np.einsum("ni,nj->ij", weighted, jacobian)
    gradient = np.einsum("ni,n->i", weighted, residuals)
    values, vectors = np.linalg.eigh(normal_matrix)
    keep = values > singular_fraction * max(float(values[-1]), 0.0)
    solution = -vectors[:, keep] @ ((vectors[:, keep].T @ gradient) / values[keep])
    rotation = rotation_exp(solution[:3] / radius)
    return rotation, centre + solution[3:] - rotation @ centre
