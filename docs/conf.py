"""Sphinx configuration of the esmicp documentation.

Build (from the repository root; warnings are errors, so a broken cross-reference fails it):

    pip install '.[docs]' && sphinx-build -W -b html docs docs/_build/html
"""

from __future__ import annotations

import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS / "_ext"))
# A build from a clone works without installing the package first (the compiled kernels are not
# needed: autodoc imports the Python modules only).
sys.path.insert(0, str(DOCS.parent / "src"))

from esmicp._version import __version__  # noqa: E402

project = "esmicp"
author = "the esmicp authors"
copyright = "the esmicp authors, MIT licence"
version = release = __version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "cli_help",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
root_doc = "index"

# Markdown: ``[text](page.md#a-heading)`` links resolve to heading anchors (and fail when missing).
myst_heading_anchors = 4
myst_enable_extensions = ["colon_fence", "dollarmath"]

# The API reference: numpy-style docstrings, signatures as written, members in source order.
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": False}
# The compiled kernels are an implementation detail of the algorithm modules: never needed for the
# reference, so a docs build does not need a C++ compiler.
autodoc_mock_imports = ["esmicp._kernels"]

# External links are not checked here (CI has no network); internal references fail the -W build.
linkcheck_ignore = [r"https?://.*"]

html_theme = "furo" if __import__("importlib").util.find_spec("furo") else "alabaster"
html_title = f"esmicp {release}"
html_static_path: list[str] = []
