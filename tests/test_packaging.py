"""The source distribution: ``python -m build --sdist`` packs what a build from source needs (the
C++ kernels, CMakeLists.txt, pyproject.toml, the package, tests, docs) and nothing of a working
copy's own: no build tree, virtual environment, results, caches or kernel built in place. And the
install hints: every extra they name exists, and the ``dev`` extra brings every extra that installs
in one step, with a persistent build folder."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sdist_members(tmp_path_factory) -> list[str]:
    if importlib.util.find_spec("build") is None:
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail("the 'build' package is missing (pip install '.[test]')")
        pytest.skip("the 'build' package is not installed (pip install '.[test]')")
    if not (REPO / "pyproject.toml").is_file():
        pytest.skip("not run from a source tree")
    out = tmp_path_factory.mktemp("dist")
    done = subprocess.run([sys.executable, "-m", "build", "--sdist", "--outdir", str(out), str(REPO)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    (archive,) = out.glob("esmicp-*.tar.gz")
    with tarfile.open(archive) as tar:
        return [name.split("/", 1)[1] for name in tar.getnames() if "/" in name]


def kernel_sources() -> list[str]:
    """The compiled kernels' files: the sources CMakeLists.txt builds and the headers beside them."""
    listed = re.findall(r"src/esmicp/_ext/\w+\.cpp", (REPO / "CMakeLists.txt").read_text())
    assert listed, "CMakeLists.txt lists no source of the kernels"
    headers = sorted(path.relative_to(REPO).as_posix() for path in (REPO / "src/esmicp/_ext").glob("*.hpp"))
    return listed + headers


def test_sdist_has_what_a_build_from_source_needs(sdist_members):
    for needed in ("pyproject.toml", "CMakeLists.txt", "README.md", *kernel_sources(),
                   "src/esmicp/__init__.py", "src/esmicp/cli/__init__.py", "tests/conftest.py",
                   "src/esmicp/py.typed", "src/esmicp/_kernels.pyi", "src/esmicp_lab/__init__.py",
                   "src/esmicp_lab/cli.py"):
        assert needed in sdist_members, needed


def test_sdist_has_nothing_of_a_working_copy(sdist_members):
    unwanted = [name for name in sdist_members
                if name.split("/")[0] in {"build", "dist", ".venv", "bench-results", ".hypothesis", ".pytest_cache"}
                or name.startswith("docs/_build/")  # a local docs build
                or "__pycache__" in name or name.endswith((".so", ".pyd", ".o"))]
    assert not unwanted, unwanted
    # Point clouds come from ../shared/data; only the fuzz corpus (tests/corpus, small files) ships.
    clouds = [name for name in sdist_members if name.endswith((".ply", ".pcd", ".npy", ".bin", ".las", ".off"))
              and not name.startswith("tests/corpus/")]
    assert not clouds, clouds


def _pyproject() -> dict:
    if not (REPO / "pyproject.toml").is_file():
        pytest.skip("not run from a source tree")
    try:
        import tomllib
    except ImportError:  # Python 3.10
        tomllib = pytest.importorskip("tomli", reason="reading pyproject.toml on Python 3.10 needs tomli")
    return tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))


#: Where an install hint can be read: the package, the tests' skip messages, the benchmark scripts,
#: the docs, the README and the CI script.
HINTED = ("src", "tests", "benchmarks", "docs", "README.md", ".ci")
#: The extras a hint names (``esmicp`` then the bracketed list), and the extra a test's ``require_module(name, "extra")`` names.
EXTRA_IN_HINT = re.compile(r"esmicp\[([\w,-]+)\]")
EXTRA_OF_REQUIRE = re.compile(r"require_module\(\s*[\"'][\w.]+[\"']\s*,\s*[\"']([\w-]+)[\"']")


def _hint_texts():
    for name in HINTED:
        root = REPO / name
        paths = [root] if root.is_file() else sorted(root.rglob("*")) if root.is_dir() else []
        for path in paths:
            if path.is_file() and path.suffix in {".py", ".md", ".toml", ""} and "_build" not in path.parts:
                yield path, path.read_text(encoding="utf-8", errors="replace")


def test_every_extra_an_install_hint_names_exists():
    extras = set(_pyproject()["project"]["optional-dependencies"])
    named = {}
    for path, text in _hint_texts():
        for match in EXTRA_IN_HINT.finditer(text):
            for extra in match.group(1).split(","):
                named.setdefault(extra, path.relative_to(REPO).as_posix())
        for match in EXTRA_OF_REQUIRE.finditer(text):
            named.setdefault(match.group(1), path.relative_to(REPO).as_posix())
    assert {"viz", "baselines", "las"} <= set(named), "the search found none of the usual hints"
    missing = {extra: where for extra, where in named.items() if extra not in extras}
    assert not missing, f"hints name extras that pyproject.toml does not define: {missing}"


def test_the_dev_extra_brings_every_extra_that_installs_in_one_step():
    """``pip install -e '.[dev]'`` is the one install line of a developer: every extra except those
    whose libraries need their own steps (docs/baselines.md)."""
    extras = _pyproject()["project"]["optional-dependencies"]
    (own,) = [requirement for requirement in extras["dev"] if requirement.startswith("esmicp[")]
    brought = set(re.fullmatch(r"esmicp\[([\w,-]+)\]", own).group(1).split(","))
    special = {"learned", "cpd", "go-icp-build"}
    assert brought == set(extras) - special - {"dev"}
    # and the build backend's own requirements, for a rebuild without build isolation
    names = {re.match(r"[\w-]+", requirement).group(0) for requirement in extras["dev"]}
    backend = {re.match(r"[\w-]+", requirement).group(0) for requirement in _pyproject()["build-system"]["requires"]}
    assert backend <= names


def test_repeated_builds_reuse_a_build_folder_git_and_the_sdist_leave_out():
    build_dir = _pyproject()["tool"]["scikit-build"]["build-dir"]
    top = build_dir.split("/")[0]
    assert "{wheel_tag}" in build_dir, "one folder per Python and platform"
    assert f"{top}/" in (REPO / ".gitignore").read_text(encoding="utf-8").split()
    assert top in _pyproject()["tool"]["scikit-build"]["sdist"]["exclude"]
