"""scripts/benchmark_suite.py's RESULTS.md tables (the suite itself takes hours: its tables are checked on
made-up rows)."""

from __future__ import annotations

import argparse

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


def test_tables_lead_with_the_truth(suite):
    initial = _eval(pattern_outline_error_m=0.05, garment_measurement_max_error_cm=11.0)
    initial.update(chamfer_truth_drape_m=0.02, chamfer_scan_m=0.015, bending_stiffness_ratio=0.25)
    rows = [{"garment": "skirt", "initial": initial, "final": _eval(), "seconds": 12.0}]
    rows.append({"garment": "polo", "error": "RuntimeError: boom"})
    table = suite._table1_lines(rows)
    head, row, failed = _cells(table[2]), _cells(table[4]), _cells(table[5])
    assert len(head) == len(row) == len(failed) == len(_cells(table[3]))
    assert head[1].startswith("outline mean") and head[3].startswith("largest measurement error")
    assert head[4].startswith("Chamfer to true drape") and head[5].startswith("Chamfer to scan")
    assert row[:7] == [
        "skirt",
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
    table = suite._table2_lines(ablations)
    head, full, x = _cells(table[3]), _cells(table[5]), _cells(table[6])
    assert head[2:7] == [
        "outline mean [cm]",
        "outline max [cm]",
        "largest measurement error [cm]",
        "Chamfer to true drape [mm]",
        "Chamfer to scan [mm]",
    ]
    assert full[2:7] == ["1.23", "3.45", "2.50", "6.10", "4.20"] and x[4] == "—"


def test_results_file_keeps_its_discussion(suite, tmp_path):
    path = tmp_path / "RESULTS.md"
    path.write_text(f"old tables\n{suite.DISCUSSION_MARKER}\nhand-written notes\n")
    args = argparse.Namespace(
        hem_up=0.05,
        hem_widen=0.1,
        scan_spacing=0.02,
        seed=0,
        garment_points=40000,
        body_points=30000,
        simulator="newton",
    )
    rows = [{"garment": "skirt", "initial": _eval(), "final": _eval(), "seconds": 1.0}]
    suite._write_results(path, rows, [], args, "2026-12-04 21:00 UTC")
    text = path.read_text()
    assert "old tables" not in text and text.endswith("hand-written notes\n")
    assert "settled again by NVIDIA Newton's VBD cloth" in text  # who draped the truth
    assert text.index("## Table 1") < text.index("## Table 2") < text.index(suite.DISCUSSION_MARKER)
