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

Agreement check (issue #4, "the two adjoints agree on a converged dress drape"). The options below set up
the comparison; ``--horizons`` makes the trajectory adjoint run exactly N frames (one run per N, each
from the same start state) so that its growth with the horizon shows:

* ``--friction``, ``--stiffness-scale`` (on k_uu, k_vv, k_uv), ``--substeps``, ``--iterations``,
  ``--speed-tol``, ``--min-steps``, ``--max-steps``, ``--velocity-scale``
  (`DrapeConfig.drape_velocity_scale`): the drape's material and XPBD settings;
* ``--presettle P``: P frames of XPBD (no grad) from the sewn state first; both modes start there;
* ``--trajectory-start polished``: the trajectory adjoint starts from the equilibrium mode's
  Newton-polished state (the minimiser of U, v = 0) instead of the start state.

``--converged`` is the setting in which both adjoints differentiate the same map — the drape's rest state
is both XPBD's fixed point and the minimiser of U, and XPBD's frame map contracts to it:

* friction 0: the equilibrium adjoint differentiates the minimiser of the potential U, and friction is not
  in U (with friction, any tangentially held state is an XPBD fixed point; measured with friction 0.4 the
  trajectory gradient stays bounded over the horizon but points elsewhere: cosines 0.02–0.8);
* stretch/shear stiffness × 0.015 (k_uu = 300 N/m): with the default cotton (2·10⁴ N/m) the XPBD rest state
  is not the minimiser of U — U's forces there are 10²–10⁴ vertex weights (4 iterations or 160 substeps lower
  them only 3–7×), the Newton polish cycles its active set without converging and moves the state 2–3 cm,
  and XPBD started from the polished state walks 3 cm away;
* 4 iterations per substep (``--iterations``; 40 substeps): XPBD's fixed point is not the minimiser of U
  either — one Gauss–Seidel sweep per substep does not solve the substep's coupled system — and the
  trajectory adjoint differentiates that fixed point. Its distance to the minimiser on the soft 0.03 m
  dress (XPBD run 96 frames from the polished state): 40 × 2 0.71 mm, 40 × 4 0.19, 80 × 1 0.78, 80 × 2
  0.19, 20 × 4 1.29, 10 × 8 2.67 mm. Substeps matter as much as iterations (a smaller substep makes the
  inertia term dominate, so each sweep converges further); the replay's cost grows with substeps ×
  iterations;
* velocity factor 0.7 per frame (instead of 0.97). Damping does not move a fixed point, but the frictionless
  drape at 0.97 used to vibrate at 0.1–0.2 m/s around a fixed mean state and the trajectory gradient then
  grew exponentially with the horizon (×64 from 8 to 32 frames). The source is in the contact detection:
  a vertex whose closest body point lies on a body-mesh edge is equally close to both faces of that edge,
  the query picks one by rounding, and their planes differ at the vertex (median 0.09 mm, up to 2.6 mm):
  at 0.03 m ~55 contacts switched plane every frame (98 % between the two faces of an edge), and with the
  contact set frozen the same drape comes to rest (2·10⁻⁴ m/s after 180 frames at 0.97). The fix (faces
  sharing the closest edge/vertex: take the farthest plane, so the plane distance is continuous) is a
  change of `collision.detect_contacts` (session 13; on main since 093b113). The 0.03 m figures below were
  measured with it. With it the 0.97 drape decays (1.2 mm/s after 180 frames) and at 0.7 the presettle
  ends at 0.7 mm/s (without it 1.8 cm/s).
  A residual 2-cycle (two vertices in a concave crease of the shoulder alternating between two face planes,
  0.05 mm) remains, a limit of one contact per vertex;
* 300 presettle frames, then the equilibrium drape (to quasi-equilibrium, Newton polish); the trajectory
  adjoint starts from the polished minimiser (v = 0) and runs N frames (``--horizons``, default 72): its
  gradient Σₖ Jᵏ b converges with N to the implicit one (I − J)⁻¹ b of XPBD's fixed point;
* the equilibrium adjoint's contacts are unilateral (session 14, `EquilibriumOptions.contact_release`): an
  active contact is released once its quadratic pulls its vertex onto the body with more than 10⁻³ of the
  vertex's weight. Before, a fixed 1e-7 m slack let a 1e4 N/m contact pull with 1e-3 N (about one vertex
  weight at 3 cm); at 0.03 m 11 of the 227 active contacts held the cloth with up to 0.76 vertex weights
  where XPBD's fixed point lifts it 2–190 µm off. A per-contact split of the body-gradient difference
  (the cotangents of each contact's point and normal, chained to the body vertices) put 32 % (Σ w·x) /
  58 % (Chamfer) of it on those contacts and most of the rest on their neighbours, which carry the load
  instead in XPBD (the top 10 cloth vertices: 87 % / 81 %); tie contacts (closest point on an edge or
  vertex) carried 0.5 % / 9 %, and no contact had a different face in the two. Not the cause: the contact
  stiffness (1e4 → 1e7 N/m changes the equilibrium gradient by cosine 1.0000 / 0.99997).

Measured (2026-12-02, cosines rest_uv / body, norm ratios eq / traj):

* 0.05 m, 40 × 2, 48 frames (before the contact fix): Σ w·x 0.9985 / 0.9960 (ratios 1.01 / 1.02),
  Chamfer 0.987 / 0.977; scalars same sign, ratios log k_b 1.24, k_uu 0.91 (Chamfer 0.89, 0.79);
* 0.03 m with the contact fix, 40 × 2, 48 frames: Σ w·x 0.880 / 0.936, Chamfer 0.985 / 0.966 (XPBD's
  fixed point 0.71 mm from the minimiser);
* 0.03 m with the contact fix, 40 × 4 (the preset): 24 frames Σ w·x 0.9915 / 0.914 (ratios 1.05 / 1.08,
  log k_b 1.52, k_uu 1.05), Chamfer 0.982 / 0.929; 48 frames Σ w·x 0.9984 / 0.970 (ratios 0.997 / 1.03,
  log k_b 1.13, k_uu 1.05), Chamfer 0.994 / 0.971 (1.06 / 1.07, 1.04, 0.96). The body group and the
  scalars still converge with the horizon (the trajectory sum is short of its limit: ratios > 1 falling
  towards 1), rest_uv meets "≥ 0.99" under both objectives. CPU: presettle 300 frames 8 s; equilibrium
  forward 4.1 s, backward 0.87 s; trajectory 20 s per frame replayed per objective (the two objectives are
  two backwards: ~32 min at 48 frames).
* its N → ∞ limit (the implicit gradient of XPBD's fixed point: (I − Jᵀ) a = b by GMRES with one frame's
  vector–Jacobian product at the fixed point, 158 products, relative residual 1e-6; a helper script of
  session 13), Σ w·x: rest_uv 0.9996 / body 0.985 (ratios 1.000 / 0.98), log k_b ratio 0.999, k_uu 1.15;
  Chamfer 0.997 / 0.990 (1.00 / 0.98), log k_b 0.988, k_uu 1.03 (GMRES residual 3e-6).
  So log k_b differs at 48 frames only because the horizon is short (slow global modes: 1.52 at 24, 1.13
  at 48, 1.00 in the limit), while k_uu (1.15) and part of the body group (0.985) differ in the limit:
  XPBD's fixed point, 0.19 mm from the minimiser, has its own sensitivity to the stretch stiffness (the
  body group's part was the equilibrium adjoint's adhesive contacts, next item).
* 0.03 m with the contact fix and the unilateral release (session 14), 40 × 4: the polish now moves the
  XPBD state 0.15 mm (216 active contacts, each pushing with ≥ 0.027 vertex weights; force residual 8e-8 N),
  and XPBD started there stays put (8.8e-6 m/s after 48 frames, frame residual 1.7e-7 m; it was 7e-4 m/s
  and 9e-6 m from the old minimiser). 48 frames (this script): Σ w·x 0.9986 / 0.985 (ratios 0.997 / 1.045,
  log k_b 1.13, k_uu 0.985), Chamfer 0.9970 / 0.981 (1.066 / 1.095, 1.05, 0.91). The N → ∞ limit: Σ w·x
  0.9998 / **0.9994**, Chamfer 0.9996 / **0.9995**; k_uu ratio 1.09 / 0.98, log k_b 0.997 / 0.999
  (GMRES at XPBD's state 48 frames from the old minimiser). The horizon sums (the N-frame Neumann sums
  of the frame map's VJP at XPBD's fixed point, ad hoc script; at 48 frames they reproduce this script's
  cosines to 5 digits), rest_uv / body:
  Σ w·x 72 frames 0.9990 / **0.9933**, 96 0.9993 / 0.9963, 144 0.9996 / 0.9986; Chamfer 72 frames
  0.9987 / **0.9928**, 96 0.9993 / 0.9969. Hence the preset's 72 frames (CPU: trajectory backward
  19.3 s per frame and objective, 46 min for the two objectives at 72 frames; equilibrium forward 6.4 s,
  backward 0.76 s). This script at 72 frames (the preset, 2026-12-02 05:23–06:16 UTC): Σ w·x 0.9990 /
  0.9933 (ratios 0.988 / 1.02, log k_b 1.04, k_uu 1.02), Chamfer 0.9987 / 0.9928 (1.02 / 1.05, 1.006,
  0.93): every group ≥ 0.99.

    PYTHONPATH=. python scripts/bench_grad.py --spacing 0.03 --cache /tmp/dress_0.03.pt --converged --chamfer
"""

from __future__ import annotations

import argparse
import dataclasses
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
    p.add_argument("--friction", type=float, default=None, help="cloth-body friction (default 0.4)")
    p.add_argument("--stiffness-scale", type=float, default=1.0, help="factor on k_uu, k_vv, k_uv")
    p.add_argument("--substeps", type=int, default=None, help="XPBD substeps of the drape")
    p.add_argument("--iterations", type=int, default=None, help="XPBD iterations per substep")
    p.add_argument("--speed-tol", type=float, default=None, help="quasi-equilibrium speed [m/s]")
    p.add_argument("--min-steps", type=int, default=None)
    p.add_argument("--max-steps", type=int, default=None)
    p.add_argument("--velocity-scale", type=float, default=None, help="velocity factor per drape frame")
    p.add_argument("--presettle", type=int, default=0, help="XPBD frames (no grad) before the drape")
    p.add_argument("--horizons", default=None, help="comma-separated fixed trajectory lengths [frames]")
    p.add_argument("--trajectory-start", default="start", choices=["start", "polished"])
    p.add_argument("--converged", action="store_true", help="the agreement setting (see the docstring)")
    args = p.parse_args()
    if args.converged:
        args.friction, args.stiffness_scale, args.presettle = 0.0, 0.015, max(args.presettle, 300)
        args.velocity_scale = 0.7 if args.velocity_scale is None else args.velocity_scale
        args.iterations = args.iterations or 4
        args.trajectory_start, args.horizons = "polished", args.horizons or "72"
    horizons = [int(n) for n in args.horizons.split(",")] if args.horizons else [None]
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)

    from torch_diffavatar.body.anny_model import default_body_mesh
    from torch_diffavatar.fit_checkpoint import safe_load
    from torch_diffavatar.pattern.library import load_template
    from torch_diffavatar.pattern.mesher import mesh_pattern
    from torch_diffavatar.sim.adjoint import EquilibriumOptions, TrajectoryOptions
    from torch_diffavatar.sim.differentiable import drape
    from torch_diffavatar.sim.forward_drape import DrapeConfig, drape_to_equilibrium, sew
    from torch_diffavatar.sim.material import ClothMaterial
    from torch_diffavatar.sim.model import ClothModelBuilder
    from torch_diffavatar.sim.placement import place_garment
    from torch_diffavatar.sim.state import ClothState

    body_verts, body_faces = default_body_mesh()
    body_verts = body_verts.to(dtype)
    config = DrapeConfig()
    base = ClothMaterial()
    mat_kw = {"friction": base.friction if args.friction is None else args.friction}
    mat_kw.update({k: getattr(base, k) * args.stiffness_scale for k in ("k_uu", "k_vv", "k_uv")})
    out = {"template": args.template, "spacing_m": args.spacing, "dtype": args.dtype}
    if args.cache and os.path.exists(args.cache):
        saved = safe_load(args.cache)  # tensors and our plain data classes only: a cache runs no code
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
    xpbd = dataclasses.replace(
        config.xpbd,
        substeps=args.substeps or config.xpbd.substeps,
        iterations=args.iterations or config.xpbd.iterations,
    )
    config = dataclasses.replace(
        config,
        xpbd=xpbd,
        **{
            k: getattr(args, k)
            for k in ("speed_tol", "min_steps", "max_steps")
            if getattr(args, k) is not None
        },
    )
    if args.velocity_scale is not None:
        config = dataclasses.replace(config, drape_velocity_scale=args.velocity_scale)
    out.update(material=mat_kw, substeps=xpbd.substeps, iterations=xpbd.iterations)
    out.update(speed_tol=config.speed_tol, velocity_scale=config.drape_velocity_scale)
    x0 = ClothState(x_sewn, torch.zeros_like(x_sewn))
    if args.presettle:
        t = time.process_time()
        pre = drape_to_equilibrium(
            model, uv0, body_verts=body_verts, body_faces=body_faces, material=ClothMaterial(**mat_kw),
            state=x0, config=dataclasses.replace(config, min_steps=args.presettle, max_steps=args.presettle),
        )  # fmt: skip
        x0 = ClothState(pre.x, torch.zeros_like(pre.x))
        out["presettle"] = {"frames": args.presettle, "cpu_s": round(time.process_time() - t, 1),
                            "max_speed": round(pre.max_speed, 5)}  # fmt: skip
    gen = torch.Generator().manual_seed(args.seed)
    weights = torch.randn(model.vert_count, 3, generator=gen, dtype=dtype)
    target = (x_sewn - x_sewn.new_tensor([0.0, 0.01, 0.0]))[::2]

    def objectives(x):
        objs = {"sum_w_x": (x * weights).sum()}
        if args.chamfer:
            objs["chamfer"] = torch.cdist(x, target).min(dim=1).values.pow(2).sum()
        return objs

    def run(adjoint, options, state=x0, frames=None):
        leaves = (
            uv0.clone().requires_grad_(True),
            body_verts.clone().requires_grad_(True),
            torch.tensor(math.log(base.bend_stiffness), dtype=dtype, requires_grad=True),
            torch.tensor(float(mat_kw["k_uu"]), dtype=dtype, requires_grad=True),
        )
        uv, bv, lkb, kuu = leaves
        stats = {}
        mat = ClothMaterial(**dict(mat_kw, bend_stiffness=lkb.exp(), k_uu=kuu))
        cfg = config if frames is None else dataclasses.replace(config, min_steps=frames, max_steps=frames)
        t0 = time.process_time()
        x = drape(uv, model, bv, mat, body_faces=body_faces, state=state, config=cfg, adjoint=adjoint,
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

    def run_trajectory(start, frames):
        x_tr, g_tr, res = run("trajectory", opts, start, frames)
        ckpts = res["xpbd_steps"] // args.checkpoint_every + 1
        res["checkpoint_mb"] = round(ckpts * 2 * model.vert_count * 3 * x_tr.element_size() / 2**20, 2)
        res["backward_cpu_s_per_frame"] = round(res["backward_cpu_s"] / res["xpbd_steps"], 3)
        res["end_moved_from_start_m"] = round(float((x_tr - start.x).norm(dim=-1).max()), 6)
        return x_tr, g_tr, res

    def compare(x_tr, g_tr, x_eq, g_eq):
        return {
            "end_state_difference_m": float((x_eq - x_tr).norm(dim=-1).max()),
            "cosine": {
                obj: {name: round(_cos(a, b), 5) for name, a, b in zip(GROUPS, g_tr[obj], g_eq[obj])}
                for obj in g_tr
            },
            "gradient_norm_ratio_eq_over_traj": {obj: _ratios(g_tr[obj], g_eq[obj]) for obj in g_tr},
        }

    polished = args.trajectory_start == "polished"
    if not polished and horizons == [None]:  # the benchmark: trajectory first (its own RSS high-water mark)
        x_tr, g_tr, res = run_trajectory(x0, None)
        res["peak_rss_increase_mb"] = round(_rss_mb() - rss0, 1)
        out["trajectory"] = res
        print(json.dumps(out), flush=True)
    x_eq, g_eq, res = run("equilibrium", EquilibriumOptions())
    res["backward_over_forward"] = round(res["backward_cpu_s"] / res["forward_cpu_s"], 3)
    out["equilibrium"] = res
    if not polished and horizons == [None]:
        out.update(compare(x_tr, g_tr, x_eq, g_eq))
        print(json.dumps(out), flush=True)
        return 0
    print(json.dumps(out), flush=True)
    start = ClothState(x_eq, torch.zeros_like(x_eq)) if polished else x0
    out["trajectory_start"] = args.trajectory_start
    out["horizons"] = {}
    for n in horizons:
        x_tr, g_tr, res = run_trajectory(start, n)
        out["horizons"][str(res["xpbd_steps"])] = dict(trajectory=res, **compare(x_tr, g_tr, x_eq, g_eq))
        print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
