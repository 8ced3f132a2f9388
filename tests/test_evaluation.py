"""Fitted assets against a known truth: `evaluation.compare_with_truth` on small asset folders."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from torch_diffavatar.assets import material_dict
from torch_diffavatar.errors import InputError
from torch_diffavatar.evaluation import compare_with_truth
from torch_diffavatar.pattern.garmentcode import save_pattern
from torch_diffavatar.pattern.spec import Edge, Panel, Pattern
from torch_diffavatar.sim.material import ClothMaterial

SIDE = 0.5  # [m]
SQUARE = np.array([[0.0, 0.0], [SIDE, 0.0], [SIDE, SIDE], [0.0, SIDE]])
TRIANGLE = np.array([[0.0, 0.0], [0.4, 0.0], [0.1, 0.3]])


def _pattern(**panels: np.ndarray) -> Pattern:
    """A pattern of straight-edged panels (name -> (N, 2) corners [m])."""
    return Pattern(
        panels={
            name: Panel(name, np.asarray(v, float), [Edge(i, (i + 1) % len(v)) for i in range(len(v))])
            for name, v in panels.items()
        }
    )


def _write_assets(folder, pattern: Pattern, bend_stiffness: float | None = None):
    """A minimal fit output folder: pattern.json, and material.json when a stiffness is given."""
    folder.mkdir(parents=True, exist_ok=True)
    save_pattern(pattern, folder / "pattern.json")
    if bend_stiffness is not None:
        material = material_dict(ClothMaterial(bend_stiffness=bend_stiffness))
        (folder / "material.json").write_text(json.dumps(material))
    return folder


def test_template_against_itself(tmp_path):
    from torch_diffavatar.pattern.library import load_template

    truth = load_template("dress")
    folder = _write_assets(tmp_path / "fit", load_template("dress"), bend_stiffness=3.7e-5)
    out = compare_with_truth(folder, truth, truth_bend_stiffness=2e-5)
    assert set(out["pattern_outline_errors"]) == set(truth.panels)
    for name, e in out["pattern_outline_errors"].items():
        assert e["mean_m"] < 1e-4 and e["max_m"] < 1e-4, name
    assert out["pattern_outline_error_m"] < 1e-4 and out["pattern_outline_hausdorff_m"] < 1e-4
    assert out["bending_stiffness_ratio"] == 3.7e-5 / 2e-5  # exactly: JSON keeps every float digit


def test_known_outline_error_and_truth_from_a_file(tmp_path):
    # panel "a" fitted 4 % too large about its centre: its sides are 1 cm out, its corners 1 cm·√2;
    # panel "b" exact: the summary is the worst panel's
    big = (SQUARE - SIDE / 2) * (1 + 0.02 / SIDE) + SIDE / 2
    folder = _write_assets(tmp_path / "fit", _pattern(a=big, b=TRIANGLE))
    truth_path = tmp_path / "truth.json"
    save_pattern(_pattern(a=SQUARE, b=TRIANGLE), truth_path)
    for truth in (truth_path, str(truth_path)):
        out = compare_with_truth(folder, truth)
        errors = out["pattern_outline_errors"]
        assert errors["a"]["mean_m"] == pytest.approx(0.01, rel=0.1)
        assert errors["a"]["max_m"] == pytest.approx(0.01 * math.sqrt(2), rel=0.1)
        assert errors["b"]["mean_m"] < 1e-5 and errors["b"]["max_m"] < 1e-5
        assert out["pattern_outline_error_m"] == errors["a"]["mean_m"]
        assert out["pattern_outline_hausdorff_m"] == errors["a"]["max_m"]
        assert (
            "bending_stiffness_ratio" not in out
        )  # no true stiffness given: no ratio, no material.json read


def test_missing_pattern_raises_input_error(tmp_path):
    truth = _pattern(a=SQUARE)
    with pytest.raises(InputError, match="pattern.json"):
        compare_with_truth(tmp_path, truth)
    with pytest.raises(InputError, match="pattern.json"):
        compare_with_truth(tmp_path / "does_not_exist", truth, truth_bend_stiffness=1e-5)


def test_different_panels_raise_input_error(tmp_path):
    folder = _write_assets(tmp_path / "fit", _pattern(a=SQUARE, b=TRIANGLE), bend_stiffness=1e-5)
    with pytest.raises(InputError, match=r"\['b'\]"):
        compare_with_truth(folder, _pattern(a=SQUARE), truth_bend_stiffness=1e-5)


def test_missing_material_raises_input_error(tmp_path):
    folder = _write_assets(tmp_path / "fit", _pattern(a=SQUARE))  # pattern.json only
    with pytest.raises(InputError, match="material.json"):
        compare_with_truth(folder, _pattern(a=SQUARE), truth_bend_stiffness=1e-5)


def test_pattern_overlay_gives_narrow_panels_room_for_their_names(tmp_path):
    """Each panel's column is as wide as its name when the panel is narrower (collars ran into the next
    panel's name); the template, truth and result outlines are drawn in their colours."""
    from PIL import Image, ImageDraw

    from torch_diffavatar.evaluation import OVERLAY_COLOURS, save_pattern_overlay

    narrow = np.array([[0.0, 0.0], [0.02, 0.0], [0.02, 0.3], [0.0, 0.3]])  # 2 cm: 8 px at the scale
    template = _pattern(a_rather_long_collar_name=narrow, square=SQUARE)
    wider = _pattern(a_rather_long_collar_name=narrow * [1.0, 1.1], square=SQUARE * 1.1)
    path = tmp_path / "overlay.png"
    result = _pattern(a_rather_long_collar_name=narrow * [1.0, 1.05], square=SQUARE * 1.05)
    save_pattern_overlay({"template": template, "truth": wider, "result": result}, path, scale=400.0)
    image = np.asarray(Image.open(path).convert("RGB"))
    label = ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength("a_rather_long_collar_name")
    assert label > 0.02 * 400.0 + 12  # the name is wider than the panel and its padding
    # the square's outline starts right of the collar's name, not under it
    square_columns = np.nonzero((image == OVERLAY_COLOURS["result"]).all(-1).any(0))[0]
    assert square_columns.max() > 12 + label + 12 + 0.9 * SIDE * 400.0
    for colour in OVERLAY_COLOURS.values():
        assert (image == colour).all(-1).any()


def test_garment_measurements_of_a_changed_hem(tmp_path):
    """A fit whose skirt hem is 10 cm too high and 20 % too wide: the hem reads 20 % long, every
    length 10 cm short, the waist exact; the largest error is the hem's."""
    from torch_diffavatar.pattern.design import changed_pattern
    from torch_diffavatar.pattern.library import load_template

    truth = load_template("skirt")
    folder = _write_assets(tmp_path / "fit", changed_pattern(truth, hem_up=0.1, hem_widen=0.2))
    out = compare_with_truth(folder, truth)
    table = out["garment_measurements"]
    assert table["waist_circumference"]["error_cm"] == pytest.approx(0.0, abs=1e-9)
    hem = table["hem_circumference"]
    assert hem["error_cm"] == pytest.approx(0.2 * hem["true_cm"]) and hem["true_cm"] > 100
    for name in ("garment_length", "length_skirt_front", "length_skirt_back"):
        assert table[name]["error_cm"] == pytest.approx(-10.0), name
        assert table[name]["fitted_cm"] - table[name]["true_cm"] == table[name]["error_cm"]
    assert out["garment_measurement_max_error_cm"] == hem["error_cm"]
    area = out["garment_area_m2"]
    assert area["fitted_m2"] < area["true_m2"] and area["error_m2"] == area["fitted_m2"] - area["true_m2"]
    # the template against itself: nothing to report
    same = compare_with_truth(_write_assets(tmp_path / "same", truth), truth)
    assert same["garment_measurement_max_error_cm"] < 1e-9


def test_eval_report_leads_with_the_truth(tmp_path):
    """The text report: the outline error and the measurements table (cm) first, then the Chamfer to the
    true drape, then to the scan beside its floor (mm), then the rest."""
    from torch_diffavatar.commands.eval import report_lines
    from torch_diffavatar.pattern.design import changed_pattern
    from torch_diffavatar.pattern.library import load_template

    truth = load_template("skirt")
    folder = _write_assets(tmp_path / "fit", changed_pattern(truth, hem_up=0.05, hem_widen=0.0))
    out = {"units": "m", "chamfer_scan_m": 0.0042, "chamfer_truth_drape_m": 0.0061}
    out["chamfer_scan_truth_m"] = 0.0031
    out.update(compare_with_truth(folder, truth))
    out["body_height_error_m"] = 0.012
    text = "\n".join(report_lines(out))
    order = [
        "outline error",
        "garment measurements [cm]",
        "waist_circumference",
        "garment_length",
        "largest measurement error: 5.00 cm",
        "Chamfer to the true drape: 6.10 mm",
        "Chamfer to the scan: 4.20 mm; the true drape's own, the floor: 3.10 mm",
        "body_height_error_m: 0.012",
    ]
    where = [text.index(s) for s in order]
    assert where == sorted(where), text
    assert "-5.00" in text.split("garment_length")[1].splitlines()[0]
    assert "pattern_outline_error" not in text  # shown in cm, not again in metres
    assert re.search(r"per panel \[cm, mean / max\]: skirt_front \d\.\d\d / \d\.\d\d, skirt_back", text)
