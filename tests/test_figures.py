"""esmicp_lab.figures: the pictures the results pages open on, drawn from a few synthetic records.
Each test checks what the picture promises (every record drawn where its numbers put it, the trust
bar where it is set, bar heights equal to the rates, the views of the frame asked for), not pixels."""

from __future__ import annotations

import numpy as np
import pytest
from test_viz_support import check_image, require_plotting

from esmicp.errors import InvalidInputError
from esmicp_lab.figures import (
    PICTURE_WIDTH_PX,
    ROTATION_FLOOR_DEG,
    confidence_error_figure,
    merged_scans_figure,
    success_bars_figure,
    success_grid_figure,
    top_view_axes,
    trajectory_figure,
    write_picture,
)

RECORDS = [
    {"confidence": 0.95, "rotation_error_deg": 0.8, "success": True, "trusted": True, "kind": "3DMatch"},
    {"confidence": 0.62, "rotation_error_deg": 170.0, "success": False, "trusted": True, "kind": "3DMatch"},
    {"confidence": 0.20, "rotation_error_deg": 95.0, "success": False, "trusted": False, "kind": "LiDAR"},
    {"confidence": 1.00, "rotation_error_deg": 0.0, "success": True, "trusted": True, "kind": "LiDAR"},
    {"confidence": 0.40, "rotation_error_deg": 2.0, "success": True, "trusted": False, "kind": "LiDAR"},
]


def _points(figure):
    axes = figure.axes[0]
    return np.concatenate([collection.get_offsets() for collection in axes.collections])


def test_every_registration_is_drawn_at_its_confidence_and_error_with_the_bar_where_it_is_set(tmp_path):
    require_plotting()
    figure = confidence_error_figure(RECORDS, trust_bar=0.55, title="pairs", group=lambda r: r["kind"])
    drawn = sorted(map(tuple, _points(figure)))
    expected = sorted((r["confidence"], max(r["rotation_error_deg"], ROTATION_FLOOR_DEG)) for r in RECORDS)
    np.testing.assert_allclose(drawn, expected)
    axes = figure.axes[0]
    assert axes.get_yscale() == "log"
    bars = [line for line in axes.get_lines() if np.ptp(line.get_xdata()) == 0]
    assert [line.get_xdata()[0] for line in bars] == [0.55]
    legend = [text.get_text() for text in axes.get_legend().get_texts()]
    assert "right (3)" in legend and "wrong (2)" in legend and "trusted and wrong: 1" in legend
    path = write_picture(figure, tmp_path / "confidence.png")
    pixels = check_image(path, min_width=PICTURE_WIDTH_PX, min_height=300)
    assert pixels.shape[1] == PICTURE_WIDTH_PX


def test_a_record_without_its_verdict_is_refused():
    with pytest.raises(InvalidInputError, match=r"records\[1\]: missing key\(s\) trusted"):
        confidence_error_figure([RECORDS[0], {"confidence": 0.5, "rotation_error_deg": 1.0, "success": True}],
                                trust_bar=0.55, title="x")


def test_bar_heights_are_the_success_rates_and_impossible_counts_are_refused():
    require_plotting()
    rates = [{"group": g, "method": m, "successes": s, "trials": 4}
             for g, m, s in (("copy", "esm", 4), ("copy", "icp", 1), ("noisy", "esm", 3), ("noisy", "icp", 0))]
    figure = success_bars_figure(rates, title="t")
    heights = sorted(round(patch.get_height(), 6) for patch in figure.axes[0].patches)
    assert heights == sorted(100.0 * r["successes"] / r["trials"] for r in rates)
    labels = [tick.get_text() for tick in figure.axes[0].get_xticklabels()]
    assert labels == ["copy", "noisy"]
    with pytest.raises(InvalidInputError, match="successes 5 of 4"):
        success_bars_figure([{"group": "g", "method": "m", "successes": 5, "trials": 4}], title="t")


def test_the_top_view_is_the_plane_a_walk_spans_whatever_the_up_axis():
    rng = np.random.default_rng(3)
    walk = np.column_stack([np.cumsum(rng.normal(size=40)), 0.01 * rng.normal(size=40), np.cumsum(rng.normal(size=40))])
    axes = top_view_axes(walk)
    assert np.allclose(np.abs(axes[:, 1]), 0.0, atol=0.05)  # y (up) is not in the view
    assert np.allclose(np.linalg.norm(axes, axis=1), 1.0)


def test_a_trajectory_is_drawn_in_the_truths_frame_and_unplaced_scans_are_counted(tmp_path):
    require_plotting()
    rng = np.random.default_rng(4)
    truth = np.cumsum(rng.normal(size=(12, 3)), axis=0)
    estimate = truth + 0.05
    estimate[5] = np.nan
    figure = trajectory_figure(truth, {"merge": estimate}, title="walk")
    lines = figure.axes[0].get_lines()
    truth_line, estimate_line = lines[0], lines[1]
    shown = (truth - truth.mean(axis=0)) @ top_view_axes(truth).T
    np.testing.assert_allclose(np.column_stack(truth_line.get_data()), shown)
    assert np.isnan(estimate_line.get_xydata()[5]).all()
    assert any("11 of 12 placed" in text.get_text() for text in figure.axes[0].get_legend().get_texts())
    with pytest.raises(InvalidInputError, match=r"estimates\['merge'\]: shape"):
        trajectory_figure(truth, {"merge": estimate[:5]}, title="walk")
    check_image(write_picture(figure, tmp_path / "walk.png"), min_width=PICTURE_WIDTH_PX, min_height=300)


def test_scans_are_drawn_where_their_poses_put_them_and_an_unplaced_one_is_named(tmp_path):
    require_plotting()
    rng = np.random.default_rng(5)
    clouds = [rng.normal(size=(200, 3)) for _ in range(3)]
    moved = np.eye(4)
    moved[:3, 3] = [10.0, 20.0, 30.0]
    poses = [np.eye(4), moved, np.full((4, 4), np.nan)]
    figure = merged_scans_figure(clouds, poses, ["a", "b", "c"], views=[("front", 0, 1), ("above", 0, 2)],
                                 title="scans", points_per_scan=50)
    front = figure.axes[0].collections
    assert len(front) == 2  # the unplaced scan is not drawn
    np.testing.assert_allclose(front[1].get_offsets().mean(axis=0), [10.0, 20.0], atol=0.5)
    above = figure.axes[1].collections
    np.testing.assert_allclose(above[1].get_offsets().mean(axis=0), [10.0, 30.0], atol=0.5)
    assert any(text.get_text() == "not placed: c" for text in figure.texts)
    path = write_picture(figure, tmp_path / "scans.png")
    assert path.read_bytes() == write_picture(merged_scans_figure(
        clouds, poses, ["a", "b", "c"], views=[("front", 0, 1), ("above", 0, 2)], title="scans",
        points_per_scan=50), tmp_path / "again.png").read_bytes()  # same records, same file
    with pytest.raises(InvalidInputError, match="unsupported picture file"):
        write_picture(figure, tmp_path / "scans.jpg")


def test_a_grid_cell_shows_its_rate_and_a_method_not_run_is_grey(tmp_path):
    require_plotting()
    rates = [{"group": "copy", "method": "esm", "percent": 100.0}, {"group": "noisy", "method": "esm", "percent": 25.0},
             {"group": "copy", "method": "dcp", "percent": None}]
    figure = success_grid_figure(rates, title="grid")
    axes = figure.axes[0]
    grid = axes.images[0].get_array()
    assert grid[0, 0] == 100.0 and grid[0, 1] == 25.0
    assert grid.mask[1, 0] and grid.mask[1, 1]  # not run, and not in the rates at all: grey
    cells = {(round(t.get_position()[1]), round(t.get_position()[0])): t.get_text() for t in axes.texts}
    assert cells == {(0, 0): "100", (0, 1): "25", (1, 0): "-", (1, 1): "-"}
    assert [t.get_text() for t in axes.get_yticklabels()] == ["esm", "dcp"]
    assert [t.get_text() for t in axes.get_xticklabels()] == ["copy", "noisy"]
    check_image(write_picture(figure, tmp_path / "grid.png"), min_width=PICTURE_WIDTH_PX, min_height=150)
    with pytest.raises(InvalidInputError, match=r"rates\[0\]: percent 120"):
        success_grid_figure([{"group": "g", "method": "m", "percent": 120.0}], title="t")
