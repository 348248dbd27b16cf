"""Sphinx directives that write the ``--help`` text of an ``esmicp`` command, generated from the
argparse parser itself, and the table of exit statuses, generated from the one table the
``--help`` epilogs are made of (:data:`esmicp.cli.args.EXIT_STATUSES`), so the CLI reference never
drifts from the code.

Usage in a MyST page::

    ```{esmicp-help} register
    ```

    ```{esmicp-exit-statuses}
    ```

(``esmicp-help`` with no argument: the top-level ``esmicp --help``).
"""

from __future__ import annotations

import os
import re

from docutils import nodes
from sphinx.util.docutils import SphinxDirective


def command_help(words: list[str]) -> str:
    """The help text of ``esmicp WORDS... --help``, at a fixed width of 100 columns."""
    os.environ["COLUMNS"] = "100"
    from esmicp.cli import build_parser

    parser = build_parser()
    for word in words:
        subparsers = next(action for action in parser._actions if action.__class__.__name__ == "_SubParsersAction")
        parser = subparsers.choices[word]
    return parser.format_help()


class EsmicpHelp(SphinxDirective):
    """``esmicp-help [COMMAND]``: a literal block with that command's ``--help``."""

    optional_arguments = 1
    has_content = False

    def run(self):
        words = self.arguments[0].split() if self.arguments else []
        try:
            text = command_help(words)
        except (KeyError, StopIteration):
            raise self.error(f"esmicp has no command {' '.join(words)!r}") from None
        block = nodes.literal_block(text, text)
        block["language"] = "text"
        return [block]


#: What is shown as code in the table: options, a method, a command line.
CODE = re.compile(r"(--[\w-]+|\w+\.\w+\(\)|esmicp \.\.\. \| head)")


def _with_code(text: str) -> nodes.paragraph:
    """A paragraph of ``text`` with its options and the like as inline code (so that ``--force``
    keeps its two hyphens)."""
    paragraph = nodes.paragraph()
    for index, part in enumerate(CODE.split(text)):
        if part:
            paragraph += nodes.literal(part, part) if index % 2 else nodes.Text(part)
    return paragraph


class EsmicpExitStatuses(SphinxDirective):
    """``esmicp-exit-statuses``: a table of every exit status, the commands it applies to and what
    it means."""

    has_content = False

    def run(self):
        from esmicp.cli.args import exit_statuses

        rows = [("status", "commands", "meaning")] + [(str(s), c, m) for s, c, m in exit_statuses()]
        table = nodes.table()
        group = nodes.tgroup(cols=3)
        table += group
        for width in (8, 16, 76):
            group += nodes.colspec(colwidth=width)
        for index, row in enumerate(rows):
            line = nodes.row()
            for cell in row:
                entry = nodes.entry()
                entry += _with_code(cell)
                line += entry
            if index == 0:
                group += nodes.thead("", line)
                body = nodes.tbody()
                group += body
            else:
                body += line
        return [table]


def setup(app):
    app.add_directive("esmicp-help", EsmicpHelp)
    app.add_directive("esmicp-exit-statuses", EsmicpExitStatuses)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
