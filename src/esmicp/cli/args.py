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
EXIT_PARTIAL = 3  # ``esmicp merge``: a scan is doubtful or unplaced (the placed scans are written)
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143  # SIGTERM (128 + 15), handled as Ctrl-C is: the unfinished outputs removed
EXIT_BROKEN_PIPE = 141  # the reader of the output closed it (128 + SIGPIPE, what a shell reports for Unix tools)

#: Every exit status, the one place they are described: ``(status, commands, meaning)``, with
#: ``commands`` None for every command not named in another row of that status. The ``--help``
#: epilogs (:func:`exit_status_epilog`) and the command-line reference page are generated from it.
EXIT_STATUSES: tuple[tuple[int, tuple[str, ...] | None, str], ...] = (
    (EXIT_OK, ("register",), "done, whatever the verdict it prints first (with --min-confidence, a pose in doubt "
     "exits 3)"),
    (EXIT_OK, ("merge",), "done, every scan placed (or --allow-partial given)"),
    (EXIT_OK, None, "done"),
    (EXIT_FAILED, ("demo",), "the transform was not recovered"),
    (EXIT_BAD_INPUT, None, "bad input: one line on stderr naming the file or argument; nothing written"),
    (EXIT_UNTRUSTED, ("register",), "with --min-confidence [X]: the pose is in doubt (the confidence below X, "
     "default the trust bar; not converged; ambiguous; degenerate; or, with --range-images, failing the free-space "
     "test: RegistrationResult.doubts()); one line on stderr, the outputs asked for written all the same"),
    (EXIT_PARTIAL, ("merge",), "a scan is doubtful or unplaced: named on stderr, the placed scans written "
     "(--allow-partial exits 0 instead)"),
    (EXIT_INTERRUPTED, ("bench",), "interrupted (Ctrl-C): the rows finished so far are kept"),
    (EXIT_INTERRUPTED, None, "interrupted (Ctrl-C): nothing written, or the last line names the outputs already "
     "written"),
    (EXIT_BROKEN_PIPE, None, "the reader of standard output went away (esmicp ... | head): nothing on stderr"),
    (EXIT_TERMINATED, None, "terminated (SIGTERM: kill, timeout, a container stopping): handled as Ctrl-C, worker "
     "processes ended, the same message"),
)


def exit_statuses(command: str | None = None) -> list[tuple[int, str, str]]:
    """``(status, commands, meaning)`` of each exit status ``command`` can end with (every row of
    :data:`EXIT_STATUSES` for None), ``commands`` in words: "all", "other commands", or the
    commands' names."""
    rows = []
    for status, commands, meaning in EXIT_STATUSES:
        named = [c for s, cs, _ in EXIT_STATUSES if s == status and cs is not None for c in cs]
        if command is None:
            who = ", ".join(commands) if commands else ("other commands" if named else "all")
            rows.append((status, who, meaning))
        elif (commands is None and command not in named) or (commands is not None and command in commands):
            rows.append((status, command, meaning))
    return rows


def exit_status_epilog(command: str | None = None) -> str:
    """The ``exit status:`` section of a ``--help`` (``command`` None: every command's, each
    status with the commands it applies to)."""
    import textwrap

    lines = ["exit status:"]
    previous = None
    for status, commands, meaning in exit_statuses(command):
        text = meaning if command is not None or commands == "all" else f"{commands}: {meaning}"
        wrapped = textwrap.wrap(text, 90, break_on_hyphens=False)
        lines.append(f"  {status if status != previous else '':<5}{wrapped[0]}")
        lines.extend(f"       {line}" for line in wrapped[1:])
        previous = status
    return "\n".join(lines)


#: ``-q`` / ``-v`` (:func:`add_verbosity`): how much a command prints.
QUIET, NORMAL, VERBOSE = -1, 0, 1


def add_verbosity(parser, verbose: str) -> None:
    """Add ``-q`` / ``--quiet`` and ``-v`` / ``--verbose`` (exclusive) to a subcommand's parser:
    ``args.verbosity`` is :data:`QUIET` (warnings, errors and the outputs asked for only),
    :data:`NORMAL` (the summary) or :data:`VERBOSE` (``verbose``: what the summary leaves out)."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument("-q", "--quiet", dest="verbosity", action="store_const", const=QUIET, default=NORMAL,
                       help="print nothing but warnings and errors (the outputs asked for are written)")
    group.add_argument("-v", "--verbose", dest="verbosity", action="store_const", const=VERBOSE,
                       help=f"print more: {verbose}")


class HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter, except that a text holding line breaks (the exit-status epilog) is
    kept as written; one-line texts are wrapped as usual."""

    def _fill_text(self, text, width, indent):
        if "\n" in text:
            return "\n".join(indent + line for line in text.splitlines())
        return super()._fill_text(text, width, indent)


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line (and exit status 2)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")
