"""The floor under the body (`DrapeConfig.floor`, `sim.floor`): cloth longer than the body rests on it
instead of hanging through, the placement folded up at it stretching no edge, the floor's own contact where
a foot meets it (`XPBDConfig.floor_faces`), and both adjoints' gradients through floor contacts (the floor's
height following the body's lowest vertex)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torch_diffavatar.errors import SimulationError
from torch_diffavatar.sim import collision, floor
from torch_diffavatar.sim.adjoint import EquilibriumOptions, TrajectoryOptions
from torch_diffavatar.sim.forward_drape import DrapeConfig, drape_to_equilibrium, sew_and_drape
from torch_diffavatar.sim.material import ClothMaterial, medium_cotton
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig
from torch_diffavatar.sim.testing import drape_gradcheck, drape_of, rectangle_garment, tube_garment

F64 = torch.float64
THICKNESS = 0.004


def octahedron(x: float = 0.0):
    """A 10 cm octahedron standing on its lowest corner at (x, 0, 0): the 'body' (6, 3), (8, 3) faces,
    outward normals; its lowest vertex is unique, so the floor's height is differentiable in it."""
    r, c = 0.05, torch.tensor([x, 0.05, 0.0], dtype=F64)
    v = torch.tensor([[0, -r, 0], [0, r, 0], [r, 0, 0], [0, 0, r], [-r, 0, 0], [0, 0, -r]], dtype=F64) + c
    faces = [[0, 3, 2], [0, 4, 3], [0, 5, 4], [0, 2, 5], [1, 2, 3], [1, 3, 4], [1, 4, 5], [1, 5, 2]]
    return v, torch.tensor(faces, dtype=torch.int64)


def _material(friction=0.3, density=0.15):
    return ClothMaterial(
        k_uu=1e3, k_vv=1e3, k_uv=3e2, bend_stiffness=1e-5, thickness=THICKNESS, friction=friction,
        damping=0.0, areal_density=density,
    )  # fmt: skip


def _cotton():
    return dataclasses.replace(medium_cotton(), thickness=THICKNESS)


def _hanging_strip():
    """A 2 × 20 cm cotton strip 15 cm beside the octahedron, pinned at its top row 8 cm above the floor: 12 cm
    of it placed through the floor."""
    g = rectangle_garment(3, 11, 0.02, 0.2, origin=(0.2, 0.08, 0.0), axis_u=(1, 0, 0), axis_v=(0, -1, 0))
    return g, ClothModelBuilder(_cotton()).add_garment(g, pinned=torch.arange(3)).finalize(dtype=F64)


@pytest.mark.parametrize("with_floor", [False, True])
def test_a_strip_longer_than_the_body_rests_on_the_floor(with_floor):
    g, model = _hanging_strip()
    verts, faces = octahedron()
    config = DrapeConfig(xpbd=XPBDConfig(substeps=10, iterations=1), floor=with_floor, max_steps=400)
    res = drape_to_equilibrium(model, g.vert_uv, body_verts=verts, body_faces=faces, config=config)
    assert res.converged
    low = float(res.x[:, 1].min())
    if not with_floor:
        assert low < -0.11  # hangs through where the floor is
        return
    assert abs(low - THICKNESS) < 5e-4  # on the floor, at the cloth's thickness
    lying = int((res.x[:, 1] < THICKNESS + 1e-3).sum())
    assert lying >= 3 * 4  # the last ~4 rows (12 cm of strip below 8 cm of height) lie on the floor
    assert res.diagnostics["penetrating_count"] == 0


def test_the_fold_stretches_no_edge():
    """A mirror: edges on one side of the fold keep their length, those across it get shorter (the crease
    is compressed), none longer."""
    g, model = _hanging_strip()
    x = model.vert_init_pos
    folded = floor.fold_above_floor(x, 0.0, THICKNESS)
    assert float(folded[:, 1].min()) >= THICKNESS
    above = x[:, 1] >= THICKNESS
    assert torch.equal(folded[above], x[above]) and bool((~above).any())
    e = model.tri_vertices[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    length = lambda p: (p[e[:, 0]] - p[e[:, 1]]).norm(dim=-1)  # noqa: E731
    side = above[e[:, 0]] == above[e[:, 1]]
    torch.testing.assert_close(length(folded)[side], length(x)[side], rtol=0, atol=1e-12)
    assert bool((length(folded)[~side] < length(x)[~side]).all()) and bool((~side).any())


def test_with_floor_appends_an_upward_quad_and_keeps_the_body():
    verts, faces = octahedron(0.3)
    verts.requires_grad_(True)
    v, f = floor.with_floor(verts, faces)
    assert v.shape == (10, 3) and f.shape == (10, 3)
    assert torch.equal(v[:6], verts) and torch.equal(f[:8], faces)
    corners = v[f[8:]].detach()
    normal = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert bool((normal[:, 1] > 0).all()) and float(normal[:, [0, 2]].abs().max()) == 0.0
    assert torch.equal(v[6:, 1].detach(), torch.zeros(4, dtype=F64))
    lo, hi = v[6:, [0, 2]].detach().amin(0), v[6:, [0, 2]].detach().amax(0)
    torch.testing.assert_close(lo, torch.tensor([0.25, -0.05], dtype=F64) - floor.FLOOR_MARGIN)
    torch.testing.assert_close(hi, torch.tensor([0.35, 0.05], dtype=F64) + floor.FLOOR_MARGIN)
    # the floor's height is the lowest vertex's: its gradient goes there, and only there
    v[6:, 1].sum().backward()
    assert verts.grad[0, 1] == 4.0 and int((verts.grad != 0).sum()) == 1
    poses, pf = floor.with_floor(torch.stack((verts.detach(), verts.detach() + 0.1)), faces, 0.0)
    assert poses.shape == (2, 10, 3) and torch.equal(poses[0, 6:], poses[1, 6:]) and torch.equal(pf, f)


def test_a_sewn_garment_through_the_floor_ends_on_it():
    """`sew_and_drape` with the floor: the sewing phase starts from the folded placement, and the drape
    lands on the floor (no vertex below it, no stitch left open)."""
    g = tube_garment(5, 9, width=0.1, height=0.2, gap=0.06, y0=-0.1)  # waist held 10 cm up, 10 cm through
    verts, faces = octahedron(0.3)
    config = DrapeConfig(xpbd=XPBDConfig(substeps=10, iterations=1), floor=True, max_steps=400)
    res = sew_and_drape(g, body_verts=verts, body_faces=faces, material=_cotton(), config=config)
    assert res.converged and abs(float(res.x[:, 1].min()) - THICKNESS) < 5e-4


def _floor_fn(group, adjoint, config, options, stats):
    """(f, t0) as tests/sim/test_adjoint.py's ``_fn``: a 1 × 4 cm strip beside the octahedron, falling onto
    the floor (trajectory) or pinned at its ends and sagging onto it (equilibrium)."""
    height = 0.006 if adjoint == "trajectory" else 0.005
    g = rectangle_garment(3, 5, 0.01, 0.04, origin=(0.1, height, 0.02), axis_u=(1, 0, 0), axis_v=(0, 0, -1))
    mat = _material(friction=0.0, density=0.15 if adjoint == "trajectory" else 15.0)
    verts, faces = octahedron()
    pins = torch.tensor([1] if adjoint == "trajectory" else [1, 13])
    model = ClothModelBuilder(mat).add_garment(g, pinned=pins).finalize(dtype=F64)
    nominal = {"rest_uv": g.vert_uv.to(F64), "body": verts}
    kwargs = dict(config=config, adjoint=adjoint, options=options, stats=stats)
    return drape_of(group, nominal, model, mat, faces, **kwargs)


def _gradcheck(f, t):
    assert drape_gradcheck(f, t)


@pytest.mark.parametrize("group", ("rest_uv", "body"))
def test_trajectory_gradcheck_on_the_floor(group):
    xpbd = XPBDConfig(substeps=4, iterations=2)
    cfg = DrapeConfig(xpbd=xpbd, dt=1 / 30, max_steps=3, min_steps=3, floor=True)
    stats = {}
    f, t = _floor_fn(group, "trajectory", cfg, TrajectoryOptions(checkpoint_every=1), stats)
    _gradcheck(f, t)
    assert stats["max_contacts"] >= 10  # the strip's free vertices reach the floor
    if group == "body":  # the floor's height follows the octahedron's lowest corner
        _, grad = torch.autograd.functional.vjp(f, t.detach(), torch.ones(15, 3, dtype=F64))
        assert abs(float(grad[0, 1])) > 0.1


@pytest.mark.parametrize("group", ("rest_uv", "body"))
def test_equilibrium_gradcheck_on_the_floor(group):
    cfg = DrapeConfig(
        xpbd=XPBDConfig(substeps=4, iterations=2), dt=1 / 30, max_steps=200, min_steps=20, speed_tol=1e-3,
        floor=True,
    )  # fmt: skip
    stats = {}
    options = EquilibriumOptions(newton_tol=1e-12, solve_tol=1e-12)
    f, t = _floor_fn(group, "equilibrium", cfg, options, stats)
    _gradcheck(f, t)
    assert stats["xpbd_converged"] and stats["active_contacts"] >= 3
    x = f(t.detach())
    assert float(x[:, 1].min()) < THICKNESS + 1e-6  # resting on the floor, pressed into its penalty


def overhang(tilt: float = 0.0):
    """A 20 cm wide plane rising at 45° from the floor line x = 0 towards +x, facing down and out (+x, −y):
    the side of a foot over the floor. (4, 3) verts, (2, 3) faces. With ``tilt`` [m] its corners at z = 0.1
    are that much higher: its lowest vertex (0, 0, −0.1) is then unique, and the floor's height
    differentiable in it."""
    v = [[0, 0, -0.1], [0, tilt, 0.1], [0.1, 0.1 + tilt, 0.1], [0.1, 0.1, -0.1]]
    return torch.tensor(v, dtype=F64), torch.tensor([[0, 2, 1], [0, 3, 2]], dtype=torch.int64)


def _wedge_strip(x_end: float = 0.006, nv: int = 11, length: float = 0.1):
    """A frictionless 4 cm wide cotton strip 0.5 mm above its rest on the floor under the overhang (not at
    it: the placement's fold is not differentiable), its far end pinned, its near end ``x_end`` [m] from the
    floor line, where the gap under the overhang is thinner than two thicknesses."""
    g = rectangle_garment(
        3,
        nv,
        0.04,
        length,
        origin=(x_end + length, THICKNESS + 5e-4, 0.02),
        axis_u=(0, 0, -1),
        axis_v=(-1, 0, 0),
    )
    mat = dataclasses.replace(_cotton(), friction=0.0)
    return g, mat, ClothModelBuilder(mat).add_garment(g, pinned=torch.arange(3)).finalize(dtype=F64)


def test_a_vertex_where_a_foot_meets_the_floor_gets_both():
    verts, faces = overhang()
    bv, bf = floor.with_floor(verts, faces)
    # in the wedge (under the overhang, 2 mm above the floor), under the overhang 6 cm out (the floor
    # beyond reach), and on the floor beside it (the floor its first contact)
    x = torch.tensor([[0.004, 0.002, 0.0], [0.06, 0.03, 0.0], [-0.05, 0.002, 0.0]], dtype=F64)
    plain = collision.detect_contacts(x, bv, bf, 0.05)
    assert plain.vert.tolist() == [0, 1, 2] and bool((plain.tri[:2] < 2).all()) and int(plain.tri[2]) >= 2
    both = collision.detect_contacts(x, bv, bf, 0.05, floor=(2, 0.005))
    assert both.vert.tolist() == [0, 1, 2, 0] and int(both.tri[3]) >= 2  # the wedge's vertex, on the floor
    assert float(collision.signed_distance_along_normal(x, bv, bf, both)[3]) == pytest.approx(0.002)
    twin = collision.detect_contacts(x, bv, bf, 0.05, floor=(2, 0.005), use_extension=False)
    assert torch.equal(twin.vert, both.vert) and torch.equal(twin.tri, both.tri)
    torch.testing.assert_close(twin.bary, both.bary)


@pytest.mark.parametrize("floor_contacts", [False, True])
def test_cloth_comes_to_rest_where_a_foot_meets_the_floor(floor_contacts):
    """One contact per vertex in the wedge: the overhang's plane pushes the vertex through the floor, the
    floor's back up, and the strip is squeezed apart (or never rests); with the floor's own contact it
    rests."""
    g, mat, model = _wedge_strip()
    verts, faces = overhang()
    if floor_contacts:
        config = DrapeConfig(
            xpbd=XPBDConfig(substeps=20, iterations=1), floor=True, min_steps=200, max_steps=300
        )
        res = drape_to_equilibrium(model, g.vert_uv, body_verts=verts, body_faces=faces, config=config)
        assert res.converged and float(res.x[:, 1].min()) > THICKNESS - 5e-4
        return
    bv, bf = floor.with_floor(verts, faces)  # the floor joined, but its faces not told to the steps
    config = DrapeConfig(xpbd=XPBDConfig(substeps=20, iterations=1), min_steps=200, max_steps=300)
    try:
        res = drape_to_equilibrium(model, g.vert_uv, body_verts=bv, body_faces=bf, config=config)
    except SimulationError:
        return  # torn apart in the wedge
    assert not res.converged


@pytest.mark.parametrize("group", ("rest_uv", "body"))
def test_trajectory_gradcheck_where_a_foot_meets_the_floor(group):
    g, mat, model = _wedge_strip(x_end=0.005, nv=4, length=0.03)
    verts, faces = overhang(tilt=0.001)
    xpbd = XPBDConfig(substeps=4, iterations=2)
    cfg = DrapeConfig(xpbd=xpbd, dt=1 / 30, max_steps=3, min_steps=3, floor=True)
    nominal = {"rest_uv": g.vert_uv.to(F64), "body": verts}
    options = TrajectoryOptions(checkpoint_every=1)
    _gradcheck(
        *drape_of(group, nominal, model, mat, faces, config=cfg, options=options, adjoint="trajectory")
    )
    bv, bf = floor.with_floor(verts, faces)
    start = collision.detect_contacts(model.vert_init_pos, bv, bf, 0.01, floor=(2, THICKNESS + 0.001))
    assert start.count > torch.unique(start.vert).numel()  # vertices with both the overhang and the floor


@pytest.mark.parametrize("group", ("rest_uv", "body"))
def test_equilibrium_gradcheck_where_a_foot_meets_the_floor(group):
    """The equilibrium adjoint where the floor's contacts join its drape: the strip's near end, pushed out
    of the wedge, comes to rest at the corner of the two planes (a thickness from each)."""
    g, mat, _ = _wedge_strip(x_end=0.005, nv=4, length=0.03)
    mat = dataclasses.replace(mat, areal_density=15.0)
    model = ClothModelBuilder(mat).add_garment(g, pinned=torch.tensor([0, 2])).finalize(dtype=F64)
    verts, faces = overhang(tilt=0.001)
    cfg = DrapeConfig(
        xpbd=XPBDConfig(substeps=4, iterations=2), dt=1 / 30, max_steps=200, min_steps=20, speed_tol=1e-3,
        floor=True,
    )  # fmt: skip
    nominal = {"rest_uv": g.vert_uv.to(F64), "body": verts}
    stats = {}
    options = EquilibriumOptions(newton_tol=1e-12, solve_tol=1e-12)
    f, t = drape_of(group, nominal, model, mat, faces, config=cfg, options=options, stats=stats)
    _gradcheck(f, t)
    assert stats["xpbd_converged"] and stats["newton_force_residual"] < 1e-12
    assert stats["active_contacts"] >= 6
    x = f(t.detach())
    bv, bf = floor.with_floor(verts, faces)
    near = x[9:].detach()  # the near row
    on_overhang = collision.detect_contacts(near, verts, faces, 0.01)
    assert on_overhang.count == 3
    s = collision.signed_distance_along_normal(near, verts, faces, on_overhang)
    torch.testing.assert_close(s, torch.full_like(s, THICKNESS), rtol=0, atol=2e-5)
    torch.testing.assert_close(near[:, 1], torch.full_like(s, THICKNESS), rtol=0, atol=2e-5)
