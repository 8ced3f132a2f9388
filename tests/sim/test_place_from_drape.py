"""`placement.place_from_drape`: a garment meshed at one spacing placed where another meshing of the same
pattern lies draped."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_diffavatar.pattern import mesh_pattern
from torch_diffavatar.pattern.library import load_template
from torch_diffavatar.pattern.spec import Edge, Panel, Pattern
from torch_diffavatar.sim.placement import place_from_drape

# a curved-edged panel (so that meshes at two spacings have different outlines) and a triangle
PANELS = {
    "a": np.array([[0.0, 0.0], [0.4, 0.0], [0.45, 0.3], [0.0, 0.35]]),
    "b": np.array([[0.0, 0.0], [0.3, 0.0], [0.1, 0.25]]),
}


def _pattern() -> Pattern:
    edges = {
        "a": [Edge(0, 1), Edge(1, 2, kind="quadratic", control=((0.5, 0.15),)), Edge(2, 3), Edge(3, 0)],
        "b": [Edge(0, 1), Edge(1, 2), Edge(2, 0)],
    }
    return Pattern(panels={n: Panel(n, v, edges[n]) for n, v in PANELS.items()})


def _field(garment, kind: str) -> torch.Tensor:
    """(Vs, 3) a drape given as a function of each panel's rest coordinates (no stitches: Vs = V)."""
    uv = garment.vert_uv
    lift = garment.vert_panel.to(uv) * 0.5  # the panels lie apart
    if kind == "affine":
        z = 0.3 * uv[:, 0] - 0.2 * uv[:, 1] + lift
    else:  # a cylinder of radius 0.2 m around the v axis
        u = uv[:, 0] / 0.2
        return torch.stack((0.2 * torch.sin(u), uv[:, 1], 0.2 * (1 - torch.cos(u)) + lift), 1)
    return torch.stack((uv[:, 0], uv[:, 1], z), 1)


def test_a_mesh_placed_from_its_own_drape_is_that_drape():
    garment = mesh_pattern(load_template("tshirt"), spacing=0.05)
    x = torch.randn(garment.sim_vert_count, 3, dtype=torch.float64)
    placed = place_from_drape(garment, garment, x)
    torch.testing.assert_close(placed.vert_pos, x[garment.vert_to_sim], atol=1e-12, rtol=0)
    # seam copies coincide, so the garment starts sewn
    pairs = garment.stitch_pairs
    assert (placed.vert_pos[pairs[:, 0]] - placed.vert_pos[pairs[:, 1]]).abs().max() < 1e-12
    assert placed.vert_uv is garment.vert_uv and placed.tri_vertices is garment.tri_vertices


def test_other_spacing_interpolates_the_drape():
    pattern = _pattern()
    source = mesh_pattern(pattern, spacing=0.03)
    fine = mesh_pattern(pattern, spacing=0.015)
    target = mesh_pattern(pattern, spacing=0.05)
    assert target.vert_count != source.vert_count
    # an affine map of each panel is interpolated exactly (the outline's points outside the source's
    # inscribed polygon take the nearest triangle's affine extension)
    placed = place_from_drape(target, source, _field(source, "affine"))
    torch.testing.assert_close(placed.vert_pos, _field(target, "affine"), atol=1e-9, rtol=0)
    # a curved drape: linear interpolation, error O(h^2) of the source's spacing
    errors = []
    for src in (source, fine):
        placed = place_from_drape(target, src, _field(src, "cylinder"))
        errors.append(float((placed.vert_pos - _field(target, "cylinder")).norm(dim=1).max()))
    assert errors[0] < 2e-3 and errors[1] < 0.5 * errors[0]


def test_bad_input():
    pattern = _pattern()
    source = mesh_pattern(pattern, spacing=0.05)
    other = mesh_pattern(Pattern(panels={"c": Panel("c", PANELS["b"], _pattern().panels["b"].edges)}), 0.05)
    with pytest.raises(ValueError, match=r"\['c'\]"):
        place_from_drape(other, source, _field(source, "affine"))
    with pytest.raises(ValueError, match="source_x must be"):
        place_from_drape(source, source, torch.zeros(3, 3))
