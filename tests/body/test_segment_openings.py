"""One vocabulary for openings: the segmentation names a scan's openings as the garment mesh names its own
(`pattern.mesher.name_boundary_loops`), so the fit matches them by name (`fit_setup.match_boundaries`)."""

from __future__ import annotations

import numpy as np
import pytest

from torch_diffavatar.body.segment import (
    _EXTREMITIES,
    _SLEEVED,
    GARMENT_TYPES,
    _opening_name,
    _part_side,
)
from torch_diffavatar.fit_setup import match_boundaries
from torch_diffavatar.pattern import load_template, mesh_pattern

# every name `name_boundary_loops` gives a garment mesh's openings, but its unnamed ``opening_<k>``
MESH_NAMES = {"neck", "waist", "hem", "cuff_left", "cuff_right", "hem_left", "hem_right"}


@pytest.mark.parametrize("kind", GARMENT_TYPES)
def test_every_opening_name_is_a_garment_mesh_name(kind):
    names = {_opening_name(extremity, kind) for extremity in _EXTREMITIES}
    assert names <= MESH_NAMES, names


@pytest.mark.parametrize(
    ("extremity", "kind", "name"),
    [
        ("head", "tshirt", "neck"),
        ("head", "pants", "waist"),
        ("hand.L", "skirt", "waist"),
        ("hand.L", "tshirt", "cuff_left"),  # a sleeve's end
        ("hand.R", "shirt", "cuff_right"),
        ("hand.L", "dress", "cuff_left"),  # a sleeveless top's armhole
        ("hand.R", "jumpsuit_sleeveless", "cuff_right"),
        ("foot.L", "dress", "hem"),
        ("foot.R", "skirt", "hem"),
        ("foot.L", "pants", "hem_left"),  # a trouser leg
        ("foot.R", "pants", "hem_right"),
        ("foot.L", "jumpsuit", "hem_left"),
        ("foot.R", "jumpsuit_sleeveless", "hem_right"),
    ],
)
def test_opening_names(extremity, kind, name):
    # left is the body's left, Anny's ".L" (+x), as the mesher's "_left" (the loop on the +x side)
    assert _opening_name(extremity, kind) == name


@pytest.mark.parametrize("kind", GARMENT_TYPES)
def test_an_openings_name_gives_back_its_body_side(kind):
    for extremity in _EXTREMITIES:
        name = _opening_name(extremity, kind)
        side = _part_side(name)
        assert side in ("", ".L", ".R")
        if side:  # a named side is the extremity's own
            assert extremity.endswith(side), (extremity, name)
        elif name.startswith("cuff"):
            pytest.fail(f"{name} without a side")


def test_cuffs_of_sleeved_and_sleeveless_tops_share_a_name():
    # an armhole is matched to the garment's "cuff_*" loop, as a sleeve's end is; only the rim rule
    # (a sleeve's far end) tells them apart, by the garment type
    assert "dress" not in _SLEEVED and "tshirt" in _SLEEVED
    assert _opening_name("hand.L", "dress") == _opening_name("hand.L", "tshirt")


def test_the_mesh_names_the_plus_x_cuff_left():
    garment = mesh_pattern(load_template("tshirt"), spacing=0.05)
    pos = garment.sim_positions().double()
    x = {lp.name: float(pos[lp.vertices, 0].mean()) for lp in garment.boundary_loops}
    assert x["cuff_left"] > x["neck"] > x["cuff_right"]


def _loop_points(garment) -> dict[str, np.ndarray]:
    pos = garment.sim_positions().double().numpy()
    return {lp.name: pos[lp.vertices.numpy()] for lp in garment.boundary_loops}


def test_scan_openings_match_the_garments_by_name():
    garment = mesh_pattern(load_template("pants"), spacing=0.05)
    points = _loop_points(garment)
    assert set(points) == {"waist", "hem_left", "hem_right"}
    # the scan's legs swapped in space: names decide, not positions
    scan = {"hem_left": points["hem_right"], "hem_right": points["hem_left"], "waist": points["waist"]}
    out = match_boundaries(garment, scan)
    assert set(out) == {"waist", "hem_left", "hem_right"}
    for name, pts in scan.items():
        assert np.array_equal(out[name].numpy(), pts)
        assert out[name].dtype == out["waist"].dtype


def test_a_scan_opening_the_garment_lacks_goes_to_the_nearest_free_loop():
    garment = mesh_pattern(load_template("tshirt"), spacing=0.05)
    points = _loop_points(garment)
    # a scan's "waist" where the garment has its neck (a top typed as trousers): matched by proximity
    scan = {"cuff_left": points["cuff_left"], "cuff_right": points["cuff_right"], "waist": points["neck"]}
    out = match_boundaries(garment, scan)
    assert set(out) == {"cuff_left", "cuff_right", "neck"}
    assert np.array_equal(out["neck"].numpy(), points["neck"])
    # beyond ``max_distance`` it is not matched
    far = {"waist": points["neck"] + np.array([0.0, 5.0, 0.0])}
    assert match_boundaries(garment, far) == {}
