"""Pattern edges much shorter than the spacing (GarmentCode's js_mean_all has 0.9 mm ones): collapsed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_diffavatar.metrics import min_angle_deg
from torch_diffavatar.pattern import mesh_pattern, mesh_report, pattern_from_dict
from torch_diffavatar.pattern.mesher import SHORT_EDGE, collapsed_edges

CHAMFER_CM = 0.1  # the corner chamfer's legs [cm]: a 1.41 mm edge


def chamfered_squares(free_chamfer: bool = False, long_partner: bool = False) -> dict:
    """A front (CCW, z = +10 cm) and a back (CW, z = -10 cm) 20 x 30 cm panel, each with its top right
    corner cut by a 1.41 mm chamfer, sewn along the right side and along the chamfer.

    Front edges: 0 bottom, 1 right side (up), 2 chamfer, 3 top, 4 left side. Back edges (mirrored): 0 left
    side, 1 top, 2 chamfer, 3 right side (down), 4 bottom. ``free_chamfer``: the chamfers are not sewn.
    ``long_partner``: the front chamfer is sewn to the back's 20 cm bottom edge instead.
    """
    c = CHAMFER_CM
    front = {
        "translation": [0, 100, 10],
        "rotation": [0, 0, 0],
        "vertices": [[0, 0], [20, 0], [20, 30 - c], [20 - c, 30], [0, 30]],
        "edges": [{"endpoints": [i, (i + 1) % 5]} for i in range(5)],
    }
    back = {
        "translation": [0, 100, -10],
        "rotation": [0, 0, 0],
        "vertices": [[0, 0], [0, 30], [20 - c, 30], [20, 30 - c], [20, 0]],
        "edges": [{"endpoints": [i, (i + 1) % 5]} for i in range(5)],
    }
    stitches = [[{"panel": "front", "edge": 1}, {"panel": "back", "edge": 3}]]
    if long_partner:
        stitches.append([{"panel": "front", "edge": 2}, {"panel": "back", "edge": 4}])
    elif not free_chamfer:
        stitches.append([{"panel": "front", "edge": 2}, {"panel": "back", "edge": 2}])
    return {
        "pattern": {"panels": {"front": front, "back": back}, "stitches": stitches},
        "properties": {"units_in_meter": 100, "curvature_coords": "relative"},
    }


def mesh_edge_lengths(g) -> np.ndarray:
    """Lengths [m] of every triangle edge of the panel meshes (in the pattern plane)."""
    t, uv = g.tri_vertices.numpy(), g.vert_uv.numpy()
    e = np.unique(np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1), axis=0)
    return np.linalg.norm(uv[e[:, 0]] - uv[e[:, 1]], axis=1)


@pytest.mark.parametrize("spacing", [0.015, 0.02, 0.03])
@pytest.mark.parametrize("free_chamfer", [False, True], ids=["sewn", "free"])
def test_short_corner_edge_is_collapsed(spacing, free_chamfer):
    pattern = pattern_from_dict(chamfered_squares(free_chamfer))
    assert pattern.panels["front"].edge_length(2) < SHORT_EDGE * spacing
    g = mesh_pattern(pattern, spacing=spacing)
    # the 1.4 mm edge neither survives as a boundary segment nor shrinks the steps at its corners
    assert mesh_edge_lengths(g).min() >= SHORT_EDGE * spacing
    assert float(min_angle_deg(g.vert_uv, g.tri_vertices)) >= 25.0 - 1e-6
    for name in ("front", "back"):
        ev = g.edge_vertices[(name, 2)]
        assert len(ev) == 1  # one point, shared with both neighbours' corners
        assert int(g.edge_vertices[(name, 1)][-1]) == int(ev[0]) == int(g.edge_vertices[(name, 3)][0])
    r = mesh_report(pattern, g)
    assert r.max_stitch_count_mismatch == 0 and r.unmerged_stitch_pairs == 0
    assert r.open_seam_edges == 0 and r.nonmanifold_edges == 0 and r.collapsed_faces == 0
    for s in pattern.stitches:
        va, vb = g.edge_vertices[(s.a.panel, s.a.edge)], g.edge_vertices[(s.b.panel, s.b.edge)]
        assert len(va) == len(vb)
        a = va if s.right_wrong else va.flip(0)
        assert torch.equal(g.vert_to_sim[a], g.vert_to_sim[vb])
    # the two chamfers' points are one garment vertex (sewn directly, or through the side seam's end)
    assert int(g.vert_to_sim[g.edge_vertices[("front", 2)][0]]) == int(
        g.vert_to_sim[g.edge_vertices[("back", 2)][0]]
    )


def test_collapse_rules():
    spacing = 0.02
    # sewn to a long edge: collapsing one side only would break the stitch's equal counts, so the front
    # chamfer keeps its samples; the back's chamfer, now unsewn, still collapses
    assert collapsed_edges(pattern_from_dict(chamfered_squares(long_partner=True)), spacing) == {("back", 2)}
    assert collapsed_edges(pattern_from_dict(chamfered_squares()), spacing) == {
        ("front", 2),
        ("back", 2),
    }
    # an edge at least SHORT_EDGE * spacing long keeps its samples
    pattern = pattern_from_dict(chamfered_squares())
    fine = 0.95 * pattern.panels["front"].edge_length(2) / SHORT_EDGE
    assert collapsed_edges(pattern, fine) == set()
    # a panel never loses so many edges that fewer than 3 remain
    tiny = {
        "pattern": {
            "panels": {
                "p": {
                    "translation": [0, 100, 0],
                    "rotation": [0, 0, 0],
                    "vertices": [[0, 0], [0.2, 0], [0, 0.2]],
                    "edges": [{"endpoints": [i, (i + 1) % 3]} for i in range(3)],
                }
            },
            "stitches": [],
        },
        "properties": {"units_in_meter": 100},
    }
    assert collapsed_edges(pattern_from_dict(tiny), spacing) == set()
