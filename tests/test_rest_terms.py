"""The rest terms' C++ kernels (`torch_diffavatar.rest_terms`) against their PyTorch twins, the loss functions
of `torch_diffavatar.losses`: values and gradients, gradcheck of the fused node, opcheck of each kernel,
bad input refused, and `FitObjective.rest_loss` through them equal to its terms' weighted sum.
The openings' terms' twins are those of `torch_diffavatar.opening_lengths`."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from torch_diffavatar._ext import has_extension
from torch_diffavatar.cage import seam_segments
from torch_diffavatar.losses import (
    REST_AREA_THRESHOLD,
    REST_DISTORTION_THRESHOLD,
    curvature_frames,
    curvature_loss,
    rest_area_loss,
    rest_distortion_loss,
    seam_length_loss,
    signed_rest_areas,
    template_edge_inverse,
)
from torch_diffavatar.opening_lengths import (
    opening_length_loss,
    opening_split_loss,
    rest_loop_edges,
    rest_loop_length,
    rest_loop_panels,
    rest_loop_shares,
)
from torch_diffavatar.pattern import load_template, mesh_pattern
from torch_diffavatar.rest_terms import fused_rest_terms, opening_slots, rest_kernels_available
from torch_diffavatar.sim.ops import extension_op

pytestmark = pytest.mark.skipif(not has_extension(), reason="C++ extension not built")
F64 = torch.float64


@pytest.fixture(scope="module")
def tshirt():
    """(garment, template uv, a pattern moved 8 mm per coordinate at random: every term and hinge live)."""
    garment = mesh_pattern(load_template("tshirt"), spacing=0.06)
    uv0 = garment.vert_uv.to(F64)
    gen = torch.Generator().manual_seed(3)
    return garment, uv0, uv0 + 0.008 * torch.randn(uv0.shape, generator=gen, dtype=F64)


def _openings(garment, uv0):
    """Every opening's (edges, panels, template shares) and the lengths to hold: the first two openings
    between 90 and 95 % of the template's (held at a length: their excess live), the others no shorter than
    5 % over it (their shortfall live)."""
    edges = [rest_loop_edges(garment, lp) for lp in garment.boundary_loops]
    panels = [rest_loop_panels(garment, e) for e in edges]
    shares = [rest_loop_shares(uv0, e, p) for e, p in zip(edges, panels, strict=True)]
    template = torch.stack([rest_loop_length(uv0, e) for e in edges])
    least, most = 1.05 * template, torch.full_like(template, torch.inf)
    least[:2], most[:2] = 0.9 * template[:2], 0.95 * template[:2]
    return edges, panels, shares, least, most


def _openings_call(garment, uv0, dtype, w_length, w_split):
    edges, panels, shares, least, most = _openings(garment, uv0)
    edges, slot, slot_opening, shares = opening_slots(edges, panels, shares)
    tables = (least.to(dtype), most.to(dtype), shares.to(dtype))
    return ("rest_openings", (edges, slot, slot_opening, *tables, w_length, w_split))


def _calls(garment, uv0, dtype=F64, w=(2.0, 3.0, 5.0, 7.0, 11.0, 13.0)):
    """The kernel calls of seam length, curvature (means, weights w[0], w[1]), the area and shape hinges
    (sums, w[2], w[3]) and the openings' length and split (w[4], w[5])."""
    seg, frames, tri = seam_segments(garment), curvature_frames(uv0, garment), garment.tri_vertices
    area, inverse = signed_rest_areas(uv0, tri), template_edge_inverse(uv0, tri)
    cast = [t.to(dtype).contiguous() for t in (frames.edges, frames.edges_perp, frames.norm, area, inverse)]
    hinges = (tri, cast[3], REST_AREA_THRESHOLD, w[2], cast[4], REST_DISTORTION_THRESHOLD, w[3])
    return [
        ("rest_seam_length", (seg, w[0] / len(seg))),
        ("rest_curvature", (frames.triplets, *cast[:3], w[1] / len(frames.triplets))),
        ("rest_triangle_hinges", hinges),
        _openings_call(garment, uv0, dtype, w[4], w[5]),
    ]


def _twin(garment, uv0, uv, w=(2.0, 3.0, 5.0, 7.0, 11.0, 13.0)):
    tri = garment.tri_vertices
    edges, panels, shares, least, most = _openings(garment, uv0)
    return (
        w[4] * opening_length_loss(uv, edges, least, most)
        + w[5] * opening_split_loss(uv, edges, panels, shares)
        + w[0] * seam_length_loss(uv, garment)
        + w[1] * curvature_loss(uv, uv0.to(uv), garment)
        + w[2] * rest_area_loss(uv, uv0.to(uv), tri)
        + w[3] * rest_distortion_loss(uv, uv0.to(uv), tri)
    )


def test_each_kernel_is_its_twin(tshirt):
    """Each kernel's value and gradient are its loss function's (float64: to 1e-12), with its hinges live."""
    garment, uv0, uv = tshirt
    tri = garment.tri_vertices
    twins = {
        "rest_seam_length": lambda u: 2.0 * seam_length_loss(u, garment),
        "rest_curvature": lambda u: 3.0 * curvature_loss(u, uv0, garment),
        "rest_triangle_hinges": lambda u: (
            5.0 * rest_area_loss(u, uv0, tri) + 7.0 * rest_distortion_loss(u, uv0, tri)
        ),
        "rest_openings": lambda u: (
            11.0 * opening_length_loss(u, edges, least, most)
            + 13.0 * opening_split_loss(u, edges, panels, shares)
        ),
    }
    edges, panels, shares, least, most = _openings(garment, uv0)
    assert len(edges) >= 4 and float(opening_length_loss(uv, edges, least)) > 0
    # the openings held at a length pay for their excess (none of them is short of it)
    held = opening_length_loss(uv, edges[:2], least[:2], most[:2])
    assert float(held) > 0 and float(opening_length_loss(uv, edges[:2], least[:2])) == 0
    assert float(rest_area_loss(uv, uv0, tri)) > 0 and float(rest_distortion_loss(uv, uv0, tri)) > 0
    for name, args in _calls(garment, uv0):
        value, grad = extension_op(name)(uv, *args)
        u = uv.clone().requires_grad_(True)
        want = twins[name](u)
        (want_grad,) = torch.autograd.grad(want, u)
        torch.testing.assert_close(value, want.detach(), rtol=1e-12, atol=0, msg=name)
        torch.testing.assert_close(grad, want_grad, rtol=1e-10, atol=1e-12 * float(want_grad.abs().max()))


def test_fused_node_gradcheck_and_float32(tshirt):
    """`fused_rest_terms` passes gradcheck (float64, finite differences) and gives the twins' value and
    gradient in float32 too (to float32's rounding)."""
    garment, uv0, uv = tshirt
    calls = _calls(garment, uv0)
    assert torch.autograd.gradcheck(lambda u: fused_rest_terms(u, calls), (uv.clone().requires_grad_(True),))
    u32 = uv.float().requires_grad_(True)
    fused = fused_rest_terms(u32, _calls(garment, uv0, torch.float32))
    want = _twin(garment, uv0, uv.clone().requires_grad_(True))
    (g_fused,) = torch.autograd.grad(fused, u32)
    assert fused.dtype == torch.float32
    torch.testing.assert_close(fused.double(), want.detach(), rtol=1e-5, atol=0)
    u = uv.clone().requires_grad_(True)
    (g_want,) = torch.autograd.grad(_twin(garment, uv0, u), u)
    torch.testing.assert_close(g_fused.double(), g_want, rtol=0, atol=1e-4 * float(g_want.abs().max()))


def test_kernels_opcheck_and_refuse_bad_input(tshirt):
    """opcheck on every kernel; an index out of range, a wrong dtype or shape is a one-line error; where the
    kernels cannot run (a batch, another dtype), `rest_kernels_available` says so."""
    garment, uv0, uv = tshirt
    for name, args in _calls(garment, uv0):
        torch.library.opcheck(extension_op(name).default, (uv, *args))
    seg = seam_segments(garment)
    with pytest.raises(RuntimeError, match="outside"):
        extension_op("rest_seam_length")(uv, seg + uv.shape[0], 1.0)
    with pytest.raises(RuntimeError, match="must be float32 or float64"):
        extension_op("rest_seam_length")(uv.half(), seg, 1.0)
    with pytest.raises(RuntimeError, match="shape"):
        extension_op("rest_seam_length")(uv, seg[:, :3].contiguous(), 1.0)
    frames = curvature_frames(uv0, garment)
    with pytest.raises(RuntimeError, match="edges must be"):
        extension_op("rest_curvature")(
            uv, frames.triplets, frames.edges.float(), frames.edges_perp, frames.norm, 1.0
        )
    assert rest_kernels_available(uv) and rest_kernels_available(uv.float())
    assert not rest_kernels_available(uv[None]) and not rest_kernels_available(uv.half())


def test_objective_rest_loss_through_the_kernels_is_its_terms_sum(skirt_problem):
    """`FitObjective.rest_loss` (the kernels and the openings' terms) gives the weighted sum of `rest_terms`
    (the loss functions) and its gradient, float64 to 1e-12, away from the template."""
    from helpers_fit import DT
    from helpers_fit import fit_config as _config

    from torch_diffavatar.objective import FitObjective, FitParameters, ScanTarget

    garment, _, target = skirt_problem
    hem = target.boundaries["hem"]  # ~20 points: resampled densely enough for `scan_loop_length`
    t = torch.linspace(0, 1, 9, dtype=DT)[:-1, None, None]
    dense = ((1 - t) * hem + t * hem.roll(-1, 0)).transpose(0, 1).reshape(-1, 3)
    target = ScanTarget(target.garment_points, {"hem": dense})
    config = _config()
    weights = replace(config.weights, opening_length=3e3, opening_split=1e4)
    names = {
        "opening_length_names": ("hem",),
        "opening_template_names": ("waist",),
        "opening_template_hold": "exact",
    }
    config = replace(config, weights=weights, **names)
    objective = FitObjective(garment, target, config, dtype=DT)
    assert sorted(objective.opening_names) == ["hem", "waist"]
    hem, waist = objective.opening_names.index("hem"), objective.opening_names.index("waist")
    assert torch.isinf(objective.opening_most[hem])
    assert objective.opening_most[waist] == objective.opening_least[waist]  # held at the template's
    objective.opening_least[hem] = 2.0  # the hem held at 2 m, longer than it is: the shortfall live
    objective.opening_most[waist] *= 0.8  # the waist held at 80 % of the template's: the excess live
    params = FitParameters.from_config(garment, config, dtype=DT)
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        params.cage.handles.add_(0.01 * torch.randn(params.cage.handles.shape, generator=gen, dtype=DT))
    rest_uv = params.cage().detach()
    u1, u2 = rest_uv.clone().requires_grad_(True), rest_uv.clone().requires_grad_(True)
    fused, terms = objective.rest_loss(u1), objective.rest_terms(u2)
    want = objective.weighted_sum(terms)
    assert set(terms) == {
        "seam_length",
        "curvature",
        "rest_area",
        "rest_shape",
        "opening_length",
        "opening_split",
    }
    assert all(
        float(terms[k].detach()) > 0 for k in ("seam_length", "curvature", "opening_length", "opening_split")
    )
    assert float(want.detach()) > 0
    torch.testing.assert_close(fused, want, rtol=1e-12, atol=0)
    (g1,) = torch.autograd.grad(fused, u1)
    (g2,) = torch.autograd.grad(want, u2)
    torch.testing.assert_close(g1, g2, rtol=1e-10, atol=1e-12 * float(g2.abs().max()))
