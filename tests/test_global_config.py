"""The global search's configuration object: frozen, round-trips, validated, taken by register."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

import esmicp
from esmicp.errors import InvalidInputError
from esmicp.globalreg.config import DEFAULT, SearchConfig, as_config
from esmicp.shapes import asymmetric_shape


def test_the_config_round_trips_through_a_dict_and_json():
    changed = dataclasses.replace(DEFAULT, ambiguity_ratio=0.9, keypoints=3000, spread_range=(0.04, 0.2),
                                  verification=dataclasses.replace(DEFAULT.verification, rounds=((100, 4, 5),)),
                                  scan=dataclasses.replace(DEFAULT.scan, last_keypoints=(8000,)))
    for config in (DEFAULT, changed):
        data = json.loads(json.dumps(config.to_dict()))
        assert SearchConfig.from_dict(data) == config
    assert SearchConfig.from_dict({}) == DEFAULT


def test_the_config_is_frozen_and_small():
    """Every record of the search's configuration is frozen and holds at most 20 fields."""
    with pytest.raises(dataclasses.FrozenInstanceError):
        DEFAULT.confident = 0.1  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        DEFAULT.scan.seeds = 1  # type: ignore[misc]
    records = [SearchConfig] + [type(getattr(DEFAULT, field.name)) for field in dataclasses.fields(SearchConfig)
                                if dataclasses.is_dataclass(getattr(DEFAULT, field.name))]
    assert len(records) == 5
    for record in records:
        assert len(dataclasses.fields(record)) <= 20, record.__name__


@pytest.mark.parametrize("changes, field", [
    ({"ambiguity_ratio": 1.5}, "SearchConfig.ambiguity_ratio"),
    ({"confident": -0.1}, "SearchConfig.confident"),
    ({"rotation": {"rotations": 0}}, "RotationSearchConfig.rotations"),
    ({"keypoints": 2.5}, "SearchConfig.keypoints"),
    ({"sharpness_range": (0.8, 0.5)}, "SearchConfig.sharpness_range"),
    ({"verification": {"score_width_spacings": float("nan")}}, "VerificationConfig.score_width_spacings"),
    ({"scan_candidates": True}, "SearchConfig.scan_candidates"),
    ({"scan_searches": 0}, "SearchConfig.scan_searches"),
    ({"scan": {"last_keypoints": (100, "many")}}, "ScanStrategyConfig.last_keypoints"),
    ({"features": {"fpfh_radius_voxels": 0.0}}, "FeatureMatchingConfig.fpfh_radius_voxels"),
])
def test_an_invalid_value_is_refused_naming_its_field(changes, field):
    with pytest.raises(InvalidInputError, match=field):
        SearchConfig(**changes)


def test_unknown_fields_and_wrong_types_are_refused():
    with pytest.raises(InvalidInputError, match="unknown field.*'confidance'"):
        SearchConfig.from_dict({"confidance": 0.5})
    with pytest.raises(InvalidInputError, match="config: expected"):
        as_config(0.5)
    with pytest.raises(InvalidInputError, match="SearchConfig.decide_ratio"):
        esmicp.register(np.eye(3) + 1, np.eye(3), config={"decide_ratio": 2.0})


def test_register_takes_a_config_and_its_values_reach_the_search():
    """The same registration with the default passed explicitly, as a dict, or implied gives the
    same pose; a config whose ambiguity ratio is 0 flags any distinct runner-up as ambiguous."""
    rng = np.random.default_rng(5)
    target = asymmetric_shape(800, rng)
    source = target[rng.permutation(len(target))][:600] + 0.2
    implied = esmicp.register(source, target, rng=1)
    explicit = esmicp.register(source, target, rng=1, config=DEFAULT)
    as_dict = esmicp.register(source, target, rng=1, config=DEFAULT.to_dict())
    assert np.array_equal(implied.transformation, explicit.transformation)
    assert np.array_equal(implied.transformation, as_dict.transformation)
    anything = esmicp.register(source, target, rng=1, config=dataclasses.replace(DEFAULT, ambiguity_ratio=0.0))
    assert anything.ambiguous == (anything.runner_up_ratio is not None)


def test_scan_searches_bounds_the_scan_strategy_and_the_default_leaves_it_unbounded(monkeypatch):
    """Two clouds that share no surface (a sphere and an asymmetric shape): no scan search is
    confident, so the default runs more than one of them (each setting, then other voxels), and
    ``scan_searches=1`` exactly one."""
    calls = _counted_scan_searches(monkeypatch)
    rng = np.random.default_rng(3)
    target = asymmetric_shape(250, rng)
    directions = rng.normal(size=(250, 3))
    source = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    esmicp.register(source, target, rng=2, workers=1)
    assert DEFAULT.scan_searches is None and len(calls) >= 2
    calls.clear()
    esmicp.register(source, target, rng=2, workers=1, config=dataclasses.replace(DEFAULT, scan_searches=1))
    assert len(calls) == 1


def test_a_cloud_of_scattered_points_gets_the_scattered_pairs_scan_searches(monkeypatch):
    """Points scattered through a cube (every one isolated: the cloud carries scattered points)
    against an asymmetric shape: no scan search is confident, and the search runs at most
    ``verification.scattered_scan_searches`` of them."""
    calls = _counted_scan_searches(monkeypatch)
    rng = np.random.default_rng(3)
    source, target = rng.uniform(-1, 1, (250, 3)), asymmetric_shape(250, rng)
    for most in (DEFAULT.verification.scattered_scan_searches, 2):
        calls.clear()
        config = dataclasses.replace(DEFAULT, verification=dataclasses.replace(DEFAULT.verification,
                                                                               scattered_scan_searches=most))
        esmicp.register(source, target, rng=2, workers=1, config=config)
        assert len(calls) == most


def _counted_scan_searches(monkeypatch) -> list:
    """The voxel of every scan-strategy search run from now on (``scan.scan_estimate`` counted)."""
    from esmicp.globalreg import scan

    calls = []
    real = scan.scan_estimate

    def counted(*args, **kwargs):
        calls.append(kwargs.get("voxel"))
        return real(*args, **kwargs)

    monkeypatch.setattr(scan, "scan_estimate", counted)
    return calls
