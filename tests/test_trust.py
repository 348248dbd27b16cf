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
