"""Result files: rows appended one line at a time (JSON Lines), flushed and synced per row, so an
interrupted run loses no finished row; the resolved configuration and the library versions beside
them.

Files in a run's folder (:data:`ROWS`, :data:`CONFIG`, :data:`VERSIONS`; tables by
:mod:`esmicp_lab.bench.tables`). A row is written with one ``write`` of one whole line on a file
opened for appending; a line cut short by a crash (no final newline) is ignored when reading and
removed before appending again.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import sys
from pathlib import Path

from esmicp.errors import InvalidInputError, PointCloudFileError

ROWS = "rows.jsonl"
CONFIG = "config.json"
VERSIONS = "versions.json"

#: Distributions whose versions are saved beside every result (when installed).
VERSIONED = ("esmicp", "numpy", "scipy", "open3d-cpu", "open3d", "small-gicp", "kiss-matcher", "probreg",
             "py-goicp", "torch", "dask", "distributed", "tqdm")


def library_versions() -> dict:
    """Python, platform, CPU count and the installed versions of :data:`VERSIONED` (None: absent)."""
    from importlib import metadata

    versions = {}
    for name in VERSIONED:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {"python": sys.version.split()[0], "platform": platform.platform(), "cpu_count": os.cpu_count(),
            "packages": versions}


def row_key(row: dict) -> tuple:
    """What identifies a row for ``--resume``: (trial_id, method, sigma)."""
    sigma = row.get("sigma")
    return (row["trial_id"], row["method"], None if sigma is None else float(sigma))


def _unique(rows: list) -> list:
    """The first row of each key, in file order (two runs that appended the same trials, as two
    ``--resume`` sessions did before the folder lock, count once)."""
    seen, unique = set(), []
    for row in rows:
        try:
            key = row_key(row)
        except (TypeError, KeyError, ValueError, AttributeError):
            unique.append(row)  # not a well-formed row: left for the caller's checks
            continue
        if key not in seen:
            seen.add(key)
            unique.append(row)
    return unique


def read_rows(path) -> list[dict]:
    """Every complete row of a rows file, in file order (a torn last line is skipped); a row whose
    key (:func:`row_key`) appeared before is dropped."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return []
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot read: {exc.strerror or exc}") from None
    lines = data.split(b"\n")
    complete = lines[:-1]  # the part after the last newline is empty or torn
    rows = []
    for number, line in enumerate(complete, start=1):
        if not line.strip():
            continue
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise PointCloudFileError(path, f"line {number} is not a JSON row ({exc.msg})") from None
        except UnicodeDecodeError:
            raise PointCloudFileError(path, f"line {number} is not UTF-8 text") from None
    return _unique(rows)


class RowWriter:
    """Appends rows to a rows file; each row is on disk (flushed, fsynced) when :meth:`write` returns."""

    def __init__(self, path):
        self.path = Path(path)
        _drop_torn_tail(self.path)
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        except OSError as exc:
            raise PointCloudFileError(self.path, f"cannot write: {exc.strerror or exc}") from None
        self.written = 0

    def write(self, row: dict) -> None:
        line = (json.dumps(row, allow_nan=False, separators=(",", ":")) + "\n").encode("utf-8")
        view = memoryview(line)
        while view:  # one write for a regular file; the loop only guards against short writes
            view = view[os.write(self._fd, view):]
        os.fsync(self._fd)
        self.written += 1

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _drop_torn_tail(path: Path) -> None:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return
    if data and not data.endswith(b"\n"):
        with open(path, "r+b") as handle:
            handle.truncate(data.rfind(b"\n") + 1)


LOCK = ".esmicp-bench.lock"


@contextlib.contextmanager
def folder_lock(out_dir: Path):
    """Hold an exclusive lock on a results folder for the duration of a run.

    A second run on the same folder (two ``--resume`` in two terminals) is refused at once instead
    of running the same trials again. The lock is an ``flock`` on :data:`LOCK` inside the folder:
    the system releases it when the process ends, however it ends (no stale lock after a kill).
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        yield
        return
    path = Path(out_dir) / LOCK
    try:
        descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot create the folder lock: {exc.strerror or exc}") from None
    try:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InvalidInputError(
                f"{out_dir}: another esmicp bench is running on this folder (it holds {path}); wait for it "
                "to finish, or give another --out"
            ) from None
        yield
    finally:
        os.close(descriptor)  # releases the lock


def write_json(path: Path, data, *, overwrite: bool) -> None:
    from esmicp.io.atomic import atomic_write

    with atomic_write(path, overwrite=overwrite, mode="w") as handle:
        json.dump(data, handle, indent=2, sort_keys=True)
        handle.write("\n")


def read_json(path: Path):
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise PointCloudFileError(path, f"cannot read the saved configuration ({exc})") from None


def check_folder(out_dir: Path, *, resume: bool, force: bool) -> None:
    """Refuse (changing nothing) a folder holding results unless ``resume`` or ``force``; refuse
    ``resume`` where there is nothing to resume."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InvalidInputError(f"{out_dir}: exists and is not a folder")
    rows = out_dir / ROWS
    if out_dir.is_dir():
        from esmicp.io.atomic import output_target

        for name in (ROWS, CONFIG, VERSIONS):  # never opened if a FIFO, a device or a dangling link
            output_target(out_dir / name, overwrite=True)
    if resume and not rows.exists():
        raise InvalidInputError(f"{rows}: nothing to resume (no rows file); run without --resume")
    existing = [p for p in (rows, out_dir / CONFIG) if p.exists()]
    if existing and not (resume or force):
        raise InvalidInputError(
            f"{existing[0]}: already exists (pass --resume to continue that run, or --force to replace it)"
        )


def prepare_folder(out_dir: Path, *, resume: bool, force: bool) -> None:
    """Create ``out_dir``; refuse a folder holding results unless ``resume`` or ``force`` (which
    removes the previous run's files: rows, configuration, versions and tables)."""
    check_folder(out_dir, resume=resume, force=force)
    out_dir = Path(out_dir)
    if resume:
        return
    rows = out_dir / ROWS
    if force:
        from .tables import TABLE_FILES_GLOB

        tables = [path for pattern in TABLE_FILES_GLOB for path in out_dir.glob(pattern)]
        for path in [rows, out_dir / CONFIG, out_dir / VERSIONS, *tables]:
            if path.is_file():
                path.unlink()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PointCloudFileError(out_dir, f"cannot create the folder: {exc.strerror or exc}") from None
