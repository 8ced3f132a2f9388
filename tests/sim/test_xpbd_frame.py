"""The XPBD frame: one Python frame (`reference.xpbd_substeps`) behind the reference twin, the trajectory
adjoint's two replays and the benchmark's unfused path, and the C++ op; each pinned to the C++ op over a
whole small drape (float64), so that no copy drifts."""

from __future__ import annotations

import pytest
import torch
from test_adjoint import material, sheet_on_sphere

from torch_diffavatar._ext import has_extension
from torch_diffavatar.sim.adjoint.replay import ReplayPlan
from torch_diffavatar.sim.adjoint.trajectory import replay_frame
from torch_diffavatar.sim.benchmark import _UnfusedSolver
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver
from torch_diffavatar.sim.testing import tube_garment

pytestmark = pytest.mark.skipif(not has_extension(), reason="C++ extension not built")

DT = torch.float64
FRAME = 1 / 30  # [s]
FRAMES = 8


def _scene(name):
    if name == "sheet":  # on a sphere, with friction
        return sheet_on_sphere(friction=0.3)
    g = tube_garment(5, 5, 0.3, 0.3, gap=0.06)  # open seams: stitches and attachments
    model = ClothModelBuilder(material()).add_garment(g, merge_seams=False).finalize(dtype=DT)
    assert model.stitch_vertices.shape[0] and model.attach_vertices.shape[0]
    return g, model, None, None


@pytest.mark.parametrize("scene", ["sheet", "tube"])
@pytest.mark.parametrize("scheme", ["gauss_seidel", "jacobi"])
def test_every_frame_copy_follows_the_cpp_op_over_a_drape(scene, scheme):
    g, model, body, faces = _scene(scene)
    rest = model.rest_data(g.vert_uv.to(DT))
    cfg = XPBDConfig(substeps=3, iterations=2, scheme=scheme)
    kw = dict(body_verts=body, body_faces=faces, velocity_scale=0.97)
    solver = XPBDSolver(model, cfg)
    state, contacts = model.initial_state(), []
    for _ in range(FRAMES):  # the C++ op
        result = solver.advance(state, rest, FRAME, **kw)
        state = result.state
        contacts.append(result.contacts)
    assert (state.x - model.vert_init_pos).abs().max() > 1e-2  # the drape moved
    if body is not None:
        assert sum(c.count for c in contacts if c is not None) > 0

    reference_solver = XPBDSolver(
        model, XPBDConfig(substeps=3, iterations=2, scheme=scheme, use_extension=False)
    )
    for label, other in (
        ("reference twin", reference_solver),
        ("unfused C++ kernels", _UnfusedSolver(model, cfg)),
    ):
        s = model.initial_state()
        for _ in range(FRAMES):
            s = other.step(s, rest, FRAME, **kw)
        torch.testing.assert_close(s.x, state.x, rtol=0, atol=1e-11, msg=label)

    replays = {"replay_frame": lambda x, v, c: replay_frame(model, cfg, x, v, rest, FRAME, contacts=c, **kw)}
    if scheme == "gauss_seidel":
        plan = ReplayPlan(model, cfg, rest.vert_inv_mass)
        replays["ReplayPlan.frame"] = lambda x, v, c: plan.frame(x, v, rest, FRAME, contacts=c, **kw)
    for label, replay in replays.items():
        x, v = model.vert_init_pos, torch.zeros_like(model.vert_init_pos)
        for c in contacts:  # the forward's contact sets, as the trajectory adjoint replays them
            x, v = replay(x, v, c)
        torch.testing.assert_close(x, state.x, rtol=0, atol=1e-11, msg=label)
        torch.testing.assert_close(v, state.v, rtol=0, atol=1e-9, msg=label)


def test_advance_returns_the_contacts_it_projected_against():
    """The contacts are an output of the step (`StepResult`), not state kept on the solver."""
    g, model, body, faces = sheet_on_sphere(friction=0.3)
    rest = model.rest_data(g.vert_uv.to(DT))
    solver = XPBDSolver(model, XPBDConfig(substeps=3, iterations=1))
    state = model.initial_state()
    seen = []
    for _ in range(6):
        result = solver.advance(state, rest, FRAME, body_verts=body, body_faces=faces)
        # the same frame stepped without contacts output is the same state
        again = XPBDSolver(model, solver.config).step(state, rest, FRAME, body_verts=body, body_faces=faces)
        assert torch.equal(again.x, result.state.x) and torch.equal(again.v, result.state.v)
        seen.append(0 if result.contacts is None else result.contacts.count)
        state = result.state
    assert seen[-1] > 0
    assert not hasattr(solver, "last_contacts")
    assert XPBDSolver(model).advance(state, rest, FRAME).contacts is None  # no body: no contacts
