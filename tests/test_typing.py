"""Type information for users: ``py.typed``, a stub of the compiled module that names what it
defines, and ``mypy --strict`` clean on a user's script (tests/typing/public_api.py) while it
reports the mistakes of tests/typing/misuse.py (so the public names are typed, not ``Any``)."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

from conftest import require_module

import esmicp
from esmicp import _kernels

PACKAGE = Path(esmicp.__file__).parent
TYPING = Path(__file__).parent / "typing"


def test_the_stub_names_what_the_compiled_module_defines():
    assert (PACKAGE / "py.typed").is_file()
    tree = ast.parse((PACKAGE / "_kernels.pyi").read_text())
    stubbed = {node.name for node in tree.body if isinstance(node, (ast.FunctionDef, ast.ClassDef))}
    stubbed |= {node.target.id for node in tree.body if isinstance(node, ast.AnnAssign)}
    compiled = {name for name in dir(_kernels) if not name.startswith("_")}
    assert stubbed == compiled


def test_mypy_strict_accepts_the_public_api_and_catches_its_misuse(tmp_path):
    require_module("mypy", "test")
    environment = {**os.environ, "PYTHONPATH": str(PACKAGE.parent)}
    done = subprocess.run(
        [sys.executable, "-m", "mypy", "--strict", "--cache-dir", str(tmp_path), "--no-error-summary",
         "--show-error-codes", str(TYPING / "public_api.py"), str(TYPING / "misuse.py")],
        capture_output=True, text=True, env=environment, cwd=tmp_path,
    )
    errors = [line for line in done.stdout.splitlines() if ": error:" in line]
    assert not [line for line in errors if "public_api.py" in line], done.stdout
    expected = {number for number, line in enumerate((TYPING / "misuse.py").read_text().splitlines(), 1)
                if line.endswith("# error")}
    found = {int(re.search(r"misuse\.py:(\d+):", line).group(1)) for line in errors if "misuse.py" in line}
    assert found == expected, done.stdout + done.stderr
