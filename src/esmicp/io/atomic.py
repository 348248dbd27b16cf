"""Atomic file output: a file appears complete at its path, or not at all; several files appear
together, or none; and what is not a regular file is never replaced.

Where the system allows it (Linux, ``O_TMPFILE``), the data is written to an *unnamed* file in the
destination's folder, which is given its name (``linkat``, with ``AT_EMPTY_PATH`` or through
``/proc/self/fd``) only once it is complete and flushed. A process killed while writing, even by SIGKILL, then leaves nothing
behind: the kernel frees an unnamed file with its last descriptor. Replacing an existing file
links the finished data under a hidden temporary name and renames it over the old one; only a
kill in the microseconds between those two calls could leave that complete hidden file. Elsewhere,
the data goes to a hidden named temporary file (``.<name>.<random>.tmp``), removed on any
exception, Ctrl-C included; only a kill that Python cannot intercept (SIGKILL, a power cut) could
leave it.

What an output path may name (:func:`output_target` decides, before anything is written):

- nothing yet: the file is created;
- a regular file, or a symbolic link to one: refused unless ``overwrite``; with it, the file is
  replaced (through a link: the file the link points to is replaced, the link stays);
- a stream, named explicitly: ``/dev/stdout``, ``/dev/stderr``, ``/dev/fd/N`` or
  ``/proc/self/fd/N`` (this process's open descriptor N), or ``/dev/null``: written through, with
  no temporary file and no rename, once the data is complete (:data:`STREAM_PATHS`);
- anything else (a directory, a FIFO, a character or block device, a socket, a dangling symbolic
  link, a link to any of these): refused, with or without ``overwrite``, since the final rename
  would replace it with a regular file.

:func:`published_together` publishes several outputs as one: inside it, each :func:`atomic_write`
of the same thread finishes its temporary file but does not name it; when the block ends, every
file is named in one step (Ctrl-C and SIGTERM deferred for those few system calls, the files
already named removed, or the replaced ones restored, if one fails), then the streams are
written. If the block raises, no file is named. Restoring uses a hidden hard link to each file
being replaced (``.<name>.<random>.old``), removed once the set is named: only a kill during those
system calls could leave one.
"""

from __future__ import annotations

import codecs
import contextlib
import contextvars
import errno
import functools
import logging
import os
import re
import secrets
import signal
import stat
import sys
import tempfile
import threading
from pathlib import Path

from ..errors import OutputExistsError, PointCloudFileError

logger = logging.getLogger(__name__)

__all__ = ["STREAM_PATHS", "atomic_write", "is_stream", "output_target", "published_together", "recording_outputs"]

#: Output paths written through rather than replaced: the process's standard streams, the null
#: device, and ``/dev/fd/N`` / ``/proc/self/fd/N`` (any open descriptor N, e.g. a shell's process
#: substitution). Recognised by name, as given (normalised), not by what they resolve to.
STREAM_PATHS = ("/dev/stdout", "/dev/stderr", "/dev/null", "/dev/fd/N", "/proc/self/fd/N")

_NAMED_STREAMS = {"/dev/stdout": 1, "/dev/stderr": 2, "/dev/null": None}
_DESCRIPTOR_PATH = re.compile(r"^/(?:dev/fd|proc/self/fd)/(\d+)$")

#: The set of outputs :func:`published_together` is gathering in this context, if any.
_GATHERING: contextvars.ContextVar["_OutputSet | None"] = contextvars.ContextVar("esmicp_outputs", default=None)
#: The list :func:`recording_outputs` fills with each output as it is published, if any.
_RECORD: contextvars.ContextVar["list[str] | None"] = contextvars.ContextVar("esmicp_published", default=None)


def _describe_os_error(exc: OSError) -> str:
    return exc.strerror or str(exc)


def _stream_name(path) -> str | None:
    """The normalised stream name ``path`` is (see :data:`STREAM_PATHS`), or None."""
    text = os.fspath(path)
    if isinstance(text, bytes) or not text.startswith("/"):
        return None
    text = os.path.normpath(text)
    if text in _NAMED_STREAMS or _DESCRIPTOR_PATH.match(text):
        return text
    return None


def is_stream(path) -> bool:
    """True when ``path`` names a stream that outputs are written through (:data:`STREAM_PATHS`)."""
    return _stream_name(path) is not None


def _stream_descriptor(name: str) -> int | None:
    """The descriptor a stream name writes to (None: the null device, nothing to write)."""
    if name in _NAMED_STREAMS:
        return _NAMED_STREAMS[name]
    return int(_DESCRIPTOR_PATH.match(name).group(1))


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


#: How to write to a stream instead, for the refusals.
_STREAM_HINT = "for standard output give /dev/stdout, or - on the command line"


def output_target(path, overwrite: bool) -> Path | None:
    """Where an output named ``path`` is written: the regular file to create or replace, or None
    for a stream (:func:`is_stream`), which is written through.

    Checks, without creating anything, what ``path`` names now (see the module docstring).

    Raises
    ------
    OutputExistsError
        ``path`` is a regular file (or a link to one) and ``overwrite`` is False.
    PointCloudFileError
        ``path`` is a directory, a FIFO, a device, a socket, a dangling symbolic link or a link
        to something other than a regular file (with or without ``overwrite``), or its folder
        does not exist.
    """
    if _stream_name(path) is not None:
        return None
    path = Path(path)
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        info = None
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot write: {_describe_os_error(exc)}") from None
    target = path
    if info is not None and stat.S_ISLNK(info.st_mode):
        try:
            resolved = os.stat(path)
        except FileNotFoundError:
            raise PointCloudFileError(path, f"is a dangling symbolic link (to {os.readlink(path)!r}); remove it "
                                      "or give another output path") from None
        except OSError as exc:
            raise PointCloudFileError(path, f"cannot write through this symbolic link: {_describe_os_error(exc)}") from None
        if not stat.S_ISREG(resolved.st_mode):
            raise PointCloudFileError(
                path, f"is a symbolic link to {_kind(resolved.st_mode)} ({os.path.realpath(path)}), not to a regular "
                f"file: it is not replaced, even with --force / overwrite; {_STREAM_HINT}")
        target = Path(os.path.realpath(path))
        info = resolved
    if info is not None:
        if stat.S_ISDIR(info.st_mode):
            raise PointCloudFileError(path, "is a directory, cannot write a file there")
        if not stat.S_ISREG(info.st_mode):
            raise PointCloudFileError(
                path, f"is {_kind(info.st_mode)}, not a regular file: it is not replaced, even with --force / "
                f"overwrite; {_STREAM_HINT}")
        if not overwrite:
            raise OutputExistsError(path)
    if not target.parent.is_dir():
        raise PointCloudFileError(path, f"cannot write: the folder {str(target.parent)!r} does not exist")
    return target


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


def _hidden_name(path: Path, suffix: str) -> Path:
    return path.parent / f".{path.name}.{secrets.token_hex(6)}.{suffix}"


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
        temporary = _hidden_name(path, "tmp")
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


def _remove(path: Path | None) -> None:
    if path is None:
        return
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    except OSError as exc:  # pragma: no cover - nothing sensible left to do
        logger.warning("could not remove temporary file %s: %s", path, exc)


class _Staged:
    """One output of a set: its finished data in a temporary file beside its target (or, for a
    stream, in an anonymous temporary file), not yet published."""

    def __init__(self, path: Path, overwrite: bool):
        self.path = path
        self.overwrite = overwrite
        self.stream = _stream_name(path)
        self.target = output_target(path, overwrite)
        self.descriptor: int | None = None  # the unnamed file (or, for a stream, the anonymous one)
        self.temporary: Path | None = None  # the named temporary file
        self.backup: Path | None = None  # a hard link to the file being replaced, until the set is published
        self.created = False  # published where nothing was

    def create(self) -> int:
        """Open the temporary file; return its descriptor (owned by this object)."""
        try:
            if self.stream is not None:
                self.descriptor = _anonymous_file()
                return self.descriptor
            directory = self.target.parent
            self.descriptor = _create_unnamed(directory)
            if self.descriptor is None:
                self.descriptor, self.temporary = _create_temporary(directory, self.target.name)
        except OSError as exc:
            raise PointCloudFileError(self.path, f"cannot write: {_describe_os_error(exc)}") from None
        # Replacing a file keeps its permission bits (a mode-600 output stays 600 under --force).
        if self.overwrite and hasattr(os, "fchmod"):
            try:
                os.fchmod(self.descriptor, os.stat(self.target).st_mode & 0o7777)
            except FileNotFoundError:
                pass
        return self.descriptor

    def finish(self) -> None:
        """Flush the finished data to disk (before it is named)."""
        if self.stream is not None:
            return
        os.fsync(self.descriptor)

    def publish(self, keep_backup: bool) -> None:
        """Name the finished file (``keep_backup``: a hard link to the file it replaces is kept
        until :meth:`commit`, so that :meth:`undo` can restore it)."""
        target = output_target(self.path, self.overwrite)  # what the path names may have changed
        if target != self.target:
            raise PointCloudFileError(self.path, "changed while the output was being written; nothing was replaced")
        existed = os.path.lexists(target)
        if existed and keep_backup:
            backup = _hidden_name(target, "old")
            try:
                os.link(target, backup)
                self.backup = backup
            except OSError:  # no hard links here: this file cannot be restored if a later one fails
                self.backup = None
        try:
            self._name(target)
        except BaseException:
            self.commit()  # the old file was not replaced: its extra link goes
            raise
        self.created = not existed

    def _name(self, target: Path) -> None:
        if self.temporary is None:
            try:
                _publish_unnamed(self.descriptor, target, self.overwrite)
            except OutputExistsError:
                raise
            except OSError:
                # This file system / mount cannot name an unnamed file (EXDEV through /proc in
                # some containers and VMs): copy it to a named temporary file, and use named
                # ones directly from now on.
                _UNNAMED_UNSUPPORTED.add(target.parent.stat().st_dev)
                self.temporary = _copy_to_named(self.descriptor, target.parent, target.name)
        if self.temporary is not None:
            _publish(self.temporary, target, self.overwrite)
            self.temporary = None

    def undo(self) -> None:
        """Take back a publication (the set it belongs to failed)."""
        if self.backup is not None:
            os.replace(self.backup, self.target)
            self.backup = None
        elif self.created:
            _remove(self.target)

    def commit(self) -> None:
        _remove(self.backup)
        self.backup = None

    def write_through(self) -> None:
        """Copy the finished data to the stream (standard output and error: through ``sys.stdout``
        and ``sys.stderr``, so that they stay in order with what the program prints there)."""
        number = _stream_descriptor(self.stream)
        if number is None:
            return
        handle = {1: sys.stdout, 2: sys.stderr}.get(number)
        text = codecs.getincrementaldecoder("utf-8")("replace")
        offset = 0
        while True:
            chunk = os.pread(self.descriptor, 1 << 20, offset)
            if not chunk:
                break
            offset += len(chunk)
            if handle is None:
                view = memoryview(chunk)
                while view:
                    view = view[os.write(number, view):]
            elif hasattr(handle, "buffer"):
                handle.flush()
                handle.buffer.write(chunk)
            else:  # a text stream without bytes underneath (io.StringIO)
                handle.write(text.decode(chunk))
        if handle is not None:
            handle.flush()

    def discard(self) -> None:
        if self.descriptor is not None:
            with contextlib.suppress(OSError):
                os.close(self.descriptor)
            self.descriptor = None
        _remove(self.temporary)
        self.temporary = None


def _anonymous_file() -> int:
    """A new anonymous temporary file (no name anywhere), as a descriptor the caller closes."""
    handle = tempfile.TemporaryFile()
    descriptor = os.dup(handle.fileno())
    handle.close()
    return descriptor


class _OutputSet:
    """The outputs :func:`published_together` gathers."""

    def __init__(self):
        self.staged: list[_Staged] = []

    def remove(self, staged: _Staged) -> None:
        if staged in self.staged:
            self.staged.remove(staged)
        staged.discard()

    def add(self, staged: _Staged) -> None:
        for other in self.staged:
            if staged.target is not None and other.target == staged.target:
                raise PointCloudFileError(staged.path, f"is the same file as the output {other.path} of this run")
        self.staged.append(staged)

    def discard(self) -> None:
        for staged in self.staged:
            staged.discard()
        self.staged.clear()

    def publish(self) -> None:
        files = [staged for staged in self.staged if staged.stream is None]
        streams = [staged for staged in self.staged if staged.stream is not None]
        record = _RECORD.get()
        try:
            with _signals_deferred():
                done: list[_Staged] = []
                try:
                    for staged in files:
                        try:
                            staged.publish(keep_backup=len(files) > 1)
                        except OSError as exc:
                            raise PointCloudFileError(staged.path, f"cannot write: {_describe_os_error(exc)}") from exc
                        done.append(staged)
                except BaseException:
                    for staged in reversed(done):
                        try:
                            staged.undo()
                        except OSError as exc:  # pragma: no cover - the file system failed twice
                            logger.warning("could not take back %s: %s", staged.target, exc)
                    raise
                for staged in done:
                    staged.commit()
                if record is not None:
                    record.extend(str(staged.path) for staged in done)
            for directory in {staged.target.parent for staged in files}:
                _fsync_directory(directory)
            for staged in streams:
                if record is not None:
                    record.append(str(staged.path))
                try:
                    staged.write_through()
                except BrokenPipeError:
                    raise
                except OSError as exc:
                    raise PointCloudFileError(staged.path, f"cannot write: {_describe_os_error(exc)}") from exc
        finally:
            self.discard()


@contextlib.contextmanager
def _signals_deferred():
    """Ctrl-C (SIGINT) and SIGTERM held back while the block runs (in the main thread, where
    Python runs signal handlers; elsewhere nothing is changed), then handled as they would have
    been. For the few system calls that publish a set of outputs, which must all happen or none."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = {}
    for number in (signal.SIGINT, getattr(signal, "SIGTERM", None)):
        if number is None:
            continue
        handler = signal.getsignal(number)
        if handler is None or handler == signal.SIG_IGN:  # installed outside Python, or ignored: left alone
            continue
        previous[number] = handler
        signal.signal(number, lambda received, frame: caught.append(received))
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
    for number in dict.fromkeys(caught):
        handler = previous[number]
        if handler == signal.SIG_DFL:
            os.kill(os.getpid(), number)
        else:
            handler(number, None)


@contextlib.contextmanager
def published_together():
    """Publish every output written (with :func:`atomic_write`, by this thread) inside the block at
    once when it ends: all of them, or, if the block raises or a publication fails, none.

    The files are named in one step at the end, Ctrl-C and SIGTERM deferred meanwhile; when one
    cannot be named, those already named are removed again, or, where one replaced an older file,
    that file is restored (where the file system has hard links). Streams (:data:`STREAM_PATHS`)
    are written after the files. Nested blocks join the outermost one.
    """
    if _GATHERING.get() is not None:
        yield
        return
    outputs = _OutputSet()
    token = _GATHERING.set(outputs)
    try:
        yield
    except BaseException:
        outputs.discard()
        raise
    finally:
        _GATHERING.reset(token)
    outputs.publish()


@contextlib.contextmanager
def recording_outputs():
    """Yield a list that every output published (by this thread) inside the block is appended to,
    as it is published: for a message that says truly what an interrupted run wrote."""
    written: list[str] = []
    token = _RECORD.set(written)
    try:
        yield written
    finally:
        _RECORD.reset(token)


@contextlib.contextmanager
def atomic_write(path, overwrite: bool = False, *, mode: str = "wb"):
    """Write a file atomically: yield an open temporary file, move it to ``path`` on success.

    The temporary file lives in the same directory as ``path`` (so the final rename is atomic), is
    flushed and fsynced, then moved into place only if the ``with`` block finishes without an
    exception. On any exception the temporary file is removed and ``path`` is left untouched. On
    Linux the temporary file has no name at all until it is complete (see the module docstring), so
    that even a killed process leaves nothing behind. Inside :func:`published_together`, the file
    is named when that block ends, with the others.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file: a new file, an existing regular file (or a link to one), or a stream
        (:data:`STREAM_PATHS`), written through once the block ends.
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
        ``path`` is a directory, a FIFO, a device, a socket or a dangling symbolic link (never
        replaced, see :func:`output_target`), its folder does not exist, or the operating system
        refused a write (permission denied, disk full, ...).
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_write: mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    outputs = _GATHERING.get()
    if outputs is None:  # on its own: a set of one, published when the block ends
        with published_together(), atomic_write(path, overwrite, mode=mode) as handle:
            yield handle
        return
    staged = _Staged(path, overwrite)
    outputs.add(staged)
    try:
        descriptor = staged.create()
        if mode == "w":
            handle = open(descriptor, "w", encoding="utf-8", newline="\n", closefd=False)
        else:
            handle = open(descriptor, "wb", closefd=False)
        with handle:
            yield handle
            handle.flush()
        staged.finish()
    except BaseException as exc:
        outputs.remove(staged)  # a failed output is never published with the others
        if isinstance(exc, OSError) and not isinstance(exc, BrokenPipeError):
            raise PointCloudFileError(path, f"cannot write: {_describe_os_error(exc)}") from exc
        raise
