"""The records a registration returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterator, Mapping

import numpy as np

from .trust.judge import DOUBT_KINDS, Verdict
from .trust.policy import DEFAULT_POLICY, TrustPolicy
from .trust.uncertainty import PoseUncertainty


@dataclass(frozen=True)
class IterationRecord:
    """What one iteration did (all distances in the clouds' units).

    ``transformation`` is ``T_target_source`` after the iteration; ``rmse`` is the root mean square
    nearest-neighbour distance of the source as placed before it; ``weight_*`` and
    ``effective_pairs`` (Kish's ``(sum w)^2 / sum w^2``) describe the weights it used (all 1 for ICP).
    """

    iteration: int
    transformation: np.ndarray
    rmse: float
    sigma: float | None
    weight_mean: float
    weight_min: float
    weight_max: float
    effective_pairs: float

    def to_dict(self) -> dict:
        return {
            "iteration": self.iteration,
            "transformation": self.transformation.tolist(),
            "rmse": self.rmse,
            "sigma": self.sigma,
            "weight_mean": self.weight_mean,
            "weight_min": self.weight_min,
            "weight_max": self.weight_max,
            "effective_pairs": self.effective_pairs,
        }


@dataclass(frozen=True, eq=False)
class Stage:
    """What one stage of :func:`esmicp.register` did (:attr:`RegistrationResult.stages`), or of
    :func:`esmicp.register_scans` (``MultiRegistrationResult.stages``; its stages and their
    counts are listed in its Returns section).

    Attributes
    ----------
    name : str
        Of ``register``: ``"prepare"`` (the arguments checked, the working frame chosen, the
        target's index built), ``"start"`` (a global search, or the given start), ``"plane"`` (``esm-plane`` iterations before ``esm`` on a
        large source after a global search), ``"refine"`` (the local refinement), ``"second try"``
        (a second run from a given start with a tighter coarse sigma), ``"evaluate"`` (fitness
        and inliers of the final pose), ``"judge"`` (the verdict, :func:`esmicp.trust.judge.judge`).
    seconds : float
        Wall time of the stage (s).
    pose : (4, 4) float64 array or None
        The ``T_target_source`` the stage passed on (the clouds' own frames); None for a stage
        that passes on no pose.
    points : int or None
        Source points the stage used (None: not a per-point stage).
    iterations : int
        Iterations the stage ran (0 for a stage that does not iterate).
    decided : mapping
        What else the stage decided, by name (read-only; plain numbers, strings, booleans and
        tuples), e.g. ``candidates`` of the global search, ``converged`` of the refinement,
        ``kept`` of the second try, ``trusted`` of the judgement.
    """

    name: str
    seconds: float
    pose: np.ndarray | None = field(default=None, repr=False)
    points: int | None = None
    iterations: int = 0
    decided: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "decided", _ReadOnly(self.decided))

    def to_dict(self) -> dict:
        """A JSON-ready dict of the stage."""
        return {"name": self.name, "seconds": self.seconds,
                "pose": None if self.pose is None else self.pose.tolist(), "points": self.points,
                "iterations": self.iterations, "decided": {key: _plain(value) for key, value in self.decided.items()}}


class _ReadOnly(Mapping):
    """A read-only copy of a mapping (unlike ``types.MappingProxyType``, it pickles: results cross
    process boundaries in :func:`esmicp.register_many`)."""

    def __init__(self, items: Mapping):
        self._items = dict(items)

    def __getitem__(self, key: str) -> Any:
        return self._items[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def __repr__(self) -> str:
        return repr(self._items)


def _plain(value):
    """``value`` as JSON holds it (tuples as lists, NumPy scalars as Python numbers)."""
    if isinstance(value, (tuple, list)):
        return [_plain(item) for item in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


@dataclass(frozen=True, eq=False)
class Correspondences:
    """The point pairs of a registration's final pose (:func:`esmicp.register` with
    ``return_correspondences=True``): every source point whose nearest target point, under the
    final ``transformation``, lies within ``inlier_distance``, the pairs ``fitness`` and
    ``inlier_rmse`` count (Open3D's ``correspondence_set``), sorted by source index.

    Attributes
    ----------
    source_index : (K,) int64 array
        Row of each pair's point in the source as given.
    target_index : (K,) int64 array
        Row of its nearest target point in the target as given.
    weight : (K,) float64 array
        The weight the method gives the pair at the final ``sigma``, in [0, 1] (``esm`` and
        ``esm-plane``: relative to the closest pair of the whole source, which weighs 1; all 1
        for ``icp``).
    distance : (K,) float64 array
        Distance between the transformed source point and its target point (cloud units).
    """

    source_index: np.ndarray
    target_index: np.ndarray
    weight: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.source_index)

    @property
    def pairs(self) -> np.ndarray:
        """``(K, 2)`` int64 array of ``(source_index, target_index)`` rows, as Open3D's
        ``numpy.asarray(result.correspondence_set)``."""
        return np.column_stack([self.source_index, self.target_index])


@dataclass(frozen=True, eq=False)
class SearchSummary:
    """What the start of :func:`esmicp.register` decided (:attr:`RegistrationResult.search`): a
    read-only view of the result's own fields, grouped.

    Attributes
    ----------
    init : str
        ``"identity"``, ``"given"`` or ``"global:<strategy>"`` (:attr:`RegistrationResult.init`).
    candidates : int
        Candidate poses the global search verified (0 without one;
        :attr:`RegistrationResult.global_candidates`).
    ambiguous : bool
        A clearly different pose fits almost as well (:attr:`RegistrationResult.ambiguous`).
    runner_up_ratio : float or None
        The lower of the two scores over the higher, 0-1 (:attr:`RegistrationResult.runner_up_ratio`).
    runner_up : (4, 4) float64 array or None
        The best clearly different pose verified, ``T_target_source`` in the clouds' own frames
        (:attr:`RegistrationResult.runner_up`).
    """

    init: str
    candidates: int
    ambiguous: bool
    runner_up_ratio: float | None
    runner_up: np.ndarray | None = field(default=None, repr=False)


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of :func:`esmicp.register`.

    Attributes
    ----------
    transformation : (4, 4) float64 array
        ``T_target_source``: ``target ~= source @ R.T + t``.
    converged : bool
        True when the convergence tolerance was met before ``max_iterations``. False also when the
        run stopped on a problem; ``message`` then says which.
    num_iterations : int
        Iterations performed.
    fitness : float
        Open3D's meaning: the fraction of source points whose nearest target point, after the
        final transformation, lies within ``inlier_distance``; on a source of more than
        ``RefineConfig.evaluated_points`` (40,000) points, of that many evenly strided ones (a
        standard error of at most 0.0025), unless ``return_correspondences`` asked for every pair.
    inlier_rmse : float
        Open3D's meaning: RMS distance of those inlier pairs (cloud units); 0 when there are none.
    inlier_distance : float
        The distance (cloud units) that defines an inlier for ``fitness`` and ``inlier_rmse``.
    runtime_s : float
        Wall time of the registration in seconds (KD-tree build, iterations, final evaluation).
    method : str
        The method's name.
    sigma : float or None
        The sigma (cloud units) of the last iteration; None for methods without a kernel.
    message : str
        Why the iterations stopped.
    history : tuple of IterationRecord, or None
        Per-iteration records of the local refinement, when asked for.
    init : str
        Where the refinement started: ``"identity"``, ``"given"`` (a 4x4 ``init``), or
        ``"global:<strategy>"`` with the strategy whose candidate won the global search.
    ambiguous : bool
        True when the global search found a clearly different pose (rotation more than 10 degrees
        away) that fits almost as well (at least 97% of the score): the object is probably
        symmetric, or the overlap too small to tell. The pose returned is the best-fitting one,
        but treat it with care. Always False without a global search.
    runner_up_ratio : float or None
        The lower of two scores, the returned pose's and the best clearly different pose's, over
        the higher: 0-1, lower is more decisive; None without a global search or without a
        distinct runner-up. When the runner-up scores higher (the returned pose was preferred
        because, unlike it, it makes the overlap coincide: a cut object's flip lies on more of the
        other part than the truth), the result is ambiguous.
    runner_up : (4, 4) float64 array or None
        The best clearly different pose the global search verified (``T_target_source``, in the
        clouds' own frames, as verified: not polished by the final refinement), the one
        ``runner_up_ratio`` compares with; None without a global search or without a distinct
        runner-up. When the result is ambiguous or not trusted, it is the other place the source
        may belong: the object's symmetric twin, or the same scan slid along a corridor or a road.
    global_candidates : int
        Number of candidate poses the global search verified (0 without one).
    confidence : float or None
        How sharply the clouds coincide *where they overlap* under the final pose, 0-1, whatever
        the overlap's size (:func:`esmicp.trust.confidence.overlap_confidence`): of the points (voxel
        centroids at the scale the data chooses) lying within 3 voxels of the other cloud, the
        fraction within 1 voxel, the worse of the two directions, mapped from 0.5-0.8 onto 0-1;
        lower when less than half of either cloud coincides and the coincident part's normals
        span fewer than three directions (one plane laid on another holds only 3 of the 6 degrees
        of freedom, a floor and one wall 5: :func:`esmicp.trust.confidence.coincident_spread`); 0 when
        fewer than 60 keypoints of either cloud coincide (``policy.min_coincident``:
        clouds of a few dozen points cannot resolve the pose, so are never trusted). Below the
        trust bar (``policy.trusted``, 0.55 by default): do not trust the pose. At or above it the pose
        is usually right, not always: a repeated structure matched in the wrong place coincides
        sharply too (frames of one room that share no surface can come back trusted, metres off).
        Measured figures: ``docs/measured-global.md``, "How far the confidence can be trusted".
    correspondences : Correspondences or None
        The final pose's inlier pairs (:class:`Correspondences`), when asked for
        (``return_correspondences=True``); else None.
    covariance : (6, 6) float64 array or None
        Covariance of the pose (:mod:`esmicp.trust.uncertainty`): a small rotation vector (radians) then a
        translation (cloud units), a perturbation applied on the LEFT of ``transformation``, in
        the target frame (``T_true = Exp(delta) @ transformation``). Calibrated on repeated
        registrations: ``docs/uncertainty.md``. None when not computed.
    information : (6, 6) float64 array or None
        The inverse of ``covariance`` (same convention); zero along any direction the data do not
        constrain at all (a pseudo-inverse). For weighting pose-graph edges.
    degenerate_directions : tuple of DegenerateDirection
        The directions the overlap barely constrains (target frame), each with its ratio to the
        best-constrained one (:class:`esmicp.trust.uncertainty.DegenerateDirection`); empty for a
        well-constrained pair.
    free_space : float or None
        When the free-space test ran (``register(..., range_images=True)``, or at the default when
        both clouds' points show range images and nothing else doubted the pose): the larger fraction (0-1) of either cloud that
        the pose puts in the space the other's sensor saw empty
        (:func:`esmicp.trust.free_space.free_space_fraction`); above ``policy.max_free_space_pair``
        the result is not trusted. None when the test did not run, or when neither sensor sees
        enough of the other cloud to judge.
    policy : TrustPolicy
        The trust policy the result is judged by (:class:`esmicp.trust.policy.TrustPolicy`: the
        bars of :attr:`trusted` and :meth:`doubts`), as ``register``'s ``config`` gave it.
    verdict : Verdict or None
        The judgement :func:`esmicp.register` made of the pose (:class:`esmicp.trust.judge.Verdict`,
        one call of :func:`esmicp.trust.judge.judge`: the measures above and every reason not to
        trust the pose); :attr:`trusted` and :meth:`doubts` return what it found. None for a result
        built by hand. A result built by hand, or one whose judged fields ``dataclasses.replace``
        changed (``converged``, ``confidence``, ``ambiguous``, ``free_space``, ``policy``, ...), is
        weighed from its own fields when asked, by the same rules
        (:func:`esmicp.trust.judge.weigh`); nothing is measured again.
    stages : tuple of Stage
        What each stage of :func:`esmicp.register` did, in order (:class:`Stage`); empty for a
        result built by hand.

    The fields also read as a core (the pose, the fit, the run) and three grouped read-only
    records, made from the fields when asked (so ``dataclasses.replace`` of a field shows in
    them): :attr:`search` (the start), :attr:`uncertainty` (the covariance, its inverse, the
    degenerate directions) and :attr:`trust` (the verdict the fields give).
    """

    transformation: np.ndarray
    converged: bool
    num_iterations: int
    fitness: float
    inlier_rmse: float
    inlier_distance: float
    runtime_s: float
    method: str
    sigma: float | None
    message: str
    history: tuple[IterationRecord, ...] | None = field(default=None, repr=False)
    init: str = "identity"
    ambiguous: bool = False
    runner_up_ratio: float | None = None
    global_candidates: int = 0
    runner_up: np.ndarray | None = field(default=None, repr=False)
    confidence: float | None = None
    correspondences: Correspondences | None = field(default=None, repr=False)
    covariance: np.ndarray | None = field(default=None, repr=False)
    information: np.ndarray | None = field(default=None, repr=False)
    degenerate_directions: tuple = ()
    free_space: float | None = None
    policy: TrustPolicy = field(default=DEFAULT_POLICY, repr=False)
    verdict: Verdict | None = field(default=None, repr=False)
    stages: tuple[Stage, ...] = field(default=(), repr=False)

    @property
    def search(self) -> SearchSummary:
        """The start as one record (:class:`SearchSummary`: ``init``, ``global_candidates``,
        ``ambiguous``, ``runner_up_ratio``, ``runner_up``)."""
        return SearchSummary(self.init, self.global_candidates, self.ambiguous, self.runner_up_ratio, self.runner_up)

    @property
    def uncertainty(self) -> PoseUncertainty:
        """``covariance``, ``information`` and ``degenerate_directions`` as one record
        (:class:`esmicp.trust.uncertainty.PoseUncertainty`, same conventions); its ``pairs``, the
        pairs the estimate used, as the stored :attr:`verdict` measured them, 0 when the result
        does not say (built by hand, or its covariance replaced)."""
        measured = None if self.verdict is None else self.verdict.uncertainty
        pairs = measured.pairs if measured is not None and measured.covariance is self.covariance else 0
        return PoseUncertainty(self.covariance, self.information, tuple(self.degenerate_directions), pairs)

    @property
    def trust(self) -> Verdict:
        """The trust report (:class:`esmicp.trust.judge.Verdict`): the :attr:`verdict`
        :func:`esmicp.register` stored while it weighed this result's fields, else the one the
        fields give (weighed by the same rules, nothing measured again); its ``doubts`` are
        :meth:`doubts`' reasons, its ``trusted`` is :attr:`trusted`."""
        return self._judged()

    @property
    def trusted(self) -> bool:
        """True when nothing casts doubt on the pose (:meth:`doubts` is empty): the refinement
        ``converged`` (a run stopped by ``max_iterations``, a callback or a problem may still be
        degrees from where it was heading, however sharply the clouds already coincide), ``confidence``
        reaches the trust bar (``policy.trusted``), the result is not
        ``ambiguous``, the overlap constrains the pose in every direction (no
        ``degenerate_directions``: a floor or a wall seen alone, or a corridor, lets the pose slide
        however sharply the clouds coincide), and ``free_space`` (when measured) is within
        ``policy.max_free_space_pair``, and no mirror image of the source fits clearly better
        (:func:`esmicp.trust.handedness.handedness`). The one test callers
        (``register_scans``, the CLI) apply."""
        return not self.doubts()

    def doubts(self, bar: float | None = None, *, ignore: tuple[str, ...] = ()) -> list[str]:
        """Why the pose is not to be trusted, one phrase per reason (empty: :attr:`trusted`), as
        the :attr:`verdict` found them. ``bar``: the confidence asked for, a number in [0, 1]
        (default the trust bar, ``policy.trusted``); ``ignore``: kinds of doubt to leave out
        (:data:`esmicp.trust.judge.DOUBT_KINDS`, e.g. ``("ambiguous",)``).

        Raises
        ------
        InvalidInputError
            ``bar`` is not a number, is NaN, or lies outside [0, 1]; ``ignore`` names an unknown kind.
        """
        unknown = [kind for kind in ignore if kind not in DOUBT_KINDS]
        if unknown or isinstance(ignore, str):
            from .errors import InvalidInputError

            raise InvalidInputError(f"ignore: expected kinds of doubt among {', '.join(DOUBT_KINDS)}, got {ignore!r}")
        if bar is not None:
            from .types import as_real

            value = as_real(bar, "bar")
            if not 0.0 <= value <= 1.0:  # NaN fails too
                from .errors import InvalidInputError

                raise InvalidInputError(f"bar: expected a confidence in [0, 1], got {bar!r}")
            bar = value
        verdict = self._judged()
        doubts = verdict.doubts if bar is None else verdict.at(bar)
        return [doubt.words for doubt in doubts if doubt.kind not in ignore]

    def _judged(self) -> Verdict:
        """The verdict ``register`` stored while it weighed this result's fields; else (a result
        built by hand, or one whose fields ``dataclasses.replace`` changed) the one its fields give."""
        if self.verdict is not None and self._weighed_by(self.verdict):
            return self.verdict
        return Verdict.of(converged=self.converged, num_iterations=self.num_iterations, confidence=self.confidence,
                          ambiguous=self.ambiguous, runner_up_ratio=self.runner_up_ratio,
                          degenerate_directions=self.degenerate_directions,
                          free_space=self.free_space, policy=self.policy,
                          handedness=None if self.verdict is None else self.verdict.handedness)

    def _weighed_by(self, verdict: Verdict) -> bool:
        """True when ``verdict`` weighed this result's own fields."""
        mine, theirs = self.degenerate_directions, verdict.degenerate_directions
        same_directions = mine is theirs or (len(mine) == len(theirs) and all(
            a.ratio == b.ratio and np.array_equal(a.rotation, b.rotation) and np.array_equal(a.translation, b.translation)
            for a, b in zip(mine, theirs)))
        return (same_directions and verdict.converged == self.converged and verdict.num_iterations == self.num_iterations
                and verdict.confidence == self.confidence and verdict.ambiguous == self.ambiguous
                and verdict.runner_up_ratio == self.runner_up_ratio and verdict.free_space == self.free_space
                and verdict.policy == self.policy)

    def __repr__(self) -> str:
        """One line: the method, the verdict, the overlap and how far the pose moves the source,
        e.g. ``RegistrationResult(method='esm', trusted=True, confidence=0.97, fitness=0.81,
        rotation=12.3 deg, translation=0.041, 0.42 s)`` (the arrays stay in the fields)."""
        confidence = "None" if self.confidence is None else f"{self.confidence:.2f}"
        return (f"{type(self).__name__}(method={self.method!r}, trusted={self.trusted}, confidence={confidence}, "
                f"fitness={self.fitness:.2f}, rotation={self.rotation_deg:.3g} deg, "
                f"translation={self.translation_norm:.3g}, {self.runtime_s:.2f} s)")

    @property
    def rotation(self) -> np.ndarray:
        """The 3x3 rotation of ``transformation``."""
        return self.transformation[:3, :3].copy()

    @property
    def rotation_deg(self) -> float:
        """The angle of ``rotation`` (degrees, 0-180): how far the pose turns the source."""
        cosine = (np.trace(self.transformation[:3, :3]) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))

    @property
    def translation_norm(self) -> float:
        """The length of ``translation`` (cloud units): how far the pose moves the source's origin."""
        return float(np.linalg.norm(self.transformation[:3, 3]))

    @property
    def translation(self) -> np.ndarray:
        """The translation of ``transformation`` (cloud units)."""
        return self.transformation[:3, 3].copy()

    def to_dict(self, *, include_history: bool = False) -> dict:
        """A JSON-ready dict (nested lists, plain floats): the fields, ``trusted`` and ``doubts``
        (:meth:`doubts`: why the pose is not to be trusted, empty when it is), and the ``stages``
        (:meth:`Stage.to_dict`)."""
        doubts = self.doubts()
        data = {
            "method": self.method,
            "transformation": self.transformation.tolist(),
            "converged": self.converged,
            "num_iterations": self.num_iterations,
            "fitness": self.fitness,
            "inlier_rmse": self.inlier_rmse,
            "inlier_distance": self.inlier_distance,
            "sigma": self.sigma,
            "runtime_s": self.runtime_s,
            "message": self.message,
            "init": self.init,
            "ambiguous": self.ambiguous,
            "runner_up_ratio": self.runner_up_ratio,
            "global_candidates": self.global_candidates,
            "runner_up": None if self.runner_up is None else self.runner_up.tolist(),
            "confidence": self.confidence,
            "trusted": not doubts,
            "doubts": doubts,
            "covariance": None if self.covariance is None else self.covariance.tolist(),
            "std_rotation_deg": None if self.covariance is None else _deviations(self.covariance)[0],
            "std_translation": None if self.covariance is None else _deviations(self.covariance)[1],
            "information": None if self.information is None else self.information.tolist(),
            "degenerate_directions": [direction.to_dict() for direction in self.degenerate_directions],
            "free_space": self.free_space,
            "stages": [stage.to_dict() for stage in self.stages],
        }
        if include_history and self.history is not None:
            data["history"] = [record.to_dict() for record in self.history]
        return data


def _deviations(covariance: np.ndarray) -> tuple[list, list]:
    """The standard deviations of ``covariance``: rotation about x, y, z (degrees), translation along
    x, y, z (cloud units)."""
    from .trust.uncertainty import standard_deviations

    rotation, translation = standard_deviations(covariance)
    return rotation.tolist(), translation.tolist()
