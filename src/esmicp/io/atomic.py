"""Atomic file output: a file either appears complete at its path, or not at all."""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
from pathlib import Path

from ..errors import OutputExistsError, PointCloudFileError

logger = logging.getLogger(__name__)

__all__ = ["atomic_write"]


def _describe_os_error(exc: OSError) -> str:
    return exc.strerror or str(exc)


def _create_temporary(directory: Path, name: str) -> tuple[int, Path]:
    """Create a new, empty, exclusive temporary file in ``directory``.

    ``os.open`` with mode 0o666 lets the process umask choose the permissions, so the final file
    gets the same permissions as any ordinary new file (``tempfile.mkstemp`` would give 0o600).
    """
    for _ in range(100):
        candidate = directory / f".{name}.{secrets.token_hex(6)}.tmp"
        try:
            descriptor = os.open(
                candidate, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666
            )
        except FileExistsError:
            continue
        return descriptor, candidate
    raise FileExistsError(f"could not create a unique temporary file in {directory}")


def _fsync_directory(directory: Path) -> None:
    """Flush the directory entry of a rename to disk (best effort; not possible on every OS)."""
    try:
        descriptor = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def _publish(temporary: Path, path: Path, overwrite: bool) -> None:
    """Move the finished temporary file to ``path``."""
    if overwrite:
        os.replace(temporary, path)
        return
    # Without overwrite, a hard link is an atomic "create only if absent": it cannot clobber a
    # file that appeared at ``path`` while we were writing.
    try:
        os.link(temporary, path)
    except FileExistsError:
        raise OutputExistsError(path) from None
    except OSError:
        # Hard links are not supported here (some network / FAT file systems): check, then rename.
        if os.path.lexists(path):
            raise OutputExistsError(path) from None
        os.replace(temporary, path)
        return
    try:
        os.unlink(temporary)
    except OSError as exc:  # pragma: no cover - the output is in place, only a stray link is left
        logger.warning("could not remove temporary file %s: %s", temporary, exc)


@contextlib.contextmanager
def atomic_write(path, overwrite: bool = False, *, mode: str = "wb"):
    """Write a file atomically: yield an open temporary file, move it to ``path`` on success.

    The temporary file lives in the same directory as ``path`` (so the final rename is atomic), is
    flushed and fsynced, then moved into place only if the ``with`` block finishes without an
    exception. On any exception the temporary file is removed and ``path`` is left untouched.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file.
    overwrite : bool
        Replace an existing file at ``path``. If False and ``path`` exists,
        :class:`~esmicp.errors.OutputExistsError` is raised before anything is written.
    mode : {"wb", "w"}
        Binary, or text (UTF-8, ``"\\n"`` line endings).

    Yields
    ------
    file object
        The open temporary file to write to.

    Raises
    ------
    OutputExistsError
        ``path`` exists and ``overwrite`` is False.
    PointCloudFileError
        ``path`` is a directory, its folder does not exist, or the operating system refused a
        write (permission denied, disk full, ...).
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_write: mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    if path.is_dir():
        raise PointCloudFileError(path, "is a directory, cannot write a file there")
    if not overwrite and os.path.lexists(path):
        raise OutputExistsError(path)
    directory = path.parent
    if not directory.is_dir():
        raise PointCloudFileError(path, f"cannot write: the folder {str(directory)!r} does not exist")

    try:
        descriptor, temporary = _create_temporary(directory, path.name)
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot write: {_describe_os_error(exc)}") from None

    published = False
    try:
        try:
            if mode == "w":
                handle = os.fdopen(descriptor, "w", encoding="utf-8", newline="\n")
            else:
                handle = os.fdopen(descriptor, "wb")
        except BaseException:
            os.close(descriptor)
            raise
        with handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        _publish(temporary, path, overwrite)
        published = True
        _fsync_directory(directory)
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot write: {_describe_os_error(exc)}") from exc
    finally:
        if not published:
            try:
                os.unlink(temporary)
            except FileNotFoundError:
                pass
            except OSError as exc:  # pragma: no cover - nothing sensible left to do
                logger.warning("could not remove temporary file %s: %s", temporary, exc)
