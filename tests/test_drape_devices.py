"""`drape` beyond one CPU tensor: a batch of rest shapes, and inputs on another device (the simulation runs
on the CPU; results and gradients come back on the caller's device)."""

from __future__ import annotations

import pytest
import torch

from torch_diffavatar.sim.adjoint import TrajectoryOptions
from torch_diffavatar.sim.differentiable import drape
from torch_diffavatar.sim.forward_drape import DrapeConfig
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig
from torch_diffavatar.sim.testing import rectangle_garment

DT = torch.float64
CONFIG = DrapeConfig(min_steps=3, max_steps=3, xpbd=XPBDConfig(substeps=2, iterations=2))
OTHER_DEVICES = [
    d for d, ok in (("cuda", torch.cuda.is_available()), ("mps", torch.backends.mps.is_available())) if ok
]


def _sheet():
    """A 5x5 sheet pinned at two corners, hanging under gravity (no body)."""
    g = rectangle_garment(5, 5, 0.4, 0.4, origin=(-0.2, 0.0, 0.2))
    material = ClothMaterial(k_uu=60.0, k_vv=60.0, k_uv=20.0, bend_stiffness=1e-5, damping=2.0)
    model = ClothModelBuilder(material).add_garment(g, pinned=torch.tensor([0, 4])).finalize(dtype=DT)
    return g, model


def _loss(x):
    return (x[:, 1] ** 2).sum() + x[:, 0].sum()


@pytest.mark.parametrize("adjoint", ["trajectory", "equilibrium"])
def test_a_batch_drapes_each_rest_shape_with_its_own_gradient(adjoint):
    g, model = _sheet()
    uv0 = g.vert_uv.to(DT)
    shapes = torch.stack((uv0, uv0 * 1.03, uv0 * torch.tensor([0.97, 1.0], dtype=DT)))
    batch = shapes.clone().requires_grad_(True)
    x = drape(batch, model, config=CONFIG, adjoint=adjoint)
    assert x.shape == (3, model.vert_count, 3)
    sum(_loss(xk) for xk in x).backward()
    for k in range(3):
        one = shapes[k].clone().requires_grad_(True)
        xk = drape(one, model, config=CONFIG, adjoint=adjoint)
        _loss(xk).backward()
        torch.testing.assert_close(x[k].detach(), xk.detach(), rtol=0, atol=0)
        torch.testing.assert_close(batch.grad[k], one.grad, rtol=1e-12, atol=1e-12)
    assert not torch.equal(x[0], x[1])  # the elements differ: each drape used its own rest shape


def test_a_batch_refuses_what_it_cannot_do():
    g, model = _sheet()
    uv = g.vert_uv.to(DT).expand(2, -1, -1)
    with pytest.raises(ValueError, match="return_trajectory"):
        drape(
            uv, model, config=CONFIG, adjoint="trajectory", options=TrajectoryOptions(return_trajectory=True)
        )
    body = torch.zeros(3, 4, 3, dtype=DT)
    with pytest.raises(ValueError, match="batch 3 but rest_uv has batch 2"):
        drape(uv, model, body, body_faces=torch.zeros(1, 3, dtype=torch.int64), config=CONFIG)


@pytest.mark.skipif(not OTHER_DEVICES, reason="no device besides the CPU here")
@pytest.mark.parametrize("device", OTHER_DEVICES)
@pytest.mark.parametrize("adjoint", ["trajectory", "equilibrium"])
def test_a_drape_on_another_device_equals_the_cpu_one(device, adjoint):
    g, model = _sheet()
    results = {}
    for dev in ("cpu", device):
        uv = g.vert_uv.to(device=dev, dtype=DT).requires_grad_(True)
        x = drape(uv, model, config=CONFIG, adjoint=adjoint)
        assert x.device.type == dev
        _loss(x).backward()
        assert uv.grad.device.type == dev
        results[dev] = (x.detach().cpu(), uv.grad.cpu())
    torch.testing.assert_close(results[device][0], results["cpu"][0], rtol=0, atol=1e-12)
    torch.testing.assert_close(results[device][1], results["cpu"][1], rtol=1e-10, atol=1e-12)
