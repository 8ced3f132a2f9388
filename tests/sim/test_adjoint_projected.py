"""The equilibrium adjoint's projected-Hessian option against the exact one on the converged small
sheet-on-sphere problem, and its option validation."""

from __future__ import annotations

import math

import pytest
import torch
from test_adjoint import DT, KB, material, settle_config, sheet_on_sphere

from torch_diffavatar.sim.adjoint import EquilibriumOptions
from torch_diffavatar.sim.differentiable import drape

TIGHT = dict(newton_tol=1e-12, solve_tol=1e-12)
EXACT = EquilibriumOptions(**TIGHT)
PROJECTED = EquilibriumOptions(hessian="projected", **TIGHT)


@pytest.fixture(scope="module")
def scene():
    return sheet_on_sphere()


def _objective_weights(model, kind: str) -> torch.Tensor:
    """(V, 3) weights w of the objective φ = Σ w·x."""
    if kind == "sin":  # a fixed, sign-changing mix of every coordinate (as in test_adjoint.py)
        return torch.sin(torch.arange(model.vert_count * 3, dtype=DT)).reshape(-1, 3)
    w = torch.zeros(model.vert_count, 3, dtype=DT)  # "height": the mean height of the sheet
    w[:, 1] = 1.0 / model.vert_count
    return w


def _gradients(scene, weights, options, *, rest_uv=None, stats=None):
    """(φ, dφ/d rest_uv, dφ/d body vertices, dφ/d log bend stiffness) of one equilibrium drape."""
    g, model, body, faces = scene
    uv = (g.vert_uv.to(DT) if rest_uv is None else rest_uv).detach().clone().requires_grad_(True)
    bv = body.detach().clone().requires_grad_(True)
    log_kb = torch.tensor(math.log(KB), dtype=DT, requires_grad=True)
    x = drape(
        uv, model, bv, material(kb=log_kb.exp()), body_faces=faces, config=settle_config(15),
        adjoint="equilibrium", options=options, stats=stats,
    )  # fmt: skip
    phi = (x * weights).sum()
    phi.backward()
    return float(phi.detach()), uv.grad, bv.grad, log_kb.grad


def _cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a * b).sum() / (a.norm() * b.norm()))


# Measured on this problem (float64, 63 free dofs, 1 active contact, Newton residual ~6e-15, exact H
# positive definite):
#   objective  cos(rest_uv)  cos(body)  projected/exact d/d log k_b
#   "sin"      0.9755        0.9966     0.70
#   "height"   0.9933        0.9962     0.76
# The element-wise PSD projection changes the matrix even where the assembled exact H is definite (the
# compressed stretch and bending blocks have negative eigenvalues), so ≥ 0.99 for every group does not
# hold for the "sin" objective's rest_uv gradient: it is tested at 0.97, the rest at 0.99. (Random
# objectives measured lower still: rest_uv 0.906–0.997, body 0.727–0.997.)
COSINE_MIN = {
    ("sin", "rest_uv"): 0.97,
    ("sin", "body"): 0.99,
    ("height", "rest_uv"): 0.99,
    ("height", "body"): 0.99,
}


@pytest.mark.parametrize("kind", ["sin", "height"])
def test_projected_gradients_point_like_the_exact_ones(scene, kind):
    weights = _objective_weights(scene[1], kind)
    stats_exact, stats_proj = {}, {}
    phi_e, uv_e, body_e, kb_e = _gradients(scene, weights, EXACT, stats=stats_exact)
    phi_p, uv_p, body_p, kb_p = _gradients(scene, weights, PROJECTED, stats=stats_proj)
    assert phi_p == phi_e  # the option changes the backward only
    for stats in (stats_exact, stats_proj):
        assert stats["newton_force_residual"] < 1e-12 and stats["active_contacts"] > 0
        assert stats["adjoint_solve_residual"] < 1e-10
    assert not stats_proj["adjoint_hessian_indefinite"]
    for group, exact, projected in (("rest_uv", uv_e, uv_p), ("body", body_e, body_p)):
        assert float(exact.norm()) > 0 and float(projected.norm()) > 0
        assert _cosine(exact, projected) >= COSINE_MIN[kind, group], (kind, group, _cosine(exact, projected))
    # the projection changes the gradient (else this test would not see the option at all) ...
    assert float((uv_p - uv_e).norm()) > 1e-3 * float(uv_e.norm())
    # ... but not the sign of the bending stiffness's
    assert float(kb_e) * float(kb_p) > 0


def test_exact_mode_is_unchanged(scene):
    """The default is the exact Hessian, the regularization does not touch it, and its directional
    derivative matches central differences of the drape."""
    weights = _objective_weights(scene[1], "sin")
    assert EquilibriumOptions().hessian == "exact"
    _, uv_e, body_e, kb_e = _gradients(scene, weights, EXACT)
    _, uv_r, body_r, kb_r = _gradients(scene, weights, EquilibriumOptions(regularization=1e-2, **TIGHT))
    for a, b in ((uv_e, uv_r), (body_e, body_r), (kb_e, kb_r)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # a large regularization does change the projected mode
    _, uv_p, _, _ = _gradients(scene, weights, PROJECTED)
    _, uv_p2, _, _ = _gradients(
        scene, weights, EquilibriumOptions(hessian="projected", regularization=1e-2, **TIGHT)
    )
    assert float((uv_p2 - uv_p).norm()) > 1e-3 * float(uv_p.norm())
    uv0 = scene[0].vert_uv.to(DT)
    direction = torch.sin(3.0 * torch.arange(uv0.numel(), dtype=DT)).reshape(uv0.shape)
    eps = 1e-6
    plus, _, _, _ = _gradients(scene, weights, EXACT, rest_uv=uv0 + eps * direction)
    minus, _, _, _ = _gradients(scene, weights, EXACT, rest_uv=uv0 - eps * direction)
    fd = (plus - minus) / (2 * eps)
    assert float((uv_e * direction).sum()) == pytest.approx(fd, rel=1e-4)


def test_options_are_validated():
    with pytest.raises(ValueError, match="hessian"):
        EquilibriumOptions(hessian="bogus")
    with pytest.raises(ValueError, match="regularization"):
        EquilibriumOptions(regularization=-1)
    with pytest.raises(ValueError, match="regularization"):
        EquilibriumOptions(hessian="projected", regularization=float("nan"))
    assert EquilibriumOptions(hessian="projected", regularization=0.0).regularization == 0.0
