"""Fit losses: boundary and interior feature terms, seam-length and curvature regularizers."""

from __future__ import annotations

import math

import pytest
import torch
from test_cage import template_mesh, tube

from torch_diffavatar.cage import seam_segments, stitched_edges
from torch_diffavatar.losses import (
    boundary_loss,
    boundary_triplets,
    curvature_loss,
    folded_collar_loop,
    interior_loss,
    rest_area_loss,
    rest_area_ratio,
    rest_distortion_loss,
    seam_length_loss,
    signed_rest_areas,
    skin_loss,
)
from torch_diffavatar.pattern import BoundaryLoop
from torch_diffavatar.pattern.mesher import mesh_pattern

F64 = torch.float64


def _rot(theta: float, scale: float = 1.0) -> torch.Tensor:
    c, s = math.cos(theta), math.sin(theta)
    return scale * torch.tensor([[c, -s], [s, c]], dtype=F64)


def _transform_panel(uv: torch.Tensor, garment, pid: int, A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    out = uv.clone()
    sel = garment.vert_panel == pid
    out[sel] = uv[sel] @ A.T + b
    return out


@pytest.fixture(scope="module")
def sewn_tube():
    return mesh_pattern(tube(spacing=0.05))


def test_reduction_is_checked_up_front(sewn_tube):
    g = sewn_tube
    x = g.sim_positions()
    for call in (
        lambda r: boundary_loss(x, g.boundary_loops, {"hem": x[:3]}, reduction=r),
        lambda r: interior_loss(x, x, reduction=r),
        lambda r: seam_length_loss(g.vert_uv, g, reduction=r),
        lambda r: curvature_loss(g.vert_uv, g.vert_uv, g, reduction=r),
    ):
        with pytest.raises(ValueError, match="reduction must be one of"):
            call("avg")
    with pytest.raises(ValueError, match="rest_uv must have shape"):
        seam_length_loss(g.vert_uv[:-1], g)
    with pytest.raises(ValueError, match="garment_x must be"):
        interior_loss(x[:, :2], x)


# ---------------------------------------------------------------------------------------------------------
# seam length (eq. 7)


def test_seam_length_zero_for_equal_seams_positive_otherwise(sewn_tube):
    g = sewn_tube
    seg = seam_segments(g)
    assert len(seg) == sum(len(s.a) - 1 for s in stitched_edges(g)) > 0
    assert seam_length_loss(g.vert_uv, g).item() < 1e-24  # equal straight sides, equal samples
    # stretching the front panel vertically lengthens its side seams only
    stretched = _transform_panel(
        g.vert_uv, g, 0, torch.diag(torch.tensor([1.0, 1.2], dtype=F64)), torch.zeros(2)
    )
    per_segment = seam_length_loss(stretched, g, segments=seg, reduction="none")
    p = g.vert_uv[seg]  # (K, 4, 2): both sides have the same length l_k on the template
    l2 = ((p[:, 1] - p[:, 0]) ** 2).sum(-1)
    torch.testing.assert_close(per_segment, (1.44 * l2 - l2) ** 2)
    torch.testing.assert_close(seam_length_loss(stretched, g, reduction="sum"), per_segment.sum())
    w = torch.linspace(0.5, 2.0, len(seg), dtype=F64)
    torch.testing.assert_close(
        seam_length_loss(stretched, g, weights=w), (w * per_segment).sum() / w.sum(), rtol=1e-12, atol=0
    )
    # rigid motions of a panel keep the seam lengths
    moved = _transform_panel(g.vert_uv, g, 1, _rot(0.7), torch.tensor([0.3, -0.1], dtype=F64))
    assert seam_length_loss(moved, g).item() < 1e-24
    # batched input: one value per batch element
    both = torch.stack([g.vert_uv, stretched])
    torch.testing.assert_close(
        seam_length_loss(both, g), torch.stack([torch.zeros((), dtype=F64), per_segment.mean()])
    )


def test_seam_length_on_templates_is_small_but_sees_the_seams():
    _, g = template_mesh("tshirt")
    base = seam_length_loss(g.vert_uv, g)
    # the template's two sides differ only by sampling of curves of equal arc length
    bigger = _transform_panel(g.vert_uv, g, 0, 1.1 * torch.eye(2, dtype=F64), torch.zeros(2))
    assert seam_length_loss(bigger, g) > 10 * base


def test_seam_length_gradcheck(sewn_tube):
    g = sewn_tube
    seg = seam_segments(g)
    gen = torch.Generator().manual_seed(0)
    uv = (g.vert_uv + 0.01 * torch.randn(g.vert_uv.shape, generator=gen, dtype=F64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda u: seam_length_loss(u, g, segments=seg), (uv,))


# ---------------------------------------------------------------------------------------------------------
# curvature (eq. 8)


def test_curvature_zero_at_template_and_similarity_invariant():
    _, g = template_mesh("tshirt")
    uv0 = g.vert_uv
    assert curvature_loss(uv0, uv0, g).item() < 1e-28
    # a similarity transform of one panel (rotation, scale, shift) keeps it at zero
    sim = _transform_panel(uv0, g, 2, _rot(0.9, 1.3), torch.tensor([0.2, 0.5], dtype=F64))
    assert curvature_loss(sim, uv0, g).item() < 1e-26
    # a shear is not a similarity: positive
    shear = torch.tensor([[1.0, 0.3], [0.0, 1.0]], dtype=F64)
    deformed = _transform_panel(uv0, g, 2, shear, torch.zeros(2))
    value = curvature_loss(deformed, uv0, g)
    assert value > 1e-8
    # of the deformed panel, a rigid motion changes nothing and a uniform scale s multiplies by s²
    moved = _transform_panel(deformed, g, 2, _rot(-0.4), torch.tensor([0.1, 0.1], dtype=F64))
    torch.testing.assert_close(curvature_loss(moved, uv0, g), value, rtol=1e-10, atol=0)
    scaled = _transform_panel(deformed, g, 2, _rot(0.0, 1.5), torch.zeros(2))
    torch.testing.assert_close(curvature_loss(scaled, uv0, g), 1.5**2 * value, rtol=1e-10, atol=0)


def test_curvature_similarity_is_the_least_squares_fit(sewn_tube):
    g = sewn_tube
    gen = torch.Generator().manual_seed(1)
    uv0 = g.vert_uv
    uv = uv0 + 0.01 * torch.randn(uv0.shape, generator=gen, dtype=F64)
    tri = boundary_triplets(g)
    assert len(tri) == sum(len(b) for b in g.panel_boundary)
    expected = []
    for prev, i, nxt in tri.tolist():
        e = torch.stack([uv[nxt] - uv[i], uv[prev] - uv[i]])  # (2, 2) rows e1, e2
        t = torch.stack([uv0[nxt] - uv0[i], uv0[prev] - uv0[i]])
        # unknowns (a, b) of T = [[a, -b], [b, a]]: T t = a t + b t_perp, stacked over both edges
        t_perp = torch.stack([-t[:, 1], t[:, 0]], dim=1)
        M = torch.stack([t.reshape(-1), t_perp.reshape(-1)], dim=1)  # (4, 2)
        ab = torch.linalg.lstsq(M, e.reshape(-1, 1)).solution.flatten()
        fitted = (M @ ab).reshape(2, 2)
        expected.append(((e - fitted).sum(0) ** 2).sum())
    got = curvature_loss(uv, uv0, g, reduction="none")
    torch.testing.assert_close(got, torch.stack(expected), rtol=1e-9, atol=1e-20)
    w = torch.rand(len(tri), generator=gen, dtype=F64)
    torch.testing.assert_close(curvature_loss(uv, uv0, g, weights=w, reduction="sum"), (w * got).sum())


def test_curvature_gradcheck(sewn_tube):
    g = mesh_pattern(tube(spacing=0.1))
    gen = torch.Generator().manual_seed(2)
    uv = (g.vert_uv + 0.01 * torch.randn(g.vert_uv.shape, generator=gen, dtype=F64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda u: curvature_loss(u, g.vert_uv, g), (uv,))


# ---------------------------------------------------------------------------------------------------------
# boundary and interior feature terms


def test_boundary_loss_values_matching_and_weights(sewn_tube):
    g = sewn_tube
    x = g.sim_positions()
    names = [lp.name for lp in g.boundary_loops]
    assert names == ["neck", "hem"]
    scan = {lp.name: x[lp.vertices] for lp in g.boundary_loops}
    assert boundary_loss(x, g.boundary_loops, scan).item() == 0.0
    # a shift much smaller than the vertex spacing: every nearest neighbour is the shifted twin
    delta = torch.tensor([0.0, 0.0, 0.003], dtype=F64)
    shifted = {k: v + delta for k, v in scan.items()}
    per_loop = boundary_loss(x, g.boundary_loops, shifted, reduction="none")
    torch.testing.assert_close(per_loop, torch.full((2,), 2 * 0.003**2, dtype=F64))
    # only the openings present on both sides count; extra scan openings are ignored
    only_hem = {"hem": shifted["hem"], "cuff_left": shifted["neck"]}
    assert boundary_loss(x, g.boundary_loops, only_hem, reduction="none").shape == (1,)
    w = torch.tensor([3.0, 1.0], dtype=F64)
    torch.testing.assert_close(boundary_loss(x, g.boundary_loops, only_hem, weights=w), per_loop[1])
    with pytest.raises(ValueError, match="no garment opening matches"):
        boundary_loss(x, g.boundary_loops, {"waist": x[:4]})
    # denser garment samples: a scan loop equal to the edge midpoints is matched exactly
    loop = g.boundary_loops[1]
    ring = x[loop.vertices]
    mids = 0.5 * (ring + torch.roll(ring, -1, 0))
    dense_scan = {"hem": torch.cat([ring, mids])}
    assert boundary_loss(x, [loop], dense_scan, samples_per_edge=2).item() < 1e-30
    assert boundary_loss(x, [loop], dense_scan, samples_per_edge=1).item() > 1e-6


def test_boundary_loss_gradcheck():
    g = mesh_pattern(tube(spacing=0.1))
    gen = torch.Generator().manual_seed(3)
    x = g.sim_positions()
    scan = {
        lp.name: x[lp.vertices] + 0.004 * torch.randn(len(lp.vertices), 3, generator=gen, dtype=F64)
        for lp in g.boundary_loops
    }
    loops = [BoundaryLoop(lp.name, lp.vertices) for lp in g.boundary_loops]
    hem = loops[1].vertices

    def f(hem_x):  # perturb the hem vertices only (keeps gradcheck's finite differences few)
        return boundary_loss(x.index_copy(0, hem, hem_x), loops, scan, samples_per_edge=2)

    assert torch.autograd.gradcheck(f, (x[hem].clone().requires_grad_(),))
    # the hem's scan seen over half of it: only the covered loop points pull garment -> scan
    from torch_diffavatar.losses import covered_loop_points

    half = scan[loops[1].name][: len(hem) // 2]
    partial = {**scan, loops[1].name: half}
    assert not bool(covered_loop_points(x[hem], half, 0.05).all())

    def f_gap(hem_x):
        return boundary_loss(x.index_copy(0, hem, hem_x), loops, partial, samples_per_edge=2, gap_bin=0.05)

    assert torch.autograd.gradcheck(f_gap, (x[hem].clone().requires_grad_(),))


def _brute_chamfer(x, y):
    d = torch.cdist(x, y) ** 2
    return d.min(1).values.mean() + d.min(0).values.mean()


def test_interior_loss_matches_brute_force_values_and_gradients():
    gen = torch.Generator().manual_seed(4)
    x = torch.randn(300, 3, generator=gen, dtype=F64).requires_grad_()
    y = torch.randn(500, 3, generator=gen, dtype=F64)
    ours = interior_loss(x, y)
    (g_ours,) = torch.autograd.grad(ours, x)
    ref = _brute_chamfer(x, y)
    (g_ref,) = torch.autograd.grad(ref, x)
    torch.testing.assert_close(ours, ref)
    torch.testing.assert_close(g_ours, g_ref)
    one = interior_loss(x, y, two_sided=False)
    torch.testing.assert_close(one, (torch.cdist(x, y) ** 2).min(1).values.mean())
    a, b = interior_loss(x, y, reduction="none")
    assert a.shape == (300,) and b.shape == (500,)
    torch.testing.assert_close(a.mean() + b.mean(), ours)
    assert interior_loss(x, y, two_sided=False, reduction="none").shape == (300,)
    w = torch.rand(300, generator=gen, dtype=F64)
    torch.testing.assert_close(
        interior_loss(x, y, two_sided=False, weights=w), (w * a).sum() / w.sum(), rtol=1e-12, atol=0
    )
    # a robust kernel caps the pull of far outliers
    far = torch.cat([y, torch.full((5, 3), 50.0, dtype=F64)])
    assert interior_loss(x, far, robust="geman_mcclure", scale=0.05) < 2 * 0.05**2
    assert interior_loss(x, far) > 50.0  # 5 of 505 points ~87 m away


def test_interior_loss_gradcheck():
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(30, 3, generator=gen, dtype=F64).requires_grad_()
    y = torch.randn(40, 3, generator=gen, dtype=F64)
    assert torch.autograd.gradcheck(lambda p: interior_loss(p, y, robust="huber", scale=0.5), (x,))


def _grid_sheet(n: int = 5, size: float = 1.0):
    """An n×n-vertex square sheet in the plane z = 0: verts (n², 3) float64, faces (2(n−1)², 3)."""
    t = torch.linspace(0.0, size, n, dtype=F64)
    gx, gy = torch.meshgrid(t, t, indexing="ij")
    verts = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.zeros(n * n, dtype=F64)], 1)
    ids = torch.arange(n * n).reshape(n, n)
    a, b, c, d = ids[:-1, :-1], ids[1:, :-1], ids[1:, 1:], ids[:-1, 1:]
    faces = torch.cat([torch.stack([a, b, c], -1).reshape(-1, 3), torch.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, faces


def test_interior_loss_to_the_surface_values():
    verts, faces = _grid_sheet()
    gen = torch.Generator().manual_seed(6)
    # points above the sheet's interior, below it, and one beside it (nearest: the edge x = 1)
    inside = torch.rand(40, 3, generator=gen, dtype=F64) * torch.tensor(
        [1.0, 1.0, 0.2], dtype=F64
    ) - 0.1 * torch.tensor([0, 0, 1.0], dtype=F64)
    beside = torch.tensor([[1.3, 0.5, 0.4]], dtype=F64)
    pts = torch.cat([inside, beside])
    to_verts, to_surface = interior_loss(verts, pts, reduction="none", garment_faces=faces)
    expected = torch.cat([inside[:, 2] ** 2, torch.tensor([0.3**2 + 0.4**2], dtype=F64)])
    torch.testing.assert_close(to_surface, expected, rtol=1e-12, atol=1e-14)
    # the garment → scan direction is the vertex one, unchanged
    torch.testing.assert_close(to_verts, interior_loss(verts, pts, reduction="none")[0])
    # to the surface is never farther than to the nearest vertex, and much nearer on a coarse mesh
    to_nearest_vertex = interior_loss(verts, pts, reduction="none")[1]
    assert bool((to_surface <= to_nearest_vertex + 1e-15).all())
    assert float(to_surface[:-1].mean()) < 0.5 * float(to_nearest_vertex[:-1].mean())
    total = interior_loss(verts, pts, garment_faces=faces)
    torch.testing.assert_close(total, to_verts.mean() + to_surface.mean())
    with pytest.raises(ValueError, match="garment_faces"):
        interior_loss(verts, pts, garment_faces=faces[:, :2])


def test_interior_loss_to_the_surface_gradcheck():
    verts, faces = _grid_sheet(4)
    gen = torch.Generator().manual_seed(7)
    verts = verts + 0.05 * torch.randn(verts.shape, generator=gen, dtype=F64)  # a bumpy sheet
    pts = torch.rand(25, 3, generator=gen, dtype=F64) * torch.tensor([1.0, 1.0, 0.3], dtype=F64)
    x = verts.clone().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda p: interior_loss(p, pts, garment_faces=faces, robust="huber", scale=0.1), (x,)
    )


def test_boundary_loss_robust_kernel_caps_a_stray_opening_point(sewn_tube):
    x = sewn_tube.sim_positions()
    loops = sewn_tube.boundary_loops
    scan = {lp.name: x[lp.vertices].clone() for lp in loops}
    assert float(boundary_loss(x, loops, scan)) == 0.0
    stray = {k: torch.cat([v, v[:1] + torch.tensor([[0.0, 0.5, 0.0]], dtype=F64)]) for k, v in scan.items()}
    l2 = boundary_loss(x, loops, stray)
    huber = boundary_loss(x, loops, stray, robust="huber", scale=0.01)
    assert float(huber) < 0.05 * float(l2)  # linear tail: 0.01·(2·0.5 − 0.01) against 0.25


# ----------------------------------------------------------------------------- rest-area barrier

# two counter-clockwise triangles sharing an edge (a unit square), a separate counter-clockwise and a
# separate clockwise one
AREA_UV = torch.tensor(
    [
        [0.0, 0.0],
        [1.0, 0.0],
        [1.0, 1.0],
        [0.0, 1.0],
        [1.5, 0.0],
        [2.5, 0.0],
        [1.7, 0.8],
        [2.0, 0.0],
        [2.0, 1.0],
        [4.0, 0.0],
    ],
    dtype=F64,
)
AREA_TRIS = torch.tensor([[0, 1, 2], [0, 2, 3], [4, 5, 6], [7, 8, 9]])  # areas +0.5, +0.5, +0.4, −1
AREAS = torch.tensor([0.5, 0.5, 0.4, -1.0], dtype=F64)


def _shrink(uv: torch.Tensor, tri: torch.Tensor, ratio: float) -> torch.Tensor:
    """``uv`` with triangle ``tri``'s vertices scaled about its centroid so its area is ``ratio`` times
    as large (a negative ratio mirrors it through the centroid's line along its first edge)."""
    out = uv.clone()
    p = uv[tri]
    c = p.mean(0)
    q = (p - c) * math.sqrt(abs(ratio)) + c
    if ratio < 0:  # reflect across the line through c along edge 0→1
        d = (p[1] - p[0]) / (p[1] - p[0]).norm()
        r = q - c
        q = c + 2 * (r @ d)[:, None] * d - r
    out[tri] = q
    return out


def test_signed_rest_areas_and_ratio_values():
    torch.testing.assert_close(signed_rest_areas(AREA_UV, AREA_TRIS), AREAS)
    torch.testing.assert_close(rest_area_ratio(AREA_UV, AREA_UV, AREA_TRIS), torch.ones(4, dtype=F64))
    scaled = rest_area_ratio(AREA_UV * 0.6 + 3.0, AREA_UV, AREA_TRIS)  # similarity: ratio 0.36 everywhere
    torch.testing.assert_close(scaled, torch.full((4,), 0.36, dtype=F64))
    # a mirror inverts every triangle, clockwise templates included (the template's sign divides out)
    mirrored = AREA_UV * torch.tensor([-1.0, 1.0], dtype=F64)
    torch.testing.assert_close(rest_area_ratio(mirrored, AREA_UV, AREA_TRIS), -torch.ones(4, dtype=F64))
    for r in (0.3, 0.0, -0.5):
        torch.testing.assert_close(
            rest_area_ratio(_shrink(AREA_UV, AREA_TRIS[3], r), AREA_UV, AREA_TRIS)[3],
            torch.tensor(r, dtype=F64),
            atol=1e-12,
            rtol=0,
        )


def test_rest_area_loss_is_zero_at_the_template_and_above_the_threshold():
    assert float(rest_area_loss(AREA_UV, AREA_UV, AREA_TRIS)) == 0.0
    for scale in (0.75, 1.0, 1.6):  # area ratios 0.5625, 1, 2.56: all above 0.5
        assert float(rest_area_loss(AREA_UV * scale, AREA_UV, AREA_TRIS)) == 0.0
    assert float(rest_area_loss(AREA_UV * 0.75, AREA_UV, AREA_TRIS, threshold=0.6)) > 0


@pytest.mark.parametrize("threshold", [0.5, 0.8, 1.0])
@pytest.mark.parametrize("tri", [2, 3])  # counter-clockwise and clockwise templates
def test_rest_area_loss_of_a_shrunk_triangle(threshold, tri):
    for r in (0.45, 0.2, 0.0):
        uv = _shrink(AREA_UV, AREA_TRIS[tri], r)
        value = rest_area_loss(uv, AREA_UV, AREA_TRIS, threshold=threshold)
        assert value.shape == ()
        assert float(value) == pytest.approx((threshold - r) ** 2, rel=1e-9, abs=1e-15)
        per_tri = rest_area_loss(uv, AREA_UV, AREA_TRIS, threshold=threshold, reduction="none")
        assert per_tri.shape == (4,)
        assert float(per_tri.sum()) == pytest.approx(float(value))
        assert int((per_tri > 0).sum()) == 1 and float(per_tri[tri]) > 0
        mean = rest_area_loss(uv, AREA_UV, AREA_TRIS, threshold=threshold, reduction="mean")
        assert float(mean) == pytest.approx(float(value) / 4)


def test_rest_area_loss_inverted_is_worse_than_collapsed():
    losses = [
        float(rest_area_loss(_shrink(AREA_UV, AREA_TRIS[2], r), AREA_UV, AREA_TRIS)) for r in (0.3, 0.0, -1.0)
    ]
    assert losses[0] < losses[1] < losses[2]
    assert losses[1] == pytest.approx(0.25) and losses[2] == pytest.approx(2.25)  # (0.5 − 0)², (0.5 + 1)²


def test_rest_area_loss_batched():
    batch = torch.stack([AREA_UV, _shrink(AREA_UV, AREA_TRIS[2], 0.1), _shrink(AREA_UV, AREA_TRIS[2], -0.4)])
    value = rest_area_loss(batch, AREA_UV, AREA_TRIS)
    assert value.shape == (3,)
    expected = torch.stack([rest_area_loss(uv, AREA_UV, AREA_TRIS) for uv in batch])
    torch.testing.assert_close(value, expected)
    torch.testing.assert_close(value, torch.tensor([0.0, 0.4**2, 0.9**2], dtype=F64))
    assert rest_area_loss(batch, AREA_UV, AREA_TRIS, reduction="none").shape == (3, 4)
    assert signed_rest_areas(batch, AREA_TRIS).shape == (3, 4)
    # a float32 template is cast to the rest coordinates' dtype
    torch.testing.assert_close(rest_area_loss(batch, AREA_UV.float(), AREA_TRIS), value)


def test_rest_area_loss_gradient_pushes_a_shrinking_triangle_apart():
    uv = _shrink(AREA_UV, AREA_TRIS[2], 0.2).requires_grad_(True)
    loss = rest_area_loss(uv, AREA_UV, AREA_TRIS)
    (grad,) = torch.autograd.grad(loss, uv)
    others = torch.ones(len(AREA_UV), dtype=torch.bool)
    others[AREA_TRIS[2]] = False
    assert float(grad[others].abs().max()) == 0.0  # the other triangles feel nothing
    assert float(grad[AREA_TRIS[2]].norm(dim=1).min()) > 0
    stepped = (uv - 1e-2 * grad).detach()
    assert float(rest_area_loss(stepped, AREA_UV, AREA_TRIS)) < float(loss.detach())
    tri = AREA_TRIS[2]
    for i, j in ((0, 1), (1, 2), (2, 0)):  # every edge of the triangle gets longer
        before = (uv.detach()[tri[i]] - uv.detach()[tri[j]]).norm()
        after = (stepped[tri[i]] - stepped[tri[j]]).norm()
        assert float(after) > float(before)
    ratio_after = rest_area_ratio(stepped, AREA_UV, AREA_TRIS)[2]
    assert float(ratio_after) > 0.2
    # and it is the gradient: float64 gradcheck (away from the relu's kink)
    assert torch.autograd.gradcheck(
        lambda x: rest_area_loss(x, AREA_UV, AREA_TRIS), (uv.detach().requires_grad_(),)
    )


def test_rest_area_loss_rejects_bad_arguments():
    for threshold in (0.0, -0.2, 1.5, float("nan")):
        with pytest.raises(ValueError, match="threshold"):
            rest_area_loss(AREA_UV, AREA_UV, AREA_TRIS, threshold=threshold)
    with pytest.raises(ValueError, match="reduction"):
        rest_area_loss(AREA_UV, AREA_UV, AREA_TRIS, reduction="max")


def test_boundary_loss_trim_drops_the_worst_points_only(sewn_tube):
    x = sewn_tube.sim_positions()
    loops = sewn_tube.boundary_loops[:1]
    loop_x = x[loops[0].vertices]
    n = loop_x.shape[0]
    shifted = {loops[0].name: loop_x + torch.tensor([0.0, 0.01, 0.0], dtype=F64)}  # every point 1 cm off
    base = boundary_loss(x, loops, shifted)
    # a uniform offset is not an outlier: trimming a quarter keeps the same (mean of equal) values
    torch.testing.assert_close(boundary_loss(x, loops, shifted, trim=0.25), base)
    far = {loops[0].name: torch.cat([shifted[loops[0].name], loop_x[:2] + 1.0])}  # two stray points 1.7 m off
    assert float(boundary_loss(x, loops, far)) > 10 * float(base)
    trimmed = boundary_loss(x, loops, far, trim=2.5 / (n + 2))  # drops the two strays (and nothing else)
    torch.testing.assert_close(trimmed, base, rtol=0.05, atol=0.0)
    with pytest.raises(ValueError, match="trim"):
        boundary_loss(x, loops, shifted, trim=1.0)


def test_skin_loss_is_the_mean_squared_distance_to_the_body_surface():
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    verts = torch.as_tensor(ico.vertices, dtype=F64)
    faces = torch.as_tensor(ico.faces, dtype=torch.int64)
    # points 1 cm out along the vertex directions of a convex mesh: their closest surface point is the vertex
    pts = verts[::3] * (1.0 + 0.01 / 0.3)
    torch.testing.assert_close(skin_loss(verts, faces, pts), torch.tensor(1e-4, dtype=F64), rtol=1e-9, atol=0)
    # the body moved 2 cm sideways is farther from its skin points, and the gradient says which way back
    shift = torch.tensor([0.02, 0.0, 0.0], dtype=F64, requires_grad=True)
    loss = skin_loss(verts + shift, faces, pts)
    loss.backward()
    assert float(loss) > 2e-4 and float(shift.grad[0]) > 0
    x = verts + 0.005 * torch.randn(verts.shape, generator=torch.Generator().manual_seed(2), dtype=F64)
    x.requires_grad_()
    assert torch.autograd.gradcheck(lambda v: skin_loss(v, faces, pts[:20], robust="huber", scale=0.02), (x,))
    with pytest.raises(ValueError, match="skin_points"):
        skin_loss(verts, faces, pts[:, :2])


def test_rest_distortion_loss_sees_shape_not_size_or_rotation():
    tri = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uv0 = torch.tensor([[0.0, 0.0], [0.1, 0.0], [0.1, 0.1], [0.0, 0.1]], dtype=F64)
    c, s = math.cos(0.7), math.sin(0.7)
    similar = 1.7 * uv0 @ torch.tensor([[c, s], [-s, c]], dtype=F64) + 0.3
    assert float(rest_distortion_loss(similar, uv0, tri, threshold=0.0)) < 1e-20
    # stretched ×2 along u: singular values 2 and 1, distortion (2 + 1/2)/2 − 1 = 0.25 in each triangle
    stretched = uv0 * torch.tensor([2.0, 1.0], dtype=F64)
    per_tri = rest_distortion_loss(stretched, uv0, tri, threshold=0.0, reduction="none")
    torch.testing.assert_close(per_tri, torch.full((2,), 0.25**2, dtype=F64))
    assert float(rest_distortion_loss(stretched, uv0, tri)) == 0.0  # the default threshold is r = 2
    sheared = uv0 + uv0[:, 1:] * torch.tensor([[1.5, 0.0]], dtype=F64)
    assert float(rest_distortion_loss(sheared, uv0, tri)) > 0.0
    x = sheared.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda u: rest_distortion_loss(u, uv0, tri, threshold=0.1), (x,))
    with pytest.raises(ValueError, match="threshold"):
        rest_distortion_loss(sheared, uv0, tri, threshold=-1.0)


def _neck_and_yoke(collar: bool) -> tuple[torch.Tensor, BoundaryLoop, torch.Tensor]:
    """A neckline of 36 vertices around a 7 cm neck, 1.5 cm lower in front (+z) than at the back, over a
    yoke of cloth sloping down and out from it; with ``collar``, a collar folded over the neckline: its
    free edge (the loop) 4 cm below its fold, which lies 1 cm above and outside the neckline."""
    a = torch.arange(36, dtype=F64) * (2 * math.pi / 36)
    ring = torch.stack([torch.sin(a), torch.zeros_like(a), torch.cos(a)], 1)  # unit radial directions

    def circle(radius: float, height) -> torch.Tensor:
        return ring * radius + torch.stack([torch.zeros_like(a), height, torch.zeros_like(a)], 1)

    neckline = 1.45 - 0.0075 * (1 + torch.cos(a))  # 1.45 m at the back, 1.435 m in front
    layers = [circle(0.07, neckline)] + [circle(0.07 + 0.02 * k, neckline - 0.015 * k) for k in (1, 2, 3)]
    if collar:
        fold = circle(0.075, neckline + 0.01)
        free = circle(0.085, neckline - 0.03)
        layers += [fold, 0.5 * (fold + free), free]
    x = torch.cat(layers)
    loop = torch.arange(36) + (36 * 6 if collar else 0)  # the free edge, else the neckline
    return x, BoundaryLoop("neck", loop), torch.arange(36 * 4, 36 * 5)


@pytest.mark.parametrize("collar", [False, True])
def test_folded_collar_loop_is_the_fold_over_a_collar_and_the_loop_otherwise(collar):
    x, loop, fold = _neck_and_yoke(collar)
    out = folded_collar_loop(x, loop)
    if not collar:  # a plain neckline is its own top edge, though it rises toward the back
        assert out is loop
        return
    assert out.name == "neck" and out.vertices.shape == loop.vertices.shape
    # every free-edge vertex is lifted to the fold, beside its own angle, and the fold goes all around
    assert set(out.vertices.tolist()) <= set(fold.tolist())
    assert ((out.vertices - fold + 18) % 36 - 18).abs().max() <= 1  # within 10 degrees
    assert len(set(out.vertices.tolist())) >= 12
    # a narrow reach misses the fold (4 cm up), and the loop stays
    assert folded_collar_loop(x, loop, reach=0.03) is loop
    # turned upright (a hood's face opening, with the hood's crown above it), the loop stays too
    upright = x[:, [0, 2, 1]] * torch.tensor([1.0, 1.0, -1.0], dtype=F64)
    assert folded_collar_loop(upright, loop) is loop
    assert folded_collar_loop(upright, loop, max_tilt_deg=90.0) is not loop


def test_pattern_change_leaves_design_changes_free_and_its_gradient_checks():
    from torch_diffavatar.losses import design_modes, pattern_change_loss
    from torch_diffavatar.pattern import load_template, mesh_pattern

    pattern = load_template("skirt")
    garment = mesh_pattern(pattern, spacing=0.05)
    template, panel = garment.vert_uv, garment.vert_panel
    assert pattern_change_loss(template, template, panel) == 0
    # each panel moved, shortened by 15 % and flared (30 % wider at the bottom than at the top, the
    # panel's u about its centre): a design change, free
    moved = template.clone()
    for k in torch.unique(panel):
        uv = template[panel == k]
        top, height, centre = uv[:, 1].max(), uv[:, 1].max() - uv[:, 1].min(), uv[:, 0].mean()
        down = (top - uv[:, 1]) / height  # 0 at the top, 1 at the bottom
        moved[panel == k, 0] = centre + (uv[:, 0] - centre) * (1 + 0.3 * down) + 0.2
        moved[panel == k, 1] = top - 0.85 * (top - uv[:, 1]) - 0.1
    assert pattern_change_loss(moved, template, panel) < 1e-9
    # one vertex pushed out by 5 cm: a reshape, about 5 cm over the vertex count (its panel's modes take a
    # little of it, and spread a little onto the panel's other vertices)
    bent = template.clone()
    bent[7, 0] += 0.05
    value = float(pattern_change_loss(bent, template, panel))
    assert 0.8 * 0.05 / len(template) < value < 1.5 * 0.05 / len(template)
    # L1-like: the gradient stops growing with the distance (a quadratic one would be 10x at 10x)
    grads = []
    for push in (1.0, 10.0):
        far = template.clone()
        far[7, 0] += push
        far.requires_grad_(True)
        grads.append(torch.autograd.grad(pattern_change_loss(far, template, panel), far)[0])
    torch.testing.assert_close(grads[1][7], grads[0][7], rtol=0.02, atol=0)
    modes = design_modes(template, panel)
    assert torch.allclose(modes.T @ modes, torch.eye(4, dtype=torch.float64) * len(torch.unique(panel)))
    gen = torch.Generator().manual_seed(0)
    rest = template + 0.01 * torch.randn(template.shape, dtype=torch.float64, generator=gen)
    small = slice(0, 40)  # gradcheck on a few vertices (the others held)

    def on_some(r):
        return pattern_change_loss(torch.cat([r, rest[40:]]), template, panel, modes=modes)

    assert torch.autograd.gradcheck(on_some, (rest[small].clone().requires_grad_(True),))
    batch = torch.stack([bent, template])
    torch.testing.assert_close(
        pattern_change_loss(batch, template, panel), torch.tensor([value, 0.0]).double()
    )


def test_seen_side_weights_leave_out_the_cloth_on_unseen_sides():
    import trimesh

    from torch_diffavatar.losses import seen_side_weights

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    x = torch.as_tensor(sphere.vertices)
    faces = torch.as_tensor(sphere.faces, dtype=torch.int64)
    seen = torch.ones(8, dtype=torch.bool)
    assert bool((seen_side_weights(x, faces, seen) == 1).all())
    seen[4] = False  # the back (-Z) unseen, as from cameras in front
    w = seen_side_weights(x, faces, seen)
    n = x / x.norm(dim=1, keepdim=True)  # a sphere's normals are radial
    back = (n[:, 2] < -0.95) & (n[:, 1].abs() < 0.3)
    side = n[:, 0].abs() > 0.9
    top = n[:, 1] > 0.8
    assert bool((w[back] == 0).all()) and bool((w[side] == 1).all()) and bool((w[top] == 1).all())
    assert 0.05 < float(1 - w.mean()) < 0.15  # about one eighth of the sphere's sides, less its poles


def test_boundary_loss_on_a_partial_scan_pulls_only_the_seen_half():
    from torch_diffavatar.losses import boundary_loss
    from torch_diffavatar.pattern.garment_mesh import BoundaryLoop

    angle = torch.linspace(0, 2 * math.pi, 33, dtype=torch.float64)[:-1]
    ring = torch.stack([0.2 * torch.sin(angle), torch.zeros_like(angle), 0.2 * torch.cos(angle)], 1)
    loop = [BoundaryLoop("hem", torch.arange(32))]
    front_scan = {"hem": ring[ring[:, 2] > 0.05] + torch.tensor([0.0, -0.01, 0.0], dtype=torch.float64)}
    seen = (ring[:, 2] > 0).double()
    full = boundary_loss(ring, loop, front_scan, samples_per_edge=2)
    partial = boundary_loss(ring, loop, front_scan, samples_per_edge=2, seen=seen)
    assert float(partial) < 0.1 * float(full)  # the back half no longer pulled onto the front's points
    assert torch.equal(
        boundary_loss(ring, loop, front_scan, seen=torch.ones(32, dtype=torch.float64)),
        boundary_loss(ring, loop, front_scan),
    )


def test_a_cuff_whose_scan_shows_a_third_of_it_is_not_pulled_onto_that_third():
    """A hole under the arm leaves a cuff's scan points on a 120° arc. Every garment point pulled to its
    nearest scan point shrinks the whole cuff onto the arc; with ``gap_bin`` only the covered sectors pull,
    so the true cuff costs a tenth as much and shrinking it pays a tenth as much."""
    from torch_diffavatar.losses import covered_loop_points

    angle = torch.linspace(0, 2 * math.pi, 25, dtype=torch.float64)[:-1]

    def ring(radius):
        return torch.stack([torch.zeros_like(angle), radius * torch.cos(angle), radius * torch.sin(angle)], 1)

    dense = torch.linspace(0, 2 * math.pi / 3, 40, dtype=torch.float64)
    arc = {
        "cuff_left": torch.stack(
            [torch.zeros_like(dense), 0.07 * torch.cos(dense), 0.07 * torch.sin(dense)], 1
        )
    }
    cov = covered_loop_points(ring(0.07), arc["cuff_left"], 0.03)
    # the arc's 9 vertices (0-120°), and no more than its end sectors (24° each) beyond them, are covered
    assert bool(cov[:9].all()) and int(cov.sum()) <= 11 and not bool(cov[11:22].any())
    loop = [BoundaryLoop("cuff_left", torch.arange(24))]
    radius = torch.tensor(0.07, dtype=torch.float64, requires_grad=True)
    loss, grad = {}, {}
    for gap_bin in (0.0, 0.03):
        loss[gap_bin] = boundary_loss(ring(radius), loop, arc, samples_per_edge=2, gap_bin=gap_bin)
        (grad[gap_bin],) = torch.autograd.grad(loss[gap_bin], radius)
    assert float(grad[0.0]) > 0  # a smaller cuff lies nearer the arc: without gaps the loss pulls it in
    assert float(loss[0.03]) < 0.1 * float(loss[0.0]) and abs(float(grad[0.03])) < 0.1 * float(grad[0.0])
    with pytest.raises(ValueError, match="gap_bin"):
        boundary_loss(ring(0.07), loop, arc, gap_bin=-1.0)
    assert bool(covered_loop_points(ring(0.07)[:2], arc["cuff_left"], 0.03).all())  # no plane: all pull


def test_dart_triangles_span_each_dart_and_nothing_else():
    """The dress's eight bodice darts give triangles (leg, tip, leg) of sewn pairs; the skirt has none, and
    a tube (two panels sewn along their sides) none."""
    from torch_diffavatar.losses import dart_triangles

    pattern, garment = template_mesh("dress")
    tri = dart_triangles(garment)
    assert len(tri) > 0
    assert len(set(tri[:, 1].tolist())) == len(pattern.darts)  # one tip per dart
    pairs = {tuple(p) for p in garment.stitch_pairs.tolist()}
    assert all((a, b) in pairs or (b, a) in pairs for a, _, b in tri.tolist())
    panel = garment.vert_panel
    assert bool((panel[tri[:, 0]] == panel[tri[:, 1]]).all() and (panel[tri[:, 1]] == panel[tri[:, 2]]).all())
    assert len(dart_triangles(template_mesh("skirt")[1])) == 0
    assert len(dart_triangles(mesh_pattern(tube(), spacing=0.05))) == 0


def test_a_dart_closed_past_zero_costs_rest_area():
    """The objective's rest-area term is 0 at the template and grows once a dart's legs pass each other
    (its base corners swapped), which the mesh's own triangles alone barely see."""
    from helpers_fit import fit_config

    from torch_diffavatar.objective import FitObjective, ScanTarget

    _, garment = template_mesh("dress")
    x = garment.sim_positions()
    objective = FitObjective(garment, ScanTarget(x, {}), fit_config(), dtype=torch.float64)
    uv = objective.template_uv.clone()
    assert float(objective.rest_terms(uv)["rest_area"]) == 0.0
    a, _, b = objective.dart_tri[0].tolist()
    crossed = uv.clone()
    crossed[a], crossed[b] = uv[b], uv[a]  # the dart's legs pass each other at its base
    dart_only = rest_area_loss(
        crossed, uv, objective.dart_tri, threshold=0.2, template_area=objective.dart_area
    )
    assert float(dart_only) > 1.0  # at least one triangle's ratio at -1: (0.2 + 1)^2
    assert float(objective.rest_terms(crossed)["rest_area"]) >= float(dart_only)


@pytest.mark.parametrize("term", ["area", "shape"])
def test_hinge_terms_with_a_graph_equal_the_whole_sum(term):
    """With a graph, the rest area and shape terms build it on their live triangles only: the value and
    the gradient are those of every triangle's penalty summed (batched too, and with none live)."""
    gen = torch.Generator().manual_seed(3)
    n = 12
    u, v = torch.meshgrid(torch.arange(n, dtype=F64), torch.arange(n, dtype=F64), indexing="ij")
    uv0 = 0.01 * torch.stack([u.reshape(-1), v.reshape(-1)], 1)
    i = torch.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).reshape(-1)
    tri = torch.cat([torch.stack([a, a + n, a + n + 1], 1), torch.stack([a, a + n + 1, a + 1], 1)])
    loss = rest_area_loss if term == "area" else rest_distortion_loss
    for jitter in (0.004, 0.0):  # some triangles live, then none
        uv = (uv0 + jitter * torch.randn(2, *uv0.shape, generator=gen, dtype=F64)).requires_grad_(True)
        value = loss(uv, uv0, tri)
        whole = loss(uv, uv0, tri, reduction="none").sum(-1)
        assert value.shape == (2,)
        live = int((loss(uv, uv0, tri, reduction="none") > 0).sum())
        assert (live > 0) == (jitter > 0)
        torch.testing.assert_close(value, whole, rtol=1e-14, atol=0.0)
        (g_value,) = torch.autograd.grad(value.sum(), uv)
        (g_whole,) = torch.autograd.grad(whole.sum(), uv)
        torch.testing.assert_close(g_value, g_whole, rtol=1e-14, atol=0.0)
        with torch.no_grad():
            torch.testing.assert_close(loss(uv, uv0, tri), whole.detach(), rtol=1e-14, atol=0.0)


def test_a_nan_rest_coordinate_still_reaches_the_hinge_terms():
    """The live-triangle path must not drop a NaN triangle: the fit's guards look for non-finite losses."""
    uv0 = torch.tensor([[0.0, 0.0], [0.1, 0.0], [0.1, 0.1], [0.0, 0.1]], dtype=F64)
    tri = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uv = uv0.clone()
    uv[2, 0] = float("nan")
    uv.requires_grad_(True)
    assert torch.isnan(rest_area_loss(uv, uv0, tri))
    assert torch.isnan(rest_distortion_loss(uv, uv0, tri))
