"""ControlCage: handle selection, mean value coordinates, template reproduction, tying, seams."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_diffavatar.cage import (
    ControlCage,
    mean_value_coordinates,
    seam_segments,
    select_handles,
    stitched_edges,
)
from torch_diffavatar.pattern import Edge, EdgeRef, Panel, Pattern, Stitch, list_templates, load_template
from torch_diffavatar.pattern.mesher import mesh_pattern, stitch_vertex_pairs

TEMPLATES = list_templates()
_MESHES: dict[str, tuple] = {}


def template_mesh(name: str):
    """(pattern, garment) of a bundled template, meshed once per test session."""
    if name not in _MESHES:
        pattern = load_template(name)
        _MESHES[name] = (pattern, mesh_pattern(pattern))
    return _MESHES[name]


def tube(width=0.2, height=0.3, spacing=0.1, back_width=None) -> Pattern:
    """Front (CCW) and back (CW) rectangles sewn along both sides: a tube with two openings."""
    bw = width if back_width is None else back_width
    edges = [Edge(i, (i + 1) % 4) for i in range(4)]
    front = Panel(
        "front",
        np.array([[0, 0], [width, 0], [width, height], [0, height]], dtype=float),
        [Edge(e.start, e.end) for e in edges],
        translation=np.array([0.0, 1.0, 0.1]),
    )
    back = Panel(
        "back",
        np.array([[0, 0], [0, height], [bw, height], [bw, 0]], dtype=float),
        [Edge(e.start, e.end) for e in edges],
        translation=np.array([0.0, 1.0, -0.1]),
    )
    stitches = [
        Stitch(EdgeRef("front", 1), EdgeRef("back", 2)),
        Stitch(EdgeRef("front", 3), EdgeRef("back", 0)),
    ]
    return Pattern({"front": front, "back": back}, stitches)


def star(n=7, r0=1.0, r1=0.45) -> torch.Tensor:
    """(2n, 2) a non-convex star polygon, counter-clockwise."""
    ang = torch.arange(2 * n, dtype=torch.float64) * math.pi / n
    rad = torch.where(torch.arange(2 * n) % 2 == 0, torch.tensor(r0), torch.tensor(r1)).double()
    return torch.stack([rad * torch.cos(ang), rad * torch.sin(ang)], dim=1)


def mvc_reference(points: torch.Tensor, cage: torch.Tensor) -> torch.Tensor:
    """Hormann–Floater with angles from atan2 (valid away from the polygon)."""
    d = cage[None] - points[:, None]
    dn = torch.roll(d, -1, dims=1)
    alpha = torch.atan2(d[..., 0] * dn[..., 1] - d[..., 1] * dn[..., 0], (d * dn).sum(-1))
    t = torch.tan(alpha / 2)
    w = (torch.roll(t, 1, dims=1) + t) / d.norm(dim=-1)
    return w / w.sum(1, keepdim=True)


# ---------------------------------------------------------------------------------------------------------
# mean value coordinates


def test_mvc_reproduces_points_inside_and_outside_nonconvex_cage():
    cage = star()
    g = torch.Generator().manual_seed(0)
    points = (torch.rand(400, 2, generator=g, dtype=torch.float64) - 0.5) * 3.0  # in and out of the star
    W = mean_value_coordinates(points, cage)
    torch.testing.assert_close(W.sum(1), torch.ones(400, dtype=torch.float64), rtol=0, atol=1e-12)
    torch.testing.assert_close(W @ cage, points, rtol=0, atol=1e-12)
    torch.testing.assert_close(W, mvc_reference(points, cage), rtol=1e-9, atol=1e-9)
    # reversing the loop orientation permutes the coordinates and nothing else
    Wr = mean_value_coordinates(points, cage.flip(0))
    torch.testing.assert_close(Wr.flip(1), W, rtol=0, atol=1e-12)


def test_mvc_on_vertices_and_edges_is_exact_interpolation():
    cage = star()
    at_vertex = mean_value_coordinates(cage, cage)
    torch.testing.assert_close(at_vertex, torch.eye(len(cage), dtype=torch.float64))
    mu = torch.tensor([0.1, 0.5, 0.93], dtype=torch.float64)
    for i in (0, 5, len(cage) - 1):  # includes the closing edge
        j = (i + 1) % len(cage)
        pts = (1 - mu)[:, None] * cage[i] + mu[:, None] * cage[j]
        W = mean_value_coordinates(pts, cage)
        expected = torch.zeros(3, len(cage), dtype=torch.float64)
        expected[:, i], expected[:, j] = 1 - mu, mu
        torch.testing.assert_close(W, expected, rtol=0, atol=1e-12)


def test_mvc_continuous_across_edges_and_positive_in_convex_cage():
    square = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=torch.float64)
    on = torch.tensor([[0.3, 0.0]], dtype=torch.float64)
    for h in (1e-4, 1e-7, -1e-7):  # inside, just inside, just outside
        near = mean_value_coordinates(on + torch.tensor([0.0, h], dtype=torch.float64), square)
        torch.testing.assert_close(near, mean_value_coordinates(on, square), rtol=0, atol=20 * abs(h))
    g = torch.Generator().manual_seed(1)
    inside = torch.rand(200, 2, generator=g, dtype=torch.float64) * 0.98 + 0.01
    assert (mean_value_coordinates(inside, square) > 0).all()


def test_mvc_rejects_bad_shapes():
    with pytest.raises(ValueError, match="cage"):
        mean_value_coordinates(torch.zeros(3, 2), torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        mean_value_coordinates(torch.zeros(3, 3), torch.zeros(4, 2))


# ---------------------------------------------------------------------------------------------------------
# handle selection


def _subdivide(poly: np.ndarray, k: int) -> np.ndarray:
    t = np.arange(k)[:, None] / k
    nxt = np.roll(poly, -1, axis=0)
    return np.concatenate([p + t * (q - p) for p, q in zip(poly, nxt)])


def test_select_handles_hull_corners_and_reflex_turns():
    square = _subdivide(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float), 5)
    assert select_handles(square).tolist() == [0, 5, 10, 15]  # collinear hull points are not corners
    ell = _subdivide(np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float), 4)
    assert select_handles(ell).tolist() == [0, 4, 8, 12, 16, 20]  # the reflex corner (12) by its turn
    # a shallow notch in the top edge: its corners turn by 15° (not on the hull)
    tan = math.tan(math.radians(15.0))
    notch = np.array([[0, 0], [3, 0], [3, 1], [2, 1], [1.5, 1 - 0.5 * tan], [1, 1], [0, 1]], dtype=float)
    assert select_handles(notch, 10.0).tolist() == [0, 1, 2, 3, 4, 5, 6]
    assert select_handles(notch, 20.0).tolist() == [0, 1, 2, 4, 6]  # 30° at the notch bottom stays
    circle = np.stack([np.cos(np.arange(64) * 2 * np.pi / 64), np.sin(np.arange(64) * 2 * np.pi / 64)], 1)
    assert len(select_handles(circle)) == 64  # every vertex of a convex curve is a hull corner
    # the mirror image has the mirrored handles
    mirrored = notch * np.array([-1.0, 1.0])
    assert select_handles(mirrored, 10.0).tolist() == select_handles(notch, 10.0).tolist()


# ---------------------------------------------------------------------------------------------------------
# the module on every template


@pytest.mark.parametrize("name", TEMPLATES)
def test_cage_reproduces_every_template(name):
    _, garment = template_mesh(name)
    cage = ControlCage(garment)
    assert cage.handles.shape == (cage.handle_count, 2) and cage.handles.dtype == torch.float64
    torch.testing.assert_close(cage(), garment.vert_uv, rtol=0, atol=1e-9)
    W = cage.weight_matrix().to_dense()
    torch.testing.assert_close(
        W.sum(1), torch.ones(garment.vert_count, dtype=torch.float64), rtol=0, atol=1e-12
    )
    torch.testing.assert_close(W @ cage.handle_rest, garment.vert_uv, rtol=0, atol=1e-9)
    # handles are boundary vertices of their own panel, contiguous per panel, at least 3 per panel
    assert torch.equal(garment.vert_panel[cage.handle_vertices], cage.handle_panel)
    boundary = set(torch.cat(garment.panel_boundary).tolist())
    assert set(cage.handle_vertices.tolist()) <= boundary
    counts = torch.bincount(cage.handle_panel, minlength=len(garment.panel_names))
    assert (counts >= 3).all() and (cage.handle_panel.diff() >= 0).all()
    # W is block-diagonal: a vertex only depends on its own panel's handles
    rows, cols = W.nonzero(as_tuple=True)
    assert torch.equal(garment.vert_panel[rows], cage.handle_panel[cols])


@pytest.mark.parametrize("name", TEMPLATES)
def test_stitched_edges_match_the_pattern_stitches(name):
    pattern, garment = template_mesh(name)
    found = {frozenset((s.a_key, s.b_key)): s for s in stitched_edges(garment)}
    assert len(found) == len(pattern.stitches)
    for st in pattern.stitches:
        ka, kb = (st.a.panel, st.a.edge), (st.b.panel, st.b.edge)
        s = found[frozenset((ka, kb))]
        expected = stitch_vertex_pairs(garment.edge_vertices[ka], garment.edge_vertices[kb], st.right_wrong)
        got = (
            np.stack([s.a.numpy(), s.b.numpy()], 1)
            if s.a_key == ka
            else np.stack([s.b.numpy(), s.a.numpy()], 1)
        )
        assert {tuple(p) for p in got.tolist()} == {tuple(p) for p in expected.tolist()}
    assert len(seam_segments(garment)) == sum(len(s.a) - 1 for s in found.values())


def test_forward_override_batch_dtype_and_gradcheck():
    garment = mesh_pattern(tube(spacing=0.1))
    cage = ControlCage(garment)
    g = torch.Generator().manual_seed(2)
    batch = cage.handle_rest + 0.01 * torch.randn(3, cage.handle_count, 2, generator=g, dtype=torch.float64)
    out = cage(batch)
    assert out.shape == (3, garment.vert_count, 2)
    torch.testing.assert_close(out[1], cage(batch[1]))
    with pytest.raises(ValueError, match="handles must have shape"):
        cage(batch[:, :-1])
    assert torch.autograd.gradcheck(cage, (batch[0].clone().requires_grad_(),))
    tied = ControlCage(garment, tie_seams=True)
    assert torch.autograd.gradcheck(tied, (batch[0].clone().requires_grad_(),))
    # float32 follows the garment; the parameter is what gets the gradient
    cage32 = ControlCage(garment.to(dtype=torch.float32))
    out32 = cage32()
    assert out32.dtype == torch.float32
    torch.testing.assert_close(out32, garment.vert_uv.float(), rtol=0, atol=1e-6)
    out32.square().sum().backward()
    assert cage32.handles.grad is not None and cage32.handles.grad.abs().sum() > 0


def test_concave_panel_with_curved_edges_reproduces_and_deforms_smoothly():
    # a panel with a concave arc (turning < 10° per sample): its boundary samples lie off the cage polygon
    panel = Panel(
        "p",
        np.array([[0, 0], [0.4, 0], [0.4, 0.4], [0, 0.4]], dtype=float),
        [Edge(0, 1), Edge(1, 2), Edge(2, 3, kind="quadratic", control=((0.5, 0.3),)), Edge(3, 0)],
    )
    garment = mesh_pattern(Pattern({"p": panel}), spacing=0.03)
    cage = ControlCage(garment)
    assert cage.handle_count == 4  # the corners only: the arc bends inwards, gently
    torch.testing.assert_close(cage(), garment.vert_uv, rtol=0, atol=1e-9)
    # an affine map of the handles maps every vertex by the same affine map (linear precision)
    A = torch.tensor([[1.1, 0.2], [-0.1, 0.9]], dtype=torch.float64)
    b = torch.tensor([0.05, -0.02], dtype=torch.float64)
    torch.testing.assert_close(cage(cage.handle_rest @ A.T + b), garment.vert_uv @ A.T + b, rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------------------------------------
# tying


def test_mirror_tying_maps_right_panels_onto_mirrored_left_ones():
    pattern, garment = template_mesh("tshirt")
    cage = ControlCage(garment, tie_mirrored=True)
    m = cage.handle_mirror
    assert (m >= 0).all() and torch.equal(m[m], torch.arange(cage.handle_count))
    names = garment.panel_names
    for h in range(cage.handle_count):
        a, b = names[int(cage.handle_panel[h])], names[int(cage.handle_panel[m[h]])]
        assert a.replace("left", "#").replace("right", "#") == b.replace("left", "#").replace("right", "#")
        assert a != b
    S = torch.tensor([-1.0, 1.0], dtype=torch.float64)
    # the bundled templates are mirrored about each frame's y axis: t = 0
    torch.testing.assert_close(cage.handle_rest[m] * S, cage.handle_rest, rtol=0, atol=1e-9)
    g = torch.Generator().manual_seed(3)
    raw = cage.handle_rest + 0.02 * torch.randn(cage.handle_count, 2, generator=g, dtype=torch.float64)
    tied = cage.tied_handles(raw)
    torch.testing.assert_close(tied[m] * S, tied, rtol=0, atol=1e-8)  # the templates mirror to ~1e-8 m
    # the shared displacement is the mean of the two raw ones (mirrored)
    d = raw - cage.handle_rest
    torch.testing.assert_close(tied - cage.handle_rest, 0.5 * (d + S * d[m]), rtol=0, atol=1e-12)
    # the mirrored panels' boundaries stay mirror images (interior meshes need not be)
    uv = cage(raw).detach()
    for left in (n for n in names if n.startswith("left_")):
        bl = garment.panel_boundary[names.index(left)]
        br = garment.panel_boundary[names.index("right_" + left[5:])]
        pl, pr = garment.vert_uv[bl] * S, garment.vert_uv[br]
        match = torch.cdist(pr, pl).argmin(1)
        assert torch.cdist(pr, pl).min(1).values.max() < 1e-7
        torch.testing.assert_close(uv[br], uv[bl][match] * S, rtol=0, atol=1e-7)
    # gradients reach the raw parameter already in the tied subspace
    cage.handles.data.copy_(raw)
    (cage()[:, 0] ** 3).sum().backward()
    grad = cage.handles.grad
    torch.testing.assert_close(grad[m] * S, grad, rtol=0, atol=1e-12)
    assert grad.abs().sum() > 0


def test_mirror_tying_leaves_unpaired_panels_free():
    _, garment = template_mesh("dress")
    cage = ControlCage(garment, tie_mirrored=True)
    skirt = torch.isin(cage.handle_panel, torch.tensor([0, 1]))  # skirt_front, skirt_back: no side
    assert (cage.handle_mirror[skirt] == -1).all() and (cage.handle_mirror[~skirt] >= 0).all()
    g = torch.Generator().manual_seed(4)
    raw = cage.handle_rest + 0.02 * torch.randn(cage.handle_count, 2, generator=g, dtype=torch.float64)
    torch.testing.assert_close(cage.tied_handles(raw)[skirt], raw[skirt], rtol=0, atol=1e-12)


def test_symmetric_tying_keeps_a_symmetric_panel_symmetric():
    """``tie_symmetric``: the dress's skirt panels have no side partner but are their own mirror images:
    each handle moves as its partner's mirror image, one on the axis along it, so the panel stays
    symmetric."""
    _, garment = template_mesh("dress")
    cage = ControlCage(garment, tie_mirrored=True, tie_symmetric=True)
    S = torch.tensor([-1.0, 1.0], dtype=torch.float64)
    g = torch.Generator().manual_seed(4)
    raw = cage.handle_rest + 0.02 * torch.randn(cage.handle_count, 2, generator=g, dtype=torch.float64)
    tied = cage.tied_handles(raw)
    for name in ("skirt_front", "skirt_back"):
        h = torch.nonzero(cage.handle_panel == garment.panel_names.index(name)).flatten()
        m = cage.handle_mirror[h]
        assert (m >= 0).all() and torch.isin(m, h).all()  # partners in the same panel
        rest, moved = cage.handle_rest, tied
        t_rest = rest[h].mean(0) - (rest[h] * S).mean(0)
        torch.testing.assert_close(rest[m] * S + t_rest, rest[h], rtol=0, atol=1e-9)
        t = moved[h].mean(0) - (moved[h] * S).mean(0)
        torch.testing.assert_close(moved[m] * S + t, moved[h], rtol=0, atol=1e-9)
        assert float((moved[h] - raw[h]).abs().max()) > 1e-3  # the raw step was lopsided; the tie is not


def test_symmetric_tying_leaves_lopsided_panels_free_and_mirror_tying_skips_non_mirrors():
    p = tube()
    p.panels["front"].vertices = p.panels["front"].vertices + np.array([[0, 0], [0, 0], [0.05, 0], [0, 0]])
    cage = ControlCage(mesh_pattern(p, spacing=0.1), tie_symmetric=True)
    front = cage.handle_panel == p.panel_names.index("front")
    assert (cage.handle_mirror[front] == -1).all() and (cage.handle_mirror[~front] >= 0).all()
    g = torch.Generator().manual_seed(4)
    raw = cage.handle_rest + 0.02 * torch.randn(cage.handle_count, 2, generator=g, dtype=torch.float64)
    torch.testing.assert_close(cage.tied_handles(raw)[front], raw[front], rtol=0, atol=1e-12)
    # a "left"/"right" pair that is not a mirror image is not tied, with a warning
    p = tube()
    p.panels = {"left_a": p.panels["front"], "right_a": p.panels["back"]}
    p.panels["right_a"].vertices = p.panels["right_a"].vertices * np.array([1.0, 1.3])
    p.stitches = []
    for name, panel in p.panels.items():
        panel.name = name
    with pytest.warns(UserWarning, match="not mirror images"):
        untied = ControlCage(mesh_pattern(p, spacing=0.1), tie_mirrored=True)
    assert (untied.handle_mirror == -1).all() and untied.tie_projector is None


def _chord_change(uv, uv0, s, u):
    return float(u @ ((uv[s[-1]] - uv[s[0]]) - (uv0[s[-1]] - uv0[s[0]])))


@pytest.mark.parametrize("mirrored", [False, True])
def test_seam_tying_keeps_stitched_edge_chords_changing_together(mirrored):
    _, garment = template_mesh("tshirt")
    cage = ControlCage(garment, tie_seams=True, tie_mirrored=mirrored)
    uv0 = garment.vert_uv
    g = torch.Generator().manual_seed(5)
    raw = cage.handle_rest + 0.02 * torch.randn(cage.handle_count, 2, generator=g, dtype=torch.float64)
    uv = cage(raw).detach()
    free = ControlCage(garment)(raw).detach()
    worst_tied = worst_free = 0.0
    for s in stitched_edges(garment):
        ua = (uv0[s.a[-1]] - uv0[s.a[0]]) / (uv0[s.a[-1]] - uv0[s.a[0]]).norm()
        ub = (uv0[s.b[-1]] - uv0[s.b[0]]) / (uv0[s.b[-1]] - uv0[s.b[0]]).norm()
        worst_tied = max(worst_tied, abs(_chord_change(uv, uv0, s.a, ua) - _chord_change(uv, uv0, s.b, ub)))
        worst_free = max(
            worst_free, abs(_chord_change(free, uv0, s.a, ua) - _chord_change(free, uv0, s.b, ub))
        )
    assert worst_tied < 1e-12 and worst_free > 1e-3
    torch.testing.assert_close(cage(), uv0, rtol=0, atol=1e-9)  # the template is still reproduced
    P = cage.tie_projector
    torch.testing.assert_close(P @ P, P, rtol=0, atol=1e-10)
    cage.handles.data.copy_(raw)
    cage.project_()
    torch.testing.assert_close(cage.handles.detach(), cage.tied_handles(raw), rtol=0, atol=1e-12)


def test_close_handles_move_together_and_keep_their_short_edge():
    """GarmentCode's tops have ~6 mm pattern edges at the shoulder tips; with ``tie_close`` the handles at
    their two ends share one displacement, so the edge moves rigidly instead of being crushed."""
    _, garment = template_mesh("tshirt")
    cage = ControlCage(garment, tie_close=0.01)
    rest = cage.handle_rest
    pairs = cage.close_handle_pairs(rest, 0.01)
    assert pairs  # the sleeves' short shoulder-tip edges
    assert all(float((rest[a] - rest[b]).norm()) < 0.01 for a, b in pairs)
    assert all(int(cage.handle_panel[a]) == int(cage.handle_panel[b]) for a, b in pairs)
    g = torch.Generator().manual_seed(3)
    raw = rest + 0.01 * torch.randn(cage.handle_count, 2, generator=g, dtype=rest.dtype)
    tied, free = cage.tied_handles(raw), ControlCage(garment).tied_handles(raw)
    for a, b in pairs:
        torch.testing.assert_close(tied[a] - rest[a], tied[b] - rest[b], rtol=0, atol=1e-12)
        assert float(((free[a] - rest[a]) - (free[b] - rest[b])).norm()) > 1e-4
    torch.testing.assert_close(cage(), garment.vert_uv, rtol=0, atol=1e-9)  # the template is still reproduced
    assert ControlCage(garment, tie_close=0.0).tie_projector is None
    with pytest.raises(ValueError, match="tie_close"):
        ControlCage(garment, tie_close=-0.01)
