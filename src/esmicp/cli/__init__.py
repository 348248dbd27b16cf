"""The ``esmicp`` command line: a thin layer that parses arguments, reads files, calls the library
and prints. Bad input ends in one line on stderr and exit status 2; nothing is written then.

One module per command family: :mod:`.register`, :mod:`.demo`, :mod:`.viz` (``view``,
``heatmap``, ``animate``), :mod:`.merge`; :mod:`.args` holds the shared argument types, the exit
codes and the parser class. ``esmicp bench`` belongs to the benchmark lab (:mod:`esmicp_lab.cli`),
the one place the library imports the lab.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import warnings

from .._version import __version__
from ..errors import EsmicpError, EsmicpWarning, MissingDependencyError
from .args import (EXIT_BAD_INPUT, EXIT_BROKEN_PIPE, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, EXIT_TERMINATED, NORMAL,
                   VERBOSE, Parser, exit_status_epilog)

__all__ = ["EXIT_BAD_INPUT", "EXIT_BROKEN_PIPE", "EXIT_FAILED", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_TERMINATED",
           "build_parser", "main"]


def build_parser() -> Parser:
    # The command modules load NumPy and the library: imported here, so `esmicp --version` does not.
    from . import demo, merge, register, viz

    parser = Parser(
        prog="esmicp",
        description="Rigid registration of 3D point clouds with ESM-ICP. Transforms are "
        "T_target_source: 4x4 matrices that map source coordinates into the target frame.",
        epilog=exit_status_epilog(),
    )
    parser.add_argument("--version", action="version", version=f"esmicp {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    commands.required = True
    register.add_parser(commands)
    demo.add_parser(commands)
    _add_bench_parser(commands)
    viz.add_parser(commands)  # view, heatmap, animate
    merge.add_parser(commands)  # merge
    for name, command in commands.choices.items():  # each command's exit statuses, from the one table
        if command.add_help and command.epilog is None:
            command.epilog = exit_status_epilog(name)
    return parser


#: What to tell a user whose esmicp has no benchmark lab (``esmicp_lab`` ships in esmicp's wheel).
LAB_INSTALL_HINT = "pip install 'esmicp[bench]'"


def _add_bench_parser(commands) -> None:
    """``esmicp bench``: the benchmark lab's command (:func:`esmicp_lab.cli.add_parser`), imported
    when the parser is built. Without the lab, ``esmicp bench ...`` (any arguments, ``--help``
    too) ends in one line saying how to install it; every other command is unaffected."""
    try:
        from esmicp_lab.cli import add_parser
    except ModuleNotFoundError as exc:
        if not (exc.name or "").startswith("esmicp_lab"):
            raise  # the lab is there but something it needs is not: show it
    else:
        add_parser(commands)
        return
    # No option prefix (argv never holds a NUL): every argument, --help too, reaches the handler.
    placeholder = commands.add_parser("bench", help=f"run the benchmark suite (needs the benchmark lab: {LAB_INSTALL_HINT})",
                                      add_help=False, prefix_chars="\0")
    placeholder.add_argument("arguments", nargs="*")
    placeholder.set_defaults(handler=_no_lab)


def _no_lab(args) -> int:
    raise MissingDependencyError("the benchmark lab (the esmicp_lab package) is not installed; install esmicp "
                                 f"with it: {LAB_INSTALL_HINT}")


def main(argv=None) -> int:
    """Entry point of the ``esmicp`` console script; returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--version"]:  # the fast path: no parser, no NumPy (what argparse would print)
        print(f"esmicp {__version__}")
        return EXIT_OK
    from ..pools import fit_address_space_limit

    # Under `ulimit -v`, threads must not each reserve a malloc arena: set before NumPy starts its
    # threads, and for the worker processes.
    fit_address_space_limit(children=True)
    from ..interrupts import Terminated, terminate_as_interrupt
    from ..io.atomic import recording_outputs

    args = build_parser().parse_args(argv)
    verbose = getattr(args, "verbosity", NORMAL) >= VERBOSE
    with warnings.catch_warnings(), _library_log_on_stderr(args.command, verbose), terminate_as_interrupt(), \
            recording_outputs() as written:
        warnings.simplefilter("always", EsmicpWarning)
        warnings.showwarning = _show_warning
        try:
            status = args.handler(args)
            sys.stdout.flush()  # a reader that closed the pipe (esmicp ... | head) shows here, not at exit
            return status
        except BrokenPipeError:
            return _stdout_closed()
        except EsmicpError as exc:
            print(f"esmicp {args.command}: error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (Terminated)
            what = "terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted"
            done = f"written before that: {', '.join(written)}" if written else "no partial output was written"
            print(f"esmicp {args.command}: {what}; {done}", file=sys.stderr)
            return EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED
        except MemoryError:
            print(f"esmicp {args.command}: error: out of memory (the clouds are too large for this "
                  "machine; downsample them or use a smaller --sample-points)", file=sys.stderr)
            return EXIT_BAD_INPUT
        except RuntimeError as exc:
            if "can't start new thread" not in str(exc):
                raise
            print(f"esmicp {args.command}: error: cannot start another thread{_address_space_note()}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except OSError as exc:  # a full disk, a folder that vanished: no traceback, one line
            where = f"{exc.filename}: " if exc.filename else ""
            print(f"esmicp {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
            return EXIT_BAD_INPUT


def _address_space_note() -> str:
    """Why a thread could not start, and what to do, for the one-line error."""
    try:
        import resource

        limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    except (ImportError, OSError, ValueError):  # pragma: no cover - not POSIX
        limit = None
    if limit is None or limit == getattr(resource, "RLIM_INFINITY", -1):
        return " (the system's thread limit): run fewer at once (--threads / --processes)"
    return (f" within the address-space limit of {limit / 2**20:.0f} MB (ulimit -v): run fewer at once (--threads "
            "1, --processes 1) or raise the limit")


def _stdout_closed() -> int:
    """The reader of our output went away (``esmicp ... | head``): end quietly, as Unix tools do.
    Standard output is pointed at the null device, so that Python's flush at exit cannot fail
    again (the recipe of Python's documentation, "Note on SIGPIPE")."""
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, sys.stdout.fileno())
    os.close(null)
    return EXIT_BROKEN_PIPE


class _CommandLogHandler(logging.Handler):
    """Prints the library's log records (warnings and above; with ``-v``, what it reports too) as
    the command's own lines: ``esmicp merge: warning: ...``, not the bare text of Python's
    last-resort handler."""

    def __init__(self, command: str, level: int = logging.WARNING):
        super().__init__(level)
        self.command = command

    def emit(self, record: logging.LogRecord) -> None:
        print(f"esmicp {self.command}: {record.levelname.lower()}: {record.getMessage()}", file=sys.stderr)


@contextlib.contextmanager
def _library_log_on_stderr(command: str, verbose: bool = False):
    """:class:`_CommandLogHandler` on the ``esmicp`` logger while a command runs (``verbose``: its
    informational records too, such as the layout a ``.bin`` scan was read in)."""
    library = logging.getLogger("esmicp")
    handler = _CommandLogHandler(command, logging.INFO if verbose else logging.WARNING)
    level = library.level
    library.addHandler(handler)
    if verbose and library.getEffectiveLevel() > logging.INFO:
        library.setLevel(logging.INFO)
    try:
        yield handler
    finally:
        library.removeHandler(handler)
        library.setLevel(level)


def _show_warning(message, category, filename, lineno, file=None, line=None):
    print(f"esmicp: warning: {message}", file=sys.stderr)

