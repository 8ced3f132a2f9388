"""The trajectory adjoint's fast replay (`sim/adjoint/replay.py`): the same frame as the C++ step, the
same gradient as autograd through the reference kernels, and the same contact set as the forward."""

from __future__ import annotations

import pytest
import torch
from test_adjoint import DT, material, sheet_on_sphere

from torch_diffavatar.sim import collision
from torch_diffavatar.sim.adjoint import TrajectoryOptions
from torch_diffavatar.sim.adjoint.replay import ReplayPlan
from torch_diffavatar.sim.adjoint.trajectory import replay_frame
from torch_diffavatar.sim.differentiable import drape
from torch_diffavatar.sim.forward_drape import DrapeConfig
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver, contact_band
from torch_diffavatar.sim.state import ClothState
from torch_diffavatar.sim.testing import tube_garment

DT_FRAME = 1 / 30


@pytest.fixture(scope="module")
def sheet():
    return sheet_on_sphere(friction=0.3)


def _frames(model, rest, body, faces, cfg, state, count):
    """``count`` solver frames; yields (state, contacts of the frame, next state)."""
    solver = XPBDSolver(model, cfg)
    for _ in range(count):
        c = None
        if body is not None:
            band = contact_band(state.v, rest.material, cfg, DT_FRAME)
            c = collision.detect_contacts(state.x, body, faces, band)
            c = c if c.count else None
        result = solver.advance(state, rest, DT_FRAME, body_verts=body, body_faces=faces, velocity_scale=0.97)
        new = result.state
        # the contacts the step used, which the trajectory adjoint's rollout records, are this very set
        last = result.contacts
        assert (last is None) == (c is None)
        if c is not None:
            assert torch.equal(last.vert, c.vert) and torch.equal(last.tri, c.tri)
            assert torch.equal(last.bary, c.bary)
        yield state, c, new
        state = new


@pytest.mark.parametrize("iterations", [1, 2])
def test_replay_matches_solver_step_with_friction(sheet, iterations):
    g, model, body, faces = sheet
    rest = model.rest_data(g.vert_uv.to(DT))
    cfg = XPBDConfig(substeps=3, iterations=iterations)
    plan = ReplayPlan(model, cfg, rest.vert_inv_mass)
    touched = 0
    for state, c, new in _frames(model, rest, body, faces, cfg, model.initial_state(), 6):
        x, v = plan.frame(state.x, state.v, rest, DT_FRAME, contacts=c, body_verts=body, body_faces=faces,
                          velocity_scale=0.97)  # fmt: skip
        torch.testing.assert_close(x, new.x, rtol=0, atol=1e-12)
        torch.testing.assert_close(v, new.v, rtol=0, atol=1e-10)
        touched += 0 if c is None else c.count
    assert touched > 0


def test_replay_matches_solver_step_with_stitches_and_attachments():
    g = tube_garment(5, 5, 0.3, 0.3, gap=0.06)
    model = ClothModelBuilder(material()).add_garment(g, merge_seams=False).finalize(dtype=DT)
    assert model.stitch_vertices.shape[0] and model.attach_vertices.shape[0]
    rest = model.rest_data(g.vert_uv.to(DT))
    cfg = XPBDConfig(substeps=2, iterations=2)
    plan = ReplayPlan(model, cfg, rest.vert_inv_mass)
    for state, _, new in _frames(model, rest, None, None, cfg, model.initial_state(), 4):
        x, v = plan.frame(state.x, state.v, rest, DT_FRAME, velocity_scale=0.97)
        torch.testing.assert_close(x, new.x, rtol=0, atol=1e-12)
        torch.testing.assert_close(v, new.v, rtol=0, atol=1e-10)


def test_replay_gradient_matches_reference_autograd(sheet):
    """One frame's VJP for x, v, every rest tensor and the body: fast replay vs the reference kernels."""
    g, model, body, faces = sheet
    rest0 = model.rest_data(g.vert_uv.to(DT))
    cfg = XPBDConfig(substeps=2, iterations=2)
    frames = list(_frames(model, rest0, body, faces, cfg, model.initial_state(), 8))
    state, c, _ = frames[-1]
    assert c is not None
    gen = torch.Generator().manual_seed(0)
    wx, wv = (torch.randn(model.vert_count, 3, generator=gen, dtype=DT) for _ in range(2))
    names = ("tri_rest_inv", "tri_compliance", "edge_compliance", "vert_inv_mass")

    def vjp(replay):
        leaves = {n: getattr(rest0, n).detach().requires_grad_(True) for n in names}
        rest = type(rest0)(**{**rest0.__dict__, **leaves})
        x, v = state.x.clone().requires_grad_(True), state.v.clone().requires_grad_(True)
        bv = body.clone().requires_grad_(True)
        xe, ve = replay(rest, x, v, bv)
        inputs = [x, v, bv, *leaves.values()]
        return torch.autograd.grad((xe * wx).sum() + (ve * wv).sum(), inputs)

    plan = ReplayPlan(model, cfg, rest0.vert_inv_mass)
    kw = dict(contacts=c, body_faces=faces, velocity_scale=0.97)
    fast = vjp(lambda r, x, v, b: plan.frame(x, v, r, DT_FRAME, body_verts=b, **kw))
    ref = vjp(lambda r, x, v, b: replay_frame(model, cfg, x, v, r, DT_FRAME, body_verts=b, **kw))
    for a, b in zip(fast, ref):
        assert float(b.abs().max()) > 0
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12 * float(b.abs().max()))


def test_fast_fall_contacts_match_the_forward():
    """A sheet thrown at the sphere: the step widens its contact band with the speed, and the rollout must
    record that same contact set, or the replay leaves the forward's trajectory."""
    g, model, body, faces = sheet_on_sphere()
    cfg = DrapeConfig(xpbd=XPBDConfig(substeps=4, iterations=1), dt=DT_FRAME, max_steps=6, min_steps=6)
    x0 = model.vert_init_pos + torch.tensor([0.0, 0.05, 0.0], dtype=DT)
    v0 = torch.zeros_like(x0)
    v0[:, 1] = -2.0  # 1.5 · 2 m/s · dt = 0.1 m, beyond the 2 cm collision band
    stats = {}
    uv = g.vert_uv.to(DT).requires_grad_(True)
    x = drape(uv, model, body, ClothMaterial(friction=0.0, damping=2.0), body_faces=faces,
              state=ClothState(x0, v0), config=cfg, adjoint="trajectory",
              options=TrajectoryOptions(checkpoint_every=2), stats=stats)  # fmt: skip
    x.sum().backward()
    assert stats["max_contacts"] > 0
    assert stats["replay_max_deviation_m"] < 1e-10
    assert float(uv.grad.abs().max()) > 0
