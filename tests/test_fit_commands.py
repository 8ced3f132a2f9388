"""`diffavatar fit`'s garment argument: a bundled template or any GarmentCode pattern file."""

from __future__ import annotations

from pathlib import Path

import pytest

from torch_diffavatar.cli import main
from torch_diffavatar.fit_commands import SEGMENT_TYPES, TYPE_CONFIGS, infer_garment_type
from torch_diffavatar.pattern import load_pattern
from torch_diffavatar.pattern.library import load_template

GARMENTCODE = Path("/work/shared/garmentcode")
# GarmentCode's own files (not our templates) and what they are
PATTERN_FILES = {
    "shirt_long_sleeve": "shirt",
    "polo_collar_short_sleeve": "polo",
    "tshirt_short_sleeve": "tshirt",
    "skirt_aline": "skirt",
    "pants_shorts": "pants",
    "dress_fitted_sleeveless_aline": "dress",
    "dress_fitted_short_sleeve_pencil": "dress",
    "repo_examples/shirt_mean": "shirt",  # sleeves to mid-forearm
    "repo_examples/hoody_mean": "dress",  # sleeveless top with a hood: the dress's regions and armholes
    "repo_examples/js_mean_all": "pants",  # jumpsuit: legs decide
}


@pytest.mark.parametrize("name", sorted(SEGMENT_TYPES))
def test_inferred_type_of_every_template_is_its_segmentation_type(name):
    assert infer_garment_type(load_template(name)) == SEGMENT_TYPES[name]


@pytest.mark.parametrize("folder", sorted(PATTERN_FILES))
def test_inferred_type_of_garmentcode_files(folder):
    specs = sorted((GARMENTCODE / folder).glob("*_specification.json"))
    if not specs:
        pytest.skip(f"{GARMENTCODE / folder} not on this machine")
    kind = infer_garment_type(load_pattern(specs[0]))
    assert kind == PATTERN_FILES[folder] and kind in TYPE_CONFIGS


def test_fit_rejects_a_garment_that_is_neither_template_nor_file(tmp_path, capsys):
    scan = tmp_path / "scan.ply"
    scan.write_text("ply\n")
    code = main(["fit", str(scan), "--garment", "cardigan", "--out", str(tmp_path / "out")])
    assert code == 2
    assert "not a template" in capsys.readouterr().err
    bad = tmp_path / "broken.json"
    bad.write_text("{not json")
    assert main(["fit", str(scan), "--garment", str(bad), "--out", str(tmp_path / "out")]) == 2
