"""The benchmark's configuration: frozen records, checked when built, saved beside every result.

The command line (``esmicp bench``) parses flags into a :class:`BenchConfig`; the library takes
the object. Everything that changes a row's content is a field here, so two runs with equal
configurations produce equal rows (up to timings); what only changes *how* trials run (workers,
scheduler, progress bar) lives in :class:`RunOptions` and is not part of the saved identity.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from esmicp.errors import InvalidInputError

#: Object protocols of :mod:`esmicp_lab.bench.protocols` plus the bench's own ``partial`` and
#: ``shuffled-45`` (DCP's training distribution: :func:`esmicp_lab.bench.trials.small_rotation_trial`).
HONEST_OBJECT_PROTOCOLS = ("copy", "shuffled", "resampled", "outliers-30", "outliers-60", "partial", "shuffled-45")
#: Protocol on datasets of scans with known poses.
SCAN_PROTOCOL = "scan-pairs"
#: The paper's randomised protocol: ``paper`` (noise-free) and its noisy variants.
PAPER_PROTOCOLS = ("paper", "paper-noise-30", "paper-noise-60")
#: The 1,000-transform tables' protocols (run only by ``paper_1000_trials`` / ``--paper-1000``).
PAPER_1000_PROTOCOLS = ("paper-1000", "paper-1000-noise-30")
#: Every protocol name ``--protocols`` accepts (``paper-table`` is only run by ``--paper``, the
#: :data:`PAPER_1000_PROTOCOLS` only by ``--paper-1000``).
PROTOCOL_NAMES = (*HONEST_OBJECT_PROTOCOLS, SCAN_PROTOCOL, *PAPER_PROTOCOLS)
#: The local-method starts the bench offers.
INIT_MODES = ("identity", "perturbed")


@dataclass(frozen=True)
class BenchConfig:
    """What to run.

    Attributes
    ----------
    protocols : tuple of str
        Names from :data:`PROTOCOL_NAMES`.
    datasets : tuple of str
        ``synthetic``, ``modelnet40``, ``bunny``, ``bunny-scans``, ``lidar-pair`` or a folder of
        point-cloud / mesh files (see :mod:`esmicp_lab.bench.datasets`).
    methods : tuple of str
        Names of :func:`esmicp_lab.bench.methods.method_names`.
    trials : int
        Trials per (protocol, dataset, points) for the randomised protocols, round-robin over the
        dataset's clouds. ``scan-pairs`` uses every overlapping pair instead (at most ``trials``).
    points : tuple of int
        Cloud sizes: each cloud is subsampled (meshes: sampled) to each size in turn.
    seed : int
        Base seed; trial seeds are children of it (``SeedSequence.spawn``).
    max_iterations : int
        Iteration budget of every local method (ours and the baselines').
    init : str
        Start of the local methods: ``identity``, or ``perturbed`` (the truth moved by a random
        rotation of ``init_perturbation_deg`` about a random axis and a translation of
        ``init_perturbation_fraction`` of the target's diagonal in a random direction).
    translation_ranges : tuple of float
        Paper protocols: each translation component uniform in ``[-range, range]`` (cloud units);
        every paper protocol runs once per range.
    sigma_sweep : tuple of float
        When not empty, ``esm`` and ``esm-paper`` run once per fixed sigma (cloud units) instead of
        once with their default; every other method runs once.
    paper_tables : bool
        Also run the paper's printed transforms (protocol ``paper-table``).
    paper_1000_trials : int
        When > 0, also run the paper's 1,000-transform tables (:data:`esmicp_lab.bench.paper.PAPER_1000_GROUPS`:
        protocols ``paper-1000`` on airplane, person and stool and ``paper-1000-noise-30`` on stool,
        translations in [-1000, 1000] whatever ``translation_ranges`` says) with this many trials per
        group, on every object dataset holding those classes. The paper's setting is 1,000 trials
        and ``max_iterations=100`` (``esmicp bench --paper-1000``).
    slow_trials : int
        Methods of :data:`esmicp_lab.bench.methods.SLOW_METHODS` (about a second or more per trial:
        Go-ICP, CPD, ICP-NL) run only on the first ``slow_trials`` trials of each randomised
        (protocol, dataset, points, range) group, and on every ``paper-table`` case; those of
        :data:`esmicp_lab.bench.methods.SLOW_ON_PRINTED_ONLY` (Go-ICP) on the printed cases without
        outliers only. 0 means every method on every trial. The tables give each cell's trial
        count, so a row run on fewer trials says so.
    data_dir : str
        The shared data folder (``modelnet40/``, ``bunny/``, ...).
    """

    protocols: tuple[str, ...] = ("copy", "shuffled", "resampled", "outliers-30", "outliers-60", "partial")
    datasets: tuple[str, ...] = ("synthetic",)
    methods: tuple[str, ...] = ("esm", "esm-paper", "icp", "esm-global")
    trials: int = 20
    points: tuple[int, ...] = (1024,)
    seed: int = 0
    max_iterations: int = 40
    init: str = "identity"
    init_perturbation_deg: float = 30.0
    init_perturbation_fraction: float = 0.1
    translation_ranges: tuple[float, ...] = (1000.0,)
    sigma_sweep: tuple[float, ...] = ()
    paper_tables: bool = False
    paper_1000_trials: int = 0
    data_dir: str = ""
    slow_trials: int = 1

    def __post_init__(self):
        _check_names("protocols", self.protocols, PROTOCOL_NAMES)
        if not self.datasets:
            raise InvalidInputError("datasets: give at least one dataset")
        if not self.methods:
            raise InvalidInputError("methods: give at least one method")
        if len(set(self.methods)) != len(self.methods):
            raise InvalidInputError(f"methods: a method is listed twice in {','.join(self.methods)}")
        _check_positive_int("trials", self.trials)
        _check_positive_int("max_iterations", self.max_iterations)
        for name in ("slow_trials", "paper_1000_trials"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise InvalidInputError(f"{name}: expected a whole number >= 0, got {value!r}")
        if not self.points:
            raise InvalidInputError("points: give at least one cloud size")
        for count in self.points:
            _check_positive_int("points", count, minimum=8)
        if self.init not in INIT_MODES:
            raise InvalidInputError(f"init: expected one of {', '.join(INIT_MODES)}, got {self.init!r}")
        for name in ("init_perturbation_deg", "init_perturbation_fraction"):
            _check_finite_non_negative(name, getattr(self, name))
        if not self.translation_ranges:
            raise InvalidInputError("translation_ranges: give at least one range")
        for value in self.translation_ranges:
            _check_finite_non_negative("translation_ranges", value)
        for sigma in self.sigma_sweep:
            if not isinstance(sigma, (int, float)) or not 0 < sigma < float("inf"):
                raise InvalidInputError(f"sigma_sweep: every sigma must be a finite number > 0, got {sigma!r}")
        if not self.protocols and not self.paper_tables and not self.paper_1000_trials:
            raise InvalidInputError("protocols: give at least one protocol (or run the paper's tables)")

    def to_dict(self) -> dict:
        """JSON-ready form (tuples become lists)."""
        return {key: list(value) if isinstance(value, tuple) else value for key, value in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict) -> "BenchConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise InvalidInputError(f"configuration: unknown keys {', '.join(unknown)}")
        return cls(**{key: tuple(value) if isinstance(value, list) else value for key, value in data.items()})

    def differences(self, other: "BenchConfig") -> list[str]:
        """Names of the fields whose values differ from ``other``'s."""
        return [f.name for f in dataclasses.fields(self) if getattr(self, f.name) != getattr(other, f.name)]


@dataclass(frozen=True)
class RunOptions:
    """How to run (never changes a row's content, only its timing).

    Attributes
    ----------
    out_dir : Path
        Folder of the result files (created if missing).
    workers : int or None
        Parallel worker processes; None: every local core; 1: serial, in this process.
    scheduler : str or None
        Address of an existing Dask scheduler (``tcp://HOST:PORT``); None: a local cluster of
        ``workers`` processes (Dask ``LocalCluster``) when ``workers != 1``.
    resume : bool
        Continue the run in ``out_dir``: skip every (trial, method) already there.
    force : bool
        Replace the results in ``out_dir``.
    progress : bool
        Show a progress bar (tqdm, on stderr) with an ETA.
    """

    out_dir: Path = Path("bench-results")
    workers: int | None = None
    scheduler: str | None = None
    resume: bool = False
    force: bool = False
    progress: bool = True

    def __post_init__(self):
        if self.workers is not None:
            _check_positive_int("workers", self.workers)
        if self.resume and self.force:
            raise InvalidInputError("resume and force: choose one (--resume continues a run, --force replaces it)")


def _check_names(what: str, names, allowed) -> None:
    for name in names:
        if name not in allowed:
            raise InvalidInputError(f"{what}: unknown {what[:-1]} {name!r}; choose from {', '.join(allowed)}")
    if len(set(names)) != len(names):
        raise InvalidInputError(f"{what}: a name is listed twice in {','.join(names)}")


def _check_positive_int(name: str, value, minimum: int = 1) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise InvalidInputError(f"{name}: expected a whole number >= {minimum}, got {value!r}")


def _check_finite_non_negative(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < float("inf"):
        raise InvalidInputError(f"{name}: expected a finite number >= 0, got {value!r}")
