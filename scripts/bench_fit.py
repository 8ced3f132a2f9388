#!/usr/bin/env python
"""Fit benchmark: seconds per iteration of the fit loop on the dress (the demo scan), by mesh spacing.

For each ``--spacings`` value: the demo's set-up (body fit, garment points and openings of the bundled
scan; run once, cached) with the ``dress`` template meshed at that spacing, then `Fitter` with
``configs/dress.yaml`` for ``--iters`` iterations. Reported per spacing: garment vertices, the first
(sew and) drape, and the median / mean seconds per iteration, wall and CPU (this process), with the
adjoint's solve statistics. Iteration = one warm-started drape + loss + backward (the adjoint) + the
Adam step with its guards.

    PYTHONPATH=. python scripts/bench_fit.py --spacings 0.03 0.02 0.015 --iters 8

Prints one JSON line per spacing. One intra-op thread (measured faster on the 2-core machine), or
``--threads N`` for the iterations.
``--profile PREFIX`` runs the timed iterations under cProfile (CPU clock; slower, so compare its figures
with each other only), writes ``PREFIX.<spacing>.prof`` and prints the CPU seconds per iteration by part.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import statistics
import sys
import time
from dataclasses import replace

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spacings", type=float, nargs="+", default=[0.03, 0.02, 0.015])
    parser.add_argument("--iters", type=int, default=8)
    parser.add_argument("--adjoint", default=None, help="override the config's adjoint")
    parser.add_argument("--profile", default=None, metavar="PREFIX", help="cProfile the iterations")
    parser.add_argument(
        "--reference",
        type=int,
        default=0,
        metavar="FRAMES",
        help="after each iteration, drape its parameters on from where its drape ended for FRAMES more "
        "frames (no prediction, no settle test) and report how far the cloth still moved: how far from "
        "rest the iteration's drape stopped",
    )
    parser.add_argument(
        "--velocity-scale",
        type=float,
        default=None,
        help="the fit's drape damping (FitConfig.drape_velocity_scale; default: the dress config's)",
    )
    parser.add_argument(
        "--settle-outliers",
        type=float,
        default=None,
        help="fraction of the vertices the settle test lets move (FitConfig.drape_settle_outliers)",
    )
    parser.add_argument(
        "--contact-bounce",
        type=float,
        default=None,
        help="the fit's drapes' contact bounce (FitConfig.drape_contact_bounce)",
    )
    parser.add_argument(
        "--valley-contacts",
        action="store_true",
        help="second contacts in the body's valleys (FitConfig.drape_valley_contacts)",
    )
    parser.add_argument(
        "--no-floor", action="store_true", help="drapes without the floor (FitConfig.drape_floor false)"
    )
    parser.add_argument(
        "--per-iteration", action="store_true", help="print each iteration's frames, gap and CPU seconds"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch intra-op threads during the iterations (the drapes' too)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)  # the set-up: Anny's body fit is fastest on one thread

    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.commands.demo import DEMO_SCAN
    from torch_diffavatar.fit import Fitter, load_config
    from torch_diffavatar.fit_setup import match_boundaries, prepare
    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.sim.material import ClothMaterial
    from torch_diffavatar.sim.placement import place_garment

    anny = load_anny(dtype=torch.float32)
    base = load_config(garment="dress")
    if args.adjoint:
        base = replace(base, adjoint=args.adjoint)
    if args.velocity_scale is not None:
        base = replace(base, drape_velocity_scale=args.velocity_scale)
    if args.settle_outliers is not None:
        base = replace(base, drape_settle_outliers=args.settle_outliers)
    if args.contact_bounce is not None:
        base = replace(base, drape_contact_bounce=args.contact_bounce)
    if args.valley_contacts:
        base = replace(base, drape_valley_contacts=True)
    if args.no_floor:
        base = replace(base, drape_floor=False)
    t0 = time.perf_counter()
    setup = prepare(DEMO_SCAN, base, anny_model=anny)
    setup_s = time.perf_counter() - t0
    target = setup["target"]
    for spacing in args.spacings:
        config = replace(base, spacing=spacing, iterations=args.iters)
        body = BodyModel(anny_model=anny)
        body.load_parameters_dict(setup["body_params"])
        with torch.no_grad():
            body_verts = body().vertices[0].double()
        garment = place_garment(mesh_pattern(load_template("dress"), spacing=spacing), body_verts, body.faces)
        # the scan's openings were found once; only their names are matched to this mesh's loops
        scan_loops = {name: pts.numpy() for name, pts in target.boundaries.items()}
        target_s = replace(target, boundaries=match_boundaries(garment, scan_loops))
        material = ClothMaterial(bend_stiffness=config.initial_bend_stiffness)
        fitter = Fitter(garment, target_s, config, body=body, material=material, progress=False)
        t1 = time.perf_counter()
        start = fitter._first_state()
        first_s = time.perf_counter() - t1
        ev = fitter.evaluate(start)
        wall, cpu, stats = [], [], []
        profiler = cProfile.Profile(time.process_time) if args.profile else None  # CPU seconds
        if profiler:
            profiler.enable()
        torch.set_num_threads(args.threads)
        for _ in range(args.iters):
            w0, c0 = time.perf_counter(), time.process_time()
            ev, start, _ = fitter.step(ev, start)
            fitter.iteration += 1
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
            stats.append({k: v for k, v in ev.stats.items() if isinstance(v, int | float | str | bool)})
            if args.reference:
                stats[-1].update(_reference_gap(fitter, ev, start, args.reference))
        torch.set_num_threads(1)
        if profiler:
            profiler.disable()
            path = f"{args.profile}.{spacing}.prof"
            profiler.dump_stats(path)
            _print_breakdown(pstats.Stats(path), args.iters, spacing)
        last = stats[-1]
        if args.per_iteration:
            for i, st in enumerate(stats):
                gap = st.get("reference_gap_mean_mm")
                gap = "" if gap is None else f", gap {gap:.3f} mm mean, {st['reference_gap_max_mm']:.2f} max"
                print(f"# iteration {i + 1}: {st['xpbd_steps']} frames, {cpu[i]:.3f} CPU s{gap}", flush=True)
        print(
            json.dumps(
                {
                    "spacing_m": spacing,
                    "vertices": garment.sim_vert_count,
                    "faces": garment.tri_count,
                    "adjoint": config.adjoint,
                    "iterations": args.iters,
                    "threads": args.threads,
                    "setup_s": round(setup_s, 2),
                    "first_drape_s": round(first_s, 2),
                    "s_per_iter_median": round(statistics.median(wall), 3),
                    "s_per_iter_mean": round(sum(wall) / len(wall), 3),
                    "cpu_s_per_iter_median": round(statistics.median(cpu), 3),
                    "rejected_steps": fitter.rejected_steps,
                    "xpbd_frames_per_iter_mean": round(statistics.mean(st["xpbd_steps"] for st in stats), 1),
                    **_gap_summary(stats),
                    "adjoint_failures": fitter.adjoint_failures,
                    "last_iteration_stats": last,  # scalars only, as every entry of ``stats``
                }
            ),
            flush=True,
        )


def _reference_gap(fitter, ev, start, frames: int) -> dict:
    """Distance [mm] of the iteration's drape ``ev.x`` from where ``frames`` more frames of the same
    parameters take it (``start``: the next iteration's start, the drape's end at rest), without the
    prediction and without the settle test."""
    from torch_diffavatar.fit_config import drape_config
    from torch_diffavatar.sim.forward_drape import drape_to_equilibrium
    from torch_diffavatar.sim.state import ClothState

    objective = fitter.objective
    config = replace(drape_config(fitter.config), min_steps=frames, max_steps=frames)
    with torch.no_grad():
        ref = drape_to_equilibrium(
            objective.cloth_model,
            ev.rest_uv.detach(),
            body_verts=None if ev.body_verts is None else ev.body_verts.detach(),
            body_faces=None if ev.body_verts is None else objective.body_faces,
            material=objective.material_at(
                ev.bend_stiffness.detach(), None if ev.stretch is None else ev.stretch.detach()
            ),
            state=ClothState(start.x, start.v),
            config=config,
            attach_height=objective.attach_height(
                None if ev.waist_shift is None else ev.waist_shift.detach()
            ),
        )
        gap = (ev.x.detach() - ref.x).norm(dim=-1) * 1000.0
    return {"reference_gap_mean_mm": float(gap.mean()), "reference_gap_max_mm": float(gap.max())}


def _gap_summary(stats: list[dict]) -> dict:
    if "reference_gap_mean_mm" not in stats[0]:
        return {}
    means = [st["reference_gap_mean_mm"] for st in stats]
    return {
        "reference_gap_mean_mm": round(statistics.mean(means), 3),
        "reference_gap_mean_mm_worst": round(max(means), 3),
        "reference_gap_max_mm_worst": round(max(st["reference_gap_max_mm"] for st in stats), 3),
    }


# Parts of one iteration, by the function that does them (cumulative time, so the parts overlap where
# one calls another: "adjoint backward" contains the Hessians, the assembly and the solve).
PARTS = {
    "whole iteration (Fitter.step)": "fit.py:.*\\(step\\)",
    "evaluate (drape + losses)": "fit.py:.*\\(evaluate\\)",
    "  drape (warm-started XPBD)": "drape.py:.*\\(drape_to_equilibrium\\)",
    "    XPBD substeps (C++)": "ops.py:.*\\(xpbd_substeps_\\)",
    "    contact detection (closest point)": "collision.py:.*\\(detect_contacts\\)",
    "adjoint backward": "equilibrium.py:.*\\(equilibrium_backward\\)",
    "  element Hessians": "energy.py:.*\\((hessian_blocks|hessian_elements)\\)",
    "    bending (C++)": "ops.py:.*\\(bend_hessians\\)",
    "    membrane (C++)": "ops.py:.*\\(stretch_hessians\\)",
    "  CSR assembly": "energy.py:.*\\((assemble|assemble_csr)\\)",
    "  pattern build (first use)": "energy.py:.*\\(_build_pattern\\)",
    "  sparse solve": "linsolve.py:.*\\(solve_symmetric\\)",
    "rest-term proximal step (L-BFGS)": "fit.py:.*\\(rest_prox\\)",
}


def _print_breakdown(st: pstats.Stats, iters: int, spacing: float) -> None:
    import re

    print(f"# cProfile breakdown at spacing {spacing} (s per iteration, cumulative):", file=sys.stderr)
    for label, pattern in PARTS.items():
        rx = re.compile(pattern)
        total = sum(v[3] for k, v in st.stats.items() if rx.search(f"{k[0]}:{k[1]}({k[2]})"))
        print(f"#   {label:40s} {total / iters:7.3f}", file=sys.stderr)


if __name__ == "__main__":
    main()
