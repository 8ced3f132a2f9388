"""The XPBD cloth simulator (paper §3.2): model / state / solver, body collision, drapes.

Typical use::

    model = ClothModelBuilder(medium_cotton()).add_garment(garment_mesh).finalize(dtype=torch.float32)
    rest = model.rest_data(garment_mesh.vert_uv.float())
    solver, state = XPBDSolver(model, XPBDConfig(substeps=10, iterations=2)), model.initial_state()
    state = solver.step(state, rest, 1 / 60, body_verts=verts, body_faces=faces)

or, for whole drapes, `drape_to_equilibrium` / `sew_and_drape` (forward only, `sim.forward_drape`) and
`drape` (differentiable: an autograd function with two adjoints, `sim.differentiable`).
`place_garment` wraps a meshed pattern around a body. Kernels: `sim.ops` (C++ or reference).
"""

from torch_diffavatar.sim.coloring import Coloring, greedy_coloring
from torch_diffavatar.sim.constraints import RestData
from torch_diffavatar.sim.differentiable import drape
from torch_diffavatar.sim.forward_drape import (
    DrapeConfig,
    DrapeResult,
    drape_to_equilibrium,
    sew,
    sew_and_drape,
)
from torch_diffavatar.sim.material import ClothMaterial, medium_cotton
from torch_diffavatar.sim.model import ClothModel, ClothModelBuilder
from torch_diffavatar.sim.placement import place_garment
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver
from torch_diffavatar.sim.state import ClothState

__all__ = [
    "ClothMaterial",
    "ClothModel",
    "ClothModelBuilder",
    "ClothState",
    "Coloring",
    "DrapeConfig",
    "DrapeResult",
    "RestData",
    "XPBDConfig",
    "XPBDSolver",
    "drape",
    "drape_to_equilibrium",
    "greedy_coloring",
    "medium_cotton",
    "place_garment",
    "sew",
    "sew_and_drape",
]
