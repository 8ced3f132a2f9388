"""Fitted assets against a known ground truth (the demo's bundled answer, synthetic scans).

`compare_with_truth` reads the assets a fit wrote (``pattern.json``, ``material.json``) and measures them
against the true pattern and material:

* ``pattern_outline_error_m``: per panel, the mean distance between the fitted and the true outline after
  a rigid alignment of the panel (`metrics.outline_distance`); the value is the worst panel's [m];
* ``pattern_outline_hausdorff_m``: the same with the largest distance (dart tips and corners dominate);
* ``pattern_outline_errors``: both per panel;
* ``bending_stiffness_ratio``: fitted / true bending stiffness [-] (1 is exact).
"""

from __future__ import annotations

import json
from pathlib import Path

from torch_diffavatar.errors import InputError


def compare_with_truth(assets_dir, truth_pattern, truth_bend_stiffness: float | None = None) -> dict:
    """Measures of the assets in ``assets_dir`` against the truth (see the module docstring).

    Args:
        assets_dir: a folder written by `assets.write_assets`.
        truth_pattern: the true pattern: a `Pattern` or a GarmentCode JSON path, with the template's
            panel names.
        truth_bend_stiffness: the true bending stiffness [N·m], or None to skip the ratio.

    Raises:
        InputError: a file is missing, or the patterns' panels differ.
    """
    from torch_diffavatar.metrics import pattern_outline_errors
    from torch_diffavatar.pattern.garmentcode import load_pattern

    folder = Path(assets_dir)
    fitted_path = folder / "pattern.json"
    if not fitted_path.is_file():
        raise InputError(f"{fitted_path} is missing: is {folder} the output folder of a fit?")
    truth = load_pattern(truth_pattern) if isinstance(truth_pattern, str | Path) else truth_pattern
    try:
        errors = pattern_outline_errors(load_pattern(fitted_path), truth)
    except ValueError as exc:
        raise InputError(f"{fitted_path} vs the true pattern: {exc}") from exc
    out = {
        "pattern_outline_error_m": max(e["mean_m"] for e in errors.values()),
        "pattern_outline_hausdorff_m": max(e["max_m"] for e in errors.values()),
        "pattern_outline_errors": errors,
    }
    if truth_bend_stiffness is not None:
        from torch_diffavatar.assets import material_from_dict

        material_path = folder / "material.json"
        if not material_path.is_file():
            raise InputError(f"{material_path} is missing: is {folder} the output folder of a fit?")
        material = material_from_dict(json.loads(material_path.read_text()))
        out["bending_stiffness_ratio"] = float(material.bend_stiffness) / float(truth_bend_stiffness)
    return out
