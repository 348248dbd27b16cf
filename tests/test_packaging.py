"""The source distribution (issue 14): ``python -m build --sdist`` packs what a build from source
needs (the C++ kernels, CMakeLists.txt, pyproject.toml, the package, tests, docs) and nothing of a
working copy's own: no build tree, virtual environment, results, caches or kernel built in place."""

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
