"""``esmicp.register_many``: many pairs on a thread pool (the default), a process pool or a Dask cluster, results in input order
and equal to sequential ``register``, a failing pair reported in its place without losing the
others. Dask is optional: locally its test skips when it is missing; in CI (``CI=true``) it fails.
"""

from __future__ import annotations

import importlib
import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import esmicp
from esmicp import InvalidInputError, RegistrationFailure, register_many
from esmicp.shapes import asymmetric_shape


def _pairs(count: int = 4):
    """Independent samples of the built-in shape, the source moved by 10-25 degrees."""
    pairs = []
    for seed in range(count):
        rng = np.random.default_rng(seed)
        target = asymmetric_shape(600, rng=rng)
        source = asymmetric_shape(500, rng=rng)
        axis = rng.normal(size=3)
        rotation = Rotation.from_rotvec(np.radians(rng.uniform(10, 25)) * axis / np.linalg.norm(axis)).as_matrix()
        pairs.append((source @ rotation.T + rng.normal(scale=0.05, size=3), target))
    return pairs


KWARGS = {"init": "identity", "max_iterations": 60}


def _assert_same(results, expected):
    assert len(results) == len(expected)
    for result, reference in zip(results, expected):
        assert isinstance(result, esmicp.RegistrationResult)
        np.testing.assert_array_equal(result.transformation, reference.transformation)
        assert result.num_iterations == reference.num_iterations
        assert result.fitness == reference.fitness


def test_process_pool_equals_sequential_register_in_input_order():
    pairs = _pairs(4)
    expected = [esmicp.register(source, target, **KWARGS) for source, target in pairs]
    assert len({result.transformation.tobytes() for result in expected}) == len(pairs)
    _assert_same(register_many(pairs, processes=2, **KWARGS), expected)
    _assert_same(register_many(pairs, processes=1, **KWARGS), expected)


def test_thread_pool_is_the_default_and_equals_sequential_register():
    """The default pool is threads (the kernels release the GIL; no ``__main__`` guard needed):
    the same results, in input order, as registering pair by pair."""
    pairs = _pairs(4)
    expected = [esmicp.register(source, target, **KWARGS) for source, target in pairs]
    _assert_same(register_many(pairs, threads=2, **KWARGS), expected)
    _assert_same(register_many(pairs, **KWARGS), expected)


def test_per_pair_inits_start_each_pair_where_given():
    """``inits``: one start per pair (None: the common ``init``); a pair started at its exact pose
    stays there, and the result equals ``register`` with that ``init``."""
    pairs = _pairs(2)
    start = np.eye(4)
    results = register_many(pairs, threads=2, inits=[None, start], init="identity", max_iterations=60)
    _assert_same(results, [esmicp.register(*pairs[0], **KWARGS), esmicp.register(*pairs[1], init=start, max_iterations=60)])
    with pytest.raises(InvalidInputError, match="inits"):
        register_many(pairs, inits=[None])


@pytest.mark.parametrize("processes", [1, 2])
def test_progress_is_reported_after_every_pair(processes):
    calls = []
    register_many(_pairs(3), processes=processes, progress=lambda done, total: calls.append((done, total)), **KWARGS)
    assert calls == [(1, 3), (2, 3), (3, 3)]


def test_failing_pair_is_reported_in_place_and_the_others_survive():
    pairs = _pairs(3)
    pairs.insert(1, (np.zeros((5, 2)), pairs[0][1]))  # malformed source
    results = register_many(pairs, processes=2, **KWARGS)
    assert isinstance(results[1], RegistrationFailure)
    assert results[1].index == 1
    assert results[1].error_type == "InvalidInputError"
    assert "source" in results[1].message and "(5, 2)" in results[1].message
    good = [esmicp.register(source, target, **KWARGS) for source, target in (pairs[0], pairs[2], pairs[3])]
    _assert_same([results[0], results[2], results[3]], good)


def test_bad_arguments_raise_one_clear_error():
    with pytest.raises(InvalidInputError, match="processes"):
        register_many(_pairs(1), processes=0)
    with pytest.raises(InvalidInputError, match="threads"):
        register_many(_pairs(1), threads=0)
    with pytest.raises(InvalidInputError, match=r"pairs\[0\]"):
        register_many([(np.zeros((4, 3)),)])
    with pytest.raises(InvalidInputError, match="pairs"):
        register_many(5)
    with pytest.raises(InvalidInputError, match="progress"):
        register_many(_pairs(1), progress=3)
    assert register_many([], processes=2) == []


def _require_dask():
    try:
        return importlib.import_module("distributed")
    except ImportError as exc:
        message = f"dask.distributed cannot be imported ({exc}): pip install 'esmicp[dask]'"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(message)
        pytest.skip(message)


def test_dask_client_equals_sequential_register():
    distributed = _require_dask()
    pairs = _pairs(3)
    pairs.append((np.full((10, 3), 1.0), pairs[0][1]))  # degenerate: all points identical
    expected = [esmicp.register(source, target, **KWARGS) for source, target in pairs[:3]]
    calls = []
    with distributed.Client(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as client:
        results = register_many(pairs, client=client, progress=lambda done, total: calls.append((done, total)), **KWARGS)
    _assert_same(results[:3], expected)
    assert calls == [(1, 4), (2, 4), (3, 4), (4, 4)]
    assert isinstance(results[3], RegistrationFailure) and results[3].index == 3
