"""The configuration tree: frozen, validated, round-trips through a dict, every field documented,
and taken by ``register_scans(config=...)`` as the keywords it mirrors."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest
from scipy.spatial import cKDTree

import esmicp
from esmicp.config import MergeConfig, RefineConfig, RegistrationConfig
from esmicp.core.config import NeighbourIndexConfig
from esmicp.core.correspondence import NearestNeighbors
from esmicp.errors import InvalidInputError
from esmicp.globalreg.config import KeypointConfig, SearchConfig
from esmicp.methods import make_estimator
from esmicp.methods.config import EsmConfig, LoopConfig, PlaneConfig
from esmicp.multiview import register_scans
from esmicp.shapes import asymmetric_shape
from esmicp.trust.policy import DEFAULT_POLICY, TrustPolicy

from test_multiview import _clouds, _patch, _truth

CONFIGS = (MergeConfig, RefineConfig, TrustPolicy, RegistrationConfig, EsmConfig, PlaneConfig, LoopConfig,
           NeighbourIndexConfig, KeypointConfig)


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
    if kind is RegistrationConfig:
        changed = {"search": SearchConfig(keypoints=3000, spread_range=(0.04, 0.2)), "trust": TrustPolicy(inflation=2.0),
                   "refine": RefineConfig(plane_iterations=0)}
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


@pytest.mark.parametrize("changes, field", [
    ({"trusted": -0.1}, "trusted"),
    ({"max_free_space": 1.5}, "max_free_space"),
    ({"free_space_points": 0}, "free_space_points"),
    ({"premise_min_points": 16}, "premise_min_points"),
    ({"min_angular_radius_deg": 180.0}, "min_angular_radius_deg"),
    ({"inflation": 0.0}, "inflation"),
    ({"degenerate_ratio": float("inf")}, "degenerate_ratio"),
    ({"negligible_weight": 1.0}, "negligible_weight"),
])
def test_an_invalid_trust_value_is_refused_naming_its_field(changes, field):
    with pytest.raises(InvalidInputError, match=rf"^TrustPolicy\.{field}: expected a "):
        TrustPolicy(**changes)


@pytest.mark.parametrize("changes, field", [
    ({"strided_points": 0}, "strided_points"),
    ({"strided_tolerance": -1e-6}, "strided_tolerance"),
    ({"plane_iterations": 2.0}, "plane_iterations"),
    ({"inlier_distance_spacings": 0.0}, "inlier_distance_spacings"),
])
def test_an_invalid_refinement_value_is_refused_naming_its_field(changes, field):
    with pytest.raises(InvalidInputError, match=rf"^RefineConfig\.{field}: expected a "):
        RefineConfig(**changes)


@pytest.mark.parametrize("kind, field, value", [(MergeConfig, "sparse_second_try", "no"),
                                                (RefineConfig, "second_try", 1), (RefineConfig, "second_try", None)])
def test_a_flag_is_true_or_false_and_nothing_else(kind, field, value):
    """A flag field takes True or False (numpy's too, stored as a bool) and refuses anything else,
    naming its field."""
    with pytest.raises(InvalidInputError, match=rf"^{kind.__name__}\.{field}: expected True or False, got "):
        kind(**{field: value})
    stored = getattr(kind(**{field: np.bool_(False)}), field)
    assert stored is False
    assert kind.from_dict(kind(**{field: True}).to_dict()) == kind(**{field: True})


def test_the_methods_take_their_values_from_the_tree():
    """A method made with the tree's records uses their values, not the defaults (lengths as gains
    times the target's spacing)."""
    spacing, diagonal = 0.01, 1.0
    esm = make_estimator("esm", None, spacing, diagonal, esm=EsmConfig(sigma_floor_spacings=5.0))
    assert esm.sigma.floor == pytest.approx(5.0 * spacing)
    assert esm.sigma.config.sigma_floor_spacings == 5.0
    paper = make_estimator("esm-paper", None, spacing, diagonal, esm=EsmConfig(paper_sigma=0.3))
    assert paper.sigma == 0.3
    plane = make_estimator("esm-plane", None, spacing, diagonal, esm=EsmConfig(sigma_floor_spacings=4.0,
                                                                                  fine_phase_step=1e-2),
                           plane=PlaneConfig(normal_neighbours=7))
    assert plane.floor == pytest.approx(4.0 * spacing)
    assert (plane.config.normal_neighbours, plane.fine_phase_step) == (7, 1e-2)
    with pytest.raises(InvalidInputError, match=r"^PlaneConfig\.normal_neighbours: expected a "):
        PlaneConfig(normal_neighbours=2)
    with pytest.raises(InvalidInputError, match=r"^EsmConfig\.start_quantile: expected a "):
        EsmConfig(start_quantile=1.5)


@pytest.mark.parametrize("index", [NeighbourIndexConfig(), NeighbourIndexConfig(near_query_min=0, hash_miss_limit=1.0,
                                                                                  near_cell_spacings=0.5),
                                   NeighbourIndexConfig(near_query_min=10**9, graph_neighbours=0)])
def test_the_index_answers_exactly_whatever_its_values(index):
    """The index's values choose how it answers (tree, hash, graph), never what: every answer is
    the exact nearest distance."""
    rng = np.random.default_rng(3)
    target = rng.normal(size=(3000, 3))
    points = target[:1000] + rng.normal(scale=0.01, size=(1000, 3))
    nearest = NearestNeighbors(target, workers=1, config=index)
    expected = cKDTree(target).query(points)[0]
    distances, indices = nearest.query_near(points)
    np.testing.assert_allclose(distances, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(target[indices] - points, axis=1), expected, rtol=0, atol=1e-12)


def test_nested_configs_are_read_from_dicts_and_checked():
    tree = MergeConfig.from_dict({"partners": 3, "registration": {"trust": {"trusted": 0.6},
                                                                  "search": {"keypoints": 3000}}})
    assert tree.registration.trust.trusted == 0.6 and tree.registration.search.keypoints == 3000
    assert tree.registration.trust == dataclasses.replace(DEFAULT_POLICY, trusted=0.6)
    with pytest.raises(InvalidInputError, match=r"^MergeConfig\.registration: unknown field\(s\) 'policy'"):
        MergeConfig.from_dict({"registration": {"policy": {}}})
    with pytest.raises(InvalidInputError, match=r"^TrustPolicy\.trusted: expected a finite number >= 0, got -1"):
        RegistrationConfig.from_dict({"trust": {"trusted": -1}})
    with pytest.raises(InvalidInputError, match=r"^RegistrationConfig\.trust: expected a TrustPolicy or a dict"):
        RegistrationConfig(trust=0.5)
    # register's config: a RegistrationConfig, a SearchConfig or a dict of either's fields
    search = SearchConfig(keypoints=3000)
    assert RegistrationConfig.of(search) == RegistrationConfig(search=search)
    assert RegistrationConfig.of({"keypoints": 3000}) == RegistrationConfig(search=search)
    assert RegistrationConfig.of({"search": {"keypoints": 3000}}) == RegistrationConfig(search=search)
    assert RegistrationConfig.of({"refine": {"plane_iterations": 0}}).refine.plane_iterations == 0
    assert RegistrationConfig.of(None) == RegistrationConfig() == RegistrationConfig.of({})
    with pytest.raises(InvalidInputError, match=r"^SearchConfig\.keypoints"):
        RegistrationConfig.of({"keypoints": 0})
    with pytest.raises(InvalidInputError, match=r"MergeConfig\(registration=\.\.\.\)"):
        MergeConfig.of(search)


def test_register_judges_by_the_policy_it_is_given_and_keeps_it():
    """The same pose under any trust policy; the bar it is judged by is the policy's, kept in the
    result."""
    rng = np.random.default_rng(5)
    target = asymmetric_shape(800, rng)
    source = target[rng.permutation(len(target))][:600] + 0.2
    default = esmicp.register(source, target, rng=1)
    assert default.trusted and default.policy == DEFAULT_POLICY
    strict = TrustPolicy(trusted=1.01)
    judged = esmicp.register(source, target, rng=1, config=RegistrationConfig(trust=strict))
    assert np.array_equal(judged.transformation, default.transformation) and judged.policy == strict
    assert not judged.trusted and f"below {1.01:g}" in judged.doubts()[0]
    as_dict = esmicp.register(source, target, rng=1, config={"trust": {"trusted": 1.01}})
    assert as_dict.policy == strict and np.array_equal(as_dict.transformation, default.transformation)


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
    # the pairwise registrations are judged by the tree's trust policy: above every pair's
    # confidence (0.9 and 0.95 here), no edge is trusted and no scan but the reference placed
    strict = dataclasses.replace(config, registration=RegistrationConfig(trust=TrustPolicy(trusted=0.99)))
    alone = merge(config=strict)
    assert alone.status == ("placed",) + ("unplaced",) * 6 and not any(e.trusted for e in alone.edges)


def test_the_merge_checks_its_pairs_no_looser_than_register_stops_after_a_search():
    """``MergeConfig.check_tolerance`` is documented as finer than the refinement's own after a
    global search (``RefineConfig.strided_tolerance``)."""
    assert MergeConfig().check_tolerance <= RefineConfig().strided_tolerance
