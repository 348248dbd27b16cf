"""Import stays light: ``import esmicp`` and ``esmicp --version`` load neither NumPy nor
any optional library; the registration path loads no plotting, Dask, torch, Open3D or file readers.

Each check runs in a fresh interpreter and reads its ``sys.modules``."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

import esmicp

#: Top-level packages that must never load with the library itself.
OPTIONAL = ("matplotlib", "plotly", "dask", "distributed", "torch", "open3d", "tqdm", "small_gicp",
            "kiss_matcher", "probreg")
#: Needed by the registration path, but not by `import esmicp` or `esmicp --version`.
NUMERIC = ("numpy", "scipy")
#: `esmicp demo` (the rotation search on a clean asymmetric pair) runs on the compiled kernels alone:
#: SciPy's import would be most of a first demo's time.
#: The file readers' libraries: loaded by reading a file, not by registering arrays.
READERS = ("plyfile", "pypcd4", "trimesh", "lzf")


def loaded_after(code: str, *args: str) -> tuple[set[str], str]:
    """The top-level packages loaded after running ``code`` in a new interpreter, and its stdout."""
    probe = (
        f"{code}\nimport sys, json\n"
        "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))"
    )
    done = subprocess.run([sys.executable, "-c", probe, *args], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    *output, modules = done.stdout.strip().splitlines()
    return set(json.loads(modules)), "\n".join(output)


def test_import_esmicp_loads_neither_numpy_nor_optional_libraries():
    loaded, _ = loaded_after("import esmicp")
    assert not loaded & {*OPTIONAL, *NUMERIC, *READERS}, sorted(loaded & {*OPTIONAL, *NUMERIC, *READERS})


def test_version_fast_path_loads_no_numpy():
    loaded, output = loaded_after("from esmicp.cli import main\nmain(['--version'])")
    assert output == f"esmicp {esmicp.__version__}"
    assert not loaded & {*OPTIONAL, *NUMERIC, *READERS}, sorted(loaded & {*OPTIONAL, *NUMERIC, *READERS})


def test_a_registration_loads_no_optional_library_nor_file_reader():
    code = (
        "import numpy as np, esmicp\n"
        "rng = np.random.default_rng(0)\n"
        "target = rng.normal(size=(3000, 3)) * [3, 2, 1]\n"
        "esmicp.register(target[::-1] + 0.01, target)\n"  # the default global start included
    )
    loaded, _ = loaded_after(code)
    assert "numpy" in loaded  # an ellipsoid: symmetric, so the feature strategy (SciPy's) runs too
    assert not loaded & {*OPTIONAL, *READERS}, sorted(loaded & {*OPTIONAL, *READERS})


def test_the_demo_command_loads_no_optional_library():
    loaded, output = loaded_after("from esmicp.cli import main\nmain(['demo', '--json'])")
    assert json.loads(output)["recovered"]
    assert not loaded & {*OPTIONAL, "scipy"}, sorted(loaded & {*OPTIONAL, "scipy"})


@pytest.mark.parametrize("module", ["esmicp", "esmicp.cli"])
def test_python_dash_m_runs_the_command(module):
    done = subprocess.run([sys.executable, "-m", module, "--version"], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == f"esmicp {esmicp.__version__}", done.stderr


def test_every_public_name_resolves_lazily():
    code = "import esmicp\nprint(' '.join(n for n in esmicp.__all__ if getattr(esmicp, n, None) is None))"
    _, missing = loaded_after(code)
    assert missing == ""
    assert set(esmicp.__all__) <= set(dir(esmicp))
    assert esmicp.register.__module__ == "esmicp.api"
    with pytest.raises(AttributeError, match="no attribute 'regster'"):
        esmicp.regster


@pytest.mark.parametrize("beside", ["open3d", "torch"])
def test_no_warning_at_import_or_first_call_beside(beside):
    # With numba, Open3D's TBB made every import warn (NumbaWarning: TBB threading layer ...).
    import importlib.util
    import os

    if importlib.util.find_spec(beside) is None:
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"{beside} is missing (bash .ci/run installs it)")
        pytest.skip(f"{beside} is not installed")
    code = (
        f"import {beside}, esmicp, numpy as np\n"
        "from esmicp.shapes import asymmetric_shape\n"
        "rng = np.random.default_rng(0)\n"
        "target = asymmetric_shape(3000, rng)\n"
        "esmicp.register(asymmetric_shape(3000, rng)[::-1] + 0.3, target, rng=0)\n"
    )
    done = subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True, text=True)
    assert done.returncode == 0 and "Warning" not in done.stderr, done.stderr[-2000:]


def test_the_library_loads_nothing_of_the_lab_and_the_command_line_only_its_bench_parser():
    """``import esmicp`` and a registration load no module of the benchmark lab (``esmicp_lab``);
    the command line loads the ``esmicp bench`` parser (``esmicp_lab.cli``) and nothing else of it:
    not the harness, the baselines or the plots."""
    probe = ("import sys, json, numpy as np, esmicp\n"
             "esmicp.register(np.random.default_rng(0).normal(size=(500, 3)) * [3, 2, 1], "
             "np.random.default_rng(0).normal(size=(500, 3)) * [3, 2, 1], init='identity')\n"
             "before = sorted(m for m in sys.modules if m.split('.')[0] == 'esmicp_lab')\n"
             "from esmicp.cli import build_parser\n"
             "build_parser().parse_args(['bench', '--paper'])\n"
             "print(json.dumps([before, sorted(m for m in sys.modules if m.split('.')[0] == 'esmicp_lab')]))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    library, command_line = json.loads(done.stdout)
    assert library == []
    assert command_line == ["esmicp_lab", "esmicp_lab.cli"]


def test_without_the_lab_esmicp_bench_names_the_install_and_other_commands_run():
    """An esmicp whose benchmark lab cannot be imported: ``esmicp bench`` (with any arguments,
    ``--help`` too) ends in one line with the install hint and exit status 2; ``esmicp demo`` runs."""
    no_lab = "import sys\nsys.modules['esmicp_lab'] = None\nfrom esmicp.cli import main\nsys.exit(main(sys.argv[1:]))"
    for arguments in (["bench", "--paper", "--trials", "1"], ["bench", "--help"], ["bench"]):
        done = subprocess.run([sys.executable, "-c", no_lab, *arguments], capture_output=True, text=True)
        assert done.returncode == 2 and done.stdout == "", (arguments, done.stdout, done.stderr)
        (line,) = done.stderr.strip().splitlines()
        assert line.startswith("esmicp bench: error: ") and "esmicp_lab" in line and "pip install" in line, line
    done = subprocess.run([sys.executable, "-c", no_lab, "demo", "--json"], capture_output=True, text=True)
    assert done.returncode == 0 and json.loads(done.stdout)["recovered"], done.stderr
