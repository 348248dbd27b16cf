"""The layout rules of docs/architecture.md, checked on the source tree: the library below the
command line holds no argument parsing and prints nothing, and the algorithm layers (core,
methods, globalreg) import no file, command-line, benchmark or plotting module."""

from __future__ import annotations

import ast
from pathlib import Path

import esmicp

PACKAGE = Path(esmicp.__file__).parent


def _modules(*parts):
    root = PACKAGE.joinpath(*parts)
    return sorted(root.rglob("*.py")) if root.is_dir() else [root]


def _imports(path: Path):
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = path.relative_to(PACKAGE.parent).with_suffix("").parts[:-1]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = list(package[: len(package) - node.level + 1]) if node.level else []
            yield ".".join(base + ([node.module] if node.module else []))


def test_only_the_command_line_parses_arguments_or_prints():
    offenders = []
    for path in _modules():
        if path.relative_to(PACKAGE).parts[0] == "cli":
            continue
        source = path.read_text(encoding="utf-8")
        tree = ast.parse(source)
        if any(name.split(".")[0] == "argparse" for name in _imports(path)):
            offenders.append(f"{path.relative_to(PACKAGE)} imports argparse")
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
                offenders.append(f"{path.relative_to(PACKAGE)}:{node.lineno} prints")
    assert not offenders, offenders


def test_the_algorithm_layers_know_nothing_of_files_printing_or_plotting():
    forbidden = ("esmicp.io", "esmicp.cli", "esmicp.bench", "esmicp.viz", "matplotlib", "plotly")
    offenders = []
    for layer in ("core", "methods", "globalreg"):
        for path in _modules(layer):
            for name in _imports(path):
                if name.startswith(forbidden):
                    offenders.append(f"{path.relative_to(PACKAGE)} imports {name}")
    assert not offenders, offenders
