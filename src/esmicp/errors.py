"""The library's own error types.

Every problem with user input surfaces as one of these, with a message that names the file or
argument and the problem, so that the command line can print one line and exit with status 2.
"""

from __future__ import annotations

import errno
import os


class EsmicpError(ValueError):
    """Base class of every error esmicp raises on bad input."""


class InvalidInputError(EsmicpError):
    """An argument (points, transform, sigma, ...) is malformed or degenerate."""


class PointCloudFileError(EsmicpError):
    """A point-cloud or transform file is missing, unreadable, malformed or of an unknown kind.

    The message always starts with the file's path.
    """

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):  # rebuilt from (path, problem), e.g. when a worker process sends it back
        return type(self), (self.path, self.problem)


class PointCloudFileNotFoundError(PointCloudFileError, FileNotFoundError):
    """An input file does not exist (or a part of its path is not a folder).

    Both a :class:`PointCloudFileError` (an esmicp error: the command line prints it in one line)
    and a :class:`FileNotFoundError` (``except FileNotFoundError``, ``except OSError`` catch it, as
    they catch :func:`open`'s); ``filename`` and ``errno`` (``ENOENT``) are set as
    :func:`open` sets them. The message starts with the file's path.
    """

    def __init__(self, path, problem: str = "no such file"):
        super().__init__(path, problem)
        self.errno = errno.ENOENT
        self.strerror = os.strerror(errno.ENOENT)
        self.filename = self.path

    def __str__(self) -> str:
        return f"{self.path}: {self.problem}"


class OutputExistsError(EsmicpError):
    """An output path already exists and overwriting was not requested."""

    def __init__(self, path):
        self.path = str(path)
        super().__init__(f"{self.path}: already exists (pass --force / overwrite=True to replace it)")


class MissingDependencyError(EsmicpError):
    """An optional library (a baseline's, Dask, matplotlib, plotly) is not installed or fails to
    import; the message says how to install it."""


class PoolError(EsmicpError):
    """The worker processes of a pool (``processes=``) could not run the jobs: they could not
    start (a script read from standard input, an unguarded script that they re-run), or one ended
    abruptly."""


class EsmicpWarning(UserWarning):
    """Base class of the warnings esmicp emits."""


class NonFinitePointsWarning(EsmicpWarning):
    """Some points had NaN or infinite coordinates and were dropped."""


class CoincidentPointsWarning(EsmicpWarning):
    """A large share of a cloud's points are exact copies of other points (repeated points, or a
    depth sensor's invalid pixels stored as (0, 0, 0))."""


class IndexAlignmentWarning(EsmicpWarning):
    """`esm-paper` was run on clouds that cannot be index-aligned (different sizes)."""
