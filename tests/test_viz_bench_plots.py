"""esmicp_lab.plots on rows measured by real registrations (esm, icp, esm-paper from the
identity on seeded trials, plus a sigma sweep), not on made-up numbers."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_viz_support import check_image, require_plotting

from esmicp.errors import InvalidInputError, OutputExistsError, PointCloudFileError
from esmicp_lab.bench.trial_rows import local_trial_rows
from esmicp_lab.plots import (
    REQUIRED_KEYS,
    error_boxplots_figure,
    read_bench_rows,
    sigma_sweep_figure,
    success_vs_angle_figure,
    time_figure,
    write_bench_plots,
)

#: The row schema's keys (helpers/bench_rows.md): every measured row must have them.
SCHEMA_KEYS = (
    "trial_id", "seed", "protocol", "dataset", "cloud", "method", "method_kind", "sigma", "max_iterations",
    "init", "status", "reason", "initial_rotation_deg", "rotation_error_deg", "translation_error", "diagonal",
    "success_strict", "success_symmetry", "mse_r", "rmse_r", "mae_r", "mse_t", "rmse_t", "mae_t", "time_s",
    "iterations", "points_source", "points_target",
)


@pytest.fixture(scope="module")
def rows():
    return local_trial_rows(trials=6, points=240, seed=1, sigma_fractions=(0.02, 0.1, 0.5))


def test_measured_rows_follow_the_schema_and_tell_the_methods_apart(rows):
    assert len(rows) == 2 * 6 * 3 + 6 * 3
    for row in rows:
        assert set(SCHEMA_KEYS) <= set(row)
        assert row["status"] == "ok"
    json.dumps(rows)  # JSON-ready
    copy = [r for r in rows if r["protocol"] == "copy" and r["sigma"] is None]
    paper = [r["success_strict"] for r in copy if r["method"] == "esm-paper"]
    resampled = [r for r in rows if r["protocol"] == "resampled" and r["method"] == "esm-paper"]
    # The paper's formulation solves index-aligned copies and none of the resampled pairs.
    assert all(paper) and not any(r["success_strict"] for r in resampled)
    angles = sorted({round(r["initial_rotation_deg"], 6) for r in copy})
    np.testing.assert_allclose(angles, (np.arange(6) + 0.5) * 30, atol=1e-6)


def test_success_curves_are_the_rows_success_rates(rows):
    require_plotting()
    figure = success_vs_angle_figure(rows, bin_deg=60)
    panels = [axes for axes in figure.axes if axes.get_title().startswith("protocol")]
    assert [axes.get_title() for axes in panels] == ["protocol: copy", "protocol: resampled"]
    for axes in panels:
        protocol = axes.get_title().split(": ")[1]
        lines = axes.get_lines()
        assert len(lines) == 3  # one curve per method
        for line in lines:
            method = line.get_label().split(" (")[0]
            chosen = [r for r in rows if r["protocol"] == protocol and r["method"] == method and r["sigma"] is None]
            for centre, rate in zip(line.get_xdata(), line.get_ydata()):
                inside = [r for r in chosen if abs(r["initial_rotation_deg"] - centre) < 30]
                assert rate == pytest.approx(100 * np.mean([r["success_strict"] for r in inside]))


def test_error_time_and_sigma_figures_draw_every_method(rows):
    require_plotting()
    errors = error_boxplots_figure(rows)
    rotation_axes = errors.axes[0]
    assert [t.get_text() for t in rotation_axes.get_xticklabels()] == ["esm", "icp", "esm-paper"]
    assert len(rotation_axes.patches) >= 6  # a box per method and protocol
    timing = time_figure(rows)
    assert [t.get_text() for t in timing.axes[0].get_xticklabels()] == ["esm", "icp", "esm-paper"]
    assert any("median" in text.get_text() for text in timing.axes[0].texts)
    sweep = sigma_sweep_figure(rows)
    line = sweep.axes[0].get_lines()[0]
    sigmas = sorted({r["sigma"] for r in rows if r["sigma"] is not None})
    np.testing.assert_allclose(line.get_xdata(), sigmas)


def test_unavailable_rows_are_left_out_and_named(rows):
    require_plotting()
    missing = dict(rows[0], method="kiss-matcher-icp", status="unavailable", reason="kiss_matcher missing",
                   rotation_error_deg=None, translation_error=None, success_strict=None, time_s=None)
    figure = success_vs_angle_figure(rows + [missing])
    assert all("kiss-matcher-icp" not in line.get_label() for axes in figure.axes for line in axes.get_lines())
    assert any("kiss-matcher-icp" in text.get_text() and "unavailable" in text.get_text() for text in figure.texts)


def test_write_bench_plots_writes_four_pngs_and_refuses_to_overwrite(rows, tmp_path):
    require_plotting()
    out = tmp_path / "plots"
    paths = write_bench_plots(rows, out)
    assert [p.name for p in paths] == ["success_vs_angle.png", "errors.png", "time.png", "sigma_sweep.png"]
    for path in paths:
        check_image(path, min_width=400, min_height=300)
    stamps = [p.stat().st_mtime_ns for p in paths]
    with pytest.raises(OutputExistsError):
        write_bench_plots(rows, out)
    assert [p.stat().st_mtime_ns for p in paths] == stamps
    no_sweep = [r for r in rows if r["sigma"] is None]
    assert len(write_bench_plots(no_sweep, tmp_path / "other")) == 3
    with pytest.raises(InvalidInputError, match="sigma"):
        sigma_sweep_figure(no_sweep)


def test_rows_file_round_trip_and_bad_rows(rows, tmp_path):
    path = tmp_path / "rows.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows) + "\n")
    assert read_bench_rows(path) == rows
    bad = tmp_path / "bad.jsonl"
    bad.write_text(json.dumps(rows[0]) + "\n{not json\n")
    with pytest.raises(PointCloudFileError, match="bad.jsonl: line 2"):
        read_bench_rows(bad)
    short = {k: v for k, v in rows[0].items() if k != "time_s"}
    with pytest.raises(InvalidInputError, match="missing key.*time_s"):
        time_figure([short])
    assert "time_s" in REQUIRED_KEYS
    with pytest.raises(InvalidInputError, match="no benchmark rows"):
        write_bench_plots([], tmp_path / "none")


def test_bench_command_with_plots_draws_the_run_and_redraws_on_resume(tmp_path):
    """``esmicp bench --plots``: the figures of the rows on disk, drawn again after ``--resume``."""
    require_plotting()
    from esmicp.cli import main

    out = tmp_path / "run"
    command = ["bench", "--protocols", "copy", "--datasets", "synthetic", "--methods", "esm,esm-paper",
               "--points", "300", "--trials", "2", "--out", str(out), "--no-progress", "--workers", "1",
               "--plots"]
    assert main(command) == 0
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert pngs == ["errors.png", "success_vs_angle.png", "time.png"]
    for name in pngs:
        check_image(out / name, min_width=400, min_height=300)
    first = {name: (out / name).stat().st_mtime_ns for name in pngs}
    assert main([*command, "--resume"]) == 0  # nothing left to run; the plots are drawn again
    assert all((out / name).stat().st_mtime_ns > first[name] for name in pngs)
