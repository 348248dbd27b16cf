"""A Sphinx directive that writes the ``--help`` text of an ``esmicp`` command, generated from the
argparse parser itself, so the CLI reference never drifts from the code.

Usage in a MyST page::

    ```{esmicp-help} register
    ```

(no argument: the top-level ``esmicp --help``).
"""

from __future__ import annotations

import os

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


def setup(app):
    app.add_directive("esmicp-help", EsmicpHelp)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
