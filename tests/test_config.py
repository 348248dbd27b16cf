"""The configuration tree: frozen, validated, round-trips through a dict, every field documented,
and taken by ``register_scans(config=...)`` as the keywords it mirrors."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

from esmicp.config import MergeConfig
from esmicp.errors import InvalidInputError
from esmicp.multiview import register_scans

from test_multiview import _clouds, _patch, _truth

CONFIGS = (MergeConfig,)


@pytest.mark.parametrize("kind", CONFIGS)
def test_a_config_round_trips_through_a_dict_and_json(kind):
    default = kind()
    assert kind.from_dict({}) == default
    assert kind.from_dict(json.loads(json.dumps(default.to_dict()))) == default
    changed = {}
    for field in dataclasses.fields(kind):
        value = getattr(default, field.name)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        changed[field.name] = value + 1 if isinstance(value, int) else value / 2
    other = kind(**changed)
    assert other != default
    assert kind.from_dict(json.loads(json.dumps(other.to_dict()))) == other


@pytest.mark.parametrize("kind", CONFIGS)
def test_a_config_is_frozen_and_every_field_is_documented(kind):
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(kind(), dataclasses.fields(kind)[0].name, 1)
    documented = set(re.findall(r"^    (\w+) : ", kind.__doc__, flags=re.MULTILINE))
    assert {field.name for field in dataclasses.fields(kind)} == documented


@pytest.mark.parametrize("changes, field", [
    ({"pair_points": 2}, "pair_points"),
    ({"partners": 0}, "partners"),
    ({"partners": 1.5}, "partners"),
    ({"stalled_rounds": True}, "stalled_rounds"),
    ({"min_predicted_overlap": 1.2}, "min_predicted_overlap"),
    ({"predict_radius_inliers": 0.0}, "predict_radius_inliers"),
    ({"refine_floor_spacings": float("nan")}, "refine_floor_spacings"),
    ({"loop_searches_per_scan": -0.1}, "loop_searches_per_scan"),
    ({"max_edge_error_deg": "2"}, "max_edge_error_deg"),
    ({"refine_rounds": -1}, "refine_rounds"),
])
def test_an_invalid_merge_value_is_refused_naming_its_field(changes, field):
    with pytest.raises(InvalidInputError, match=rf"^MergeConfig\.{field}: expected a "):
        MergeConfig(**changes)
    with pytest.raises(InvalidInputError, match=rf"^MergeConfig\.{field}: expected a "):
        dataclasses.replace(MergeConfig(), **changes)


def test_unknown_fields_and_other_types_are_refused():
    with pytest.raises(InvalidInputError, match=r"^MergeConfig: unknown field\(s\) 'partner'; known: "):
        MergeConfig.from_dict({"partner": 3})
    with pytest.raises(InvalidInputError, match="^MergeConfig: expected a dict"):
        MergeConfig.from_dict([("partners", 3)])
    with pytest.raises(InvalidInputError, match="^config: expected a MergeConfig or a dict, got float"):
        register_scans([np.eye(3), np.eye(3)], config=0.5)
    with pytest.raises(InvalidInputError, match="^MergeConfig.partners"):
        register_scans([np.eye(3), np.eye(3)], config={"partners": 0})
    # a keyword keeps its own name in the message
    with pytest.raises(InvalidInputError, match=r"^refine_rounds: expected a whole number >= 0, got -1$"):
        register_scans([np.eye(3), np.eye(3)], refine_rounds=-1)


def _digest(result):
    return (result.poses.tobytes(), result.status, result.reasons, result.pairs_registered,
            [(e.i, e.j, e.T_i_j.tobytes(), e.kept, e.reason) for e in result.edges])


def test_register_scans_takes_a_config_as_the_keywords_it_mirrors(monkeypatch):
    """The same merge from the keywords, from a MergeConfig and from its dict; a keyword given
    wins over the config's field; and the config's values reach the merge (fewer partners, fewer
    pairs)."""
    rng = np.random.default_rng(12)
    truth = _truth(7, rng)
    clouds = _clouds(truth, rng)

    def merge(**options):
        monkeypatch.undo()  # each merge with its own stand-in (it follows one merge's subsets)
        _patch(monkeypatch, truth, clouds, wrong={(1, 3)})
        return register_scans(clouds, threads=1, **options)

    keywords = merge(partners=3, max_edge_error_deg=1.0, refine_rounds=0)
    assert keywords.status == ("placed",) * 7 and keywords.rejected_edges, keywords.reasons
    config = MergeConfig(partners=3, max_edge_error_deg=1.0, refine_rounds=0)
    assert _digest(merge(config=config)) == _digest(keywords)
    assert _digest(merge(config=config.to_dict())) == _digest(keywords)
    assert _digest(merge(partners=3, config=dataclasses.replace(config, partners=1))) == _digest(keywords)
    fewer = merge(config=dataclasses.replace(config, partners=1))
    assert fewer.pairs_registered < keywords.pairs_registered
