"""torch_diffavatar: simulation-ready avatar assets from one noisy scan, through differentiable XPBD cloth.

The public API, all from the top level (each name is imported on first use, so ``import torch_diffavatar``
stays light)::

    import torch_diffavatar as tda

    garment = tda.mesh_pattern(tda.load_template("skirt"), spacing=0.03)  # pattern -> GarmentMesh
    body = tda.BodyModel().stand_on_floor()                               # Anny, feet on y = 0
    verts, faces = body().vertices[0].detach(), body.faces
    garment = tda.place_garment(garment, verts, faces)                    # wrapped around the body
    first = tda.sew_and_drape(garment, body_verts=verts, body_faces=faces)  # forward only: sewn, settled
    cage = tda.ControlCage(garment).float()
    x = tda.drape(cage(), first.model, verts, body_faces=faces,           # differentiable drape
                  state=tda.ClothState(first.x, first.v))
    loss = my_loss(x); loss.backward()                                    # reaches cage.handles

`FitObjective` is the paper's whole loss as a module, for the same loop over `FitParameters`.
World frame everywhere: Y up, metres, feet on y = 0, the body facing +Z.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

# public name -> the module that defines it
_EXPORTS = {
    # patterns
    "GarmentMesh": "torch_diffavatar.pattern",
    "Pattern": "torch_diffavatar.pattern",
    "list_templates": "torch_diffavatar.pattern",
    "load_pattern": "torch_diffavatar.pattern",
    "load_template": "torch_diffavatar.pattern",
    "mesh_pattern": "torch_diffavatar.pattern",
    "save_pattern": "torch_diffavatar.pattern",
    # simulation
    "ClothMaterial": "torch_diffavatar.sim",
    "ClothModel": "torch_diffavatar.sim",
    "ClothModelBuilder": "torch_diffavatar.sim",
    "ClothState": "torch_diffavatar.sim",
    "DrapeConfig": "torch_diffavatar.sim",
    "XPBDConfig": "torch_diffavatar.sim",
    "drape": "torch_diffavatar.sim.differentiable",
    "drape_to_equilibrium": "torch_diffavatar.sim",
    "place_garment": "torch_diffavatar.sim.placement",
    "sew_and_drape": "torch_diffavatar.sim",
    # body and scans
    "BodyModel": "torch_diffavatar.body.model",
    "BodyOutput": "torch_diffavatar.body.model",
    "load_scan": "torch_diffavatar.scan",
    # the fit
    "ControlCage": "torch_diffavatar.cage",
    "FitConfig": "torch_diffavatar.fit_config",
    "FitObjective": "torch_diffavatar.objective",
    "FitParameters": "torch_diffavatar.objective",
    "Fitter": "torch_diffavatar.fit",
    "LossWeights": "torch_diffavatar.fit_config",
    "ObjectiveOutput": "torch_diffavatar.objective",
    "ScanTarget": "torch_diffavatar.objective",
    "load_config": "torch_diffavatar.fit_config",
    # assets
    "load_assets": "torch_diffavatar.assets",
    "write_assets": "torch_diffavatar.assets",
}

__all__ = ["__version__", *sorted(_EXPORTS)]


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'torch_diffavatar' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # once imported, a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
