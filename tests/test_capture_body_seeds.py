"""scripts/capture_body_seeds.py (issue #29's body-fit criterion on captures): its table marks the misses."""

from __future__ import annotations

from helpers_scripts import load_script

seeds = load_script("capture_body_seeds")


def _row(seed: int, height_error: float, surface: float) -> dict:
    return {
        "garment": "pants",
        "seed": seed,
        "true_height_m": 1.32,
        "height_error_m": height_error,
        "surface_m": surface,
        "vertex_m": 0.012,
        "sole_m": 0.02,
        "yaw_true_deg": -151.4,
        "yaw_deg": 208.9,
        "chamfer_m": 0.021,
        "seconds": 16.2,
        "warnings": [],
    }


def test_the_table_bolds_each_missed_target_and_counts_the_scans_that_meet_both():
    text = seeds.table([_row(1, -0.010, 0.004), _row(2, -0.0205, 0.004), _row(3, 0.002, 0.0125)])
    lines = text.splitlines()
    assert "| pants 1 | 1.320 | -1.00 | 0.40 / 1.20 | +2.0 | 208.6 / 208.9 | 21.0 | 16 |" in lines
    assert "| **-2.05** |" in lines[3] and "| **1.25** / 1.20 |" in lines[4]
    assert text.endswith("Both targets met on 1 of 3.")


def test_the_front_only_table_asks_for_the_height_within_2_cm_alone():
    """`--capture front`: #29's front-only criterion is the height within 2 cm; no surface target."""
    text = seeds.table([_row(1, -0.018, 0.015), _row(2, 0.0205, 0.004)], front=True)
    lines = text.splitlines()
    assert "| -1.80 | 1.50 / 1.20 |" in lines[2] and "| **+2.05** |" in lines[3]
    assert text.endswith("The height target met on 1 of 2.")
