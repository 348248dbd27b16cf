"""DCP-v1 (esmicp_lab.baselines.dcp, .dcp_model): the authors' state loads strictly from a
weights-only file, the model recovers poses inside its training distribution (rotations of up to 45
degrees per Euler angle, translations of up to 0.5, ModelNet40 objects in the unit sphere), and the
adapter maps the pose back to the caller's units and frames.

Needs torch and the shared ``dcp/dcp_v1.t7``: skipped locally when missing, failed in CI.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import require_shared
from scipy.spatial.transform import Rotation
from conftest import require_module
from test_baselines_methods import _weights_from_the_shared_folder, require_weights  # noqa: F401 (fixture)

from esmicp_lab.baselines import get_baseline
from esmicp.metrics import rotation_error_deg, translation_error

WEIGHTS = "dcp/dcp_v1.t7"

#: Non-symmetric ModelNet40 objects (vase / bottle / cup / lamp turn about their axis).
OBJECTS = ("airplane_0126", "guitar_0165", "chair_0848", "piano_0226", "person_0025")


@pytest.fixture(autouse=True)
def _needs_torch_and_weights():
    require_module("torch", "learned")
    require_weights(WEIGHTS)


def _object(name: str, points: int, seed: int) -> np.ndarray:
    path = require_shared(f"modelnet40/{name.split('_')[0]}/{name}.txt")
    cloud = np.loadtxt(path, delimiter=",")[:, :3]
    return cloud[np.random.default_rng(seed).choice(len(cloud), points, replace=False)]


def _training_pair(cloud: np.ndarray, rng: np.random.Generator):
    """The authors' ModelNet40 protocol: target = R source + t, Euler angles in [0, 45] degrees,
    t in [-0.5, 0.5]^3, both clouds the same points in independent orders. Returns
    ``(source, target, T_target_source)``."""
    rotation = Rotation.from_euler("zyx", rng.uniform(0.0, np.pi / 4, 3)).as_matrix()
    shift = rng.uniform(-0.5, 0.5, 3)
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = rotation, shift
    source = cloud[rng.permutation(len(cloud))]
    target = (cloud @ rotation.T + shift)[rng.permutation(len(cloud))]
    return source, target, truth


def test_the_authors_state_loads_strictly_from_a_weights_only_file():
    import torch

    from esmicp_lab.baselines.dcp import load_model
    from esmicp_lab.baselines.dcp_model import DCPv1

    path = require_weights(WEIGHTS)
    state = torch.load(path, map_location="cpu", weights_only=True)  # raises on anything but tensors
    fresh = DCPv1()
    assert list(fresh.state_dict()) == list(state)  # same keys, same order
    assert sum(v.numel() for v in state.values()) == 311_694  # as the weights README says
    fresh.load_state_dict(state, strict=True)  # raises on any missing or unexpected key
    model = load_model()
    assert not model.training
    assert torch.equal(model.emb_nn.conv5.weight, state["emb_nn.conv5.weight"])
    assert torch.equal(model.head.reflect, torch.diag(torch.tensor([1.0, 1.0, -1.0])))


def test_dcp_v1_recovers_poses_of_its_training_distribution():
    # Measured on 5 objects x 2 poses: 0.4-3.2 degrees (DCP's paper: a rotation RMSE of a few
    # degrees on this protocol). A wrong port (source / target swapped, R transposed, the pointer's
    # doubling missed) gives tens of degrees.
    rng = np.random.default_rng(7)
    errors, shifts = [], []
    for name in OBJECTS:
        cloud = _object(name, 1024, seed=1)
        for _ in range(2):
            source, target, truth = _training_pair(cloud, rng)
            result = get_baseline("dcp-v1")(source, target, rng=3)
            assert result.method == "dcp-v1" and "dcp_v1.t7" in result.notes
            errors.append(rotation_error_deg(result.transformation, truth))
            shifts.append(translation_error(result.transformation, truth))
    errors = np.array(errors)
    assert np.median(errors) < 3.0, errors
    assert np.mean(errors < 5.0) >= 0.8, errors
    assert np.median(shifts) < 0.02, shifts


def test_the_pose_comes_back_in_the_callers_units_and_frames():
    # The same problem 40x larger and 1,000 units away: the network sees the same normalised
    # clouds, so the rotation is the same and the translation scales. (1,024 points: with more,
    # the two clouds are subsampled independently and DCP-v1, trained on copies, degrades.)
    cloud = _object("chair_0848", 1024, seed=2)
    source, target, truth = _training_pair(cloud, np.random.default_rng(11))
    small = get_baseline("dcp-v1")(source, target, rng=5)
    offset = np.array([1000.0, -400.0, 250.0])
    big = get_baseline("dcp-v1")(40.0 * source + offset, 40.0 * target - offset, rng=5)
    big_truth = np.eye(4)
    big_truth[:3, :3] = truth[:3, :3]
    big_truth[:3, 3] = 40.0 * truth[:3, 3] - offset - truth[:3, :3] @ offset
    assert rotation_error_deg(small.transformation, truth) < 5.0
    assert rotation_error_deg(big.transformation, small.transformation) < 0.05
    assert translation_error(big.transformation, big_truth, 40.0 * source.mean(axis=0) + offset) < 40.0 * 0.03
    # init moves the source first: from the truth, a second estimate stays near it.
    again = get_baseline("dcp-v1")(source, target, init=small.transformation, rng=5)
    assert rotation_error_deg(again.transformation, truth) < 5.0
