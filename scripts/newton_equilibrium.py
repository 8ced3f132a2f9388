#!/usr/bin/env python
"""Is a Newton-made truth an equilibrium of OUR cloth? (docs/BENCHMARKS.md, "Newton's drape is not an
equilibrium of our cloth").

    PYTHONPATH=. python scripts/newton_equilibrium.py SCAN [--frames 300] [--json]

SCAN is a ``diffavatar make-scan ... --simulator newton`` folder. The true pattern is meshed as make-scan
meshed it, the truth's material is read in our units (`truth/material.json`), and the waist vertices of a
waist-held garment are pinned exactly where Newton's drape has them. From Newton's final positions our
simulator then drapes (XPBD, the fit's 40 substeps) with the truth's material and with variants of it, and
our energy is minimised by the equilibrium adjoint's Newton polish; each row says how far our cloth moves
away from Newton's drape (mean / max [mm]) and how much it rises on average [mm]. The forces of our energy
at Newton's drape (membrane, bending, gravity; mean per free vertex [N]) come last.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import torch

from torch_diffavatar.mesh_io import read_obj
from torch_diffavatar.pattern import mesh_pattern
from torch_diffavatar.pattern.garmentcode import load_pattern
from torch_diffavatar.sim import constraints
from torch_diffavatar.sim.adjoint import EquilibriumOptions
from torch_diffavatar.sim.differentiable import drape
from torch_diffavatar.sim.forward_drape import DrapeConfig, drape_to_equilibrium
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig
from torch_diffavatar.sim.state import ClothState

DT = torch.float64


def load_truth(scan: Path):
    """(garment, material, Newton's drape (Vs, 3), body verts, body faces, model with the waist pinned
    where Newton's drape has it)."""
    info = json.loads((scan / "truth" / "truth.json").read_text())
    if info.get("simulator") != "newton":
        raise SystemExit(f"{scan} is not a Newton-made scan (make-scan --simulator newton)")
    garment = mesh_pattern(load_pattern(scan / "truth" / "pattern.json"), spacing=info["spacing_m"])
    material = ClothMaterial(**{k: v for k, v in info["material"].items() if k != "unit"})
    drape_n = read_obj(scan / "truth" / "draped.obj")
    body = read_obj(scan / "truth" / "body.obj")
    x_newton = torch.as_tensor(drape_n.verts, dtype=DT)
    if x_newton.shape[0] != garment.sim_vert_count:
        raise SystemExit(
            f"the truth's drape has {x_newton.shape[0]} vertices, the pattern's mesh {garment.sim_vert_count}"
        )
    at_newton = dataclasses.replace(
        garment, vert_pos=x_newton[garment.vert_to_sim].to(garment.vert_pos.dtype)
    )
    pinned = garment.vert_labels.get("lower_interface")
    model = ClothModelBuilder(material).add_garment(at_newton, pinned=pinned).finalize(dtype=DT)
    bv, bf = torch.as_tensor(body.verts, dtype=DT), torch.as_tensor(body.faces, dtype=torch.int64)
    return garment, material, x_newton, bv, bf, model


def _row(name, x, x_newton, extra=None) -> dict:
    d = (x - x_newton).norm(dim=1)
    row = {"variant": name, "move_mean_mm": 1e3 * float(d.mean()), "move_max_mm": 1e3 * float(d.max())}
    row["rise_mm"] = 1e3 * float((x - x_newton)[:, 1].mean())
    return row | (extra or {})


def variants(material: ClothMaterial) -> dict[str, ClothMaterial]:
    m = material

    def soft(s: float, b: float = 1.0) -> dict:
        return dict(k_uu=m.k_uu * s, k_vv=m.k_vv * s, k_uv=m.k_uv * s, bend_stiffness=m.bend_stiffness * b)

    changes = {"the truth's material": {}, "friction 0": dict(friction=0.0)}
    changes |= {"k_b x0.01": dict(bend_stiffness=m.bend_stiffness * 0.01), "Poisson 0": dict(poisson=0.0)}
    changes |= {f"membrane x{s}": soft(s) for s in (0.3, 0.1, 0.03, 0.01, 0.003)}
    changes |= {"membrane x0.01, k_b x0.3": soft(0.01, 0.3)}
    return {name: dataclasses.replace(m, **kw) for name, kw in changes.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scan", type=Path)
    ap.add_argument("--frames", type=int, default=300, help="our drape's frames at most")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    garment, material, x_newton, bv, bf, model = load_truth(args.scan)
    uv = garment.vert_uv.to(DT)
    start = ClothState(x_newton.clone(), torch.zeros_like(x_newton))
    config = DrapeConfig(xpbd=XPBDConfig(substeps=40), max_steps=args.frames, min_steps=50)
    rows = []
    for name, mat in variants(material).items():
        res = drape_to_equilibrium(
            model, uv, body_verts=bv, body_faces=bf, material=mat, state=start, config=config
        )
        rows.append(_row(name, res.x, x_newton, {"frames": res.steps}))
        print(rows[-1], flush=True)
    stats: dict = {}
    polish = EquilibriumOptions(newton_iterations=60, active_set_rounds=8, hessian="projected")
    one = DrapeConfig(xpbd=XPBDConfig(substeps=40), max_steps=1, min_steps=1)
    x = drape(uv, model, bv, material, body_faces=bf, state=start, config=one, options=polish, stats=stats)
    rows.append(
        _row("our energy minimised", x, x_newton, {"force_residual_N": stats["newton_force_residual"]})
    )
    print(rows[-1], flush=True)
    rest = model.rest_data(uv, material)
    free = ~model.vert_pinned
    gravity = torch.tensor([0.0, -9.81, 0.0], dtype=DT)
    energies = {
        "membrane": lambda y: constraints.stretch_energy(y, model.tri_vertices, rest, material),
        "bending": lambda y: constraints.bend_energy(y, model.edge_quads, rest, material),
        "gravity": lambda y: constraints.gravity_energy(y, rest.vert_mass, gravity),
    }
    forces = {}
    for name, energy in energies.items():
        y = x_newton.clone().requires_grad_(True)
        (f,) = torch.autograd.grad(energy(y), y)
        forces[name] = float(f[free].norm(dim=1).mean())
    print({"force_at_newton_drape_mean_N": forces})
    if args.json:
        print(json.dumps({"scan": str(args.scan), "rows": rows, "forces_mean_N": forces}))


if __name__ == "__main__":
    main()
