"""Inverse toy problems through the differentiable drape (equilibrium adjoint): from a target drape,
gradient-based optimisation (L-BFGS on the gradients of `drape`) recovers (a) a sheet's bending
stiffness, (b) a rectangular panel's width and height, (c) a sphere body's radius through the contacts."""

from __future__ import annotations

import math

import torch

from torch_diffavatar.sim.adjoint import EquilibriumOptions
from torch_diffavatar.sim.differentiable import drape
from torch_diffavatar.sim.forward_drape import DrapeConfig
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig
from torch_diffavatar.sim.state import ClothState
from torch_diffavatar.sim.testing import rectangle_garment

DT = torch.float64
OPTS = EquilibriumOptions(newton_tol=1e-11, solve_tol=1e-10)
FIRST = DrapeConfig(xpbd=XPBDConfig(substeps=8, iterations=4), dt=1 / 30, max_steps=30, min_steps=30)
WARM = DrapeConfig(xpbd=XPBDConfig(substeps=8, iterations=4), dt=1 / 30, max_steps=3, min_steps=3)


def _material(kb=1e-5):
    return ClothMaterial(k_uu=60.0, k_vv=60.0, k_uv=20.0, bend_stiffness=kb, thickness=0.005, friction=0.0)


class _Fit:
    """Minimise the mean squared distance to ``target`` over ``params`` with L-BFGS; warm-started drapes."""

    def __init__(self, forward, target):
        self.forward, self.target, self.state = forward, target, None

    def loss(self, params):
        cfg = FIRST if self.state is None else WARM
        x = self.forward(params, cfg, self.state)
        self.state = ClothState(x.detach(), torch.zeros_like(x))
        return 1e6 * ((x - self.target) ** 2).sum(-1).mean()  # [mm²]

    def run(self, params, iterations=4):
        opt = torch.optim.LBFGS(
            params,
            lr=1.0,
            max_iter=12,
            tolerance_grad=1e-12,
            tolerance_change=1e-16,
            line_search_fn="strong_wolfe",
        )

        def closure():
            opt.zero_grad()
            loss = self.loss(params)
            loss.backward()
            return loss

        for _ in range(iterations):
            loss = opt.step(closure)
            if float(loss.detach()) < 1e-8:
                break
        return float(loss)


def test_recover_bending_stiffness():
    # a sheet clamped along one edge (two pinned rows) droops under gravity: the droop depends on k_b
    n = 6
    g = rectangle_garment(n, n, 0.3, 0.3, origin=(0.0, 0.0, 0.0), axis_u=(1, 0, 0), axis_v=(0, 0, -1))
    pins = torch.arange(2 * n)
    model = ClothModelBuilder(_material()).add_garment(g, pinned=pins).finalize(dtype=DT)
    uv = g.vert_uv.to(DT)

    def forward(params, cfg, state):
        return drape(uv, model, None, _material(kb=params[0].exp()), config=cfg, state=state, options=OPTS)

    true_kb = 2e-5
    with torch.no_grad():
        target = forward([torch.tensor(math.log(true_kb), dtype=DT)], FIRST, None)
    log_kb = torch.tensor(math.log(6e-6), dtype=DT, requires_grad=True)
    _Fit(forward, target).run([log_kb])
    assert abs(float(log_kb.exp()) / true_kb - 1) < 0.02


def test_recover_panel_width_and_height():
    # a sheet hanging from its two top corners: its rest width and height set the sag and the length
    n = 5
    g = rectangle_garment(n, n, 0.4, 0.4, origin=(0.0, 0.4, 0.0), axis_u=(1, 0, 0), axis_v=(0, -1, 0))
    model = ClothModelBuilder(_material()).add_garment(g, pinned=torch.tensor([0, n - 1])).finalize(dtype=DT)
    unit = g.vert_uv.to(DT) / 0.4

    def forward(params, cfg, state):
        uv = unit * (0.4 + 0.01 * torch.stack((params[0], params[1])))  # params: offsets [cm]
        return drape(uv, model, None, _material(), config=cfg, state=state, options=OPTS)

    with torch.no_grad():
        target = forward(
            [torch.tensor(3.0, dtype=DT), torch.tensor(-2.0, dtype=DT)], FIRST, None
        )  # 0.43, 0.38
    w = torch.tensor(0.0, dtype=DT, requires_grad=True)
    h = torch.tensor(0.0, dtype=DT, requires_grad=True)
    _Fit(forward, target).run([w, h])
    assert abs(0.01 * float(w) - 0.03) < 2e-3 and abs(0.01 * float(h) + 0.02) < 2e-3


def test_recover_sphere_radius_through_contacts():
    import trimesh

    n = 5
    g = rectangle_garment(n, n, 0.6, 0.6, origin=(-0.3, 0.0, 0.3))
    pins = torch.tensor([0, n - 1, n * (n - 1), n * n - 1])
    model = ClothModelBuilder(_material()).add_garment(g, pinned=pins).finalize(dtype=DT)
    s = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    unit, faces = torch.as_tensor(s.vertices, dtype=DT), torch.as_tensor(s.faces, dtype=torch.int64)
    center = torch.tensor([0.013, -0.21, -0.007], dtype=DT)
    uv = g.vert_uv.to(DT)
    stats = {}

    def forward(params, cfg, state):
        body = center + 0.01 * params[0] * unit  # params: radius [cm]
        return drape(uv, model, body, _material(), body_faces=faces, config=cfg, state=state, options=OPTS,
                     stats=stats)  # fmt: skip

    with torch.no_grad():
        target = forward([torch.tensor(20.0, dtype=DT)], FIRST, None)
    assert stats["active_contacts"] > 0
    r = torch.tensor(18.0, dtype=DT, requires_grad=True)
    _Fit(forward, target).run([r])
    assert stats["active_contacts"] > 0
    assert abs(0.01 * float(r) - 0.20) < 2e-3
