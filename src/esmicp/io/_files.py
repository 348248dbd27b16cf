"""Checks of file arguments shared by the readers and writers (``esmicp.io``, its transform and
Stanford ``.conf`` readers)."""

from __future__ import annotations

import stat
from pathlib import Path

from ..errors import InvalidInputError, PointCloudFileError, PointCloudFileNotFoundError


def as_path(path) -> Path:
    """``path`` as a :class:`~pathlib.Path`, or one clear error."""
    try:
        return Path(path)
    except TypeError:
        raise InvalidInputError(f"expected a file path, got {path!r}") from None


def check_input_file(path: Path) -> None:
    """Refuse a missing, non-regular, empty or unreadable input file, in plain words (a missing one
    with :class:`~esmicp.errors.PointCloudFileNotFoundError`, also a :class:`FileNotFoundError`)."""
    try:
        info = path.stat()
    except FileNotFoundError:
        raise PointCloudFileNotFoundError(path) from None
    except NotADirectoryError:
        raise PointCloudFileNotFoundError(path, "no such file (a part of the path is not a folder)") from None
    except PermissionError:
        raise PointCloudFileError(path, "permission denied") from None
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot access: {exc.strerror or exc}") from None
    if stat.S_ISDIR(info.st_mode):
        raise PointCloudFileError(path, "is a directory, not a file")
    if not stat.S_ISREG(info.st_mode):
        raise PointCloudFileError(path, "is not a regular file")
    if info.st_size == 0:
        raise PointCloudFileError(path, "file is empty")
    try:
        with open(path, "rb"):
            pass
    except PermissionError:
        raise PointCloudFileError(path, "permission denied (the file is not readable)") from None
    except OSError as exc:
        raise PointCloudFileError(path, f"cannot open: {exc.strerror or exc}") from None
