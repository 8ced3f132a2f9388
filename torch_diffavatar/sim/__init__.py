"""The XPBD cloth simulator (paper §3.2): model / state / solver, body collision, drapes.

Typical use::

    model = ClothModelBuilder(medium_cotton()).add_garment(garment_mesh).finalize(dtype=torch.float32)
    rest = model.rest_data(garment_mesh.vert_uv.float())
    solver, state = XPBDSolver(model, XPBDConfig(substeps=10, iterations=2)), model.initial_state()
    state = solver.step(state, rest, 1 / 60, body_verts=verts, body_faces=faces)

or `drape_to_equilibrium` / `sew_and_drape` for whole drapes. Kernels: `sim.ops` (C++ or reference).
"""

from torch_diffavatar.sim.coloring import Coloring, greedy_coloring
from torch_diffavatar.sim.constraints import RestData
from torch_diffavatar.sim.drape import DrapeConfig, DrapeResult, drape_to_equilibrium, sew, sew_and_drape
from torch_diffavatar.sim.material import ClothMaterial, medium_cotton
from torch_diffavatar.sim.model import ClothModel, ClothModelBuilder
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
    "drape_to_equilibrium",
    "greedy_coloring",
    "medium_cotton",
    "sew",
    "sew_and_drape",
]
