"""Evaluation protocols: build registration trials (source, target, true pose) from point arrays.

Every transform is ``T_target_source`` (4x4): ``target ~= source @ R.T + t``.

Protocols on one object (:data:`PROTOCOLS`, built by :func:`make_trials`):

``copy``
    The target is the cloud; the source is the same points, in the same order, moved by a random
    rigid transform ``G`` (:func:`random_rigid_transform`); the truth is ``G^-1``.
``shuffled``
    As ``copy``, with the source's point order shuffled.
``resampled``
    The cloud's points split at random into two disjoint halves (by index): one half is the
    target, the other half, moved by ``G``, is the source.
``outliers-30``, ``outliers-60``
    As ``resampled``, with the ESM-ICP paper's noise (:func:`paper_noise`) added to 30 % / 60 % of
    the source points, in the object's frame (before the source is moved).

Real scans with known poses give :func:`scan_pairs` (every ordered pair that overlaps).

Randomness comes only from numpy Generators built from :class:`numpy.random.SeedSequence`. A
trial of :func:`make_trials` is reproducible alone: ``make_trial(protocol, cloud, seed, index)``
rebuilds trial ``index`` of ``make_trials(protocol, ..., seed=seed)`` without the others.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from esmicp.core.procrustes import apply, bounding_box_diagonal, rigid_inverse, to_matrix
from esmicp.metrics import random_rotation

#: Names of the single-object protocols :func:`make_trials` builds.
PROTOCOLS = ("copy", "shuffled", "resampled", "outliers-30", "outliers-60")

#: Fraction of corrupted source points of each outlier protocol.
OUTLIER_FRACTIONS = {"outliers-30": 0.3, "outliers-60": 0.6}

#: The paper's noise mixture, in units of a unit-size object: ``(variance, clip)`` per component.
#: Each corrupted point draws one component with equal probability, then per-coordinate noise
#: ``clip(N(0, variance), -clip, clip)``.
PAPER_NOISE_MIXTURE = ((0.01, 0.05), (0.04, 1.0), (0.1, 10.0))

#: Protocol name given to the trials of :func:`scan_pairs`.
SCAN_PAIRS = "scan-pairs"


@dataclass(frozen=True, eq=False)
class Trial:
    """One registration problem with its ground truth.

    Attributes
    ----------
    protocol : str
        Protocol name (one of :data:`PROTOCOLS`, or ``"scan-pairs"``).
    cloud : str
        Name of the object (``"source->target"`` for scan pairs).
    source, target : (N, 3), (M, 3) read-only float64 arrays
    T_target_source : (4, 4) read-only float64 array
        The true pose: ``apply(T_target_source, source)`` lies on ``target``.
    seed : int, tuple or None
        What the trial was drawn from: ``(seed, index)`` for :func:`make_trials`,
        ``(base, i, j)`` for :func:`scan_pairs`, whatever the caller passed otherwise.
    diagonal : float
        Bounding-box diagonal of the target (cloud units); the scale of success thresholds.
    clean : (N,) read-only bool array or None
        For the outlier protocols, True for the source points the noise left untouched; None when
        every source point is clean. Evaluate "up to symmetry" on these points only: a corrupted
        point turned about a symmetry axis does not land on itself.
    """

    protocol: str
    cloud: str
    source: np.ndarray
    target: np.ndarray
    T_target_source: np.ndarray
    seed: int | tuple | None
    diagonal: float
    clean: np.ndarray | None = None

    @property
    def clean_source(self) -> np.ndarray:
        """The source points untouched by noise (all of them when there is no noise)."""
        return self.source if self.clean is None else self.source[self.clean]


def _frozen(array) -> np.ndarray:
    array = np.array(array, dtype=np.float64, copy=True)
    array.setflags(write=False)
    return array


def _trial(protocol, cloud, source, target, truth, seed, clean=None) -> Trial:
    if clean is not None:
        clean = np.array(clean, dtype=bool, copy=True)
        clean.setflags(write=False)
    return Trial(
        protocol=protocol,
        cloud=cloud,
        source=_frozen(source),
        target=_frozen(target),
        T_target_source=_frozen(truth),
        seed=seed,
        diagonal=bounding_box_diagonal(target),
        clean=clean,
    )


def random_rigid_transform(
    rng: np.random.Generator, diameter: float, *, max_angle_deg: float = 180.0
) -> np.ndarray:
    """A random 4x4 rigid transform for a cloud of bounding-box diagonal ``diameter``.

    The rotation is uniform on SO(3) (:meth:`scipy.spatial.transform.Rotation.random` driven by
    ``rng``), or, when ``max_angle_deg < 180``, about a uniformly random axis by an angle uniform
    in ``[0, max_angle_deg]``. The translation is uniform in a box 10x the diameter: each
    component uniform in ``[-5 diameter, 5 diameter]``.
    """
    rotation = random_rotation(rng, max_angle_deg)
    translation = rng.uniform(-5.0 * diameter, 5.0 * diameter, size=3)
    return to_matrix(rotation, translation)


def _as_cloud(cloud) -> np.ndarray:
    array = np.asarray(cloud, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3 or len(array) < 3:
        raise ValueError(f"cloud: expected (N, 3) points with N >= 3, got shape {array.shape}")
    return array


def _moved(protocol, name, target, source_object, rng, seed, *, shuffle=False, clean=None) -> Trial:
    """Move ``source_object`` (in the target's frame) by a random ``G``; truth ``G^-1``."""
    moved_by = random_rigid_transform(rng, bounding_box_diagonal(target))
    source = apply(moved_by, source_object)
    if shuffle:
        source = source[rng.permutation(len(source))]
    return _trial(protocol, name, source, target, rigid_inverse(moved_by), seed, clean)


def copy_trial(cloud, rng: np.random.Generator, *, name: str = "", seed=None) -> Trial:
    """``copy`` protocol: the source is the target's points, same order, moved by a random ``G``."""
    cloud = _as_cloud(cloud)
    return _moved("copy", name, cloud, cloud, rng, seed)


def shuffled_trial(cloud, rng: np.random.Generator, *, name: str = "", seed=None) -> Trial:
    """``shuffled`` protocol: as :func:`copy_trial`, with the source's point order shuffled."""
    cloud = _as_cloud(cloud)
    return _moved("shuffled", name, cloud, cloud, rng, seed, shuffle=True)


def _split(cloud: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Two disjoint random halves (by index) of ``floor(N / 2)`` points each: target, source."""
    order = rng.permutation(len(cloud))
    half = len(cloud) // 2
    return cloud[order[:half]], cloud[order[half : 2 * half]]


def resampled_trial(cloud, rng: np.random.Generator, *, name: str = "", seed=None) -> Trial:
    """``resampled`` protocol: a random half of the points is the target, the other half, moved
    by a random ``G``, the source (each ``floor(N / 2)`` points; no point index is in both)."""
    target, source_object = _split(_as_cloud(cloud), rng)
    return _moved("resampled", name, target, source_object, rng, seed)


def paper_noise_draw(count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` noise vectors of the paper's mixture for a unit-size object.

    Returns ``(noise, component)``: ``(count, 3)`` offsets and, per row, the index of the
    :data:`PAPER_NOISE_MIXTURE` component it was drawn from (each with probability 1/3).
    """
    component = rng.integers(0, len(PAPER_NOISE_MIXTURE), size=count)
    variance = np.array([v for v, _ in PAPER_NOISE_MIXTURE])[component]
    clip = np.array([c for _, c in PAPER_NOISE_MIXTURE])[component]
    noise = rng.normal(size=(count, 3)) * np.sqrt(variance)[:, None]
    return np.clip(noise, -clip[:, None], clip[:, None]), component


def paper_noise(
    points, fraction: float, rng: np.random.Generator, scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """Corrupt ``round(fraction * N)`` randomly chosen points with the paper's noise.

    Each corrupted point gets :func:`paper_noise_draw` offsets multiplied by ``scale`` (the
    object's half-diagonal, as the mixture is given for a unit-size object).

    Returns
    -------
    corrupted : (N, 3) array
        A new array; rows outside ``mask`` are exact copies of ``points``.
    mask : (N,) bool array
        True for the corrupted rows.
    """
    points = np.array(points, dtype=np.float64, copy=True)
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction: expected a number in [0, 1], got {fraction!r}")
    count = round(fraction * len(points))
    mask = np.zeros(len(points), dtype=bool)
    mask[rng.choice(len(points), size=count, replace=False)] = True
    noise, _ = paper_noise_draw(count, rng)
    points[mask] += scale * noise
    return points, mask


def outlier_trial(
    cloud, rng: np.random.Generator, fraction: float, *, name: str = "", seed=None
) -> Trial:
    """``outliers-*`` protocol: :func:`resampled_trial` with :func:`paper_noise` on ``fraction``
    of the source points, applied in the object's frame before moving the source; the noise scale
    is half the bounding-box diagonal of ``cloud``."""
    cloud = _as_cloud(cloud)
    target, source_object = _split(cloud, rng)
    noisy, corrupted = paper_noise(source_object, fraction, rng, 0.5 * bounding_box_diagonal(cloud))
    protocol = f"outliers-{round(100 * fraction)}"
    return _moved(protocol, name, target, noisy, rng, seed, clean=~corrupted)


def _subsample(points: np.ndarray, count: int | None, rng: np.random.Generator) -> np.ndarray:
    if count is None or len(points) <= count:
        return points
    return points[np.sort(rng.choice(len(points), size=count, replace=False))]


def make_trial(protocol: str, cloud, seed: int, index: int, *, name: str = "", points: int = 2000) -> Trial:
    """Trial ``index`` of :func:`make_trials` for ``protocol`` and ``seed``, built alone.

    Its generator is ``default_rng(SeedSequence(seed).spawn(count)[index])`` (the same for any
    ``count > index``). The cloud is first subsampled to ``points`` points (``2 * points`` for
    the resampled / outlier protocols, so each half has ``points``); fewer points are kept as is.
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol: expected one of {', '.join(PROTOCOLS)}, got {protocol!r}")
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(index,)))
    cloud = _as_cloud(cloud)
    trial_seed = (seed, index)
    if protocol in ("copy", "shuffled"):
        cloud = _subsample(cloud, points, rng)
        build = copy_trial if protocol == "copy" else shuffled_trial
        return build(cloud, rng, name=name, seed=trial_seed)
    cloud = _subsample(cloud, 2 * points, rng)
    if protocol == "resampled":
        return resampled_trial(cloud, rng, name=name, seed=trial_seed)
    return outlier_trial(cloud, rng, OUTLIER_FRACTIONS[protocol], name=name, seed=trial_seed)


def make_trials(protocol: str, clouds: dict, count: int, seed: int, *, points: int = 2000) -> list[Trial]:
    """``count`` trials of ``protocol``, round-robin over ``clouds`` (name -> ``(N, 3)`` array).

    Trial ``i`` uses cloud ``i % len(clouds)`` (in the dict's order) and the generator of child
    ``i`` of ``SeedSequence(seed)``; see :func:`make_trial`. Same (protocol, seed, index, cloud)
    -> same trial.
    """
    if not clouds:
        raise ValueError("clouds: need at least one cloud")
    names = list(clouds)
    trials = []
    for index in range(count):
        name = names[index % len(names)]
        trials.append(make_trial(protocol, clouds[name], seed, index, name=name, points=points))
    return trials


def median_spacing(points: np.ndarray, tree: cKDTree | None = None) -> float:
    """Median distance from each point to its nearest other point."""
    tree = cKDTree(points) if tree is None else tree
    distances, _ = tree.query(points, k=2)
    return float(np.median(distances[:, 1]))


def scan_overlap(
    source: np.ndarray,
    target: np.ndarray,
    T_target_source: np.ndarray,
    overlap_distance: float | None = None,
) -> float:
    """Fraction of ``source`` points that, mapped by the true pose, have a ``target`` point within
    ``overlap_distance`` (default: 3x the target's median point spacing)."""
    tree = cKDTree(target)
    if overlap_distance is None:
        overlap_distance = 3.0 * median_spacing(target, tree)
    distances, _ = tree.query(apply(T_target_source, source), distance_upper_bound=overlap_distance)
    return float(np.mean(distances <= overlap_distance))


def _base_entropy(rng) -> int:
    if isinstance(rng, np.random.Generator):
        return int(rng.integers(0, 2**63))
    return int(rng)


def scan_pairs(
    scans: dict,
    rng,
    *,
    min_overlap: float = 0.3,
    overlap_distance: float | None = None,
    max_points: int | None = None,
) -> list[Trial]:
    """A trial for every ordered pair of scans (both directions) whose overlap is >= ``min_overlap``.

    Parameters
    ----------
    scans : dict name -> (points, T_world_scan)
        Each scan in its own frame with its 4x4 pose in the common frame (see
        :func:`esmicp.io.stanford_conf.load_scans`).
    rng : int or numpy.random.Generator
        A seed, or a generator from which one seed ``base`` is drawn.
    min_overlap, overlap_distance
        See :func:`scan_overlap`; computed on the (subsampled) clouds of the trial.
    max_points : int, optional
        Subsample each scan to this many points (random subset).

    Returns
    -------
    list of Trial
        In the dict's order, source-major. Target: the target scan in its own frame. Source: the
        source scan in its own frame, further rotated about its centroid by a rotation uniform on
        SO(3); ``T_target_source`` is composed accordingly. ``seed = (base, i, j)`` for source
        ``i`` and target ``j`` (indices in the dict): scan ``k`` is subsampled with
        ``SeedSequence(base, spawn_key=(0, k))`` and the pair's rotation drawn with
        ``SeedSequence(base, spawn_key=(1, i, j))``, so each trial is reproducible alone.
    """
    base = _base_entropy(rng)
    names = list(scans)
    clouds, poses = [], []
    for k, name in enumerate(names):
        points, pose = scans[name]
        generator = np.random.default_rng(np.random.SeedSequence(base, spawn_key=(0, k)))
        clouds.append(_subsample(_as_cloud(points), max_points, generator))
        poses.append(np.asarray(pose, dtype=np.float64))
    trials = []
    for i, source_name in enumerate(names):
        for j, target_name in enumerate(names):
            if i == j:
                continue
            truth = rigid_inverse(poses[j]) @ poses[i]
            if scan_overlap(clouds[i], clouds[j], truth, overlap_distance) < min_overlap:
                continue
            generator = np.random.default_rng(np.random.SeedSequence(base, spawn_key=(1, i, j)))
            rotation = random_rotation(generator)
            centroid = clouds[i].mean(axis=0)
            moved_by = to_matrix(rotation, centroid - rotation @ centroid)
            trials.append(
                _trial(
                    SCAN_PAIRS,
                    f"{source_name}->{target_name}",
                    apply(moved_by, clouds[i]),
                    clouds[j],
                    truth @ rigid_inverse(moved_by),
                    (base, i, j),
                )
            )
    return trials
