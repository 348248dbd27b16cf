"""Argument types shared by the ``esmicp`` subcommands: each turns a flag's text into a checked
value, or raises :class:`argparse.ArgumentTypeError` with a one-line reason."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Iterable, Mapping


def whole_number(minimum: int):
    """A parser of whole numbers >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {text!r}")
        return value

    return parse


#: Whole numbers >= 1 (counts, iterations, points).
positive_int = whole_number(1)
#: Whole numbers >= 0.
nonnegative_int = whole_number(0)


def positive_float(text: str) -> float:
    """A finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


#: What ``-`` means as an output path: standard output, written through (esmicp.io.atomic).
STANDARD_OUTPUT = "/dev/stdout"


def output_path(text: str) -> Path:
    """An output file argument: ``-`` is standard output (:data:`STANDARD_OUTPUT`), written through."""
    return Path(STANDARD_OUTPUT if text == "-" else text)


def add_workers(parser, default: str = "every core") -> None:
    """Add ``--workers N`` to a subcommand's parser: the threads of every compiled kernel of its
    registrations (``workers=`` of :func:`esmicp.register`; None when absent: the library's
    default, which ``default`` describes in the help)."""
    parser.add_argument(
        "--workers", type=positive_int, metavar="N",
        help=f"threads of each registration's compiled kernels (default: {default})",
    )


def same_file(path: Path, other: Path) -> bool:
    """True when ``path`` and ``other`` name one file: the same path once made absolute with its
    symbolic links resolved, or, when both exist, the same file on disk (a hard link, a bind mount)."""
    if os.path.realpath(path) == os.path.realpath(other):
        return True
    try:
        return os.path.samefile(path, other)
    except OSError:  # one of them does not exist (yet)
        return False


def check_distinct_files(outputs: Mapping[str, Path | None], inputs: Iterable[Path] = ()) -> None:
    """Refuse, before any work, two outputs that are one file (the second would replace the
    first) and an output that is one of the ``inputs`` (it would replace that input, ``--force`` or
    not). ``outputs`` maps each output flag (``"--output"``) to its path, None when not given
    (``/dev/null`` is never refused).

    Raises
    ------
    InvalidInputError
        One line naming both flags / files.
    """
    from ..errors import InvalidInputError

    # /dev/null takes any number of outputs
    given = [(flag, path) for flag, path in outputs.items() if path is not None and os.path.normpath(path) != os.devnull]
    for index, (flag, path) in enumerate(given):
        for source in inputs:
            if same_file(path, source):
                raise InvalidInputError(f"{flag} {path}: is the input file {source}; writing it would replace "
                                        "that input (even with --force): give another output file")
        for other_flag, other in given[index + 1:]:
            if same_file(path, other):
                raise InvalidInputError(f"{other_flag} {other}: is the same file as {flag} {path}; "
                                        "give two different files")


#: Exit statuses of every ``esmicp`` command.
EXIT_OK = 0
EXIT_FAILED = 1  # ``esmicp demo``: the transform was not recovered
EXIT_BAD_INPUT = 2
EXIT_UNTRUSTED = 3  # ``esmicp register --min-confidence``: the pose is below the bar, or ambiguous
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143  # SIGTERM (128 + 15), handled as Ctrl-C is: the unfinished outputs removed
EXIT_BROKEN_PIPE = 141  # the reader of the output closed it (128 + SIGPIPE, what a shell reports for Unix tools)


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line (and exit status 2)."""

    def error(self, message):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")
