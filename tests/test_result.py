"""What a result shows a person and a program: a one-line ``repr`` (not its arrays), the pose's
size, and ``to_dict``'s ``trusted`` and ``doubts`` agreeing with the result's own."""

from __future__ import annotations

import numpy as np

from esmicp.core.procrustes import to_matrix
from esmicp.metrics import rotation_error_deg
from esmicp.result import RegistrationResult


def _result(**fields) -> RegistrationResult:
    angle = np.radians(30.0)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    values = dict(transformation=to_matrix(rotation, [0.3, 0.0, 0.4]), converged=True, num_iterations=12, fitness=0.81,
                  inlier_rmse=0.01, inlier_distance=0.05, runtime_s=0.42, method="esm", sigma=0.02, message="converged",
                  confidence=0.97, covariance=np.eye(6) * 1e-6, information=np.eye(6) * 1e6,
                  runner_up=np.eye(4), history=())
    values.update(fields)
    return RegistrationResult(**values)


def test_repr_is_one_line_with_the_verdict_and_the_pose_not_the_arrays():
    result = _result()
    text = repr(result)
    assert "\n" not in text and len(text) < 160, text
    assert text.startswith("RegistrationResult(method='esm', trusted=True, confidence=0.97, fitness=0.81")
    assert "rotation=30 deg" in text and "translation=0.5," in text and "0.42 s" in text
    assert "array" not in text and str(result) == text
    untrusted = repr(_result(confidence=0.2))
    assert "trusted=False, confidence=0.20" in untrusted
    assert "confidence=None" in repr(_result(confidence=None))


def test_the_pose_size_is_the_rotation_angle_and_the_translation_length():
    result = _result()
    assert np.isclose(result.rotation_deg, rotation_error_deg(result.transformation, np.eye(4)))
    assert np.isclose(result.rotation_deg, 30.0) and np.isclose(result.translation_norm, 0.5)
    flipped = _result(transformation=to_matrix(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.0]))
    assert np.isclose(flipped.rotation_deg, 180.0) and flipped.translation_norm == 0.0


def test_to_dict_carries_trusted_and_the_doubts_behind_it():
    for result in (_result(), _result(confidence=0.2), _result(converged=False), _result(ambiguous=True)):
        report = result.to_dict()
        assert report["doubts"] == result.doubts()
        assert report["trusted"] is result.trusted is (not report["doubts"])
    assert _result(confidence=0.2).to_dict()["doubts"] and not _result().to_dict()["doubts"]


def test_the_grouped_records_read_the_fields_and_follow_a_replaced_one():
    """``search``, ``uncertainty`` and ``trust`` group the flat fields as frozen records, made from
    the fields when asked: a field replaced shows in its record."""
    import dataclasses

    import pytest

    result = _result(init="global:scan", global_candidates=7, ambiguous=True, runner_up_ratio=0.98)
    search = result.search
    assert (search.init, search.candidates, search.ambiguous, search.runner_up_ratio) == ("global:scan", 7, True, 0.98)
    assert search.runner_up is result.runner_up
    uncertainty = result.uncertainty
    assert uncertainty.covariance is result.covariance and uncertainty.information is result.information
    assert uncertainty.degenerate_directions == () and uncertainty.pairs == 0  # built by hand: not said
    assert not result.trust.trusted and [d.kind for d in result.trust.doubts] == ["ambiguous"]
    assert [d.words for d in result.trust.doubts] == result.doubts()
    with pytest.raises(dataclasses.FrozenInstanceError):
        search.init = "given"
    with pytest.raises(dataclasses.FrozenInstanceError):
        uncertainty.pairs = 1
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.trust.confidence = 0.0
    cleared = dataclasses.replace(result, ambiguous=False, covariance=None, init="given")
    assert cleared.search.init == "given" and not cleared.search.ambiguous and cleared.uncertainty.covariance is None
    assert cleared.trust.trusted and cleared.trusted
