"""Warm starts that land: the equilibrium backward's linearization predicts where the next drape settles
(`sim.adjoint.linearization`)."""

from __future__ import annotations

import pytest
import torch
from test_adjoint import DT, material, settle_config, sheet_on_sphere

from torch_diffavatar._ext import has_extension
from torch_diffavatar.sim.adjoint import EquilibriumOptions
from torch_diffavatar.sim.adjoint.linearization import Linearization
from torch_diffavatar.sim.contacts import contact_frames
from torch_diffavatar.sim.differentiable import drape
from torch_diffavatar.sim.state import ClothState

pytestmark = pytest.mark.skipif(not has_extension(), reason="the kept factor needs the C++ extension")

# the fit's options: the projected Hessian, factored by the block Cholesky, no Newton polish
OPTIONS = EquilibriumOptions(
    hessian="projected", solve_method="direct", newton_iterations=0, active_set_rounds=1
)


def _drape(scene, uv, *, state=None, frames=None, stats=None, friction=0.0):
    """One equilibrium drape of the sheet; ``frames`` fixes the frame count (0: the start itself)."""
    g, model, body, faces = scene
    config = settle_config(120)
    if frames is not None:
        from dataclasses import replace

        config = replace(config, min_steps=frames, max_steps=frames)
    return drape(
        uv, model, body, material(friction=friction), body_faces=faces, state=state, config=config,
        adjoint="equilibrium", options=OPTIONS, stats=stats,
    )  # fmt: skip


def _linearized(scene, friction=0.0):
    """(x*, its linearization) of a settled drape of the template whose backward ran."""
    g = scene[0]
    uv = g.vert_uv.to(DT).clone().requires_grad_(True)
    stats: dict = {}
    x = _drape(scene, uv, stats=stats, friction=friction)
    x[:, 1].sum().backward()
    return x.detach(), stats["linearization"]


@pytest.fixture(scope="module")
def scene():
    return sheet_on_sphere()


def test_the_prediction_lands_near_the_new_equilibrium(scene):
    x0, lin = _linearized(scene)
    assert lin.factor is not None and torch.equal(lin.x, x0) and lin.contacts is not None
    uv1 = scene[0].vert_uv.to(DT) * 1.003  # the pattern 0.3 % larger: the sheet sags lower
    zeros = torch.zeros_like(x0)
    target = _drape(scene, uv1, state=ClothState(x0, zeros), frames=600)
    stats: dict = {}
    predicted = _drape(scene, uv1, state=ClothState(x0, zeros, lin), frames=0, stats=stats)
    assert stats["predicted_move"] > 0
    before = float((x0 - target).norm(dim=-1).mean())
    after = float((predicted - target).norm(dim=-1).mean())
    # measured: 0.18 of the distance is left (1.81 -> 0.33 mm), and the settled drape takes 36 frames, not 56
    assert before > 1e-4 and after < 0.3 * before


def test_a_restored_linearization_drapes_bit_for_bit_alike(scene):
    x0, lin = _linearized(scene)
    restored = Linearization.from_state_dict(lin.state_dict())
    assert restored.factor is None  # rebuilt from its inputs on first use
    uv1 = scene[0].vert_uv.to(DT) * 1.002
    zeros = torch.zeros_like(x0)
    a = _drape(scene, uv1, state=ClothState(x0, zeros, lin))
    b = _drape(scene, uv1, state=ClothState(x0, zeros, restored))
    assert torch.equal(a, b)
    assert torch.equal(restored.factor.l_val, lin.factor.l_val)


def test_no_prediction_from_another_start(scene):
    x0, lin = _linearized(scene)
    moved = x0 + 1e-6
    uv1 = scene[0].vert_uv.to(DT) * 1.002
    stats: dict = {}
    with_lin = _drape(scene, uv1, state=ClothState(moved, torch.zeros_like(x0), lin), stats=stats)
    without = _drape(scene, uv1, state=ClothState(moved, torch.zeros_like(x0)))
    assert stats["predicted_move"] == 0.0 and torch.equal(with_lin, without)


def test_friction_holds_the_contacts_in_the_prediction():
    scene = sheet_on_sphere(friction=0.5)
    x0, lin = _linearized(scene, friction=0.5)
    uv1 = scene[0].vert_uv.to(DT) * 1.003
    zeros = torch.zeros_like(x0)
    stats: dict = {}
    predicted = _drape(scene, uv1, state=ClothState(x0, zeros, lin), frames=0, stats=stats, friction=0.5)
    assert stats["predicted_move"] > 0
    _, normal = contact_frames(scene[2], scene[3], lin.contacts)
    step = (predicted - x0)[lin.contacts.vert]
    tangential = step - (step * normal).sum(-1, keepdim=True) * normal
    assert float(tangential.abs().max()) < 1e-12
    free = predicted - x0
    free[lin.contacts.vert] = 0.0
    assert float(free.abs().max()) > 0  # the rest of the sheet moves


def test_keep_linearization_false_frees_the_factor(scene):
    from dataclasses import replace

    g, model, body, faces = scene
    uv = g.vert_uv.to(DT).clone().requires_grad_(True)
    stats: dict = {}
    x = drape(
        uv, model, body, material(), body_faces=faces, config=settle_config(120), adjoint="equilibrium",
        options=replace(OPTIONS, keep_linearization=False), stats=stats,
    )  # fmt: skip
    x[:, 1].sum().backward()
    assert stats["adjoint_solve_method"] == "cholesky" and "linearization" not in stats
