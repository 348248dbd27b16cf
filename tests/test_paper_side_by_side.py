"""The paper's tables beside ours (esmicp_lab.bench.side_by_side, benchmarks/paper_side_by_side.py):
the checks of the paper's cells, the records built from bench rows, the summary CSV round trip,
the marker replacement, and that docs/bench-paper.md holds exactly what the script writes from
the committed summary and the paper's tables in ../shared."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from conftest import REPO_ROOT, require_shared

from esmicp_lab.bench import BenchConfig, RunOptions, read_rows, run_bench
from esmicp_lab.bench.side_by_side import (
    BEGIN,
    END,
    PICTURES,
    implied_rotation_error_deg,
    paper_quirks,
    paper_table_of,
    ratio_text,
    read_summary_csv,
    regenerate,
    replace_sections,
    sections,
    side_by_side_markdown,
    success_rates,
    summary_csv,
    summary_records,
)
from esmicp.errors import InvalidInputError


def _row(method, mse_r, mae_r, mse_t, mae_t, rmse_r=None, rmse_t=None):
    return {"method": method, "MSE(R)": mse_r, "RMSE(R)": math.sqrt(mse_r) if rmse_r is None else rmse_r,
            "MAE(R)": mae_r, "MSE(t)": mse_t, "RMSE(t)": math.sqrt(mse_t) if rmse_t is None else rmse_t, "MAE(t)": mae_t}


def _table(rows, trials=1, table_id="person"):
    return {"id": table_id, "dataset": "ModelNet40 person", "trials": trials, "rows": rows}


def test_consistent_cells_are_not_flagged():
    table = _table([_row("ICP", 0.5, 0.6, 4.0, 1.5), _row("ESM-ICP", 1e-16, 8e-9, 1e-12, 9e-7)])
    assert paper_quirks(table) == {}


def test_a_cell_repeated_from_the_rotation_metrics_is_flagged():
    # The airplane table's ICP row: MAE(t) = MAE(R), far below RMSE(t) / sqrt(3).
    table = _table([_row("ICP", 0.888774, 0.722478, 444942.0, 0.722478, rmse_r=0.942748, rmse_t=667.04)])
    flags = paper_quirks(table)
    assert set(flags) == {("ICP", "MAE(t)")}
    text = " ".join(flags[("ICP", "MAE(t)")])
    assert "repeats this row's MAE(R)" in text and "sqrt(3)" in text


def test_mae_above_rmse_and_rmse_not_sqrt_mse_are_flagged_for_one_trial():
    table = _table([_row("ICP NL", 0.812057, 0.808517, 0.0107494, 0.808517, rmse_r=0.901142, rmse_t=0.103679),
                    _row("X", 0.25, 0.3, 1.0, 0.9, rmse_r=0.7)])
    flags = paper_quirks(table)
    assert any("> RMSE(t)" in f for f in flags[("ICP NL", "MAE(t)")])
    assert any("sqrt(MSE(R)) = 0.5" in f for f in flags[("X", "RMSE(R)")])


def test_means_allow_rmse_below_sqrt_mse_but_not_above():
    below = _table([_row("A (ESM-ICP)", 0.073224, 0.179977, 0.04, 0.14, rmse_r=0.220009, rmse_t=0.16)], trials=1000)
    assert paper_quirks(below) == {}
    above = _table([_row("A (ESM-ICP)", 0.01, 0.2, 0.04, 0.14, rmse_r=0.3, rmse_t=0.16)], trials=1000)
    assert ("A (ESM-ICP)", "RMSE(R)") in paper_quirks(above)
    # ... while one trial needs them equal.
    assert ("A (ESM-ICP)", "RMSE(R)") in paper_quirks(dict(below, trials=1))


def test_repeated_rows_and_mae_equal_to_rmse_are_flagged():
    table = _table([_row("ICP NL", 0.888659, 0.813719, 4741.5, 58.4), _row("DCP", 0.888659, 0.813719, 84140.6, 245.2),
                    _row("B", 0.826324, math.sqrt(0.826324), 2648.4, 49.7)])
    flags = paper_quirks(table)
    assert any("repeat ICP NL's" in f for f in flags[("DCP", "MSE(R)")])
    assert ("ICP NL", "MSE(R)") not in flags
    assert any("equals RMSE(R)" in f for f in flags[("B", "MAE(R)")])


def test_implied_rotation_error_and_ratios():
    assert implied_rotation_error_deg(8 / 9) == pytest.approx(180.0)
    assert implied_rotation_error_deg(0.0) == 0.0
    theta = math.radians(30.0)  # ||R1 - R2||_F^2 = 4 (1 - cos theta)
    assert implied_rotation_error_deg(4 * (1 - math.cos(theta)) / 9) == pytest.approx(30.0)
    assert ratio_text(2.0, 1.0) == "x2"
    assert ratio_text(1e-16, 1e-8) == "x10^-8"
    assert ratio_text(500.0, 1.0) == "x10^3"
    assert ratio_text(None, 1.0) == "-" and ratio_text(1.0, 0.0) == "-"


def test_records_from_real_bench_rows_and_the_csv_round_trip(tmp_path):
    # A folder holding one cloud named like a ModelNet40 vase: --paper's printed vase case runs on it.
    import numpy as np

    from esmicp.io import write_points
    from esmicp.shapes import asymmetric_shape

    folder = tmp_path / "objects"
    folder.mkdir()
    write_points(folder / "vase_0001.xyz", asymmetric_shape(300, np.random.default_rng(0)))
    config = BenchConfig(protocols=(), paper_tables=True, datasets=(str(folder),), methods=("esm-paper", "icp"),
                         points=(200,), max_iterations=40)
    run_bench(config, RunOptions(out_dir=tmp_path / "out", workers=1, progress=False))
    rows = read_rows(tmp_path / "out" / "rows.jsonl")
    assert {paper_table_of(r) for r in rows} == {"vase-outliers-30"}
    records = summary_records(rows, {"vase-outliers-30"})
    assert {(r["table"], r["cloud"], r["method"], r["points"]) for r in records} == \
        {("vase-outliers-30", "vase_0001", "esm-paper", 200), ("vase-outliers-30", "vase_0001", "icp", 200)}
    assert summary_records(rows, {"person"}) == []
    esm = next(r for r in records if r["method"] == "esm-paper")
    row = next(r for r in rows if r["method"] == "esm-paper")
    assert esm["mean_mse_r"] == pytest.approx(row["mse_r"]) and esm["ok"] == 1
    back = read_summary_csv(summary_csv(records))
    assert [(r["method"], r["points"], r["ok"]) for r in back] == [(r["method"], r["points"], r["ok"]) for r in records]
    assert back[0]["mean_mse_t"] == pytest.approx(records[0]["mean_mse_t"], rel=1e-5)
    table = dict(_table([_row("ICP", 0.888147, 0.811008, 1823.66, 25.7527), _row("ESM-ICP", 2.5e-16, 9.9e-9, 1.2e-12, 9.1e-7)],
                        table_id="vase-outliers-30"), dataset="ModelNet40 vase")
    text = side_by_side_markdown({}, table, back)
    assert "ours: `esm-paper`" in text and "ours: `icp`" in text and "ours: `open3d-icp`" not in text


def test_a_reason_in_a_results_table_keeps_no_folder_of_the_machine(tmp_path):
    from esmicp_lab.bench.tables import without_folders

    weights = tmp_path / "weights" / "rpm-net" / "model-best.pth"
    reason = f"rpm-net: weights not available: no rpm-net/model-best.pth in {weights}; put it there"
    assert without_folders(reason) == ("rpm-net: weights not available: no rpm-net/model-best.pth in "
                                       ".../rpm-net/model-best.pth; put it there")
    kept = "a ratio 1/2, a relative path rpm-net/model-best.pth, /dev/zero"
    assert without_folders(kept) == kept


def test_the_summary_reader_names_the_file_and_the_problem():
    with pytest.raises(InvalidInputError, match="s.csv: not a side-by-side summary"):
        read_summary_csv("a,b\n1,2\n", "s.csv")
    good = summary_csv([{"table": "person", "cloud": "person_0001", "method": "icp", "points": 10, "rows": 1, "ok": 1,
                         "failed": 0, "timeout": 0, "unavailable": 0}])
    with pytest.raises(InvalidInputError, match="s.csv: line 2, column points: not a number"):
        read_summary_csv(good.replace(",10,", ",ten,"), "s.csv")


def test_replace_sections_needs_both_markers_once():
    doc = f"intro\n{BEGIN.format(id='a')}\nold\n{END.format(id='a')}\nafter\n"
    assert replace_sections(doc, {"a": "new"}) == f"intro\n{BEGIN.format(id='a')}\n\nnew\n\n{END.format(id='a')}\nafter\n"
    with pytest.raises(InvalidInputError, match="exactly one"):
        replace_sections(doc, {"b": "new"}, "doc.md")
    with pytest.raises(InvalidInputError, match="before its begin"):
        replace_sections(f"{END.format(id='a')}{BEGIN.format(id='a')}", {"a": "x"})


def test_docs_hold_what_the_script_writes():
    """docs/bench-paper.md's side-by-side tables = the script's output from the committed summary
    and the paper's tables (regenerate: python benchmarks/paper_side_by_side.py write)."""
    paper = json.loads(require_shared("esm_icp_paper/paper_tables.json").read_text(encoding="utf-8"))
    doc = (REPO_ROOT / "docs" / "bench-paper.md").read_text(encoding="utf-8")
    summary = (REPO_ROOT / "docs" / "bench-paper-side-by-side.csv").read_text(encoding="utf-8")
    assert len(paper["tables"]) == 6
    assert regenerate(doc, paper, summary) == doc
    # ... and the check can fail: a changed figure in the summary changes the docs.
    records = read_summary_csv(summary)
    assert records
    changed = dict(records[0], mean_mse_r=(records[0]["mean_mse_r"] or 1.0) * 7.0)
    assert replace_sections(doc, sections(paper, [changed, *records[1:]])) != doc


def test_the_pages_pictures_draw_the_summarys_success_rates():
    """The bench pages' pictures (``python benchmarks/paper_side_by_side.py pictures``) show, for every record of the
    committed summary that ran, its strict success rate: one bar per record, none made up."""
    summary = (REPO_ROOT / "docs" / "bench-paper-side-by-side.csv").read_text(encoding="utf-8")
    records = [r for r in read_summary_csv(summary) if r["rows"] > r["unavailable"]]
    drawn = [rate for _, keep in PICTURES.values() for rate in success_rates(summary, keep)]
    assert len(drawn) == len(records)
    assert sorted(100.0 * r["successes"] / r["trials"] for r in drawn) == pytest.approx(
        sorted(r["success_strict_pct"] or 0.0 for r in records), abs=0.05)
    assert sum(r["trials"] for r in drawn) == sum(r["rows"] - r["unavailable"] for r in records)
