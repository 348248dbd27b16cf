"""Shared fixtures: where the real data lives, and seeded generators.

The real point clouds live in ``../shared/data`` beside the repository (override with the
``ESMICP_SHARED_DATA`` environment variable; docs/guide/data.md says what it holds and where each set
comes from). Tests that need them skip when they are missing on a developer's machine, but FAIL in
CI (``CI=true``), where their absence is a broken setup.
"""

from __future__ import annotations

import importlib
import os
import signal
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def _shared_data_dir() -> Path:
    override = os.environ.get("ESMICP_SHARED_DATA")
    if override:
        return Path(override)
    return REPO_ROOT.parent / "shared" / "data"


def require_shared(relative: str) -> Path:
    """Return the path of ``relative`` inside the shared data folder, or skip / fail if missing."""
    path = _shared_data_dir() / relative
    if not path.exists():
        message = (f"shared data not found: {path} (set ESMICP_SHARED_DATA or put shared/ beside the repo; "
                   "docs/guide/data.md says where each set comes from)")
        if in_ci():
            pytest.fail(message)
        pytest.skip(message)
    return path


def in_ci() -> bool:
    """True under CI (``CI=true``): a test whose data or optional library is missing fails there."""
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_module(name: str, extra: str, hint: str | None = None):
    """Import the optional module ``name``; skip the test when it is missing locally, fail it in CI.
    ``extra``: the ``esmicp[...]`` extra of pyproject.toml that installs it; ``hint``: the whole
    install command instead, for a library that needs more than the extra (probreg, py-goicp)."""
    try:
        return importlib.import_module(name)
    except (ImportError, OSError) as exc:  # OSError: open3d-cpu without libusb
        install = hint or f"pip install 'esmicp[{extra}]'"
        message = f"{name} cannot be imported ({exc}): {install}"
        if in_ci():
            pytest.fail(message)
        pytest.skip(message)


@pytest.fixture
def shared_data() -> Path:
    """The shared data folder (skipped locally / failed in CI when missing)."""
    return require_shared("")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def interruptible_child() -> None:
    """``preexec_fn`` for a child process a test will interrupt: Ctrl-C's signal as in a terminal.

    A shell starts a background job (``cmd &`` without job control, as in a CI script or under
    ``nohup``) with SIGINT ignored; its children inherit that, Python then installs no
    ``KeyboardInterrupt`` handler, and an interrupt test would see its SIGINT ignored.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def assert_file_error(excinfo, path, *words):
    """The error names the file first, on one line, and says the problem in the given words."""
    message = str(excinfo.value)
    assert message.startswith(str(path)), message
    assert "\n" not in message and "Traceback" not in message, message
    assert excinfo.value.path == str(path)
    for word in words:
        assert word in message, f"{word!r} not in {message!r}"


def random_cloud(seed: int, count: int) -> np.ndarray:
    """``count`` points drawn around the origin (standard deviation 20, cloud units), seeded."""
    return np.random.default_rng(seed).normal(scale=20.0, size=(count, 3))
