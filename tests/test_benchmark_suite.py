"""scripts/benchmark_suite.py's RESULTS.md tables (the suite itself takes hours: its tables are checked on
made-up rows)."""

from __future__ import annotations

import argparse
import json

import pytest
from helpers_scripts import load_script


@pytest.fixture(scope="module")
def suite():
    return load_script("benchmark_suite")


def _eval(**changes) -> dict:
    """The measures of `evaluate_assets` that the tables read (metres, measurement errors in cm)."""
    out = {
        "pattern_outline_error_m": 0.0123,
        "pattern_outline_hausdorff_m": 0.0345,
        "garment_measurement_max_error_cm": 2.5,
        "chamfer_truth_drape_m": 0.0061,
        "chamfer_scan_m": 0.0042,
        "chamfer_scan_truth_m": 0.0031,
        "bending_stiffness_ratio": 1.1,
        "body_height_error_m": 0.004,
        "draped_quality": {"min": 0.3},
        "rest_quality": {"min": 0.4},
        "inverted_rest_triangles": 0,
        "seam_length_mismatch": {"max_m": 0.0007},
    }
    out.update(changes)
    return out


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip("|").split("|")]


def _newton_row(garment: str) -> dict:
    """A row of a Newton run: its truth's draws and settle as `_newton_summary` keeps them."""
    newton = {
        "stretch_factor": 0.25,
        "bend_factor": 1.5,
        "friction": 0.3,
        "waist_drop_m": 0.0,
        "drape": {"frames": 40, "converged": True, "mean_speed_m_per_s": 0.004, "max_speed_m_per_s": 0.03},
        "iterations_per_step": 120,
        "edge_strain_mean_abs": {"newton": 0.012, "ours": 0.0015},
        "chamfer_to_ours_drape_m": 0.02,
    }
    return {"garment": garment, "initial": _eval(), "final": _eval(), "seconds": 1.0, "scan_seconds": 90.0,
            "newton": newton}  # fmt: skip


def test_tables_lead_with_the_truth(suite):
    initial = _eval(pattern_outline_error_m=0.05, garment_measurement_max_error_cm=11.0)
    initial.update(chamfer_truth_drape_m=0.02, chamfer_scan_m=0.015, bending_stiffness_ratio=0.25)
    rows = [{"garment": "skirt", "initial": initial, "final": _eval(), "seconds": 12.0}]
    rows.append({"garment": "polo", "error": "RuntimeError: boom"})
    table = suite._table1_lines([{"simulator": "ours", "rows": rows, "ablations": []}])
    head, row, failed = _cells(table[2]), _cells(table[4]), _cells(table[5])
    assert len(head) == len(row) == len(failed) == len(_cells(table[3]))
    assert head[1] == "scans by" and head[2].startswith("outline mean")
    assert head[4].startswith("largest measurement error")
    assert head[5].startswith("Chamfer to true drape") and head[6].startswith("Chamfer to scan")
    assert row[:8] == [
        "skirt",
        "ours",
        "5.00 → 1.23",
        "3.45 → 3.45",
        "11.00 → 2.50",
        "20.00 → 6.10 (70 % lower)",
        "15.00 → 4.20 (72 % lower)",
        "3.10",
    ]
    # an ablation from before the measurements existed: a dash, not a crash
    old = _eval()
    del old["garment_measurement_max_error_cm"]
    ablations = [
        {"garment": "dress", "name": "full", "eval": _eval()},
        {"garment": "dress", "name": "x", "eval": old},
    ]
    table = suite._table2_lines([{"simulator": "ours", "rows": [], "ablations": ablations}])
    head, full, x = _cells(table[3]), _cells(table[5]), _cells(table[6])
    assert head[1:8] == [
        "scans by",
        "variant",
        "outline mean [cm]",
        "outline max [cm]",
        "largest measurement error [cm]",
        "Chamfer to true drape [mm]",
        "Chamfer to scan [mm]",
    ]
    assert full[3:8] == ["1.23", "3.45", "2.50", "6.10", "4.20"] and x[5] == "—"


def test_generators_side_by_side(suite):
    """Each garment's rows together, ours first; Newton's truths in a table of their own."""
    ours = {"simulator": "ours", "rows": [_newton_row("dress"), _newton_row("tshirt")], "ablations": []}
    for r in ours["rows"]:
        del r["newton"]
    newton = {"simulator": "newton", "rows": [_newton_row("tshirt"), _newton_row("dress")], "ablations": []}
    body = [_cells(line)[:2] for line in suite._table1_lines([ours, newton])[4:]]
    assert body == [["dress", "ours"], ["dress", "newton"], ["tshirt", "ours"], ["tshirt", "newton"]]
    del newton["rows"][0]["newton"]["iterations_per_step"]  # a truth made before the generator said
    table = suite._newton_lines([ours, newton])
    assert [_cells(line)[0] for line in table[-2:]] == ["tshirt", "dress"]
    assert _cells(table[-1])[1:9] == [
        "0.25",
        "1.50",
        "0.30",
        "120",
        "40 (yes)",
        "0.004 / 0.030",
        "1.20 / 0.15",
        "20.00",
    ]
    assert _cells(table[-2])[4] == "–"
    assert suite._newton_lines([ours]) == [] and suite._table2_lines([ours, newton]) == []


def _args(**changes) -> argparse.Namespace:
    settings = dict(
        hem_up=0.05, hem_widen=0.1, scan_spacing=0.02, seed=0, garment_points=40000, body_points=30000
    )
    return argparse.Namespace(**(settings | changes))


def test_results_file_keeps_its_discussion(suite, tmp_path):
    path = tmp_path / "RESULTS.md"
    path.write_text(f"old tables\n{suite.DISCUSSION_MARKER}\nhand-written notes\n")
    runs = [
        {"simulator": "ours", "rows": [_newton_row("skirt")], "ablations": [], "commit": "abc1234"},
        {
            "simulator": "newton",
            "rows": [_newton_row("skirt")],
            "ablations": [],
            "command": "x --simulator newton",
        },
    ]
    suite._write_results(path, runs, _args())
    text = path.read_text()
    assert "old tables" not in text and text.endswith("hand-written notes\n")
    assert "settled again by NVIDIA Newton's VBD cloth" in text  # who draped the truth
    assert "at commit abc1234" in text and "`x --simulator newton`" in text  # where each table comes from
    assert "results/newton_skirt_drapes.png" in text and "results/skirt_drapes.png" in text
    assert text.index("## Table 1") < text.index("### Newton's truths") < text.index(suite.DISCUSSION_MARKER)
    assert "## Table 2" not in text  # no ablations


def test_runs_of_a_suite_json_are_read_back(suite, tmp_path):
    path = tmp_path / "suite.json"
    run = {"simulator": "newton", "rows": [], "ablations": []}
    path.write_text(json.dumps({"runs": [run]}))
    assert suite.load_runs(path) == [run]
    path.write_text(json.dumps({"rows": [1], "ablations": []}))  # a suite.json from before the generators
    assert suite.load_runs(path) == [{"simulator": "ours", "rows": [1], "ablations": []}]
