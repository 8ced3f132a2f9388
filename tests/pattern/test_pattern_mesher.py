"""Mesher properties: quality, equal stitch counts, watertight seams, orientation, stitch rules, loops."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers_pattern import VALID_SPECS, dart_panel, two_squares

from torch_diffavatar.metrics import min_angle_deg
from torch_diffavatar.pattern import (
    list_templates,
    load_pattern,
    load_template,
    mesh_pattern,
    mesh_report,
    pattern_from_dict,
)
from torch_diffavatar.pattern.mesher import name_boundary_loops

CASES = [("template", n) for n in list_templates()] + [("spec", str(p)) for p in VALID_SPECS]


@pytest.fixture(scope="module")
def meshed():
    out = {}
    for kind, name in CASES:
        pattern = load_template(name) if kind == "template" else load_pattern(name)
        out[name] = (pattern, mesh_pattern(pattern))
    return out


@pytest.mark.parametrize("case", CASES, ids=lambda c: c[1].split("/")[-1])
def test_quality_counts_and_watertight_seams(meshed, case):
    pattern, g = meshed[case[1]]
    assert float(min_angle_deg(g.vert_uv, g.tri_vertices)) >= 25.0 - 1e-6
    r = mesh_report(pattern, g)
    assert r.max_stitch_count_mismatch == 0
    assert r.unmerged_stitch_pairs == 0
    assert r.seam_edges > 0 and r.open_seam_edges == 0
    assert r.nonmanifold_edges == 0 and r.collapsed_faces == 0
    # every stitched edge pair has equal vertex counts and its pairs coincide after merging
    for s in pattern.stitches:
        va, vb = g.edge_vertices[(s.a.panel, s.a.edge)], g.edge_vertices[(s.b.panel, s.b.edge)]
        assert len(va) == len(vb)
        a = va if s.right_wrong else va.flip(0)
        assert torch.equal(g.vert_to_sim[a], g.vert_to_sim[vb])
    # boundary samples stay at most one spacing apart
    for loop in g.panel_boundary:
        uv = g.vert_uv[loop]
        steps = (uv - uv.roll(-1, 0)).norm(dim=1)
        assert float(steps.max()) <= g.spacing * (1 + 1e-6)


@pytest.mark.parametrize("name", ["dress", "tshirt", "pants", "skirt", "polo"])
def test_placed_normals_point_out_of_the_garment(meshed, name):
    _, g = meshed[name]
    p = g.vert_pos
    f = g.tri_vertices
    n = torch.linalg.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    centre = g.sim_positions().mean(dim=0)
    radial = p[f].mean(dim=1) - centre
    radial[:, 1] = 0.0  # away from the garment's vertical axis
    outward = ((n * radial).sum(dim=1) > 0).double().mean()
    assert float(outward) > 0.8


@pytest.mark.parametrize(
    "name,expected",
    [
        ("dress", {"neck", "hem", "cuff_left", "cuff_right"}),
        ("tshirt", {"neck", "hem", "cuff_left", "cuff_right"}),
        ("longsleeve", {"neck", "hem", "cuff_left", "cuff_right"}),
        ("skirt", {"waist", "hem"}),
        ("pants", {"waist", "hem_left", "hem_right"}),
        ("shorts", {"waist", "hem_left", "hem_right"}),
    ],
)
def test_boundary_loop_names(meshed, name, expected):
    _, g = meshed[name]
    names = [b.name for b in g.boundary_loops]
    assert set(names) == expected and len(names) == len(expected)
    pos = g.sim_positions()
    loops = {b.name: b.vertices for b in g.boundary_loops}
    y = {k: float(pos[v, 1].mean()) for k, v in loops.items()}
    x = {k: float(pos[v, 0].mean()) for k, v in loops.items()}
    top = "waist" if "waist" in loops else "neck"
    assert y[top] == max(y.values())
    if "cuff_left" in loops:
        assert x["cuff_left"] > 0 > x["cuff_right"]
    if "hem_left" in loops:
        assert x["hem_left"] > 0 > x["hem_right"]
    # loops are closed chains of boundary edges (each consecutive pair is an edge of exactly one face)
    faces = g.sim_faces
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).sort(dim=1).values
    uniq, counts = torch.unique(e, dim=0, return_counts=True)
    boundary = {tuple(k) for k, c in zip(uniq.tolist(), counts.tolist()) if c == 1}
    total = 0
    for v in loops.values():
        pairs = torch.stack([v, v.roll(-1)], dim=1).sort(dim=1).values
        assert all(tuple(p) in boundary for p in pairs.tolist())
        total += len(v)
    assert total == len(boundary)
    if "waist" in loops:  # GarmentCode's lower_interface edges are the waist
        waist = set(loops["waist"].tolist())
        li = set(g.vert_to_sim[g.vert_labels["lower_interface"]].tolist())
        assert li <= waist


def test_garment_mesh_fields(meshed):
    pattern, g = meshed["dress"]
    assert g.garment_type == "dress" and g.panel_names == list(pattern.panels)
    assert g.vert_uv.dtype == torch.float64 and g.tri_vertices.dtype == torch.int64
    assert sum(len(b) for b in g.panel_boundary) <= g.vert_count
    for (name, k), idx in g.edge_vertices.items():
        panel = pattern.panels[name]
        e = panel.edges[k]
        np.testing.assert_allclose(
            g.vert_uv[idx[[0, -1]]].numpy(), panel.vertices[[e.start, e.end]], atol=1e-12
        )
        assert bool((g.vert_panel[idx] == g.panel_names.index(name)).all())
        # placement: world = R (x, y, 0) + t
        np.testing.assert_allclose(
            g.vert_pos[idx].numpy(), panel.to_world(g.vert_uv[idx].numpy()), atol=1e-12
        )
    g32 = g.to(dtype=torch.float32)
    assert g32.vert_uv.dtype == torch.float32 and g32.tri_vertices.dtype == torch.int64


@pytest.mark.parametrize("right_wrong", [False, True])
def test_stitch_orientation_rule(right_wrong):
    g = mesh_pattern(pattern_from_dict(two_squares(right_wrong)), spacing=0.05)
    pairs = g.stitch_pairs
    assert len(pairs) == 7  # 30 cm side at 5 cm spacing: 6 segments, 7 vertices
    # the two squares are placed so that the seam lines up in x, y: paired vertices coincide there
    pa, pb = g.vert_pos[pairs[:, 0]], g.vert_pos[pairs[:, 1]]
    np.testing.assert_allclose(pa[:, :2].numpy(), pb[:, :2].numpy(), atol=1e-12)
    assert g.sim_vert_count == g.vert_count - 7
    assert len(g.boundary_loops) == 1  # two squares sewn along one side: one open sheet


def test_dart_is_sewn_closed():
    g = mesh_pattern(pattern_from_dict(dart_panel()), spacing=0.02)
    legs_a, legs_b = g.edge_vertices[("front", 1)], g.edge_vertices[("front", 2)]
    assert len(legs_a) == len(legs_b)
    tip = int(legs_a[-1])
    assert tip == int(legs_b[0])
    assert tip not in g.stitch_pairs.flatten().tolist()  # the tip joins itself: no pair
    assert len(g.stitch_pairs) == len(legs_a) - 1
    assert torch.equal(g.vert_to_sim[legs_a.flip(0)], g.vert_to_sim[legs_b])
    # after sewing, the dart's mouth is one point on a single boundary loop
    assert len(g.boundary_loops) == 1
    r = mesh_report(pattern_from_dict(dart_panel()), g)
    assert r.open_seam_edges == 0 and r.collapsed_faces == 0


def test_bad_mesher_arguments():
    p = pattern_from_dict(two_squares())
    with pytest.raises(ValueError, match="spacing"):
        mesh_pattern(p, spacing=0)
    with pytest.raises(ValueError, match="min_angle"):
        mesh_pattern(p, min_angle=40)


def _named_rings(rings: list[tuple[list[float], float]]) -> tuple[dict[str, float], set[str]]:
    """Name horizontal rings of 12 vertices (centre [m], radius [m]) as a top's loops (no garment type):
    (name -> its centroid's x [m], the names)."""
    a = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
    circle = np.stack([np.cos(a), np.zeros(12), np.sin(a)], axis=1)
    pos = np.concatenate([np.asarray(c) + r * circle for c, r in rings])
    loops = [np.arange(12 * k, 12 * k + 12) for k in range(len(rings))]
    named = name_boundary_loops(loops, pos, None, set())
    return {b.name: float(pos[b.vertices.numpy(), 0].mean()) for b in named}, {b.name for b in named}


def test_a_top_with_two_legs_names_them_as_trouser_hems():
    """A jumpsuit's two lowest loops lie below the crotch, each wholly on one side of the centre:
    ``hem_left`` (x > 0) and ``hem_right``; a dress's single hem around the centre stays ``hem``."""
    neck, cuffs = ([0.0, 1.45, 0.0], 0.08), [([0.6, 1.2, 0.0], 0.05), ([-0.6, 1.2, 0.0], 0.05)]
    x, names = _named_rings([neck, *cuffs, ([0.1, 0.1, 0.0], 0.07), ([-0.1, 0.1, 0.0], 0.07)])
    assert names == {"neck", "cuff_left", "cuff_right", "hem_left", "hem_right"}
    assert x["hem_left"] > 0 > x["hem_right"] and x["cuff_left"] > 0 > x["cuff_right"]
    _, names = _named_rings([neck, *cuffs, ([0.0, 0.4, 0.0], 0.3)])
    assert names == {"neck", "cuff_left", "cuff_right", "hem"}
    # a cropped top's long sleeves end below its hem (above the crotch): cuffs, and the hem is the loop
    # around the body, not the lowest
    x, names = _named_rings(
        [neck, ([0.0, 1.05, 0.0], 0.2), ([0.6, 0.9, 0.0], 0.05), ([-0.6, 0.9, 0.0], 0.05)]
    )
    assert names == {"neck", "hem", "cuff_left", "cuff_right"}
    assert x["cuff_left"] > 0 > x["cuff_right"] and abs(x["hem"]) < 1e-9
