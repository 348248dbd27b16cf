"""Hypothesis-generated malformed files for every reader: every input ends in a valid cloud or the
library's own error with a clear message (the contract of ``fuzz/harness.py``).

The files are valid seeds (``harness.seeds``) broken the ways real files break: cut short, bits
flipped, bytes overwritten, a header number that lies (counts of 0, -1, 2^32, 10^12, "nan", ...),
a type word replaced by a wrong one, and combinations. The default run tries
``ESMICP_FUZZ_EXAMPLES`` (default 40) files per reader; the ``slow`` variant 2,000.
Run the long one with ``python -m pytest -m slow tests/test_fuzz_hypothesis.py``.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fuzz"))

import harness  # noqa: E402
import mutations  # noqa: E402

DEFAULT_EXAMPLES = int(os.environ.get("ESMICP_FUZZ_EXAMPLES", "40"))
SLOW_EXAMPLES = 2000

_SEEDS: dict[str, list[bytes]] = {}


def seed_files(target: str) -> list[bytes]:
    if target not in _SEEDS:
        _SEEDS[target] = harness.seeds(target)
    return _SEEDS[target]


_positions = st.integers(0, 1 << 16)
_one_mutation = st.one_of(
    st.tuples(st.just("cut"), _positions),
    st.tuples(st.just("flip"), st.lists(st.tuples(_positions, st.integers(0, 7)), min_size=1, max_size=6)),
    st.tuples(st.just("overwrite"), _positions, st.binary(min_size=1, max_size=12)),
    st.tuples(st.just("lie"), st.integers(0, 40), st.sampled_from(mutations.HOSTILE_NUMBERS)),
    st.tuples(st.just("type"), st.integers(0, 20), st.sampled_from(mutations.WRONG_TYPES)),
)
mutation_lists = st.lists(_one_mutation, min_size=1, max_size=3)


def mutate(data: bytes, steps) -> bytes:
    for step in steps:
        kind, *arguments = step
        if kind == "cut":
            data = mutations.cut(data, *arguments)
        elif kind == "flip":
            data = mutations.flip_bits(data, *arguments)
        elif kind == "overwrite":
            data = mutations.overwrite(data, *arguments)
        elif kind == "lie":
            data = mutations.header_lie(data, *arguments)
        else:
            data = mutations.wrong_type(data, *arguments)
    return data


def check_mutated(target: str, seed_index: int, steps) -> None:
    seeds = seed_files(target)
    data = mutate(seeds[seed_index % len(seeds)], steps)
    if not data:
        return  # an empty file: covered by test_io's empty-file tests
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / f"mutated{harness.TARGETS[target].extension}"
        path.write_bytes(data)
        harness.check_file(path)


def _fuzz_test(examples: int):
    @settings(
        max_examples=examples, deadline=None, database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(seed_index=st.integers(0, 10), steps=mutation_lists)
    def run(target, seed_index, steps):
        check_mutated(target, seed_index, steps)

    return run


_default_run = _fuzz_test(DEFAULT_EXAMPLES)
_slow_run = _fuzz_test(SLOW_EXAMPLES)


@pytest.mark.parametrize("target", sorted(harness.TARGETS))
def test_mutated_files_end_in_points_or_a_clear_error(target):
    _default_run(target)


@pytest.mark.slow
@pytest.mark.parametrize("target", sorted(harness.TARGETS))
def test_mutated_files_long_run(target):
    _slow_run(target)


def test_every_seed_is_a_valid_cloud():
    """The mutations start from valid files: each seed reads back as a cloud."""
    with tempfile.TemporaryDirectory() as directory:
        for target in harness.TARGETS.values():
            for index, data in enumerate(seed_files(target.name)):
                path = Path(directory) / f"seed{index}{target.extension}"
                path.write_bytes(data)
                assert harness.check_file(path) == "points", (target.name, index)


def test_the_contract_catches_violations(tmp_path, monkeypatch):
    """The oracle can fail: a stray exception, a catch-all message and a NaN cloud are all caught."""
    import numpy as np

    import esmicp.io

    path = tmp_path / "cloud.xyz"
    path.write_bytes(b"1 2 3\n4 5 6\n7 8 9\n")
    assert harness.check_file(path) == "points"

    def raises_index_error():
        raise IndexError("list index out of range")

    monkeypatch.setattr(esmicp.io.text, "read_text", lambda _path: raises_index_error())
    with pytest.raises(harness.ContractViolation, match="catch-all"):
        harness.check_file(path)
    monkeypatch.setattr(esmicp.io, "read_points", lambda _path: raises_index_error())
    with pytest.raises(harness.ContractViolation, match="IndexError escaped"):
        harness.check_file(path)
    monkeypatch.setattr(esmicp.io, "read_points", lambda _path: np.full((3, 3), np.nan))
    with pytest.raises(harness.ContractViolation, match="NaN"):
        harness.check_file(path)


def test_mutations_do_what_they_say():
    ply = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n2\n3\n"
    assert mutations.header_lie(ply, 1, "1000000000000").count(b"element vertex 1000000000000") == 1
    assert b"property double x" in mutations.wrong_type(ply, 0, "double")
    assert mutations.cut(ply, 10) == ply[:10]
    assert mutations.flip_bits(b"\x00", [(0, 3)]) == b"\x08"
    npy = seed_files("npy")[0]
    assert b"'>f4'" in mutations.wrong_type(npy, 0, ">f4")
    stl = seed_files("stl")[1]
    assert mutations.header_lie(stl, 0, "4294967295")[80:84] == b"\xff\xff\xff\xff"
