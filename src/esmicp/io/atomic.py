"""Atomic file output: a file either appears complete at its path, or not at all.

Where the system allows it (Linux, ``O_TMPFILE``), the data is written to an *unnamed* file in the
destination's folder, which is given its name (``linkat``, with ``AT_EMPTY_PATH`` or through
``/proc/self/fd``) only once it is complete and flushed. A process killed while writing, even by SIGKILL, then leaves nothing
behind: the kernel frees an unnamed file with its last descriptor. Replacing an existing file
links the finished data under a hidden temporary name and renames it over the old one; only a
kill in the microseconds between those two calls could leave that complete hidden file. Elsewhere,
the data goes to a hidden named temporary file (``.<name>.<random>.tmp``), removed on any
exception, Ctrl-C included; only a kill that Python cannot intercept (SIGKILL, a power cut) could
leave it.
"""

from __future__ import annotations

import contextlib
import errno
import functools
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


#: Devices on which an unnamed file could not be given a name (so the named temporary file is used).
_UNNAMED_UNSUPPORTED: set[int] = set()

_AT_FDCWD = -100
_AT_EMPTY_PATH = 0x1000


def _create_unnamed(directory: Path) -> int | None:
    """An unnamed file in ``directory`` (Linux ``O_TMPFILE``), or None where that is not possible."""
    flag = getattr(os, "O_TMPFILE", None)
    if flag is None:
        return None
    try:
        if directory.stat().st_dev in _UNNAMED_UNSUPPORTED:
            return None
        return os.open(directory, flag | os.O_RDWR, 0o666)
    except OSError:  # EOPNOTSUPP, EISDIR (old kernels), EINVAL (some file systems), ...
        return None


@functools.lru_cache(maxsize=1)
def _libc_linkat():
    try:
        import ctypes
        import ctypes.util

        function = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True).linkat
    except (ImportError, OSError, AttributeError, TypeError):  # pragma: no cover - not glibc / musl
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_int]
    return function


def _link_descriptor(descriptor: int, destination: Path) -> None:
    """Give the open unnamed file ``descriptor`` the name ``destination``.

    ``linkat(fd, "", AT_EMPTY_PATH)`` where permitted (it needs CAP_DAC_READ_SEARCH), else the
    documented ``/proc/self/fd/<fd>`` link. Raises FileExistsError when ``destination`` exists,
    another OSError when the system allows neither.
    """
    linkat = _libc_linkat()
    if linkat is not None:
        import ctypes

        if linkat(descriptor, b"", _AT_FDCWD, os.fsencode(destination), _AT_EMPTY_PATH) == 0:
            return
        code = ctypes.get_errno()
        if code == errno.EEXIST:
            raise FileExistsError(code, os.strerror(code), str(destination))
    os.link(f"/proc/self/fd/{descriptor}", destination, follow_symlinks=True)


def _publish_unnamed(descriptor: int, path: Path, overwrite: bool) -> None:
    """Give the finished unnamed file its name (atomically; never clobbering without overwrite)."""
    try:
        _link_descriptor(descriptor, path)
        return
    except FileExistsError:
        if not overwrite:
            raise OutputExistsError(path) from None
    # Replace the existing file: a hidden name first, then an atomic rename over the old file.
    for _ in range(100):
        temporary = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
        try:
            _link_descriptor(descriptor, temporary)
        except FileExistsError:
            continue
        try:
            os.replace(temporary, path)
        except BaseException:
            os.unlink(temporary)
            raise
        return
    raise FileExistsError(f"could not create a unique temporary file in {path.parent}")


def _copy_to_named(descriptor: int, directory: Path, name: str) -> Path:
    """Copy the unnamed file's content to a new named temporary file (flushed); return its path."""
    target, temporary = _create_temporary(directory, name)
    try:
        offset = 0
        while True:
            chunk = os.pread(descriptor, 1 << 20, offset)
            if not chunk:
                break
            view = memoryview(chunk)
            while view:
                written = os.write(target, view)
                view = view[written:]
            offset += len(chunk)
        os.fsync(target)
    except BaseException:
        os.close(target)
        os.unlink(temporary)
        raise
    os.close(target)
    return temporary


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
    exception. On any exception the temporary file is removed and ``path`` is left untouched. On
    Linux the temporary file has no name at all until it is complete (see the module docstring), so
    that even a killed process leaves nothing behind.

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
        descriptor = _create_unnamed(directory)
        temporary = None
        if descriptor is None:
            descriptor, temporary = _create_temporary(directory, path.name)
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot write: {_describe_os_error(exc)}") from None

    # Replacing a file keeps its permission bits (a mode-600 output stays 600 under --force).
    try:
        replaced_mode = os.stat(path).st_mode & 0o7777 if overwrite else None
    except OSError:
        replaced_mode = None
    published = False
    try:
        if replaced_mode is not None and hasattr(os, "fchmod"):
            os.fchmod(descriptor, replaced_mode)
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
            if temporary is None:  # named while still open: the name refers to the descriptor
                try:
                    _publish_unnamed(handle.fileno(), path, overwrite)
                except OutputExistsError:
                    raise
                except OSError:
                    # This file system / mount cannot name an unnamed file (EXDEV through /proc in
                    # some containers and VMs): copy it to a named temporary file, and use named
                    # ones directly from now on.
                    _UNNAMED_UNSUPPORTED.add(directory.stat().st_dev)
                    temporary = _copy_to_named(handle.fileno(), directory, path.name)
        if temporary is not None:
            _publish(temporary, path, overwrite)
        published = True
        _fsync_directory(directory)
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot write: {_describe_os_error(exc)}") from exc
    finally:
        if not published and temporary is not None:
            try:
                os.unlink(temporary)
            except FileNotFoundError:
                pass
            except OSError as exc:  # pragma: no cover - nothing sensible left to do
                logger.warning("could not remove temporary file %s: %s", temporary, exc)
