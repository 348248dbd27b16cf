"""``RegistrationResult.trusted`` on a scene built to fool it: ray-cast depth frames of a box room,
whose overlaps are mostly single walls (a pose may slide along them) and whose corners all look
alike (a pose may land on the wrong one). Whatever the method or start, a pose far off is never
trusted, and ``doubts()`` says why."""

from __future__ import annotations

import numpy as np
import pytest

import esmicp
from esmicp_lab.bench.real_pairs import pair_errors

from test_merge_visibility import walk  # noqa: F401  (ray-cast depth frames of a room, 25 degrees apart)


@pytest.mark.parametrize("frame", [1, 2, 3])
def test_no_pose_far_off_is_trusted_on_a_box_room(walk, frame):  # noqa: F811
    clouds, poses, _ = walk
    truth = poses[frame]
    runs = {method: esmicp.register(clouds[frame], clouds[0], init=truth, method=method, workers=1)
            for method in ("esm", "esm-plane", "icp")}
    runs["global"] = esmicp.register(clouds[frame], clouds[0], rng=0, workers=1)
    for name, result in runs.items():
        rotation, translation = pair_errors(result.transformation, truth)
        assert result.trusted == (not result.doubts())
        if rotation > 5.0 or translation > 0.2:
            assert not result.trusted, (name, rotation, translation, result.confidence)
            assert result.doubts(), name


def test_the_trace_caption_says_why_a_sharp_pose_is_not_trusted():
    """A corridor registered from the identity coincides sharply but slides along its axis: the
    visualisation's caption names the direction, not LOW."""
    from esmicp.viz.trace import trace_registration
    from test_uncertainty import corridor

    rng = np.random.default_rng(2)
    target, source = corridor(6000, rng), corridor(6000, rng) + [0.03, 0.01, 0.0]
    trace = trace_registration(source, target, init="identity", per_point=False)
    assert trace.result.confidence >= 0.55
    assert "not trusted: translation along x (target frame) is poorly constrained" in trace.label


def test_a_run_stopped_before_its_tolerance_is_never_trusted():
    """However sharply the clouds already coincide, a refinement cut short by ``max_iterations`` may
    still be degrees from where it was heading: it is not trusted, and ``doubts()`` says so; the
    same run let to converge is."""
    from esmicp.core.procrustes import apply, to_matrix
    from esmicp.metrics import random_rotation
    from esmicp.shapes import asymmetric_shape

    rng = np.random.default_rng(7)
    target = asymmetric_shape(1500, rng)
    source = apply(to_matrix(random_rotation(rng, 20.0), [0.1, -0.2, 0.05]), asymmetric_shape(1500, rng))
    sharp_but_cut_short = 0
    for method in ("icp", "esm"):
        for iterations in (8, 12, 20):
            result = esmicp.register(source, target, init="identity", method=method, max_iterations=iterations,
                                     workers=1)
            assert not result.converged, (method, iterations)
            assert not result.trusted
            assert any("not converged" in reason for reason in result.doubts())
            sharp_but_cut_short += result.confidence >= result.policy.trusted
        settled = esmicp.register(source, target, init="identity", method=method, workers=1)
        assert settled.converged and settled.trusted, (method, settled.doubts())
    assert sharp_but_cut_short  # the rule, not the confidence, is what refuses them


@pytest.mark.parametrize("method", ["icp", "esm"])
def test_the_bunny_scan_cut_short_is_not_trusted(method):
    """``bun045`` onto ``bun000`` from the identity, cut at 10 iterations: a few degrees off with the
    confidence at its top, so only the convergence can refuse it."""
    from conftest import require_shared
    from esmicp.io.stanford_conf import load_scans

    scans = load_scans(require_shared("bunny_scans"))
    (source, world_source), (target, world_target) = scans["bun045"], scans["bun000"]
    truth = np.linalg.inv(world_target) @ world_source
    result = esmicp.register(source, target, init="identity", method=method, max_iterations=10, workers=1)
    rotation, _ = pair_errors(result.transformation, truth)
    assert rotation > 1.0 and not result.converged  # the case the rule exists for
    assert not result.trusted and result.doubts()[0].startswith("not converged")
