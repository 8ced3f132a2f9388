#!/usr/bin/env python
"""Gradient benchmark: both adjoints of the differentiable drape on the dress, timed and compared.

Meshes the ``dress`` template at ``--spacing``, wraps it around the default Anny body and sews it (our
sewing phase; ``--cache`` keeps the sewn state in a file for reruns). From the sewn state, with the
default `DrapeConfig` (XPBD 40 substeps × 1 iteration, drape to quasi-equilibrium):

* ``trajectory``: `drape(..., adjoint="trajectory")` — the XPBD drape with checkpoints — and its backward
  (every frame replayed, `sim/adjoint/replay.py`); the peak-RSS increase over the run (the run goes first,
  so the process high-water mark is its own) and the checkpoint memory;
* ``equilibrium``: `drape(..., adjoint="equilibrium")` — the same XPBD drape, then the Newton polish —
  and its backward (one sparse solve);
* the per-group cosine of the two gradients (rest_uv, body vertices, log bending stiffness, k_uu) for the
  objective ``Σ w·x`` with fixed random weights (``--seed``), and with ``--chamfer`` also for a one-sided
  squared Chamfer distance to a fixed target cloud (the sewn dress 1 cm lower, every other vertex).

    PYTHONPATH=. python scripts/bench_grad.py --spacing 0.03 --cache /tmp/dress_0.03.pt

Times are CPU seconds of this process (``time.process_time``; the machine is shared). Prints a JSON line
after each phase (the last one is complete).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import sys
import time

import torch


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cos(a, b) -> float:
    a, b = a.reshape(-1), b.reshape(-1)
    return float((a * b).sum() / (a.norm() * b.norm()).clamp_min(1e-300))


def _ratios(ga, gb) -> dict:
    return {n: round(float(b.norm() / a.norm().clamp_min(1e-300)), 4) for n, a, b in zip(GROUPS, ga, gb)}


GROUPS = ("rest_uv", "body_verts", "log_bend_stiffness", "k_uu")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--template", default="dress")
    p.add_argument("--spacing", type=float, default=0.03, help="mesh spacing [m] (mesher default: 0.015)")
    p.add_argument("--checkpoint-every", type=int, default=8)
    p.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    p.add_argument("--seed", type=int, default=0, help="seed of the objective's random weights")
    p.add_argument("--chamfer", action="store_true", help="also compare under a Chamfer-like objective")
    p.add_argument("--cache", default=None, help="file for the sewn state (written once, then read)")
    args = p.parse_args()
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)

    from torch_diffavatar.body.anny_model import default_body_mesh
    from torch_diffavatar.pattern.library import load_template
    from torch_diffavatar.pattern.mesher import mesh_pattern
    from torch_diffavatar.sim.adjoint import EquilibriumOptions, TrajectoryOptions
    from torch_diffavatar.sim.differentiable import drape
    from torch_diffavatar.sim.drape import DrapeConfig, sew
    from torch_diffavatar.sim.material import ClothMaterial
    from torch_diffavatar.sim.model import ClothModelBuilder
    from torch_diffavatar.sim.placement import place_garment
    from torch_diffavatar.sim.state import ClothState

    body_verts, body_faces = default_body_mesh()
    body_verts = body_verts.to(dtype)
    config = DrapeConfig()
    out = {"template": args.template, "spacing_m": args.spacing, "dtype": args.dtype}
    if args.cache and os.path.exists(args.cache):
        saved = torch.load(args.cache, weights_only=False)
        garment, x_sewn = saved["garment"], saved["x0"].to(dtype)
    else:
        garment = place_garment(
            mesh_pattern(load_template(args.template), spacing=args.spacing), body_verts, body_faces
        )
        sew_model = ClothModelBuilder().add_garment(garment, merge_seams=False).finalize(dtype=dtype)
        t = time.process_time()
        sewn = sew(sew_model, garment.vert_uv.to(dtype), body_verts=body_verts, body_faces=body_faces,
                   config=config)  # fmt: skip
        out["sew_cpu_s"] = round(time.process_time() - t, 1)
        x_sewn = None
    model = ClothModelBuilder().add_garment(garment, merge_seams=True).finalize(dtype=dtype)
    if x_sewn is None:
        x_sewn = model.sim_positions(sewn.x)
        if args.cache:
            torch.save({"garment": garment, "x0": x_sewn, "spacing": args.spacing}, args.cache)
    uv0 = garment.vert_uv.to(dtype)
    out.update(vertices=model.vert_count, triangles=model.tri_count, edges=model.edge_count)
    x0 = ClothState(x_sewn, torch.zeros_like(x_sewn))
    gen = torch.Generator().manual_seed(args.seed)
    weights = torch.randn(model.vert_count, 3, generator=gen, dtype=dtype)
    target = (x_sewn - x_sewn.new_tensor([0.0, 0.01, 0.0]))[::2]

    def objectives(x):
        objs = {"sum_w_x": (x * weights).sum()}
        if args.chamfer:
            objs["chamfer"] = torch.cdist(x, target).min(dim=1).values.pow(2).sum()
        return objs

    def run(adjoint, options):
        leaves = (
            uv0.clone().requires_grad_(True),
            body_verts.clone().requires_grad_(True),
            torch.tensor(math.log(ClothMaterial().bend_stiffness), dtype=dtype, requires_grad=True),
            torch.tensor(float(ClothMaterial().k_uu), dtype=dtype, requires_grad=True),
        )
        uv, bv, lkb, kuu = leaves
        stats = {}
        mat = ClothMaterial(bend_stiffness=lkb.exp(), k_uu=kuu)
        t0 = time.process_time()
        x = drape(uv, model, bv, mat, body_faces=body_faces, state=x0, config=config, adjoint=adjoint,
                  options=options, stats=stats)  # fmt: skip
        fwd = time.process_time() - t0
        grads, bwd = {}, []
        objs = objectives(x)
        for i, (name, phi) in enumerate(objs.items()):
            t1 = time.process_time()
            grads[name] = torch.autograd.grad(phi, leaves, retain_graph=i + 1 < len(objs))
            bwd.append(time.process_time() - t1)
        res = {"forward_cpu_s": round(fwd, 2), "backward_cpu_s": round(bwd[0], 2)}
        res.update({k: v for k, v in stats.items() if not k.endswith("seconds")})
        return x.detach(), grads, res

    print(json.dumps(out), flush=True)
    rss0 = _rss_mb()
    opts = TrajectoryOptions(checkpoint_every=args.checkpoint_every)
    x_tr, g_tr, res = run("trajectory", opts)
    res["peak_rss_increase_mb"] = round(_rss_mb() - rss0, 1)
    ckpts = res["xpbd_steps"] // args.checkpoint_every + 1
    res["checkpoint_mb"] = round(ckpts * 2 * model.vert_count * 3 * x_tr.element_size() / 2**20, 2)
    res["backward_cpu_s_per_frame"] = round(res["backward_cpu_s"] / res["xpbd_steps"], 3)
    out["trajectory"] = res
    print(json.dumps(out), flush=True)
    x_eq, g_eq, res = run("equilibrium", EquilibriumOptions())
    res["backward_over_forward"] = round(res["backward_cpu_s"] / res["forward_cpu_s"], 3)
    out["equilibrium"] = res
    out["end_state_difference_m"] = float((x_eq - x_tr).norm(dim=-1).max())
    out["cosine"] = {
        obj: {name: round(_cos(a, b), 5) for name, a, b in zip(GROUPS, g_tr[obj], g_eq[obj])} for obj in g_tr
    }
    out["gradient_norm_ratio_eq_over_traj"] = {obj: _ratios(g_tr[obj], g_eq[obj]) for obj in g_tr}
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
