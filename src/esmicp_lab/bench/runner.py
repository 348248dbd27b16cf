"""Run a benchmark: plan the trials, skip the finished ones (``resume``), run the rest serially or
on Dask (a local cluster by default, or the scheduler at ``RunOptions.scheduler``: the same
function per trial either way), append every row as it arrives, then write the tables.

Nothing finished is lost on Ctrl-C: each row is on disk before the next is awaited; the
interrupted trials are the only ones ``resume`` runs again.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from esmicp.errors import InvalidInputError, PointCloudFileError
from . import results, tables
from .config import PAPER_PROTOCOLS, SCAN_PROTOCOL, BenchConfig, RunOptions
from .datasets import POINTS_INDEPENDENT, load_dataset
from .methods import SIGMA_METHODS, SLOW_METHODS, SLOW_ON_PRINTED_ONLY, check_methods
from .paper import PAPER_CASES
from .trials import (
    PAPER_TABLE,
    TrialSpec,
    build_case_trial,
    build_trial,
    group_seeds,
    object_specs,
    paper_1000_specs,
    paper_case_specs,
    perturbed_init,
)
from .work import WorkItem, row_key, run_item

logger = logging.getLogger(__name__)

#: What to tell a user who lacks the bench's optional libraries.
BENCH_HINT = "pip install 'esmicp[bench]'"


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (or, ``terminated``, SIGTERM: :class:`esmicp.interrupts.Terminated`) during a run;
    ``rows_written`` rows of this session are on disk in ``rows_path``."""

    def __init__(self, rows_written: int, rows_path: Path, terminated: bool = False):
        super().__init__(f"{rows_written} rows written to {rows_path}")
        self.rows_written = rows_written
        self.rows_path = rows_path
        self.terminated = terminated


@dataclass(frozen=True)
class BenchOutcome:
    """What a run did: rows written now, rows skipped as already done, files written."""

    out_dir: Path
    rows_written: int
    rows_skipped: int
    rows_total: int
    files: tuple[Path, ...]


@dataclass(frozen=True, eq=False)
class _Planned:
    spec: TrialSpec
    build: object  # () -> Trial


def _runs(config: BenchConfig) -> list[tuple[str, float | None]]:
    runs = []
    for method in config.methods:
        if method in SIGMA_METHODS and config.sigma_sweep:
            runs.extend((method, float(sigma)) for sigma in config.sigma_sweep)
        else:
            runs.append((method, None))
    return runs


#: Outlier fraction of each printed paper case, by name.
PAPER_CASE_NOISE = {case.name: case.noise_fraction for case in PAPER_CASES}


def _runs_of(spec, runs, config: BenchConfig) -> list[tuple[str, float | None]]:
    """The runs of one trial: every run, but slow methods only within their trial budget: the
    first ``slow_trials`` trials of a randomised group and every ``paper-table`` case, and for
    :data:`~esmicp_lab.bench.methods.SLOW_ON_PRINTED_ONLY` the printed cases without outliers only."""
    if config.slow_trials == 0:
        return runs
    printed = spec.case is not None
    printed_clean = printed and PAPER_CASE_NOISE[spec.case] == 0.0
    return [
        (method, sigma) for method, sigma in runs
        if method not in SLOW_METHODS
        or (printed_clean if method in SLOW_ON_PRINTED_ONLY else printed or spec.index < config.slow_trials)
    ]


def plan(config: BenchConfig) -> list[_Planned]:
    """Every trial of ``config``, in a fixed order, each with a builder of its arrays."""
    data_dir = Path(config.data_dir)
    planned = []
    loaded = {}
    for name in config.datasets:
        for points in config.points:
            # Only meshes (sampled per size) depend on the size: load everything else once.
            key = (name, points) if name not in POINTS_INDEPENDENT else name
            if key not in loaded:
                loaded[key] = load_dataset(name, data_dir, points)
            dataset = loaded[key]
            if dataset.is_scans:
                if SCAN_PROTOCOL in config.protocols:
                    planned.extend(_scan_plan(dataset, points, config))
                continue
            clouds = list(dataset.clouds)
            for protocol in config.protocols:
                if protocol == SCAN_PROTOCOL:
                    continue
                ranges = config.translation_ranges if protocol in PAPER_PROTOCOLS else (None,)
                for translation_range in ranges:
                    for spec in object_specs(protocol, dataset.name, clouds, points, config.trials, config.seed,
                                             translation_range):
                        cloud = dataset.clouds[spec.cloud]
                        planned.append(_Planned(spec, lambda s=spec, c=cloud: build_trial(s, c)))
            if config.paper_tables:
                for spec in paper_case_specs(dataset.name, clouds, points, config.seed):
                    cloud = dataset.clouds[spec.cloud]
                    planned.append(_Planned(spec, lambda s=spec, c=cloud: build_case_trial(s, c, data_dir)))
            if config.paper_1000_trials:
                for spec in paper_1000_specs(dataset.name, clouds, points, config.paper_1000_trials, config.seed):
                    cloud = dataset.clouds[spec.cloud]
                    planned.append(_Planned(spec, lambda s=spec, c=cloud: build_trial(s, c)))
    if not planned:
        raise InvalidInputError(
            "nothing to run: no protocol applies to these datasets (scan datasets take only scan-pairs; "
            "object datasets every other protocol)"
        )
    return planned


def _scan_plan(dataset, points: int, config: BenchConfig) -> list[_Planned]:
    from .protocols import scan_pairs

    seed = group_seeds(config.seed, SCAN_PROTOCOL, dataset.name, points, 1)[0]
    pairs = scan_pairs(dataset.scans, seed, max_points=points)
    if len(pairs) > config.trials:
        keep = np.linspace(0, len(pairs) - 1, config.trials).round().astype(int)
        pairs = [pairs[k] for k in keep]
    planned = []
    for index, trial in enumerate(pairs):
        spec = TrialSpec(f"{dataset.name}/{trial.cloud}/n{points}/{SCAN_PROTOCOL}", SCAN_PROTOCOL, dataset.name,
                         trial.cloud, seed, index, points)
        planned.append(_Planned(spec, lambda t=trial: t))
    return planned


def _work_item(planned: _Planned, runs, config: BenchConfig, threads: int | None = None) -> WorkItem:
    trial = planned.build()
    if config.init == "perturbed":
        init = perturbed_init(trial.T_target_source, trial.target, planned.spec.seed,
                              config.init_perturbation_deg, config.init_perturbation_fraction)
        label = "given"
    else:
        init, label = np.eye(4), "identity"
    return WorkItem(planned.spec, trial, tuple(runs), config.max_iterations, init, label, threads)


def _save_config(config: BenchConfig, out_dir: Path, resume: bool) -> None:
    config_path = out_dir / results.CONFIG
    if resume:
        saved = results.read_json(config_path)
        if saved is None:
            raise InvalidInputError(f"{config_path}: missing, cannot check that --resume continues the same run")
        saved_config = BenchConfig.from_dict(saved)
        changed = config.differences(saved_config)
        if changed:
            detail = "; ".join(f"{name}: saved {getattr(saved_config, name)!r}, now {getattr(config, name)!r}"
                               for name in changed)
            raise InvalidInputError(f"{config_path}: --resume needs the same configuration ({detail})")
    else:
        results.write_json(config_path, config.to_dict(), overwrite=False)
    versions_path = out_dir / results.VERSIONS
    sessions = results.read_json(versions_path) if resume else None
    sessions = (sessions if isinstance(sessions, list) else []) + [results.library_versions()]
    results.write_json(versions_path, sessions, overwrite=resume)


def _progress(total: int, enabled: bool):
    try:
        from tqdm import tqdm
    except ImportError:
        tqdm = None
    if tqdm is None or not enabled:
        return _NoBar()
    return tqdm(total=total, unit="run", desc="esmicp bench", dynamic_ncols=True, smoothing=0.05)


class _NoBar:
    def update(self, n=1):
        pass

    def close(self):
        pass


def default_workers() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def run_bench(config: BenchConfig, options: RunOptions = RunOptions()) -> BenchOutcome:
    """Run ``config`` into ``options.out_dir`` (see the module docstring).

    Raises
    ------
    InvalidInputError
        Results exist and neither ``resume`` nor ``force`` was given; ``resume`` with a different
        configuration; unknown methods; a missing dataset.
    Interrupted
        On Ctrl-C, after closing the rows file (every finished row is in it).
    """
    check_methods(config.methods)
    out_dir = Path(options.out_dir)
    results.check_folder(out_dir, resume=options.resume, force=options.force)
    planned = plan(config)  # before anything is written or replaced: a bad dataset changes nothing
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PointCloudFileError(out_dir, f"cannot create the folder: {exc.strerror or exc}") from None
    with results.folder_lock(out_dir):  # one run per folder at a time
        return _run_locked(config, options, out_dir, planned)


def _run_locked(config: BenchConfig, options: RunOptions, out_dir: Path, planned) -> BenchOutcome:
    results.prepare_folder(out_dir, resume=options.resume, force=options.force)
    _save_config(config, out_dir, options.resume)
    rows_path = out_dir / results.ROWS
    done = {row_key(row) for row in results.read_rows(rows_path)}
    runs = _runs(config)
    todo, skipped = [], 0
    for item in planned:
        remaining = [(m, s) for m, s in _runs_of(item.spec, runs, config)
                     if (item.spec.trial_id, m, s) not in done]
        skipped += len(_runs_of(item.spec, runs, config)) - len(remaining)
        if remaining:
            todo.append((item, remaining))
    total_runs = sum(len(remaining) for _, remaining in todo)
    workers = options.workers or default_workers()
    with results.RowWriter(rows_path) as writer:
        bar = _progress(total_runs, options.progress)
        try:
            if workers == 1 and options.scheduler is None:
                for item, remaining in todo:
                    _write(writer, bar, run_item(_work_item(item, remaining, config)))
            else:
                _run_dask(todo, config, options, workers, writer, bar)
        except KeyboardInterrupt as stop:
            from esmicp.interrupts import Terminated

            raise Interrupted(writer.written, rows_path, isinstance(stop, Terminated)) from None
        finally:
            bar.close()
        written = writer.written
    files = write_tables(out_dir)
    return BenchOutcome(out_dir, written, skipped, len(results.read_rows(rows_path)), files)


def _write(writer, bar, rows) -> None:
    for row in rows:
        writer.write(row)
    bar.update(len(rows))


def _run_dask(todo, config, options, workers, writer, bar) -> None:
    try:
        from dask.distributed import Client, as_completed
    except ImportError as exc:
        from esmicp.errors import MissingDependencyError

        raise MissingDependencyError(
            f"parallel runs need dask.distributed ({exc}); install it with {BENCH_HINT}, or run serially with --workers 1"
        ) from exc
    cluster = None
    if options.scheduler is None:
        # The worker processes start with Ctrl-C ignored (they inherit it): this process alone
        # handles it, closing the cluster, instead of every worker printing a traceback.
        with _sigint_ignored():
            cluster = local_cluster(workers)
        client = Client(cluster)
    else:
        from esmicp.batch import dask_client

        client = dask_client(options.scheduler)
    futures = []
    try:
        futures = [client.submit(run_item, _work_item(item, remaining, config, threads=1), pure=False)
                   for item, remaining in todo]
        for future in as_completed(futures):
            _write(writer, bar, future.result())
    except KeyboardInterrupt:
        # Closing a client whose event loop was interrupted mid-call can make distributed's own
        # cancel callback fail (a NameError inside distributed.utils.sync), which tornado logs as a
        # traceback on stderr; the interruption is reported by the caller in one line instead.
        for name in ("tornado.application", "distributed"):
            logging.getLogger(name).setLevel(logging.CRITICAL)
        raise
    finally:
        for future in futures:
            future.cancel()
        client.close(timeout=10)
        if cluster is not None:
            cluster.close(timeout=10)


#: The environment of every worker process of :func:`local_cluster`: the thread pools of the
#: libraries the methods use (OpenMP: Open3D, torch's intra-op pool; MKL; OpenBLAS) at one thread.
WORKER_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


def local_cluster(workers: int):
    """The bench's local Dask cluster: ``workers`` processes of one thread each (one task at a
    time), whose libraries also run on one thread (:data:`WORKER_ENV`): the processes share the
    cores, and a process that ran every core's worth of threads on top would oversubscribe them.
    Bound to this machine only, its status page on a free port (8787 may belong to someone else).
    Its processes log only critical errors: a task's failure reaches the bench anyway, as its
    future's exception, while at Ctrl-C a worker's heartbeat to the scheduler being closed fails,
    and at ERROR it printed that as a traceback (seen once in a CI run)."""
    from dask.distributed import LocalCluster

    return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                        dashboard_address=":0", silence_logs=logging.CRITICAL, env=WORKER_ENV)


@contextlib.contextmanager
def _sigint_ignored():
    try:
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: nothing to change
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _inside(out_dir: Path, name: str) -> Path:
    """``out_dir / name``, checked to be a plain file name that stays inside ``out_dir`` (table
    names carry row content, and a results folder may come from someone else)."""
    path = out_dir / name
    if Path(name).name != name or name in (".", "..") or "\\" in name or \
            os.path.dirname(os.path.abspath(path)) != os.path.abspath(out_dir):
        raise InvalidInputError(f"{out_dir}: refusing to write the table {name!r} outside the folder")
    return path


def write_tables(out_dir: Path) -> tuple[Path, ...]:
    """(Re)write the tables of ``out_dir`` from its rows file: they are derived, never edited."""
    from esmicp.io.atomic import atomic_write

    rows = results.read_rows(out_dir / results.ROWS)
    if not rows:
        return ()
    texts = {tables.SUMMARY_MD: tables.summary_markdown(rows), tables.SUMMARY_CSV: tables.summary_csv(rows),
             **tables.paper_tables(rows)}
    if any(tables.paper_1000_table(row) for row in rows):
        texts[tables.PAPER_1000_MD] = tables.paper_1000_markdown(rows)
        texts[tables.PAPER_1000_CSV] = tables.paper_1000_csv(rows)
    written = []
    for name, text in texts.items():
        path = _inside(out_dir, name)
        with atomic_write(path, overwrite=True, mode="w") as handle:
            handle.write(text)
        written.append(path)
    return tuple(written)


__all__ = ["BENCH_HINT", "WORKER_ENV", "BenchOutcome", "Interrupted", "PAPER_TABLE", "local_cluster", "plan", "run_bench",
           "write_tables"]
