"""Cloth model building, colouring, rest data and constraint energies (gradients in float64)."""

from __future__ import annotations

import warnings

import pytest
import torch

from torch_diffavatar.sim import constraints
from torch_diffavatar.sim.coloring import coloring_is_valid, greedy_coloring
from torch_diffavatar.sim.material import ClothMaterial, medium_cotton
from torch_diffavatar.sim.model import ClothModelBuilder, interior_edges
from torch_diffavatar.sim.testing import rectangle_garment, tube_garment

F64 = torch.float64


def test_coloring_is_valid_on_meshes_and_random_constraints():
    g = rectangle_garment(7, 5)
    model = ClothModelBuilder().add_garment(g).finalize(dtype=F64)
    assert coloring_is_valid(model.tri_vertices, model.tri_coloring)
    assert coloring_is_valid(model.edge_quads, model.edge_coloring)
    assert model.tri_coloring.color_count <= 12
    gen = torch.Generator().manual_seed(0)
    cons = torch.randint(0, 30, (200, 3), generator=gen)
    cons = cons[(cons[:, 0] != cons[:, 1]) & (cons[:, 1] != cons[:, 2]) & (cons[:, 0] != cons[:, 2])]
    col = greedy_coloring(cons)
    assert coloring_is_valid(cons, col)
    # a broken colouring is detected
    bad = type(col)(torch.arange(cons.shape[0]), torch.tensor([0, cons.shape[0]]))
    assert not coloring_is_valid(cons, bad)


def test_interior_edges_of_grid_and_quads_are_consistent():
    g = rectangle_garment(4, 3)
    quads, tris, _, skipped = interior_edges(g.tri_vertices)
    # a 4x3 grid has 12 triangles; interior edges = (3 * 12 - boundary 10) / 2 = 13
    assert quads.shape == (13, 4) and skipped == 0
    f = g.tri_vertices
    for q, (t1, t2) in zip(quads.tolist(), tris.tolist()):
        a = f[t1].tolist()
        k = a.index(q[0])
        assert a[(k + 1) % 3] == q[1] and a[(k + 2) % 3] == q[2]  # (v0, v1, v2) is triangle 1's order
        b = f[t2].tolist()
        k = b.index(q[1])
        assert b[(k + 1) % 3] == q[0] and b[(k + 2) % 3] == q[3]  # (v1, v0, v3) is triangle 2's order


def test_tube_merged_and_unmerged_models():
    g = tube_garment(nx=5, ny=4)
    merged = ClothModelBuilder().add_garment(g).finalize(dtype=torch.float32)
    unmerged = ClothModelBuilder().add_garment(g, merge_seams=False).finalize(dtype=torch.float32)
    assert merged.vert_count == g.sim_vert_count == 2 * 5 * 4 - 2 * 4
    assert merged.stitch_vertices.shape == (0, 2) and merged.skipped_edge_count == 0
    assert unmerged.vert_count == g.vert_count and unmerged.stitch_vertices.shape == (8, 2)
    # bending exists across the merged seams: 3 edges per seam, 2 seams
    assert merged.edge_count == unmerged.edge_count + 2 * (4 - 1)
    # attachments: top rows minus the stitched corners, held at the initial height
    assert merged.attach_vertices.numel() == 2 * (5 - 2)
    torch.testing.assert_close(merged.attach_height, merged.vert_init_pos[merged.attach_vertices, 1])
    # sim positions of the merged placement are means of panel positions
    x = merged.sim_positions(g.vert_pos.float())
    torch.testing.assert_close(x, merged.vert_init_pos)


def test_rest_data_masses_areas_and_dtypes():
    mat = ClothMaterial(areal_density=0.2)
    g = rectangle_garment(5, 4, width=0.8, height=0.6)
    for dtype in (torch.float32, F64):
        model = ClothModelBuilder(mat).add_garment(g, pinned=torch.tensor([0])).finalize(dtype=dtype)
        rest = model.rest_data(g.vert_uv)
        assert rest.tri_rest_inv.dtype == dtype and rest.tri_compliance.is_contiguous()
        torch.testing.assert_close(rest.tri_area.sum(), torch.tensor(0.48, dtype=dtype))
        torch.testing.assert_close(rest.vert_mass.sum(), torch.tensor(0.2 * 0.48, dtype=dtype))
        assert float(rest.vert_inv_mass[0]) == 0 and bool((rest.vert_inv_mass[1:] > 0).all())
        torch.testing.assert_close(rest.edge_rest_angle, torch.zeros_like(rest.edge_rest_angle))


def test_material_validation_and_defaults():
    m = medium_cotton()
    assert 0.05 < m.areal_density < 0.4 and m.k_uu > m.k_uv > 0 and m.bend_stiffness > 0
    with pytest.raises(ValueError, match="poisson"):
        ClothMaterial(poisson=1.0)
    with pytest.raises(ValueError, match="k_uu"):
        ClothMaterial(k_uu=0.0)
    with pytest.raises(ValueError, match="finite"):
        ClothMaterial(damping=float("nan"))
    with pytest.raises(ValueError, match="k_vv"):
        ClothMaterial(k_vv=torch.tensor(0.0, requires_grad=True))


def test_material_with_fitted_tensors_validates_without_warnings():
    # a fit passes its stiffness as a tensor that requires grad: validating it is no reason to warn
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ClothMaterial(
            k_uu=torch.tensor(60.0, requires_grad=True), poisson=torch.tensor(0.2, requires_grad=True)
        )


def test_energies_and_rest_data_gradcheck():
    g = rectangle_garment(3, 3, width=0.2, height=0.2)
    model = ClothModelBuilder().add_garment(g).finalize(dtype=F64)
    gen = torch.Generator().manual_seed(1)
    x = (
        model.vert_init_pos + 0.01 * torch.randn(model.vert_count, 3, generator=gen, dtype=F64)
    ).requires_grad_()
    uv = (g.vert_uv + 0.005 * torch.randn(g.vert_count, 2, generator=gen, dtype=F64)).requires_grad_()
    kb = torch.tensor(5e-6, dtype=F64, requires_grad=True)

    def energy(x, uv, kb):
        mat = ClothMaterial(bend_stiffness=kb, k_uu=100.0, k_vv=80.0, k_uv=20.0, poisson=0.3)
        rest = model.rest_data(uv, mat)
        return (
            constraints.stretch_energy(x, model.tri_vertices, rest)
            + 1e3 * constraints.bend_energy(x, model.edge_quads, rest)
            + constraints.gravity_energy(x, rest.vert_mass, x.new_tensor([0.0, -9.81, 0.0]))
        )

    assert torch.autograd.gradcheck(energy, (x, uv, kb))


def test_stretch_energy_matches_compliance_form():
    """U = ½ Cᵀ α⁻¹ C per triangle: the energy and the kernel's compliance describe the same material."""
    g = rectangle_garment(3, 3, width=0.2, height=0.2)
    mat = ClothMaterial(k_uu=100.0, k_vv=80.0, k_uv=20.0, poisson=0.3)
    model = ClothModelBuilder(mat).add_garment(g).finalize(dtype=F64)
    rest = model.rest_data(g.vert_uv)
    gen = torch.Generator().manual_seed(2)
    x = model.vert_init_pos + 0.02 * torch.randn(model.vert_count, 3, generator=gen, dtype=F64)
    c = constraints.green_strain(x, model.tri_vertices, rest.tri_rest_inv)
    u = 0.5 * (c[:, None, :] @ torch.linalg.inv(rest.tri_compliance) @ c[:, :, None]).sum()
    torch.testing.assert_close(u, constraints.stretch_energy(x, model.tri_vertices, rest))


def test_builder_validation():
    with pytest.raises(ValueError, match="at least one garment"):
        ClothModelBuilder().finalize()


def test_two_garments_in_one_model_are_independent():
    a = rectangle_garment(4, 4, origin=(0.0, 1.0, 0.0))
    b = rectangle_garment(3, 5, origin=(2.0, 1.0, 0.0))
    model = ClothModelBuilder().add_garment(a).add_garment(b, pinned=torch.tensor([0])).finalize(dtype=F64)
    assert model.vert_count == 16 + 15 and model.panel_vert_count == 31
    assert (
        int(model.tri_vertices[: a.tri_count].max()) < 16
        and int(model.tri_vertices[a.tri_count :].min()) >= 16
    )
    uv = torch.cat((a.vert_uv, b.vert_uv))
    rest = model.rest_data(uv)
    assert float(rest.vert_inv_mass[16]) == 0.0 and float(rest.vert_inv_mass[0]) > 0
    assert coloring_is_valid(model.tri_vertices, model.tri_coloring)
