"""The layout rules of docs/architecture.md, checked on the source tree: the library below the
command line holds no argument parsing and prints nothing, the algorithm layers (core, methods,
trust, globalreg) import no file, command-line, benchmark or plotting module, the floors
(core < methods < trust < globalreg < multiview < api) import nothing from a floor above them, and
the benchmark lab (``esmicp_lab``) is a floor above the whole library, which never imports it."""

from __future__ import annotations

import ast
from pathlib import Path

import esmicp
import esmicp_lab

PACKAGE = Path(esmicp.__file__).parent
LAB = Path(esmicp_lab.__file__).parent
#: The library's one import of the lab: the ``esmicp bench`` parser, built inside this function of
#: ``esmicp/cli/__init__.py``.
BENCH_HOOK = ("cli/__init__.py", "_add_bench_parser", "esmicp_lab.cli")


def _modules(*parts):
    root = PACKAGE.joinpath(*parts)
    return sorted(root.rglob("*.py")) if root.is_dir() else [root]


def _imports(path: Path):
    yield from (name for _, name in _imports_in_functions(path))


def _imports_in_functions(path: Path):
    """(the name of the function an import statement sits in, or None at module level; the
    dotted module it imports) for every import of the module at ``path``, relative ones resolved;
    ``importlib.import_module("...")`` of a literal name counts as an import."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    root = next(folder for folder in (PACKAGE.parent, LAB.parent) if path.is_relative_to(folder))
    package = path.relative_to(root).with_suffix("").parts[:-1]

    def visit(node, function):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            function = node.name
        if isinstance(node, ast.Import):
            yield from ((function, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = list(package[: len(package) - node.level + 1]) if node.level else []
            if node.module:
                yield function, ".".join(base + [node.module])
            else:  # ``from . import name``: the module ``name`` of that package
                yield from ((function, ".".join(base + [alias.name])) for alias in node.names)
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            yield function, node.args[0].value
        for child in ast.iter_child_nodes(node):
            yield from visit(child, function)

    yield from visit(tree, None)


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
    forbidden = ("esmicp.io", "esmicp.cli", "esmicp_lab", "esmicp.viz", "matplotlib", "plotly")
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


def test_a_pose_is_judged_in_one_place():
    """``trust.judge`` measures and weighs a registered pose; the result stores its verdict and
    measures nothing (no overlap confidence, no free-space test), and ``register`` reaches the
    covariance and the free-space test only through it."""
    measures = ("esmicp.trust.confidence", "esmicp.trust.free_space")
    result = [name for name in _imports(PACKAGE / "result.py") if _within(name, measures)]
    assert not result, result
    api = [name for name in _imports(PACKAGE / "api.py") if _within(name, ("esmicp.trust.uncertainty",
                                                                          "esmicp.trust.free_space"))]
    assert not api, api


def test_trust_and_core_import_no_search_merge_registration_or_lab():
    above = tuple(f"esmicp.{name}" for name in ("globalreg", "multiview", "api", "batch", "cli", "viz")) + ("esmicp_lab",)
    offenders = _imports_from(("trust", "core"), above)
    assert not offenders, offenders


def test_the_methods_import_no_search_or_merge():
    offenders = _imports_from(("methods",), ("esmicp.globalreg", "esmicp.multiview"))
    assert not offenders, offenders


def test_the_library_imports_nothing_of_the_lab():
    """No module of ``esmicp`` imports ``esmicp_lab`` (the harness, the baselines, the benchmark
    plots, the bench command), at module level or inside a function, but for the ``esmicp bench``
    parser (:data:`BENCH_HOOK`)."""
    offenders = []
    for path in _modules():
        where = path.relative_to(PACKAGE).as_posix()
        for function, name in _imports_in_functions(path):
            if _within(name, ("esmicp_lab",)) and (where, function, name) != BENCH_HOOK:
                offenders.append(f"{where} ({function or 'module level'}) imports {name}")
    assert not offenders, offenders
    hook_file, hook_function, hook_module = BENCH_HOOK
    assert (hook_function, hook_module) in set(_imports_in_functions(PACKAGE / hook_file)), "the bench hook moved"


def test_the_lab_is_a_floor_above_the_library():
    """The lab sits beside the library, not in it: none of its rooms is left inside ``esmicp``,
    and it reaches the library through ``esmicp``'s modules (which it imports) and its own."""
    left = [room for room in ("bench", "baselines", "viz/bench_plots.py", "cli/bench.py") if PACKAGE.joinpath(room).exists()]
    assert not left, f"lab rooms inside the library: {left}"
    lab_modules = sorted(LAB.rglob("*.py"))
    ours = {name for path in lab_modules for name in _imports(path) if _within(name, ("esmicp", "esmicp_lab"))}
    assert any(_within(name, ("esmicp",)) for name in ours)  # the lab stands on the library
    assert {path.relative_to(LAB).parts[0] for path in lab_modules} >= {"bench", "baselines", "plots.py", "cli.py"}


def test_the_configuration_tree_is_data_only():
    """The configuration objects import nothing of ours but each other, the errors and the input
    checks: any floor takes its values without loading an algorithm."""
    tree = ("esmicp.config", "esmicp.core.config", "esmicp.methods.config", "esmicp.trust.policy",
            "esmicp.globalreg.config")
    offenders = []
    for module in tree:
        path = PACKAGE.joinpath(*module.split(".")[1:]).with_suffix(".py")
        offenders.extend(f"{module} imports {name}" for name in _imports(path)
                         if _within(name, ("esmicp",)) and not _within(name, tree + ("esmicp.errors", "esmicp.types")))
    assert not offenders, offenders


#: The algorithm layers whose numeric module constants are counted.
ALGORITHM_LAYERS = ("core", "methods", "globalreg", "multiview", "trust", "api.py")
#: At most this many numeric module constants in :data:`ALGORITHM_LAYERS`: a tuned value belongs
#: in the configuration tree (``esmicp.config``), so the count may fall, never grow.
MAX_MODULE_CONSTANTS = 10
#: Layers with no numeric module constant left.
WITHOUT_CONSTANTS = ("multiview", "trust")
#: Layers whose constants left are design values only, at most this many each: memory bounds of
#: chunked work (``_SCORE_CHUNK``), caps on iterations (``_LEADING_STEPS``), a switch between two exact nearest-neighbour
#: searches (``_BRUTE_FORCE_PAIRS``), speed-only sizes of exact searches (``GRAPH_NEIGHBOURS``,
#: ``LEAF_SIZE``), mathematical constants (``_PSI``, ``_MAD_SCALE``), floating-point bounds
#: (``SIGMA_FLOOR``, ``RESULT_RIGID_TOLERANCE``), the default seed (``DEFAULT_SEED``).
MAX_CONSTANTS_PER_LAYER = {"core": 2, "methods": 2, "globalreg": 5, "api.py": 1}


def _numeric(node) -> bool:
    """True for a number, or arithmetic of numbers and names (``REFINE_POINTS // 2``)."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, (int, float)) and not isinstance(node.value, bool)
    if isinstance(node, ast.UnaryOp):
        return _numeric(node.operand)
    if isinstance(node, ast.BinOp):
        return all(_numeric(side) or isinstance(side, (ast.Name, ast.Attribute)) for side in (node.left, node.right))
    if isinstance(node, ast.Tuple):
        return bool(node.elts) and all(_numeric(element) for element in node.elts)
    return False


def _constants(tree: ast.Module) -> list[str]:
    """Every upper-case name a module (``tree``) binds at module level to a number, to arithmetic of
    numbers, or to another upper-case name (an alias)."""
    found = []
    for node in tree.body:
        if isinstance(node, ast.Assign):
            targets, value = node.targets, node.value
        elif isinstance(node, ast.AnnAssign) and node.value is not None:
            targets, value = [node.target], node.value
        else:
            continue
        alias = isinstance(value, ast.Name) and value.id.isupper()
        found.extend(target.id for target in targets
                     if isinstance(target, ast.Name) and target.id.isupper() and (_numeric(value) or alias))
    return found


def module_constants(*layers) -> list[str]:
    """``path: NAME`` of every numeric module constant (:func:`_constants`) of ``layers``."""
    return [f"{path.relative_to(PACKAGE)}: {name}" for layer in layers for path in _modules(layer)
            for name in _constants(ast.parse(path.read_text(encoding="utf-8")))]


def test_the_module_constants_cannot_grow():
    """Tuned values live in the configuration tree: the algorithm layers' numeric module constants
    are counted, so a new one cannot slip in unseen (lower :data:`MAX_MODULE_CONSTANTS` as they
    move into a config)."""
    found = module_constants(*ALGORITHM_LAYERS)
    assert len(found) <= MAX_MODULE_CONSTANTS, "\n".join(found)
    left = module_constants(*WITHOUT_CONSTANTS)
    assert not left, left
    for layer, most in MAX_CONSTANTS_PER_LAYER.items():
        found = module_constants(layer)
        assert len(found) <= most, "\n".join(found)


def test_the_constant_count_sees_what_it_should():
    source = ("import numpy as np\nA = 3\nB: float = 0.5\nC = A // 2\nD = -1e-6\nE = A\nF = (0.5, 0.8)\n"
              "names = 2\nG = 'text'\nH = np.eye(3)\nI = True\nJ = K = 4\n")
    assert _constants(ast.parse(source)) == ["A", "B", "C", "D", "E", "F", "J", "K"]


#: The library layers that must name no benchmark data set: a docstring there states a meaning and a
#: unit, and the data a value was chosen and confirmed on are in ``docs/design.md`` ("Tuned values")
#: and the results pages. The built-in demo shapes (``shapes.py``), the readers (``io``), the
#: command line and the pictures are outside.
NAMELESS_LAYERS = ALGORITHM_LAYERS + ("config.py", "result.py")
#: The benchmark data sets of ``docs/`` (a word of each that names it, matched case-insensitively).
BENCHMARK_DATA_SETS = ("3dmatch", "kitchen", "bunny", "kitti", "modelnet", "newer college", "newer_college",
                       "turntable", "lomatch", "redkitchen", "real_pairs")


def data_set_names(source: str) -> list[str]:
    """``line: name`` of every mention of a :data:`BENCHMARK_DATA_SETS` name in ``source``."""
    return [f"{number}: {name}" for number, line in enumerate(source.splitlines(), 1)
            for name in BENCHMARK_DATA_SETS if name in line.lower()]


def test_the_library_names_no_benchmark_data_set():
    offenders = [f"{path.relative_to(PACKAGE)}:{hit}" for layer in NAMELESS_LAYERS for path in _modules(layer)
                 for hit in data_set_names(path.read_text(encoding="utf-8"))]
    assert not offenders, "\n".join(offenders)


def test_the_data_set_check_sees_what_it_should():
    source = '"""Chosen on 3DMatch crops,\nconfirmed on the Kitchen walk and Newer College."""\nX = 1\n'
    assert data_set_names(source) == ["1: 3dmatch", "2: kitchen", "2: newer college"]
    assert data_set_names('"""A scan pair, a walk, an object turned in small steps."""') == []
