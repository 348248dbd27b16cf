"""Trial plans: what every row of a run is about, with the seed that rebuilds it alone.

A :class:`TrialSpec` is small and names everything a trial depends on; :func:`build_trial` turns
it (with its cloud) into an :class:`esmicp_lab.bench.protocols.Trial`. Seeds: for every (protocol,
dataset, points, translation range) a ``SeedSequence`` built from the run's seed and those names
is spawned (``SeedSequence.spawn``) into one child per trial; a trial's ``seed`` is a 32-bit int
drawn from its child, and ``build_trial(spec, cloud)`` needs nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from esmicp.core.procrustes import apply, bounding_box_diagonal, rigid_inverse, to_matrix
from .protocols import PROTOCOLS, Trial, make_trial, random_rigid_transform
from .config import PAPER_1000_PROTOCOLS, PAPER_PROTOCOLS
from .datasets import name_seed
from .paper import (
    PAPER_1000_GROUPS,
    PAPER_1000_TRANSLATION_RANGE,
    PAPER_CASES,
    PaperCase,
    case_protocol,
    paper_motion,
    paper_trial,
)

#: Fraction of each half a ``partial`` crop keeps.
PARTIAL_KEEP = 0.7
#: ``shuffled-45``: the largest angle of each Euler angle (degrees) and the largest translation
#: per axis as a fraction of the cloud's radius about its centroid (DCP's ModelNet40 training
#: setting: 45 degrees and 0.5 on objects in the unit sphere).
SMALL_ROTATION_MAX_DEG = 45.0
SMALL_ROTATION_SHIFT = 0.5
PAPER_TABLE = "paper-table"


@dataclass(frozen=True)
class TrialSpec:
    """One trial, by name and seed.

    ``index`` is the trial's number within its (protocol, dataset, points, range) group;
    ``translation_range`` is set for the paper protocols, ``case`` for ``paper-table``.
    """

    trial_id: str
    protocol: str
    dataset: str
    cloud: str
    seed: int
    index: int
    points: int
    translation_range: float | None = None
    case: str | None = None


def group_seeds(base_seed: int, protocol: str, dataset: str, points: int, count: int, translation_range=None) -> list[int]:
    """``count`` trial seeds: children of one ``SeedSequence`` per group, spawned."""
    entropy = [int(base_seed), name_seed(protocol), name_seed(dataset), int(points)]
    if translation_range is not None:
        entropy.append(name_seed(repr(float(translation_range))))
    children = np.random.SeedSequence(entropy).spawn(count)
    return [int(child.generate_state(1)[0]) for child in children]


def _range_label(value: float) -> str:
    return f"t{value:g}"


def object_specs(protocol: str, dataset: str, clouds: list[str], points: int, trials: int, seed: int, translation_range=None) -> list[TrialSpec]:
    """Trials of an object protocol, round-robin over ``clouds``."""
    seeds = group_seeds(seed, protocol, dataset, points, trials, translation_range)
    label = protocol if translation_range is None else f"{protocol}-{_range_label(translation_range)}"
    specs = []
    for index, trial_seed in enumerate(seeds):
        cloud = clouds[index % len(clouds)]
        specs.append(
            TrialSpec(f"{dataset}/{cloud}/n{points}/{label}/{index}", protocol, dataset, cloud, trial_seed,
                      index, points, translation_range)
        )
    return specs


def paper_case_specs(dataset: str, clouds: list[str], points: int, seed: int) -> list[TrialSpec]:
    """One ``paper-table`` trial per :data:`PAPER_CASES` entry whose class is in ``clouds``."""
    specs = []
    for index, case in enumerate(PAPER_CASES):
        cloud = find_class(case, clouds)
        if cloud is None:
            continue
        trial_seed = group_seeds(seed, PAPER_TABLE, f"{dataset}/{case.name}", points, 1)[0]
        specs.append(TrialSpec(f"{dataset}/{cloud}/n{points}/{PAPER_TABLE}/{case.name}", PAPER_TABLE, dataset,
                               cloud, trial_seed, index, points, case=case.name))
    return specs


def find_class(case: PaperCase | str, clouds: list[str]) -> str | None:
    """The first cloud named ``<class>`` or ``<class>_<number>`` (``case``: a class name or a
    :class:`PaperCase`, whose ``cloud`` is the class)."""
    name = case if isinstance(case, str) else case.cloud
    for cloud in clouds:
        if cloud == name or (cloud.startswith(name + "_") and cloud[len(name) + 1 :].isdigit()):
            return cloud
    return None


def paper_1000_specs(dataset: str, clouds: list[str], points: int, trials: int, seed: int) -> list[TrialSpec]:
    """``trials`` trials of each :data:`esmicp_lab.bench.paper.PAPER_1000_GROUPS` group whose class is
    in ``clouds``: ids ``<dataset>/<cloud>/n<points>/<protocol>-t1000/<index>``, seeds spawned per
    (protocol, dataset/cloud, points, range) as :func:`group_seeds` does."""
    specs = []
    for _, name, protocol in PAPER_1000_GROUPS:
        cloud = find_class(name, clouds)
        if cloud is None:
            continue
        label = f"{protocol}-{_range_label(PAPER_1000_TRANSLATION_RANGE)}"
        seeds = group_seeds(seed, protocol, f"{dataset}/{cloud}", points, trials, PAPER_1000_TRANSLATION_RANGE)
        for index, trial_seed in enumerate(seeds):
            specs.append(TrialSpec(f"{dataset}/{cloud}/n{points}/{label}/{index}", protocol, dataset, cloud,
                                   trial_seed, index, points, PAPER_1000_TRANSLATION_RANGE))
    return specs


def _subsample(cloud: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    if len(cloud) <= count:
        return cloud
    return cloud[np.sort(rng.choice(len(cloud), size=count, replace=False))]


def _crop(points: np.ndarray, rng: np.random.Generator, keep: float) -> np.ndarray:
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    height = (points - points.mean(axis=0)) @ direction
    return points[height >= np.quantile(height, 1.0 - keep)]


def partial_trial(cloud: np.ndarray, rng: np.random.Generator, *, name: str, seed, points: int) -> Trial:
    """``partial``: two disjoint random halves of ``points`` points, each cropped by its own random
    half-space to :data:`PARTIAL_KEEP` of its points (so the overlap is partial), the source half
    moved by :func:`esmicp_lab.bench.protocols.random_rigid_transform`; truth = the inverse move."""
    cloud = _subsample(np.asarray(cloud, dtype=np.float64), 2 * points, rng)
    order = rng.permutation(len(cloud))
    half = len(cloud) // 2
    target = _crop(cloud[order[:half]], rng, PARTIAL_KEEP)
    source_object = _crop(cloud[order[half : 2 * half]], rng, PARTIAL_KEEP)
    moved_by = random_rigid_transform(rng, bounding_box_diagonal(target))
    return Trial("partial", name, _frozen(apply(moved_by, source_object)), _frozen(target),
                 _frozen(rigid_inverse(moved_by)), seed, bounding_box_diagonal(target))


def small_rotation_trial(cloud: np.ndarray, rng: np.random.Generator, *, name: str, seed, points: int) -> Trial:
    """``shuffled-45``, DCP's ModelNet40 training distribution: the cloud subsampled to ``points``;
    source = those points, target = the same points moved by ``[R | t]``, each cloud in its own
    random order; ``R = Rotation.from_euler("zyx", angles)`` with the three angles uniform in
    ``[0, SMALL_ROTATION_MAX_DEG]`` degrees, ``t`` uniform in ``[-s, s]`` per axis with ``s =
    SMALL_ROTATION_SHIFT x`` the cloud's radius about its centroid. Truth ``[R | t]``."""
    from scipy.spatial.transform import Rotation

    cloud = _subsample(np.asarray(cloud, dtype=np.float64), points, rng)
    rotation = Rotation.from_euler("zyx", rng.uniform(0.0, np.radians(SMALL_ROTATION_MAX_DEG), 3)).as_matrix()
    radius = float(np.max(np.linalg.norm(cloud - cloud.mean(axis=0), axis=1)))
    shift = rng.uniform(-SMALL_ROTATION_SHIFT * radius, SMALL_ROTATION_SHIFT * radius, 3)
    truth = to_matrix(rotation, shift)
    source = cloud[rng.permutation(len(cloud))]
    target = apply(truth, cloud)[rng.permutation(len(cloud))]
    return Trial("shuffled-45", name, _frozen(source), _frozen(target), _frozen(truth), seed,
                 bounding_box_diagonal(target))


def _frozen(array) -> np.ndarray:
    array = np.array(array, dtype=np.float64, copy=True)
    array.setflags(write=False)
    return array


def build_trial(spec: TrialSpec, cloud: np.ndarray) -> Trial:
    """The trial ``spec`` describes, on ``cloud`` (the dataset's full cloud), from ``spec.seed``."""
    if spec.protocol in PROTOCOLS:
        return make_trial(spec.protocol, cloud, spec.seed, 0, name=spec.cloud, points=spec.points)
    rng = np.random.default_rng(spec.seed)
    if spec.protocol == "partial":
        return partial_trial(cloud, rng, name=spec.cloud, seed=spec.seed, points=spec.points)
    if spec.protocol == "shuffled-45":
        return small_rotation_trial(cloud, rng, name=spec.cloud, seed=spec.seed, points=spec.points)
    if spec.protocol in PAPER_PROTOCOLS or spec.protocol in PAPER_1000_PROTOCOLS:
        target = _subsample(np.asarray(cloud, dtype=np.float64), spec.points, rng)
        moved_by = paper_motion(rng, spec.translation_range)
        return paper_trial(spec.protocol, target, moved_by, rng, name=spec.cloud, seed=spec.seed)
    raise ValueError(f"protocol: {spec.protocol!r} is not built from a spec (use build_case_trial / scan pairs)")


def build_case_trial(spec: TrialSpec, cloud: np.ndarray, data_dir) -> Trial:
    """A ``paper-table`` trial: the printed transform of ``spec.case`` on ``cloud``."""
    case = next(c for c in PAPER_CASES if c.name == spec.case)
    rng = np.random.default_rng(spec.seed)
    target = _subsample(np.asarray(cloud, dtype=np.float64), spec.points, rng)
    trial = paper_trial(case_protocol(case), target, case.motion(data_dir), rng, name=spec.cloud, seed=spec.seed)
    return Trial(PAPER_TABLE, trial.cloud, trial.source, trial.target, trial.T_target_source, trial.seed,
                 trial.diagonal, trial.clean)


def perturbed_init(truth: np.ndarray, target: np.ndarray, seed: int, angle_deg: float, fraction: float) -> np.ndarray:
    """A start near the truth: ``truth`` followed by a rotation of exactly ``angle_deg`` about a
    random axis through the target's centroid, and a shift of ``fraction`` of the target's
    diagonal in a random direction. Drawn from ``seed`` alone (the same for every method)."""
    rng = np.random.default_rng([int(seed), 1])
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_rotvec(np.radians(angle_deg) * axis).as_matrix()
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    centroid = np.asarray(target).mean(axis=0)
    shift = fraction * bounding_box_diagonal(target) * direction
    delta = to_matrix(rotation, centroid - rotation @ centroid + shift)
    return delta @ truth


def perturbed_start(truth: np.ndarray, source: np.ndarray, angle_deg: float, shift: float, rng) -> np.ndarray:
    """``truth`` followed by a rotation of ``angle_deg`` about a random axis through the placed
    source's centroid and a translation of length ``shift`` (cloud units) in a random direction,
    both drawn from ``rng`` (``benchmarks/start_drift.py``'s perturbed starts)."""
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    matrix = Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
    centre = apply(truth, source).mean(axis=0)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    return to_matrix(matrix, centre - matrix @ centre + shift * direction) @ truth


__all__ = [
    "PAPER_TABLE",
    "TrialSpec",
    "build_case_trial",
    "build_trial",
    "object_specs",
    "paper_1000_specs",
    "paper_case_specs",
    "partial_trial",
    "small_rotation_trial",
    "perturbed_init",
    "perturbed_start",
]
