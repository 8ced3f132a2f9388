#!/usr/bin/env python
"""Gradient benchmark: forward and backward time of the differentiable drape per adjoint on the dress.

Meshes the ``dress`` template at ``--spacing``, wraps it around the default Anny body, sews it (our
sewing phase), then from the sewn state:

* ``equilibrium``: `drape(..., adjoint="equilibrium")` (XPBD to quasi-equilibrium + Newton polish) and
  its backward (one sparse solve) for a loss ``Σ w·x`` with fixed random weights, gradients for rest_uv,
  body vertices, log bending stiffness and k_uu;
* ``trajectory``: ``--frames`` frames of the drape with ``adjoint="trajectory"`` (forward with
  checkpoints), and the backward of a ``--window``-frame trajectory started from the equilibrium; the
  full drape's forward/backward (every frame replayed at that per-frame cost) and checkpoint memory are
  reported as extrapolations to the equilibrium drape's frame count.

    PYTHONPATH=. python scripts/bench_grad.py --spacing 0.02
Prints a JSON line after each phase (the last one is complete). Timings are wall time on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import sys
import time

import torch


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cos(a, b) -> float:
    return float((a * b).sum() / (a.norm() * b.norm()).clamp_min(1e-300))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--template", default="dress")
    p.add_argument("--spacing", type=float, default=0.015, help="mesh spacing [m] (the mesher's default)")
    p.add_argument("--window", type=int, default=2, help="frames of the timed trajectory backward")
    p.add_argument("--checkpoint-every", type=int, default=8)
    p.add_argument("--frames", type=int, default=10, help="frames of the timed trajectory forward")
    p.add_argument("--dtype", default="float64", choices=["float32", "float64"])
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
    garment = place_garment(
        mesh_pattern(load_template(args.template), spacing=args.spacing), body_verts, body_faces
    )
    config = DrapeConfig()
    sew_model = ClothModelBuilder().add_garment(garment, merge_seams=False).finalize(dtype=dtype)
    model = ClothModelBuilder().add_garment(garment, merge_seams=True).finalize(dtype=dtype)
    uv0 = garment.vert_uv.to(dtype)
    t = time.perf_counter()
    sewn = sew(sew_model, uv0, body_verts=body_verts, body_faces=body_faces, config=config)
    out = {
        "template": args.template,
        "spacing_m": args.spacing,
        "dtype": args.dtype,
        "vertices": model.vert_count,
        "triangles": model.tri_count,
        "sew_s": round(time.perf_counter() - t, 1),
    }
    x0 = ClothState(model.sim_positions(sewn.x), torch.zeros(model.vert_count, 3, dtype=dtype))
    weights = torch.sin(torch.arange(model.vert_count * 3, dtype=dtype)).reshape(-1, 3)

    def leaves():
        return (
            uv0.clone().requires_grad_(True),
            body_verts.clone().requires_grad_(True),
            torch.tensor(math.log(5e-6), dtype=dtype, requires_grad=True),
            torch.tensor(2e4, dtype=dtype, requires_grad=True),
        )

    def run(adjoint, options, state, cfg):
        uv, bv, lkb, kuu = leaves()
        stats = {}
        mat = ClothMaterial(bend_stiffness=lkb.exp(), k_uu=kuu)
        t0 = time.perf_counter()
        x = drape(
            uv,
            model,
            bv,
            mat,
            body_faces=body_faces,
            state=state,
            config=cfg,
            adjoint=adjoint,
            options=options,
            stats=stats,
        )
        t1 = time.perf_counter()
        (x * weights).sum().backward()
        t2 = time.perf_counter()
        return x.detach(), (uv.grad, bv.grad, lkb.grad, kuu.grad), t1 - t0, t2 - t1, stats

    print(json.dumps(out), flush=True)
    x_eq, g_eq, fwd, bwd, st = run("equilibrium", EquilibriumOptions(), x0, config)
    out["equilibrium"] = {
        "forward_s": round(fwd, 2),
        "backward_s": round(bwd, 2),
        "backward_over_forward": round(bwd / fwd, 3),
        **{k: v for k, v in st.items() if not k.endswith("seconds")},
    }
    print(json.dumps(out), flush=True)
    rss0 = _rss_mb()
    opts = TrajectoryOptions(checkpoint_every=args.checkpoint_every)
    frames = DrapeConfig(max_steps=args.frames, min_steps=args.frames)
    uv, bv, lkb, kuu = leaves()
    t0 = time.perf_counter()
    with torch.no_grad():
        drape(uv, model, bv, ClothMaterial(bend_stiffness=lkb.exp(), k_uu=kuu), body_faces=body_faces,
              state=x0, config=frames, adjoint="trajectory", options=opts)  # fmt: skip
    per_frame_fwd = (time.perf_counter() - t0) / args.frames
    steps = st["xpbd_steps"]
    ckpt_mb = (steps // args.checkpoint_every + 1) * 2 * model.vert_count * 3 * x_eq.element_size() / 2**20
    window = DrapeConfig(max_steps=args.window, min_steps=args.window)
    _, g_w, _, bwd_w, _ = run("trajectory", opts, ClothState(x_eq, torch.zeros_like(x_eq)), window)
    per_frame = bwd_w / args.window
    out["trajectory"] = {
        "forward_s_per_frame": round(per_frame_fwd, 3),
        "backward_s_per_frame": round(per_frame, 2),
        "drape_frames": steps,
        "forward_s_full_extrapolated": round(per_frame_fwd * steps, 1),
        "backward_s_full_extrapolated": round(per_frame * steps, 1),
        "checkpoint_every": args.checkpoint_every,
        "checkpoint_mb_full_drape": round(ckpt_mb, 2),
        "peak_rss_increase_mb_during_window": round(_rss_mb() - rss0, 1),
    }
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
