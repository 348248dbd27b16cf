"""Argument types shared by the ``esmicp`` subcommands: each turns a flag's text into a checked
value, or raises :class:`argparse.ArgumentTypeError` with a one-line reason."""

from __future__ import annotations

import argparse
import math


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


def add_workers(parser, default: str = "every core") -> None:
    """Add ``--workers N`` to a subcommand's parser: the threads of every compiled kernel of its
    registrations (``workers=`` of :func:`esmicp.register`; None when absent: the library's
    default, which ``default`` describes in the help)."""
    parser.add_argument(
        "--workers", type=positive_int, metavar="N",
        help=f"threads of each registration's compiled kernels (default: {default})",
    )


#: Exit statuses of every ``esmicp`` command.
EXIT_OK = 0
EXIT_FAILED = 1  # ``esmicp demo``: the transform was not recovered
EXIT_BAD_INPUT = 2
EXIT_UNTRUSTED = 3  # ``esmicp register --min-confidence``: the pose is below the bar, or ambiguous
EXIT_INTERRUPTED = 130


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line (and exit status 2)."""

    def error(self, message):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")
