"""Replay of the inputs the fuzzers found (``tests/corpus/<target>/<what>--<outcome><ext>``).

Each file once broke the readers' contract (``fuzz/harness.py``): a stray exception or warning, a
message that dumped the file's bytes, a valid file refused. It must now keep the contract AND end
the way its name says (``--points``: a valid cloud; ``--error``: a clear PointCloudFileError).
Add new findings with ``python fuzz/add_to_corpus.py``.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "fuzz"))

import harness  # noqa: E402

CORPUS = Path(__file__).resolve().parent / "corpus"
CASES = sorted(path for path in CORPUS.glob("*/*") if path.is_file())


def test_corpus_is_not_empty_and_well_named():
    assert len(CASES) >= 10
    for path in CASES:
        assert path.parent.name in harness.TARGETS, path
        assert path.suffix == harness.TARGETS[path.parent.name].extension, path
        assert path.stem.rsplit("--", 1)[-1] in ("points", "error"), path
        assert path.stat().st_size <= 4096, f"{path}: keep corpus files tiny"


@pytest.mark.parametrize("path", CASES, ids=[f"{p.parent.name}/{p.name}" for p in CASES])
def test_corpus_case(path, tmp_path):
    # Read a copy: the error message must name the file that was given, wherever it is.
    copy = tmp_path / path.name
    shutil.copyfile(path, copy)
    expected = path.stem.rsplit("--", 1)[-1]
    assert harness.check_file(copy) == expected
