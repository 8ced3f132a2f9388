"""scripts/capture_fit_seeds.py (issue #29's end-to-end criterion on captures): its table marks the misses
and counts the fits that meet each target."""

from __future__ import annotations

import pytest
from helpers_scripts import ROOT, load_script


@pytest.fixture
def seeds(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "scripts"))  # it imports capture_body_seeds, its neighbour
    return load_script("capture_fit_seeds")


def _row(seed: int, chamfer: float, neck: float) -> dict:
    return {
        "garment": "tshirt",
        "seed": seed,
        "labelled": True,
        "outline_mean_m": 0.0031,
        "outline_max_m": 0.0086,
        "openings_cm": {"neck_circumference": neck, "hem_circumference": -0.4},
        "chamfer_scan_m": [0.0070, chamfer],
        "chamfer_truth_drape_m": [0.0056, 0.0038],
        "body_height_error_m": 0.0042,
        "body_vertex_error_m": 0.0052,
        "warnings": [],
        "seconds": 119.4,
    }


def test_the_table_bolds_each_missed_target_and_counts_each(seeds):
    """T-shirt: 1.5 × 6.57 mm = 9.855 mm of Chamfer; every opening within 2 cm."""
    failed = {"garment": "tshirt", "seed": 4, "labelled": True, "failed": "W/tshirt_4/log.txt"}
    text = seeds.table([_row(1, 0.0090, 1.2), _row(2, 0.0099, -0.5), _row(3, 0.0060, -2.1), failed])
    lines = text.splitlines()
    assert lines[2] == (
        "| tshirt 1 | 3.1 / 8.6 | neck +1.2, hem -0.4 | 7.00 → 9.00 | 5.60 → 3.80 | +0.42 / 5.2 | 0 | 119 |"
    )
    assert "7.00 → **9.90**" in lines[3] and "**neck -2.1**, hem -0.4" in lines[4]
    assert "**the fit failed** (W/tshirt_4/log.txt)" in lines[5]
    assert text.endswith("Chamfer: 2 of 4; every opening within 2 cm: 2 of 4.")


def test_rig_artefacts_become_make_scan_options(seeds):
    assert seeds.rig_options(0.0, None) == ()
    rig = ("--flying-pixels", "0.3", "--calibration-error", "2", "0.15")
    assert seeds.rig_options(0.3, [2.0, 0.15]) == rig
    assert seeds.rig_options(0.0, (5.0, 0.0)) == ("--calibration-error", "5", "0")
