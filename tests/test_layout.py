"""The layout rules of docs/architecture.md, checked on the source tree: the library below the
command line holds no argument parsing and prints nothing, the algorithm layers (core, methods,
trust, globalreg) import no file, command-line, benchmark or plotting module, and the floors
(core < methods < trust < globalreg < multiview < api) import nothing from a floor above them."""

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
            if node.module:
                yield ".".join(base + [node.module])
            else:  # ``from . import name``: the module ``name`` of that package
                yield from (".".join(base + [alias.name]) for alias in node.names)


def _within(name: str, packages) -> bool:
    """True when the dotted ``name`` is one of ``packages`` or inside one of them."""
    return any(name == package or name.startswith(package + ".") for package in packages)


def _imports_from(layers, packages):
    """Every import of a module of ``layers`` (under ``esmicp``) from one of ``packages``."""
    offenders = []
    for layer in layers:
        assert PACKAGE.joinpath(layer).exists(), f"esmicp.{layer} is missing"
        for path in _modules(layer):
            offenders.extend(f"{path.relative_to(PACKAGE)} imports {name}" for name in _imports(path)
                             if _within(name, packages))
    return offenders


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
    for layer in ("core", "methods", "trust", "globalreg"):
        for path in _modules(layer):
            for name in _imports(path):
                if name.startswith(forbidden):
                    offenders.append(f"{path.relative_to(PACKAGE)} imports {name}")
    assert not offenders, offenders


def test_the_result_imports_nothing_of_ours_but_trust_core_types_and_errors():
    """A result records a registration and judges it through the trust floor; it never reaches up
    to the search, the merge or the registration that builds it."""
    allowed = ("esmicp.trust", "esmicp.core", "esmicp.types", "esmicp.errors")
    ours = [name for name in _imports(PACKAGE / "result.py") if _within(name, ("esmicp",))]
    assert not [name for name in ours if not _within(name, allowed)], ours


def test_trust_and_core_import_no_search_merge_registration_or_lab():
    above = tuple(f"esmicp.{name}" for name in
                  ("globalreg", "multiview", "api", "batch", "cli", "bench", "viz", "baselines"))
    offenders = _imports_from(("trust", "core"), above)
    assert not offenders, offenders


def test_the_methods_import_no_search_or_merge():
    offenders = _imports_from(("methods",), ("esmicp.globalreg", "esmicp.multiview"))
    assert not offenders, offenders
