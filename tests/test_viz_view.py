"""The viewer's contract: a pose the caller holds is drawn as given, without registering; the
registration run is drawn only when asked; large scenes keep enough points, evenly spread; a scene
much wider than tall opens in a top view down the declared upward axis."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import require_module, require_shared
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from test_viz_support import require_plotting

from esmicp import io, register
from esmicp.core.procrustes import apply, to_matrix
from esmicp.errors import InvalidInputError
from esmicp.viz import builtin_pair, display_indices, fixed_trace, scene_camera, view, view_figure, view_html
from esmicp.viz.view import DISPLAY_CELLS_ACROSS, DISPLAY_POINTS_CAP


def drawn(figure, trace_index: int) -> np.ndarray:
    data = figure.data[trace_index]
    return np.column_stack([np.asarray(data.x), np.asarray(data.y), np.asarray(data.z)])


def layout_text(figure) -> str:
    """Every text the page shows outside the plot itself: the title and the captions."""
    return " ".join([figure.layout.title.text or ""] + [a.text or "" for a in figure.layout.annotations])


def moved(pose: np.ndarray, degrees: float, seed: int = 0) -> np.ndarray:
    """``pose`` followed by a rotation of ``degrees`` about a random axis and a small shift."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    turn = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix()
    return to_matrix(turn, rng.normal(size=3) * 0.1) @ pose


def test_a_given_pose_is_drawn_as_given_without_registering(monkeypatch):
    """On a 3DMatch pair (fragments 0 and 6, 1 point in 16), drawing a pose the caller holds
    registers nothing (every way into ``register`` is closed while it draws), and draws exactly the
    source moved by that pose (``T_target_source`` maps the source into the target frame), even a
    pose 25 degrees from the registered one: nothing refines it."""
    import esmicp.api
    import esmicp.viz.trace

    require_plotting()
    folder = require_shared("real_pairs/3dmatch_redkitchen")
    source = io.read_points(folder / "geotransformer_src.npy")[::16]
    target = io.read_points(folder / "geotransformer_ref.npy")[::16]
    result = register(source, target)
    wrong = moved(result.transformation, 25.0)
    given = dataclasses.replace(result, transformation=wrong)  # a result the caller holds

    def closed(*args, **kwargs):
        raise AssertionError("the view registered the pair again")

    monkeypatch.setattr(esmicp.api, "register", closed)
    monkeypatch.setattr(esmicp.viz.trace, "register", closed)
    figures = [view_html(source, target, pose) for pose in (wrong, given)]

    shown = display_indices(source)
    for figure in figures:
        np.testing.assert_allclose(drawn(figure, 2), apply(wrong, source)[shown], atol=1e-5)
        np.testing.assert_allclose(drawn(figure, 1), source[shown], atol=1e-5)  # the source as given
        np.testing.assert_allclose(drawn(figure, 0), target[display_indices(target)], atol=1e-5)
        assert figure.layout.meta["registered"] is False
        assert figure.layout.meta["poses"] == [[wrong.tolist()]]
        assert not figure.layout.sliders and not figure.frames
    # A result's verdict captions its view.
    assert f"confidence {result.confidence:.2f}" in figures[1].layout.annotations[0].text


@dataclasses.dataclass
class Open3DLikeResult:  # what open3d.pipelines.registration.RegistrationResult holds
    transformation: np.ndarray
    fitness: float
    inlier_rmse: float


@dataclasses.dataclass
class SmallGicpLikeResult:  # small_gicp.RegistrationResult keeps its pose here
    T_target_source: np.ndarray


def test_other_libraries_results_are_drawn_at_their_pose():
    require_plotting()
    pair = builtin_pair(points=300, angle_deg=50)
    pose = moved(pair.T_target_source, 10.0, seed=3)
    for given in (Open3DLikeResult(pose, 0.75, 0.01), SmallGicpLikeResult(pose), pose.tolist()):
        figure = view_html(pair.source, pair.target, given, truth=pair.T_target_source)
        np.testing.assert_allclose(drawn(figure, 2), apply(pose, pair.source)[display_indices(pair.source)], atol=1e-5)
        assert "rotation error 10 deg" in layout_text(figure)
    labelled = view_html(pair.source, pair.target, Open3DLikeResult(pose, 0.75, 0.01))
    assert "fitness 0.75" in labelled.layout.annotations[0].text
    with pytest.raises(InvalidInputError, match="transformation"):
        view_html(pair.source, pair.target, np.diag([2.0, 1.0, 1.0, 1.0]))  # not rigid


def test_the_run_is_drawn_only_when_asked():
    """``view_html(source, target)`` registers as ``register`` does and draws its pose, with no
    slider and no word of one; ``show_run=True`` adds the iterations, ending at the same pose."""
    require_plotting()
    pair = builtin_pair(points=300, angle_deg=120)
    reference = register(pair.source, pair.target)
    figure = view_html(pair.source, pair.target)
    assert figure.layout.meta["registered"] is True
    np.testing.assert_array_equal(np.array(figure.layout.meta["poses"][0][-1]), reference.transformation)
    assert len(figure.layout.meta["poses"][0]) == 1
    assert not figure.layout.sliders and not figure.frames and "slider" not in layout_text(figure)

    run = view_html(pair.source, pair.target, show_run=True)
    poses = run.layout.meta["poses"][0]
    assert len(run.frames) == len(poses) == run.layout.meta["iterations"][0] + 1 >= 2
    assert len(run.layout.sliders[0].steps) == len(poses)
    np.testing.assert_array_equal(np.array(poses[-1]), reference.transformation)

    shown = view_figure([fixed_trace(pair.source, pair.target, np.eye(4), "as given")])
    assert not shown.layout.sliders and not shown.frames and "slider" not in layout_text(shown)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"transformation": np.eye(4), "show_run": True}, "show_run"),
        ({"transformation": np.eye(4), "compare": "icp"}, "compare"),
        ({"shown_iteration": 3}, "show_run=True"),
        ({"transformation": np.eye(4), "camera": "fisheye"}, "camera"),
        ({"transformation": np.eye(4), "up": "w"}, "up"),
    ],
)
def test_contradictory_or_bad_options_are_refused_before_any_work(options, message):
    pair = builtin_pair(points=100)
    with pytest.raises(InvalidInputError, match=message):
        view_html(pair.source, pair.target, **options)


def test_a_lidar_scan_keeps_a_point_within_one_display_cell_of_every_point():
    """A KITTI scan (124,668 points, 156 m across): the display keeps a point in every occupied cell
    of a grid of :data:`DISPLAY_CELLS_ACROSS` cells across, so no point of the scan is farther than
    a cell's diagonal from a drawn one (a random subset of the same count leaves metres-wide
    gaps far from the sensor); at most the cap asked for; and the scan opens in a top view."""
    scan = io.read_points(require_shared("real_pairs/kitti_00/000000.bin"), bin_columns=3)
    shown = display_indices(scan)
    extent = float(np.max(scan.max(axis=0) - scan.min(axis=0)))
    assert 2_000 < len(shown) <= DISPLAY_POINTS_CAP
    assert np.array_equal(shown, np.unique(shown))
    gaps, _ = cKDTree(scan[shown]).query(scan)
    assert gaps.max() <= np.sqrt(3) * extent / DISPLAY_CELLS_ACROSS
    random = np.random.default_rng(0).choice(len(scan), len(shown), replace=False)
    assert cKDTree(scan[random]).query(scan)[0].max() > 3 * gaps.max()
    capped = display_indices(scan, 3000)
    assert 1500 <= len(capped) <= 3000
    assert scene_camera(scan)[1] == "top"


def test_a_small_object_is_drawn_whole_and_obliquely():
    """2,000 points spread evenly on a sphere: their spacing (about 0.08 radii) exceeds a display
    cell (2 radii / DISPLAY_CELLS_ACROSS), so every point is drawn."""
    k = np.arange(2000) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / 2000), np.pi * (1 + 5**0.5) * k
    object_points = np.column_stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])
    np.testing.assert_array_equal(display_indices(object_points), np.arange(len(object_points)))
    assert scene_camera(object_points)[1] == "oblique"


def test_the_top_view_looks_down_the_declared_up_axis():
    """A scene 100 x 5 x 80 (flat along y): with ``up="-y"`` (a depth camera's frame) it is much
    wider than tall, and the view looks down from -y, orthographic; with ``up="z"`` it is not."""
    rng = np.random.default_rng(0)
    scene = rng.uniform(0.0, 1.0, size=(2000, 3)) * [100.0, 5.0, 80.0]
    camera, chosen = scene_camera(scene, up="-y")
    assert chosen == "top" and camera["projection"]["type"] == "orthographic"
    eye = np.array([camera["eye"][axis] for axis in "xyz"])
    np.testing.assert_allclose(eye / np.linalg.norm(eye), [0.0, -1.0, 0.0])
    assert scene_camera(scene, up="z")[1] == "oblique"
    assert scene_camera(scene, camera="top", up="z")[0]["eye"]["z"] > 0


def test_view_shows_the_figure_through_a_plotly_renderer():
    require_plotting()
    base = require_module("plotly.io.base_renderers", "viz")
    renderers = require_module("plotly.io", "viz").renderers
    shown = []

    class Keep(base.ExternalRenderer):
        def render(self, fig_dict):
            shown.append(fig_dict)

    renderers["esmicp-test-keep"] = Keep()
    pair = builtin_pair(points=200)
    figure = view(pair.source, pair.target, pair.T_target_source, renderer="esmicp-test-keep")
    assert len(shown) == 1 and shown[0]["layout"]["meta"] == figure.layout.meta
    assert figure.layout.meta["registered"] is False
