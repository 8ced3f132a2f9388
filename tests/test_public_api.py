"""What a pipeline author writes: template -> body -> placement -> drape -> their own loss -> a torch
optimizer, with top-level imports only."""

from __future__ import annotations

import pytest
import torch

pytestmark = pytest.mark.anny


def test_every_public_name_imports():
    import torch_diffavatar

    for name in torch_diffavatar.__all__:
        assert getattr(torch_diffavatar, name) is not None
    assert set(torch_diffavatar.__all__) <= set(dir(torch_diffavatar))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        torch_diffavatar.nope  # noqa: B018


@pytest.mark.slow
def test_a_new_user_s_fit_loop_needs_only_top_level_imports(anny_model):
    from torch_diffavatar import (
        BodyModel,
        ClothMaterial,
        ClothState,
        ControlCage,
        drape,
        load_template,
        mesh_pattern,
        place_garment,
        sew_and_drape,
    )

    body = BodyModel(anny_model, dtype=torch.float32).stand_on_floor()
    with torch.no_grad():
        out = body()
    verts, faces = out.vertices[0], out.faces
    garment = place_garment(mesh_pattern(load_template("skirt"), spacing=0.05), verts, faces)
    material = ClothMaterial(bend_stiffness=5e-6)
    first = sew_and_drape(garment, body_verts=verts, body_faces=faces, material=material)
    hem = next(loop.vertices for loop in garment.boundary_loops if loop.name == "hem")
    target = float(first.x[hem, 1].mean()) + 0.02  # the user's own goal: the hem 2 cm higher

    cage = ControlCage(garment).float()
    optimizer = torch.optim.Adam(cage.parameters(), lr=2e-3)
    state, losses = ClothState(first.x, first.v), []
    for _ in range(3):
        x = drape(cage(), first.model, verts, material, body_faces=faces, state=state)
        loss = (x[hem, 1].mean() - target) ** 2
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
        state = ClothState(x.detach(), torch.zeros_like(x))
    assert cage.handles.grad is not None and torch.isfinite(cage.handles.grad).all()
    assert losses[-1] < losses[0]  # the hem rose toward the goal
