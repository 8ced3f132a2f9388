"""Second contacts where the body folds inward (`XPBDConfig.valley_contacts`): detection, the op against its
twin with two contacts per vertex, gradchecks of both adjoints in a groove, and cloth at rest in a groove
that one contact per vertex flings out."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torch_diffavatar.sim import collision, ops, reference
from torch_diffavatar.sim.adjoint import EquilibriumOptions, TrajectoryOptions
from torch_diffavatar.sim.adjoint.equilibrium import _not_held
from torch_diffavatar.sim.contacts import Contacts, apply_friction, damp_bounce, occurrence_layers
from torch_diffavatar.sim.forward_drape import DrapeConfig
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver
from torch_diffavatar.sim.testing import drape_gradcheck, drape_of, rectangle_garment

F64 = torch.float64


def groove(slope: float = 1.0, depth: float = 0.0):
    """A V-shaped valley along z (crease at x = 0, y = ``depth``; walls rising ``slope`` per metre),
    outward normals up into the groove: (6, 3) verts, (4, 3) faces."""
    v = [[0, 0, -1], [0, 0, 1], [-1, slope, -1], [-1, slope, 1], [1, slope, -1], [1, slope, 1]]
    verts = torch.tensor(v, dtype=F64) + torch.tensor([0.0, depth, 0.0], dtype=F64)
    faces = torch.tensor([[0, 3, 1], [0, 2, 3], [0, 5, 4], [0, 1, 5]], dtype=torch.int64)
    return verts, faces


def roof():
    """The groove upside down: a convex ridge (outward normals up, away from the ridge)."""
    verts, faces = groove()
    return verts * verts.new_tensor([1.0, -1.0, 1.0]), faces[:, [0, 2, 1]]


def test_occurrence_layers():
    layers = occurrence_layers(torch.tensor([3, 1, 3, 2, 1, 3]))
    assert [t.tolist() for t in layers] == [[0, 1, 3], [2, 4], [5]]
    assert occurrence_layers(torch.tensor([4, 1, 2])) is None


def test_a_point_in_a_groove_gets_both_walls():
    verts, faces = groove()
    # near the crease (within 4 mm of both walls), near one wall only, and 2 cm up (far from the other)
    x = torch.tensor([[0.0005, 0.004, 0.1], [0.004, 0.006, -0.2], [0.02, 0.023, 0.0]], dtype=F64)
    one = collision.detect_contacts(x, verts, faces, 0.05)
    assert one.vert.tolist() == [0, 1, 2]
    two = collision.detect_contacts(x, verts, faces, 0.05, valley=0.004)
    assert two.vert.tolist() == [0, 1, 2, 0]
    twin = collision.detect_contacts(x, verts, faces, 0.05, valley=0.004, use_extension=False)
    assert torch.equal(twin.vert, two.vert) and torch.equal(twin.tri, two.tri)
    torch.testing.assert_close(twin.bary, two.bary)
    assert {int(two.tri[0]) // 2, int(two.tri[3]) // 2} == {0, 1}  # one contact on each wall
    # the second contact is the foot of the point on the left wall (y = -x), its closest wall point
    point, normal = collision.contact_frames(verts, faces, two)
    foot = torch.tensor([(0.0005 - 0.004) / 2, (0.004 - 0.0005) / 2], dtype=F64)
    torch.testing.assert_close(point[3, :2], foot, rtol=0, atol=1e-12)
    torch.testing.assert_close(normal[3], torch.tensor([1.0, 1.0, 0.0], dtype=F64) / 2**0.5)
    # a ridge is convex: its sides never add a contact
    rv, rf = roof()
    assert collision.detect_contacts(x, rv, rf, 0.05, valley=0.004).count == 3


def test_valley_partners_follow_the_body():
    """Each face's partners are kept while the body stays the same, and worked out again when it moves."""
    verts, faces = groove()
    features = collision._FeatureFaces(faces, verts.shape[0])
    tri = torch.tensor([0, 2, 0])
    first = features.valley_candidates(verts, tri)
    assert {int(t) for t in first[0] if t >= 0} == {2, 3} and {int(t) for t in first[1] if t >= 0} == {0, 1}
    assert torch.equal(features.valley_candidates(verts, tri), first)
    flat = verts * verts.new_tensor([1.0, 0.0, 1.0])  # the groove flattened: no valley left
    assert bool((features.valley_candidates(flat, tri) == -1).all())
    roof_verts, _ = roof()
    assert bool((features.valley_candidates(roof_verts, tri) == -1).all())  # a ridge (same winding): none
    assert torch.equal(features.valley_candidates(verts, tri), first)


def test_the_layered_response_is_differentiable():
    """Projection, friction and bounce with two contacts on one vertex, through both passes."""
    verts, faces = groove()
    x0 = torch.tensor([[0.0005, 0.003, 0.1], [0.003, 0.0045, -0.2]], dtype=F64)
    contacts = collision.detect_contacts(x0, verts, faces, 0.05, valley=0.004)
    assert contacts.layers is not None
    w = torch.ones(2, dtype=F64)
    x_start = x0 + x0.new_tensor([[0.001, 0.002, 0.003], [-0.002, 0.001, 0.002]])

    def f(body_verts, x):
        y, depth, normal = collision.project_contacts(x, w, body_verts, faces, contacts, 0.005)
        y = apply_friction(y, x_start, contacts, normal, depth, 0.3)
        v = damp_bounce((y - x_start) * 30.0, contacts, normal, depth, 0.4)
        return y, v

    y, v = f(verts, x0)
    assert bool((y[:, 1] > x0[:, 1]).all())
    assert torch.autograd.gradcheck(f, (verts.clone().requires_grad_(), x0.clone().requires_grad_()))


def _sphere_args(monkeypatch, scheme):
    """(x, v, inputs) of one `XPBDSolver.step` of a moving sheet pressed onto a sphere (every constraint
    kind of a body drape active), captured at `ops.xpbd_substeps_`."""
    from torch_diffavatar.sim.state import ClothState

    trimesh = pytest.importorskip("trimesh")
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    verts, faces = torch.as_tensor(s.vertices, dtype=F64), torch.as_tensor(s.faces, dtype=torch.int64)
    mat = ClothMaterial(
        k_uu=800.0, k_vv=600.0, k_uv=100.0, bend_stiffness=1e-4, thickness=0.005, friction=0.4
    )
    g = rectangle_garment(10, 10, 0.6, 0.6, origin=(-0.3, 0.31, 0.3))
    model = ClothModelBuilder(mat).add_garment(g).finalize(dtype=F64)
    gen = torch.Generator().manual_seed(7)
    x = model.vert_init_pos + 0.004 * torch.randn(model.vert_init_pos.shape, generator=gen, dtype=F64)
    v = 0.3 * torch.randn(x.shape, generator=gen, dtype=F64)
    v[:, 1] -= 0.5
    captured = []
    monkeypatch.setattr(ops, "xpbd_substeps_", lambda *args, use_extension=True: captured.append(args))
    XPBDSolver(model, XPBDConfig(substeps=6, iterations=2, scheme=scheme)).step(
        ClothState(x, v), model.rest_data(g.vert_uv.to(F64)), 1 / 60, body_verts=verts, body_faces=faces
    )
    monkeypatch.undo()
    return captured[0]


@pytest.mark.parametrize("scheme", ["gauss_seidel", "jacobi"])
def test_the_op_answers_two_contacts_per_vertex_as_its_twin(scheme, monkeypatch):
    """Second contacts (here a neighbouring face of every third contact, listed before and after the
    first) are answered one after the other by the op and pass by pass by the twin: the same result."""
    from torch_diffavatar._ext import has_extension

    if not has_extension():
        pytest.skip("C++ extension not built")
    x, v, inputs = _sphere_args(monkeypatch, scheme)
    body = inputs.body
    pick = torch.arange(0, body.contact_vert.numel(), 3)
    other = (body.contact_tri[pick] + 1) % body.body_faces.shape[0]
    half = pick.numel() // 2
    two = dataclasses.replace(
        body,
        contact_vert=torch.cat(
            (body.contact_vert[pick[:half]], body.contact_vert, body.contact_vert[pick[half:]])
        ),
        contact_tri=torch.cat((other[:half], body.contact_tri, other[half:])),
        contact_bary=torch.cat(
            (body.contact_bary[pick[:half]], body.contact_bary, body.contact_bary[pick[half:]])
        ),
    )
    params = dataclasses.replace(inputs.params, thickness=0.02, contact_bounce=0.5)
    results = {}
    for name, b in (("one", body), ("two", two)):
        for kind, fn in (("op", torch.ops.diffavatar.xpbd_substeps_), ("twin", reference.xpbd_substeps_)):
            xx, vv = x.clone(), v.clone()
            fn(xx, vv, *dataclasses.replace(inputs, body=b, params=params).op_args())
            results[name, kind] = xx, vv
    assert float((results["two", "op"][0] - results["one", "op"][0]).abs().max()) > 1e-5
    torch.testing.assert_close(results["two", "op"][0], results["two", "twin"][0], rtol=0.0, atol=1e-10)
    torch.testing.assert_close(results["two", "op"][1], results["two", "twin"][1], rtol=0.0, atol=1e-7)


def _strip(length: float, stiffness: float, width: float = 0.02, height: float = 0.02, off: float = 0.002):
    """A 3 × 5 strip along the groove, its middle ``off`` [m] off the crease, ``height`` [m] above it;
    frictionless."""
    k = stiffness
    mat = ClothMaterial(
        k_uu=k, k_vv=k, k_uv=k / 3, bend_stiffness=1e-5, thickness=0.004, friction=0.0, damping=0.0
    )
    origin = (off - width / 2, height, length / 2)
    g = rectangle_garment(3, 5, width, length, origin=origin, axis_u=(1, 0, 0), axis_v=(0, 0, -1))
    return g, mat


@pytest.mark.parametrize("valley", [False, True])
def test_cloth_comes_to_rest_in_a_frictionless_groove(valley):
    """One contact plane per vertex lets a vertex slide along one wall's plane through the other wall; the
    next frame that wall pushes it back: in a frictionless groove the strip is flung out. With valley
    contacts it rests at the thickness from both walls."""
    g, mat = _strip(0.04, 1e3)
    verts, faces = groove()
    model = ClothModelBuilder(mat).add_garment(g).finalize(dtype=F64)
    rest = model.rest_data(g.vert_uv)
    solver = XPBDSolver(model, XPBDConfig(substeps=10, iterations=1, valley_contacts=valley))
    state = model.initial_state()
    for _ in range(80):
        state = solver.step(state, rest, 1 / 30, body_verts=verts, body_faces=faces)
    speed = float(state.v.norm(dim=-1).max())
    if not valley:
        assert speed > 0.5  # what valley contacts cure
        return
    assert speed < 1e-3
    # the crease's vertices sit thickness · √2 above it (the corner of the two walls' offset planes)
    torch.testing.assert_close(
        state.x[:, 1].min(), torch.tensor(0.004 * 2**0.5, dtype=F64), rtol=0, atol=2e-4
    )


def _groove_fn(group, adjoint, config, options, stats):
    """(f, t0) as tests/sim/test_adjoint.py's ``_fn``: a strip falling into the groove (trajectory) or
    folded into it (equilibrium)."""
    if adjoint == "trajectory":
        # 12 mm up, the walls 3.5 mm or more from it
        g, mat = _strip(0.04, 1e3, width=0.01, height=0.012)
    else:
        # pinned 1.7 mm below the corner of the walls' offset planes, and heavy (100x), so that its rows are
        # pulled into the corner and the penalty equilibrium presses both walls
        g, mat = _strip(0.04, 1e3, width=0.01 * 2**0.5, height=0.004, off=0.0)
        mat = dataclasses.replace(mat, areal_density=15.0)
    verts, faces = groove()
    # the groove does not hold it along z: pinned at the middle of its first row (and of its last one,
    # in the corner, for a well-posed equilibrium)
    pins = torch.tensor([1] if adjoint == "trajectory" else [1, 13])
    model = ClothModelBuilder(mat).add_garment(g, pinned=pins).finalize(dtype=F64)
    nominal = {"rest_uv": g.vert_uv.to(F64), "body": verts}
    kwargs = dict(config=config, adjoint=adjoint, options=options, stats=stats)
    return drape_of(group, nominal, model, mat, faces, **kwargs)


def _gradcheck(f, t):
    assert drape_gradcheck(f, t)


@pytest.mark.parametrize("group", ("rest_uv", "body"))
def test_trajectory_gradcheck_in_a_groove(group):
    xpbd = XPBDConfig(substeps=4, iterations=2, valley_contacts=True)
    cfg = DrapeConfig(xpbd=xpbd, dt=1 / 30, max_steps=3, min_steps=3)
    stats = {}
    f, t = _groove_fn(group, "trajectory", cfg, TrajectoryOptions(checkpoint_every=1), stats)
    _gradcheck(f, t)
    assert stats["max_contacts"] > 15  # more contacts than vertices: second ones take part


@pytest.mark.parametrize("group", ("rest_uv", "body"))
def test_equilibrium_gradcheck_in_a_groove(group):
    """The equilibrium adjoint with valley contacts in its drape and its active set: at its equilibrium
    vertices press both walls, each with its two contacts in the energy and the Hessian."""
    cfg = DrapeConfig(
        xpbd=XPBDConfig(substeps=4, iterations=2, valley_contacts=True), dt=1 / 30, max_steps=120,
        min_steps=20, speed_tol=1e-3,
    )  # fmt: skip
    stats = {}
    options = EquilibriumOptions(newton_tol=1e-12, solve_tol=1e-12)
    f, t = _groove_fn(group, "equilibrium", cfg, options, stats)
    _gradcheck(f, t)
    assert stats["xpbd_converged"] and stats["newton_force_residual"] < 1e-12
    x = f(t.detach())
    verts, faces = groove()
    contacts = collision.detect_contacts(x, verts, faces, 0.01, valley=0.005)
    pressing = collision.signed_distance_along_normal(x, verts, faces, contacts) < 0.004
    free = torch.isin(contacts.vert, torch.tensor([1, 13]), invert=True)
    both = torch.bincount(contacts.vert[pressing & free], minlength=x.shape[0]) == 2
    assert int(both.sum()) >= 2  # vertices held by both walls at the equilibrium


def test_the_active_set_adds_a_second_contact_but_not_a_second_first_one():
    held = Contacts(torch.tensor([0, 1]), torch.tensor([5, 6]), torch.zeros(2, 3, dtype=F64))
    # candidates: vertex 0 again on face 5 (held), vertex 1 on face 7 (a new first contact: not added),
    # vertex 2 (new), vertex 0's valley contact on face 8 (new), vertex 1's on face 6 (held)
    cand = Contacts(
        torch.tensor([0, 1, 2, 0, 1]), torch.tensor([5, 7, 9, 8, 6]), torch.zeros(5, 3, dtype=F64)
    )
    assert _not_held(cand, held, 10).tolist() == [False, False, True, True, False]


def test_valley_margin_is_checked():
    for bad in (-0.001, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="valley_margin"):
            XPBDConfig(valley_margin=bad)
    assert XPBDConfig().valley_radius(0.003) is None
    assert XPBDConfig(valley_contacts=True).valley_radius(0.003) == pytest.approx(0.004)
