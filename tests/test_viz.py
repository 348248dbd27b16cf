"""esmicp.viz and the view / heatmap / animate commands: figures built on the solver's real
iterations, files written and opened again, bad input refused in one line."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from conftest import require_shared
from test_viz_support import check_image, require_plotting

from esmicp.cli import main
from esmicp.core.procrustes import apply
from esmicp.metrics import rotation_error_deg
from esmicp.errors import InvalidInputError, OutputExistsError, PointCloudFileError
from esmicp.methods.esm_paper import paper_cross_covariance
from esmicp.methods.esm_paper import similarity_matrix as solver_similarity_matrix
from esmicp import register
from esmicp.viz import (
    builtin_pair,
    downsample,
    farthest_point_subset,
    heatmap,
    moved_copy,
    similarity_matrix,
    trace_registration,
    view_html,
    view_page,
    write_view,
)
from esmicp.viz.view import DATA_ID, display_indices


def run(capsys, *argv):
    try:
        code = main(list(argv))
    except SystemExit as exit_:
        code = exit_.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


# --- the traced iterations --------------------------------------------------------------------


@pytest.mark.parametrize("method", ["esm", "esm-paper", "icp"])
def test_trace_poses_are_the_solvers_history(method):
    pair = builtin_pair(points=300, angle_deg=25)
    trace = trace_registration(pair.source, pair.target, method=method)
    reference = register(pair.source, pair.target, method=method, init="identity", record_history=True)
    assert trace.iterations == reference.num_iterations == len(reference.history)
    assert len(trace.poses) == trace.iterations + 1
    np.testing.assert_array_equal(trace.poses[0], np.eye(4))
    for pose, record in zip(trace.poses[1:], reference.history):
        np.testing.assert_allclose(pose, record.transformation, atol=1e-12)
    np.testing.assert_allclose(trace.poses[-1], reference.transformation, atol=1e-12)
    # Each step's correspondences are the nearest target points of the source as placed before it.
    step = trace.steps[2]
    moved = apply(trace.poses[2], pair.source)
    nearest = np.argmin(np.linalg.norm(moved[:, None, :] - pair.target[None, :, :], axis=2), axis=1)
    np.testing.assert_array_equal(step.indices, nearest)


def test_a_global_trace_starts_at_the_search_pose_and_ends_at_registers_pose():
    """After the global search, the trace is the local refinement that follows it: its poses end
    at the pose ``register`` gives by default (bitwise: the callback changes nothing), and the
    first iteration starts at the search's pose."""
    pair = builtin_pair(points=400, angle_deg=120)
    trace = trace_registration(pair.source, pair.target, init="global")
    reference = register(pair.source, pair.target)
    np.testing.assert_array_equal(trace.poses[-1], reference.transformation)
    assert trace.start.startswith("global search") and trace.iterations == reference.num_iterations >= 1
    assert rotation_error_deg(trace.poses[0], pair.T_target_source) < 5.0  # the search's pose, near the truth


def test_trace_from_a_given_pose_starts_there():
    pair = builtin_pair(points=200, angle_deg=60)
    start = np.array(pair.T_target_source)
    trace = trace_registration(pair.source, pair.target, init=start)
    np.testing.assert_allclose(trace.poses[0], start)
    assert trace.start == "given pose"
    assert trace.iterations <= 3  # already at the solution


# --- inputs -----------------------------------------------------------------------------------


def test_farthest_point_subset_is_deterministic_and_well_spread():
    cloud = builtin_pair(points=None).target
    chosen = farthest_point_subset(cloud, 21)
    assert len(chosen) == len(np.unique(chosen)) == 21
    np.testing.assert_array_equal(chosen, farthest_point_subset(cloud, 21))

    def min_gap(points):
        gaps = np.linalg.norm(points[:, None] - points[None], axis=2)
        return gaps[~np.eye(len(points), dtype=bool)].min()

    random_gaps = [min_gap(cloud[np.random.default_rng(s).choice(len(cloud), 21, replace=False)]) for s in range(20)]
    assert min_gap(cloud[chosen]) > max(random_gaps)


def test_moved_copy_is_index_aligned_with_the_true_pose():
    cloud = downsample(builtin_pair(points=None).target, 40)
    pair = moved_copy(cloud, angle_deg=35, seed=3)
    np.testing.assert_allclose(apply(pair.T_target_source, pair.source), pair.target, atol=1e-12)
    angle = np.degrees(np.arccos((np.trace(pair.T_target_source[:3, :3]) - 1) / 2))
    assert angle == pytest.approx(35)


# --- the similarity matrix --------------------------------------------------------------------


def test_similarity_matrix_is_the_one_the_paper_solver_uses():
    """The heat map's dense M gives the solver's H: Src_c M^T TgtMatched_c^T (paper notation)."""
    pair = moved_copy(downsample(builtin_pair(points=None).target, 21), angle_deg=40)
    trace = trace_registration(pair.source, pair.target, method="esm-paper", max_iterations=5)
    step = trace.steps[0]
    dense = similarity_matrix("esm-paper", step.indices, step.weights, 21, 21)
    np.testing.assert_array_equal(dense, solver_similarity_matrix(step.indices, step.weights, 21).toarray())
    assert dense.shape == (21, 21)
    for i, c in enumerate(step.indices):  # M(i, c(i)) = M(c(i), i) = w_i up to later writes
        assert dense[i, c] in step.weights and dense[c, i] in step.weights
    moved = apply(trace.poses[0], pair.source)
    matched = pair.target[step.indices]
    source_centred = (moved - moved.mean(axis=0)).T
    target_centred = (matched - matched.mean(axis=0)).T
    expected, _, _ = paper_cross_covariance(moved, matched, step.indices, step.weights)
    np.testing.assert_allclose(source_centred @ dense.T @ target_centred.T, expected, atol=1e-12)


def test_similarity_matrix_of_esm_is_rectangular_with_one_weight_per_row():
    weights = np.array([0.5, 1.0, 0.25])
    dense = similarity_matrix("esm", [4, 0, 4], weights, 3, 6)
    assert dense.shape == (3, 6)
    np.testing.assert_array_equal(dense[[0, 1, 2], [4, 0, 4]], weights)
    assert np.count_nonzero(dense) == 3
    with pytest.raises(InvalidInputError, match="downsample"):
        similarity_matrix("esm", np.zeros(5000, dtype=int), np.ones(5000), 5000, 5000)


# --- figures through the API ------------------------------------------------------------------


def test_heatmap_panels_show_the_traced_matrices():
    require_plotting()
    figure = heatmap(methods=["esm-paper", "esm"], columns=4)
    panels = [axes for axes in figure.axes if axes.images]
    pair = builtin_pair(points=21)
    for row, method in enumerate(["esm-paper", "esm"]):
        trace = trace_registration(pair.source, pair.target, method=method, max_iterations=30)
        first = [axes for axes in panels if axes.get_ylabel().startswith(method)][0]
        row_panels = panels[panels.index(first) : panels.index(first) + min(4, trace.iterations)]
        final = trace.steps[-1]
        expected = similarity_matrix(method, final.indices, final.weights, 21, 21)
        np.testing.assert_allclose(np.asarray(row_panels[-1].images[0].get_array()), expected)
        assert f"iteration {trace.iterations}" in row_panels[-1].get_title()
    assert "start: identity" in figure._suptitle.get_text()


def test_view_page_is_self_contained_and_carries_the_poses(tmp_path):
    require_plotting()
    pair = builtin_pair(points=600, angle_deg=30)
    figure = view_html(pair.source, pair.target, method="esm", compare="icp", max_display_points=250,
                       truth=pair.T_target_source, init="identity", show_run=True)
    path = tmp_path / "view.html"
    write_view(figure, path)
    html = path.read_text(encoding="utf-8")
    assert not re.search(r"<script[^>]*\bsrc=", html), "the page must not load scripts from elsewhere"
    assert len(html) > 1_000_000 and "plotly" in html.lower()  # plotly.js inlined
    data = json.loads(re.search(rf'<script type="application/json" id="{DATA_ID}">(.*?)</script>', html, re.S).group(1))
    assert data["methods"] == ["esm", "icp"]
    for method, poses in zip(data["methods"], data["poses"]):
        trace = trace_registration(pair.source, pair.target, method=method)
        assert len(poses) == trace.iterations + 1
        np.testing.assert_allclose(np.array(poses), np.array(trace.poses), atol=1e-12)
    shown = display_indices(pair.source, 250)
    assert data["shown_source"] == len(shown) <= 250 and data["points_source"] == 600
    assert "thinned evenly for display" in html
    assert len(figure.frames) == max(data["iterations"]) + 1
    # Frame k carries the aligned sources at iteration k (display subset, float32).
    k = 3
    expected = apply(np.array(data["poses"][0][k]), pair.source)[shown]
    np.testing.assert_allclose(np.asarray(figure.frames[k].data[0].x), expected[:, 0], atol=1e-5)
    with pytest.raises(OutputExistsError):
        write_view(figure, path)
    assert view_page(figure) == html


def test_view_opens_at_the_iteration_asked_for():
    require_plotting()
    pair = builtin_pair(points=300, angle_deg=30)
    trace = trace_registration(pair.source, pair.target)
    for asked, shown in ((4, 4), (10_000, trace.iterations)):
        figure = view_html(pair.source, pair.target, shown_iteration=asked, init="identity", show_run=True)
        assert figure.layout.sliders[0].active == shown
        np.testing.assert_allclose(np.asarray(figure.data[2].x), trace.aligned(shown)[:, 0], atol=1e-5)
    with pytest.raises(InvalidInputError, match="shown_iteration"):
        view_html(pair.source, pair.target, shown_iteration=-1, show_run=True)


# --- the commands -----------------------------------------------------------------------------


def test_heatmap_command_on_the_bunny_writes_a_readable_png(tmp_path, capsys):
    require_plotting()
    bunny = require_shared("bunny/bun_zipper_res4.ply")
    out = tmp_path / "m.png"
    code, stdout, stderr = run(capsys, "heatmap", str(bunny), "--angle", "20", "-o", str(out))
    assert code == 0, stderr
    assert str(out) in stdout
    check_image(out, min_width=600, min_height=400)


def test_heatmap_command_with_source_and_target_files(tmp_path, capsys):
    require_plotting()
    pair = builtin_pair(points=400, angle_deg=15)
    np.savetxt(tmp_path / "s.xyz", pair.source)
    np.savetxt(tmp_path / "t.xyz", pair.target)
    out = tmp_path / "m.svg"
    code, _, stderr = run(capsys, "heatmap", str(tmp_path / "s.xyz"), str(tmp_path / "t.xyz"),
                          "--methods", "esm", "--points", "15", "-o", str(out))
    assert code == 0, stderr
    assert out.read_text().lstrip().startswith("<?xml") and "<svg" in out.read_text()


def test_animate_command_writes_one_frame_per_iteration_plus_the_start(tmp_path, capsys):
    image_module = require_plotting()
    out = tmp_path / "run.gif"
    code, stdout, stderr = run(capsys, "animate", "--points", "300", "--angle", "35", "-o", str(out))
    assert code == 0, stderr
    pair = builtin_pair(points=300, angle_deg=35)
    trace = trace_registration(pair.source, pair.target)
    with image_module.open(out) as gif:
        assert gif.n_frames == trace.iterations + 1
        frames = []
        for index in (0, gif.n_frames - 1):
            gif.seek(index)
            frames.append(np.asarray(gif.convert("RGB"), dtype=np.int16))
    assert f"{trace.iterations + 1} frames" in stdout
    assert np.abs(frames[0] - frames[1]).mean() > 0.5  # the source moved
    check_image(out, min_width=300, min_height=300)


def test_view_command_writes_html_and_refuses_to_overwrite(tmp_path, capsys):
    require_plotting()
    out = tmp_path / "view.html"
    code, stdout, stderr = run(capsys, "view", "--points", "200", "--compare", "esm-paper", "-o", str(out))
    assert code == 0, stderr
    assert "esm-paper" in stdout
    before = out.read_bytes()
    code, _, stderr = run(capsys, "view", "--points", "200", "-o", str(out))
    assert code == 2 and "already exists" in stderr and len(stderr.strip().splitlines()) == 1
    assert out.read_bytes() == before
    code, _, stderr = run(capsys, "view", "--points", "200", "-o", str(out), "--force")
    assert code == 0, stderr


def view_meta(path):
    """The data block of a written viewer page (methods, poses, iterations, ...)."""
    html = path.read_text()
    return json.loads(re.search(rf'<script type="application/json" id="{DATA_ID}">(.*?)</script>', html, re.S).group(1))


def test_view_shows_what_register_gives_a_given_transform_or_the_files_as_they_are(tmp_path, capsys):
    """``esmicp view`` registers as ``esmicp register`` does (global by default) and shows that
    pose (with ``--show-run``, the last slider step); ``--transform`` shows a given pose, ``--as-is``
    the clouds unmoved."""
    require_plotting()
    from esmicp.io import read_transform

    pair = builtin_pair(points=300, angle_deg=120)
    source, target, out = tmp_path / "s.xyz", tmp_path / "t.xyz", tmp_path / "v.html"
    np.savetxt(source, pair.source, fmt="%.17g")
    np.savetxt(target, pair.target, fmt="%.17g")
    code, stdout, stderr = run(capsys, "register", str(source), str(target), "--transform-out", str(tmp_path / "T.txt"))
    assert code == 0, stderr
    registered = read_transform(tmp_path / "T.txt")
    code, stdout, stderr = run(capsys, "view", str(source), str(target), "-o", str(out))
    assert code == 0, stderr
    assert "from global search" in stdout and "confidence" in stdout
    meta = view_meta(out)
    np.testing.assert_allclose(meta["poses"][0], [registered], atol=1e-8)  # the text file's 17 digits
    code, stdout, stderr = run(capsys, "view", str(source), str(target), "-o", str(out), "--force", "--show-run")
    assert code == 0, stderr
    meta = view_meta(out)
    np.testing.assert_allclose(meta["poses"][0][-1], registered, atol=1e-8)
    assert meta["iterations"][0] >= 1 and rotation_error_deg(np.array(meta["poses"][0][0]), pair.T_target_source) < 5
    for flags, expected in (([ "--transform", str(tmp_path / "T.txt")], registered), (["--as-is"], np.eye(4))):
        code, stdout, stderr = run(capsys, "view", str(source), str(target), "-o", str(out), "--force", *flags)
        assert code == 0, stderr
        meta = view_meta(out)
        assert meta["iterations"] == [0]
        np.testing.assert_allclose(meta["poses"][0][0], expected, atol=1e-12)
    code, _, stderr = run(capsys, "view", str(source), str(target), "-o", str(out), "--force", "--as-is",
                          "--transform", str(tmp_path / "T.txt"))
    assert code == 2 and "not allowed with" in stderr



def test_view_shows_the_result_register_json_wrote_without_registering(tmp_path, capsys):
    """``esmicp register --json > r.json`` then ``esmicp view --transform r.json``: the page shows
    that result's pose, captioned with its verdict, and registers nothing; a JSON file without a
    pose is one line naming it."""
    require_plotting()
    pair = builtin_pair(points=300, angle_deg=120)
    source, target, out = tmp_path / "s.xyz", tmp_path / "t.xyz", tmp_path / "v.html"
    np.savetxt(source, pair.source, fmt="%.17g")
    np.savetxt(target, pair.target, fmt="%.17g")
    code, stdout, stderr = run(capsys, "register", str(source), str(target), "--json")
    assert code == 0, stderr
    (tmp_path / "r.json").write_text(stdout)
    result = json.loads(stdout)
    code, stdout, stderr = run(capsys, "view", str(source), str(target), "-o", str(out), "--transform",
                               str(tmp_path / "r.json"))
    assert code == 0, stderr
    verdict = "trusted" if result["trusted"] else "not trusted"
    assert f"r.json ({result['method']}, confidence {result['confidence']:.2f}, {verdict})" in stdout
    meta = view_meta(out)
    assert meta["iterations"] == [0]
    np.testing.assert_allclose(meta["poses"][0][0], result["transformation"], atol=1e-12)
    (tmp_path / "other.json").write_text(json.dumps({"fitness": 1.0}))
    code, _, stderr = run(capsys, "view", str(source), str(target), "-o", str(tmp_path / "w.html"), "--transform",
                          str(tmp_path / "other.json"))
    assert code == 2 and "other.json: no 'transformation'" in stderr and len(stderr.strip().splitlines()) == 1
    assert not (tmp_path / "w.html").exists()

@pytest.mark.parametrize(
    "argv, message",
    [
        (["animate", "-o", "{tmp}/run.png"], "unsupported animation file"),
        (["heatmap", "-o", "{tmp}/m.gif"], "unsupported image file"),
        (["view", "-o", "{tmp}/v.png"], "unsupported viewer file"),
        (["view", "-o", "{tmp}/missing/v.html"], "does not exist"),
        (["view", "{tmp}/nowhere.ply", "-o", "{tmp}/v.html"], "nowhere.ply: no such file"),
        (["view", "a.xyz", "b.xyz", "c.xyz", "-o", "{tmp}/v.html"], "at most two files"),
        (["heatmap", "--methods", "esm,bogus", "-o", "{tmp}/m.png"], "unknown method"),
        (["view", "--init", "{tmp}/nowhere.txt", "-o", "{tmp}/v.html"], "nowhere.txt"),
        (["animate", "--angle", "200", "-o", "{tmp}/run.gif"], "[0, 180]"),
        (["view", "--compare", "bogus", "-o", "{tmp}/v.html"], "invalid choice"),
        (["view", "--show-iteration", "3", "-o", "{tmp}/v.html"], "add --show-run"),
        (["view", "--as-is", "--show-run", "-o", "{tmp}/v.html"], "--show-run"),
        (["view", "--up", "w", "--as-is", "-o", "{tmp}/v.html"], "up: expected an axis"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, argv, message):
    require_plotting()  # without the plotting libraries, the commands refuse that first
    argv = [part.replace("{tmp}", str(tmp_path)) for part in argv]
    code, stdout, stderr = run(capsys, *argv)
    assert code == 2
    assert message in stderr and len(stderr.strip().splitlines()) == 1, stderr
    assert list(tmp_path.iterdir()) == []


def test_garbage_cloud_file_is_one_line(tmp_path, capsys):
    require_plotting()
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply at all")
    code, _, stderr = run(capsys, "heatmap", str(bad), "-o", str(tmp_path / "m.png"))
    assert code == 2 and "bad.ply" in stderr and len(stderr.strip().splitlines()) == 1
    assert not (tmp_path / "m.png").exists()


def test_missing_plotting_library_is_one_line_with_the_install_hint(tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "plotly.graph_objects", None)  # makes the import fail
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    for argv in (["view", "--points", "50"], ["heatmap"]):
        out = tmp_path / ("v.html" if argv[0] == "view" else "m.png")
        code, _, stderr = run(capsys, *argv, "-o", str(out))
        assert code == 2 and "pip install 'esmicp[viz]'" in stderr and len(stderr.strip().splitlines()) == 1
        assert not out.exists()


def test_commands_start_from_a_given_transform_file(tmp_path, capsys):
    image_module = require_plotting()
    from esmicp.io import write_transform

    pair = builtin_pair(points=300, angle_deg=35)
    np.savetxt(tmp_path / "s.xyz", pair.source)
    np.savetxt(tmp_path / "t.xyz", pair.target)
    write_transform(tmp_path / "T.txt", pair.T_target_source)
    out = tmp_path / "run.gif"
    code, stdout, stderr = run(capsys, "animate", str(tmp_path / "s.xyz"), str(tmp_path / "t.xyz"),
                               "--init", str(tmp_path / "T.txt"), "-o", str(out))
    assert code == 0, stderr
    assert "from given pose" in stdout
    trace = trace_registration(pair.source, pair.target, init=pair.T_target_source)
    with image_module.open(out) as gif:
        assert gif.n_frames == trace.iterations + 1 <= 4


# --- the merged model of many scans -----------------------------------------------------------


def _scans(count, per_scan=500, seed=0):
    rng = np.random.default_rng(seed)
    points = np.concatenate([rng.normal(size=(per_scan, 3)) + [k, 0.0, 0.0] for k in range(count)])
    return points, np.repeat(np.arange(count), per_scan), [f"walk/frame_{k:04d}.ply" for k in range(count)]


def test_a_merged_view_of_a_few_scans_has_one_legend_entry_per_scan_in_the_files_colours(tmp_path):
    require_plotting()
    from esmicp.io import scan_palette
    from esmicp.viz import merged_scans_figure

    points, labels, names = _scans(5)
    figure = merged_scans_figure(points, labels, names)
    assert figure.layout.showlegend and len(figure.data) == 5
    for k, trace in enumerate(figure.data):
        assert trace.name == f"{k}: {names[k]}"
        assert trace.marker.color == "#{:02x}{:02x}{:02x}".format(*scan_palette(5)[k])
        drawn = np.stack([trace.x, trace.y, trace.z], axis=1)
        assert len(drawn) == 500  # few scans: all their points
        np.testing.assert_allclose(drawn, points[labels == k], atol=1e-5)  # each scan's own points


def test_a_merged_view_of_100_scans_is_one_cloud_on_a_colour_scale_with_names_on_hover(tmp_path):
    """100 scans: no legend of 100 lines taking the page; one trace coloured by scan index with
    a colour bar, each point's hover text naming its scan, the drawn points bounded in all."""
    require_plotting()
    from esmicp.viz import merged_scans_figure
    from esmicp.viz.scans import VIEW_POINTS_TOTAL

    points, labels, names = _scans(100, per_scan=1500)
    figure = merged_scans_figure(points, labels, names)
    assert not figure.layout.showlegend and len(figure.data) == 1
    trace = figure.data[0]
    assert trace.marker.colorbar.title.text and trace.marker.cmax == 99
    index = np.asarray(trace.marker.color)
    assert set(index.tolist()) == set(range(100)) and len(index) <= VIEW_POINTS_TOTAL
    assert [text.split(": ", 1)[1] for text in trace.hovertext] == [names[k] for k in index]
    from scipy.spatial import cKDTree

    distance, nearest = cKDTree(points).query(np.stack([trace.x, trace.y, trace.z], axis=1))
    assert distance.max() < 1e-5  # float32 for display
    np.testing.assert_array_equal(labels[nearest], index)  # every point drawn in its own scan's colour
    assert figure.layout.meta["legend"] is False and figure.layout.meta["scans"] == list(range(100))
    path = tmp_path / "merged.html"
    write_view(figure, path)
    assert path.stat().st_size < 20_000_000
    with pytest.raises(InvalidInputError):
        merged_scans_figure(points, labels, names[:50])  # a scan index with no name


def test_a_merged_view_thins_each_scan_evenly_over_its_extent():
    """A scan whose points crowd near its sensor and thin out far away (a LiDAR sweep) keeps its
    far part drawn: the thinning is even over space, not a random pick that follows the density."""
    require_plotting()
    from scipy.spatial import cKDTree

    from esmicp.viz import merged_scans_figure
    from esmicp.viz.scans import VIEW_POINTS_PER_SCAN

    rng = np.random.default_rng(4)
    near = rng.uniform(-1.0, 1.0, size=(60_000, 3)) * [1.0, 1.0, 0.01]
    far = rng.uniform(-1.0, 1.0, size=(300, 3)) * [1.0, 1.0, 0.01] + [40.0, 0.0, 0.0]
    points = np.concatenate([near, far])
    figure = merged_scans_figure(points, np.zeros(len(points), dtype=int), ["sweep"])
    drawn = np.stack([figure.data[0].x, figure.data[0].y, figure.data[0].z], axis=1)
    assert len(drawn) <= VIEW_POINTS_PER_SCAN
    gap, _ = cKDTree(drawn).query(far)
    assert gap.max() < 0.2  # a random pick of 3,000 of 60,300 draws about 15 of the far 300 points
