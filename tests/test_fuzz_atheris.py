"""Coverage-guided fuzzing (atheris) of every reader, for a bounded time: no input may break the
readers' contract (``fuzz/harness.py``: a valid cloud or a clear PointCloudFileError).

The default run fuzzes each target ``ESMICP_FUZZ_SECONDS_CI`` seconds (default 2; two targets at
a time, esmicp instrumented only, so that start-up stays short); the ``slow`` run fuzzes each
target ``ESMICP_FUZZ_SECONDS`` seconds (default 60) with plyfile, pypcd4 and trimesh instrumented
too: ``python -m pytest -m slow tests/test_fuzz_atheris.py``. For longer campaigns and a table of
inputs tried, use ``python fuzz/run_all.py --seconds 600``.

atheris is a test dependency (``pip install '.[test]'``): missing, these tests skip locally and
fail in CI (``CI=true``).
"""

from __future__ import annotations

import os
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "fuzz"))

import harness  # noqa: E402
import run_all  # noqa: E402

CI_SECONDS = float(os.environ.get("ESMICP_FUZZ_SECONDS_CI", "2"))
SLOW_SECONDS = float(os.environ.get("ESMICP_FUZZ_SECONDS", "60"))


def _in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_atheris() -> None:
    try:
        import atheris  # noqa: F401
    except ImportError as exc:
        message = f"atheris cannot be imported ({exc}): pip install 'esmicp[test]'"
        if _in_ci():
            pytest.fail(message)
        pytest.skip(message)


def _report(outcome: run_all.Outcome) -> str:
    found = "; ".join(dict.fromkeys(outcome.violations)) or "none"
    return f"{outcome.target}: {outcome.runs} inputs in {outcome.seconds:.1f} s, violations: {found}"


def _assert_clean(outcome: run_all.Outcome) -> None:
    assert outcome.failed is None, f"{outcome.target}: the fuzzer did not run:\n{outcome.failed}"
    assert outcome.runs > 0, _report(outcome)
    assert not outcome.crashes, (
        _report(outcome) + "\ninputs saved: " + ", ".join(map(str, outcome.crashes))
        + "\n(fix the reader, then keep the input: python fuzz/add_to_corpus.py)"
    )


def test_every_reader_survives_a_short_fuzzing_run(tmp_path, capsys):
    require_atheris()
    names = sorted(harness.TARGETS)
    with ThreadPoolExecutor(max_workers=2) as pool:
        outcomes = list(
            pool.map(lambda name: run_all.fuzz_target(name, CI_SECONDS, tmp_path / name, light=True), names)
        )
    with capsys.disabled():
        total = sum(outcome.runs for outcome in outcomes)
        print(f"\natheris, {CI_SECONDS:g} s per reader: {total} inputs tried")
    for outcome in outcomes:
        _assert_clean(outcome)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(harness.TARGETS))
def test_reader_survives_a_long_fuzzing_run(name, tmp_path, capsys):
    require_atheris()
    outcome = run_all.fuzz_target(name, SLOW_SECONDS, tmp_path / "artifacts")
    with capsys.disabled():
        print(f"\n{_report(outcome)}")
    _assert_clean(outcome)


def test_the_fuzzer_reports_a_violation(tmp_path, monkeypatch):
    """The set-up can fail: a reader that raises a stray exception is caught and its input saved."""
    require_atheris()
    monkeypatch.setenv("ESMICP_FUZZ_BREAK_READER", "1")
    outcome = run_all.fuzz_target("xyz", 20, tmp_path / "artifacts", light=True)
    assert outcome.crashes, _report(outcome)
    assert any("escaped read_points" in violation for violation in outcome.violations), _report(outcome)
