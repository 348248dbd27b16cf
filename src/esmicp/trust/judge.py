"""Judging a registered pose in one call: :func:`judge` measures what a verdict rests on (the overlap
confidence, the pose covariance and its degenerate directions, the free-space test of range
images) and weighs it against a :class:`~esmicp.trust.policy.TrustPolicy`, as Open3D's
``evaluate_registration`` is one function. :func:`esmicp.register` calls it once and the
:class:`~esmicp.result.RegistrationResult` keeps the :class:`Verdict` it returns.

Transforms are ``T_target_source`` (``target ~= source @ R.T + t``).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np

from ..core.correspondence import NearestNeighbors
from ..core.keypoints import Keypoints
from ..core.sampling import evenly_strided
from .confidence import ConfidenceRanges, overlap_confidence, surface_part
from .handedness import Handedness, handedness as handedness_of
from .policy import DEFAULT_POLICY, TrustPolicy
from .uncertainty import DegenerateDirection, PoseUncertainty, from_registration

#: The kinds of :class:`Doubt`, in the order a verdict lists them.
DOUBT_KINDS = ("not converged", "confidence", "ambiguous", "degenerate", "free space", "mirrored", "no support",
               "not judged")


@dataclass(frozen=True)
class Doubt:
    """One reason not to trust a pose: its ``kind`` (one of :data:`DOUBT_KINDS`) and the reason in
    ``words``."""

    kind: str
    words: str


@dataclass(frozen=True, eq=False)
class Verdict:
    """What a pose was judged on and what the judgement found.

    Attributes
    ----------
    confidence : float or None
        The overlap confidence (0-1, :func:`esmicp.trust.confidence.overlap_confidence`); None when
        not measured.
    uncertainty : PoseUncertainty or None
        The pose covariance, its inverse and the degenerate directions
        (:func:`esmicp.trust.uncertainty.from_registration`); None when not measured.
    degenerate_directions : tuple of DegenerateDirection
        The directions the overlap barely constrains (target frame), as weighed; empty when none.
    free_space : float or None
        The free-space fraction of a pair of range images (0-1,
        :func:`esmicp.trust.free_space.free_space_fraction`); None when not tested, or when neither
        sensor saw enough of the other cloud.
    free_space_words : str or None
        The free-space test's outcome in words (:func:`esmicp.trust.free_space.pair_verdict`);
        None when the test did not apply (clouds not declared range images).
    converged, num_iterations, ambiguous, runner_up_ratio
        What the refinement and the search reported, as weighed.
    handedness : Handedness or None
        The pose's fit against the best mirror image of the source near it
        (:func:`esmicp.trust.handedness.handedness`); None when not tested: the test runs only on a
        pose nothing else casts doubt on at the policy's bar.
    policy : TrustPolicy
        The bars the pose was judged by.
    unsupported : str or None
        Why the global search stopped before its last searches (no pose of its first searches made
        the clouds coincide: :attr:`esmicp.globalreg.search.GlobalEstimate.unsupported`), in
        words; None when it did not.
    doubts : tuple of Doubt
        Every reason not to trust the pose at the policy's trust bar (empty: trusted).
    """

    confidence: float | None
    uncertainty: PoseUncertainty | None
    degenerate_directions: tuple[DegenerateDirection, ...]
    free_space: float | None
    free_space_words: str | None
    converged: bool
    num_iterations: int
    ambiguous: bool
    runner_up_ratio: float | None
    policy: TrustPolicy
    doubts: tuple[Doubt, ...]
    handedness: Handedness | None = None
    unsupported: str | None = None

    @property
    def trusted(self) -> bool:
        """True when nothing casts doubt on the pose (:attr:`doubts` is empty)."""
        return not self.doubts

    def at(self, bar: float) -> tuple[Doubt, ...]:
        """The doubts with the overlap confidence held to ``bar`` (0-1) instead of the policy's bar."""
        return weigh(self.converged, self.num_iterations, self.confidence, self.ambiguous, self.runner_up_ratio,
                     self.degenerate_directions, self.free_space, self.policy, bar, self.handedness,
                     unsupported=self.unsupported)

    @classmethod
    def of(cls, *, converged: bool, num_iterations: int, confidence: float | None, ambiguous: bool = False,
           runner_up_ratio: float | None = None, uncertainty: PoseUncertainty | None = None,
           degenerate_directions: tuple[DegenerateDirection, ...] | None = None, free_space: float | None = None,
           free_space_words: str | None = None, policy: TrustPolicy = DEFAULT_POLICY,
           handedness: Handedness | None = None, judged: bool = True, unsupported: str | None = None) -> "Verdict":
        """The verdict on measurements already made (no measuring: :func:`judge` measures).
        ``degenerate_directions``: those of ``uncertainty`` when None (none without it);
        ``judged`` False: the pose was not measured for a judgement (never trusted); ``unsupported``:
        the global search's words when it stopped for want of support (never trusted)."""
        if degenerate_directions is None:
            degenerate_directions = () if uncertainty is None else uncertainty.degenerate_directions
        doubts = weigh(converged, num_iterations, confidence, ambiguous, runner_up_ratio, degenerate_directions,
                       free_space, policy, handedness=handedness, judged=judged, unsupported=unsupported)
        return cls(confidence, uncertainty, tuple(degenerate_directions), free_space, free_space_words,
                   bool(converged), int(num_iterations), bool(ambiguous), runner_up_ratio, policy, doubts, handedness,
                   unsupported)


def weigh(converged: bool, num_iterations: int, confidence: float | None, ambiguous: bool,
          runner_up_ratio: float | None, degenerate_directions, free_space: float | None,
          policy: TrustPolicy = DEFAULT_POLICY, bar: float | None = None,
          handedness: Handedness | None = None, judged: bool = True,
          unsupported: str | None = None) -> tuple[Doubt, ...]:
    """Every reason not to trust a pose, in the order of :data:`DOUBT_KINDS`: the refinement did not
    converge (a run stopped by ``max_iterations``, a callback or a problem may still be degrees
    from where it was heading), the overlap ``confidence`` is missing or below ``bar`` (default
    ``policy.trusted``), the search found the pose ``ambiguous``, a direction is degenerate (a
    floor or a wall seen alone, or a corridor, lets the pose slide however sharply the clouds
    coincide), the ``free_space`` fraction (when measured) is above ``policy.max_free_space_pair``,
    a mirror image of the source fits clearly better than the pose (``handedness``, when tested:
    no rotation turns a left hand into a right one), the global search stopped for want of support
    (``unsupported``, its words: no pose of its first searches made the clouds coincide), the pose was
    not ``judged`` (its covariance, mirror test and free-space test not run: ``register(judge=False)``)."""
    bar = policy.trusted if bar is None else bar
    doubts = []
    if not converged:
        doubts.append(Doubt("not converged", f"not converged: the refinement stopped after {num_iterations} "
                                             f"iteration(s) before reaching its tolerance, so the pose may still be "
                                             f"moving"))
    if confidence is None:
        doubts.append(Doubt("confidence", "no overlap confidence"))
    elif confidence < bar:
        doubts.append(Doubt("confidence", f"confidence {confidence:.2f} is below {bar:g}"))
    if ambiguous:
        ratio = "" if runner_up_ratio is None else f" (score ratio {runner_up_ratio:.3f})"
        doubts.append(Doubt("ambiguous", f"ambiguous: a clearly different pose fits almost as well{ratio}"))
    doubts.extend(Doubt("degenerate", direction.describe()) for direction in degenerate_directions)
    if free_space is not None:
        from .free_space import pair_verdict  # here: it loads SciPy

        failed, words = pair_verdict(free_space, policy)
        if failed:
            doubts.append(Doubt("free space", words))
    if handedness is not None and handedness.mirrored:
        doubts.append(Doubt("mirrored", f"mirrored: a mirror image of the source coincides with the target on "
                                        f"{100 * handedness.improper:.0f}% of the overlap, the pose on "
                                        f"{100 * handedness.proper:.0f}%: one cloud looks left-handed to the other"))
    if unsupported is not None:
        doubts.append(Doubt("no support", unsupported))
    if not judged:
        doubts.append(Doubt("not judged", "not judged: the covariance, the mirror test and the free-space test "
                                          "were not run (register(judge=False))"))
    return tuple(doubts)


@dataclass(frozen=True, eq=False)
class SensorClouds:
    """The two clouds of a pair, each in its own frame, for the free-space test; the inlier
    distance (cloud units) the test's tolerance is a gain of; and whether they are range images
    in their sensor frames (the sensor at the origin): ``range_images`` True or False as declared,
    None to establish it from each cloud's own points
    (:func:`esmicp.trust.free_space.range_image_test`; the test then runs only when both are)."""

    source: np.ndarray
    target: np.ndarray
    inlier_distance: float
    range_images: bool | None = True

    def premise(self, policy: TrustPolicy) -> str | None:
        """None when both clouds are range images (declared, or as their points show); else why
        not, in words."""
        if self.range_images is not None:
            return None if self.range_images else "declared not range images"
        from .free_space import range_image_test  # here: it loads SciPy

        for name, cloud in (("source", self.source), ("target", self.target)):
            cloud = np.asarray(cloud, dtype=np.float64)
            subset = cloud[np.linspace(0, len(cloud) - 1, min(len(cloud), policy.free_space_points)).astype(np.intp)]
            test = range_image_test(subset, policy)
            if not test.range_image:
                return f"the {name} is not a range image from its origin: {test.reason}"
        return None


def judge(transformation: np.ndarray, *, source: np.ndarray, target_index, keypoints: Keypoints,
          pairs: tuple[np.ndarray, np.ndarray] | None, sigma: float | None, converged: bool, num_iterations: int,
          sample: np.ndarray | None = None,
          config: ConfidenceRanges, policy: TrustPolicy = DEFAULT_POLICY, ambiguous: bool = False,
          runner_up_ratio: float | None = None, confidence: float | None = None, origin: np.ndarray | None = None,
          sensors: SensorClouds | None = None, workers: int | None = None,
          unsupported: str | None = None,
          made: Keypoints | None = None, scatter: bool | None = None) -> Verdict:
    """The verdict on a registered pose.

    ``transformation`` (4x4 ``T_target_source``), ``source`` (N, 3) and ``keypoints`` are in the
    frame of ``target_index`` (a :class:`~esmicp.core.correspondence.NearestNeighbors`), whose
    origin lies at ``origin`` in the target's own coordinates (None: the same frame). ``pairs``:
    each source point's nearest target ``(distances, indices)`` at this pose, if known (``sample``:
    the indices of the evenly strided source points they are of, None: every point; see
    :func:`~esmicp.trust.uncertainty.from_registration`); ``sigma``:
    the Gaussian weights' width (cloud units; None: unit weights, as ICP); ``converged``,
    ``num_iterations``: the refinement's; ``ambiguous``, ``runner_up_ratio``: the global search's
    (False and None without one). ``confidence``: the overlap confidence of this pose on
    ``keypoints`` when the refinement already measured it (else measured here, with the ranges of
    ``config``, a :class:`~esmicp.globalreg.config.SearchConfig`); when either cloud carries
    scattered points (:func:`scattered_keypoints`), the confidence is measured here on the pair's
    own keypoints instead, on the surface of that cloud (:func:`~esmicp.trust.confidence.surface_part`:
    keypoints already chosen among, e.g. the search's with its isolated ones dropped, no longer
    show the scatter). ``sensors``: the clouds in their
    own frames for the free-space test (None: no such test); declared range images are tested
    always, clouds of unknown kind (``sensors.range_images`` None) only when nothing else casts
    doubt on the pose and both prove range images (:meth:`SensorClouds.premise`). The handedness
    test (:func:`esmicp.trust.handedness.handedness`) runs last, on a pose nothing else casts doubt
    on. ``policy``: the bars and the measures' values; ``workers``: threads of the compiled
    kernels (None: every core); ``unsupported``: the global search's words when it stopped for want
    of support (a doubt), else None. ``made``: the whole clouds' keypoints as
    :func:`scattered_keypoints` makes them, when the caller already made them (None: made there
    when needed). ``scatter``: :func:`scattered_keypoints`'s reading of these clouds when the caller
    already made it, with the same ``config``, ``policy`` and ``workers`` (True: a cloud carries
    scattered points, and ``made`` holds the keypoints it returned; False: none does; None: read
    here).
    """
    # The covariance and the scatter test read the clouds apart: on more than one thread, the
    # covariance is estimated on a second thread meanwhile (the same numbers).
    with ThreadPoolExecutor(max_workers=1) if workers != 1 else nullcontext() as pool:
        arguments = (source, target_index, transformation, sigma)
        options = dict(origin=origin, workers=workers, pairs=pairs, sample=sample, policy=policy)
        covariance = None if pool is None else pool.submit(from_registration, *arguments, **options)
        if scatter is None:
            scattered = scattered_keypoints(source, target_index, config, policy, workers, made=made)
        else:
            scattered = made if scatter else None
            if scatter and made is None:
                raise ValueError("judge: scatter=True needs the keypoints the reading returned (made=)")
        if scattered is not None:
            keypoints, confidence = scattered, None
        if confidence is None:
            confidence = overlap_confidence(transformation, keypoints, workers, config=config, policy=policy)
        uncertainty = from_registration(*arguments, **options) if covariance is None else covariance.result()
    measured = dict(converged=converged, num_iterations=num_iterations, confidence=confidence, ambiguous=ambiguous,
                    runner_up_ratio=runner_up_ratio, uncertainty=uncertainty, policy=policy, unsupported=unsupported)
    verdict = Verdict.of(**measured)
    if sensors is not None and (sensors.range_images or (verdict.trusted and sensors.premise(policy) is None)):
        from . import free_space as test  # here: it loads SciPy

        own = _unshifted(transformation, origin)
        measured["free_space"] = test.free_space_fraction(
            sensors.target, sensors.source, own, policy.free_space_tolerance_inliers * sensors.inlier_distance, policy)
        measured["free_space_words"] = test.pair_verdict(measured["free_space"], policy)[1]
        verdict = Verdict.of(**measured)
    if verdict.trusted:  # the handedness test costs some hundred keypoint queries: only where it decides
        verdict = Verdict.of(**measured, handedness=handedness_of(
            transformation, keypoints, workers, coincide_voxels=config.scan.keypoint.coincide_voxels, policy=policy))
    return verdict


def scattered_keypoints(source: np.ndarray, target_index, config, policy: TrustPolicy = DEFAULT_POLICY,
                        workers: int | None = None, *, made: Keypoints | None = None) -> Keypoints | None:
    """The pair's :class:`~esmicp.core.keypoints.Keypoints` (``source`` and the points of
    ``target_index``, at the voxel of ``config``, a :class:`~esmicp.globalreg.config.SearchConfig`)
    when either cloud carries scattered points
    (:attr:`esmicp.trust.confidence.SurfacePart.surface` not None), read from the clouds alone;
    None when neither does. Clouds of more than ``policy.scatter_points`` points are read first on
    that many evenly strided points of each (:func:`~esmicp.core.sampling.evenly_strided`: their own
    keypoints, at their own spacing), and on the whole clouds only when those carry scattered
    points. ``made``: the whole clouds' keypoints (``Keypoints.of(source, target_index.points,
    target_index.spacing(), config.keypoints, config.scan.keypoint.min_voxel_spacings)``) when the
    caller already made them: used instead of the same made again (with their trees, and the
    surface parts already read from them)."""
    target = target_index.points

    def whole() -> Keypoints:
        if made is not None:
            return made
        return Keypoints.of(source, target, target_index.spacing(), config.keypoints,
                            config.scan.keypoint.min_voxel_spacings)

    if max(len(source), len(target)) <= policy.scatter_points:
        return _if_scattered(whole(), config, policy, workers)
    source_sample = source[evenly_strided(len(source), policy.scatter_points)]
    target_sample = target[evenly_strided(len(target), policy.scatter_points)]
    sample_spacing = NearestNeighbors(target_sample, workers=workers).spacing()
    probe = Keypoints.of(source_sample, target_sample, sample_spacing, config.keypoints,
                         config.scan.keypoint.min_voxel_spacings)
    if _if_scattered(probe, config, policy, workers) is None:
        return None
    return _if_scattered(whole(), config, policy, workers)


def _if_scattered(keypoints: Keypoints, config, policy: TrustPolicy, workers: int | None) -> Keypoints | None:
    """``keypoints`` when either cloud's carries scattered points, else None."""
    spacings = config.scan.keypoint.min_voxel_spacings
    for points, tree in ((keypoints.source, keypoints.source_tree), (keypoints.target, keypoints.target_tree)):
        if surface_part(points, tree, keypoints.voxel, spacings, workers, policy=policy).surface is not None:
            return keypoints
    return None


def _unshifted(transformation: np.ndarray, origin: np.ndarray | None) -> np.ndarray:
    """``transformation`` of a frame whose origin lies at ``origin`` in the clouds' own coordinates,
    in those coordinates (same rotation, translation ``t + o - R o``)."""
    if origin is None:
        return transformation
    own = transformation.copy()
    own[:3, 3] = transformation[:3, 3] + (origin - transformation[:3, :3] @ origin)
    return own
