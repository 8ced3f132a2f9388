#!/usr/bin/env python
"""Drape benchmark: our XPBD simulator vs Newton's XPBD cloth solver on the same dress mesh.

For each spacing: mesh the ``dress`` template, wrap it around the default Anny body, sew it (our sewing
phase), then from the *same* sewn state run (a) our drape phase and (b) Newton's XPBD
(/work/shared/bench/newton_drape.py, in its own venv) for the same number of frames on the same body,
and report time per frame and per substep, and mean / max edge strain against the 2D pattern's rest
lengths. With ``--equilibrium`` our drape runs to quasi-equilibrium and the time to equilibrium is
reported too.

    PYTHONPATH=. python scripts/bench_drape.py --spacings 0.02 0.015 0.01 --frames 30
    PYTHONPATH=. python scripts/bench_drape.py --spacings 0.02 --equilibrium

Newton needs ``python3 -m venv /tmp/newton_venv && /tmp/newton_venv/bin/pip install warp-lang==1.19.0
newton==1.8.0``; without it (``--newton-python`` missing) only our side is measured. Newton's
rest shape is the sewn state (its script takes one rest mesh with the garment's vertices; the seams of
our sewn mesh carry two rest shapes), so its strains are measured, like ours, against the pattern.
Prints one JSON line per spacing; timings are wall time on whatever else the machine is doing.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

NEWTON_SCRIPT = "/work/shared/bench/newton_drape.py"


def pattern_edge_strain(garment, x: np.ndarray) -> tuple[float, float]:
    """Mean and max of (length / rest length − 1) over the edges of the sewn mesh.

    Rest lengths come from the panel vertices' 2D rest coordinates (averaged when an edge's two
    triangles lie in different panels, as along seams).
    """
    tri_p = garment.tri_vertices.numpy()
    tri_s = garment.sim_faces.numpy()
    uv = garment.vert_uv.numpy()
    sim_e = np.concatenate([tri_s[:, [0, 1]], tri_s[:, [1, 2]], tri_s[:, [2, 0]]])
    pan_e = np.concatenate([tri_p[:, [0, 1]], tri_p[:, [1, 2]], tri_p[:, [2, 0]]])
    rest = np.linalg.norm(uv[pan_e[:, 0]] - uv[pan_e[:, 1]], axis=1)
    key = np.sort(sim_e, axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    rest_u = np.bincount(inv, weights=rest) / np.bincount(inv)
    length = np.linalg.norm(x[uniq[:, 0]] - x[uniq[:, 1]], axis=1)
    strain = length / rest_u - 1.0
    return float(strain.mean()), float(strain.max())


def write_obj(path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    with open(path, "w") as fh:
        fh.writelines(f"v {a:.9g} {b:.9g} {c:.9g}\n" for a, b, c in verts)
        fh.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)


def read_obj_verts(path: Path) -> np.ndarray:
    with open(path) as fh:
        return np.array([[float(t) for t in line.split()[1:4]] for line in fh if line.startswith("v ")])


def bench_spacing(spacing: float, args, body_verts, body_faces) -> dict:
    from torch_diffavatar.pattern.library import load_template
    from torch_diffavatar.pattern.mesher import mesh_pattern
    from torch_diffavatar.sim.drape import DrapeConfig, drape_to_equilibrium, sew
    from torch_diffavatar.sim.model import ClothModelBuilder
    from torch_diffavatar.sim.placement import place_garment

    garment = place_garment(
        mesh_pattern(load_template(args.template), spacing=spacing), body_verts, body_faces
    )
    bv, bf = body_verts.to(torch.float32), body_faces
    config = DrapeConfig()
    sew_model = ClothModelBuilder().add_garment(garment, merge_seams=False).finalize(dtype=torch.float32)
    model = ClothModelBuilder().add_garment(garment, merge_seams=True).finalize(dtype=torch.float32)
    rest_uv = garment.vert_uv.to(torch.float32)
    sewn = sew(sew_model, rest_uv, body_verts=bv, body_faces=bf, config=config)
    x0 = model.sim_positions(sewn.x)
    out = {
        "template": args.template,
        "spacing_m": spacing,
        "vertices": garment.sim_vert_count,
        "triangles": garment.tri_count,
        "sew_frames": sewn.steps,
        "sew_s": round(sewn.seconds, 2),
        "sew_max_gap_m": round(sewn.diagnostics["max_stitch_gap_m"], 6),
    }
    # (a) ours: fixed frame count from the sewn state
    fixed = DrapeConfig(max_steps=args.frames, min_steps=args.frames)
    run = drape_to_equilibrium(
        model, rest_uv, body_verts=bv, body_faces=bf, state=model.initial_state(x0), config=fixed
    )
    substeps = config.xpbd.substeps
    out.update(
        ours_frames=run.steps,
        ours_substeps_per_frame=substeps,
        ours_iterations=config.xpbd.iterations,
        ours_frame_ms=round(1e3 * run.seconds / run.steps, 2),
        ours_substep_ms=round(1e3 * run.seconds / run.steps / substeps, 3),
    )
    x_ours = run.x.double().numpy()
    if args.equilibrium:
        eq = drape_to_equilibrium(
            model, rest_uv, body_verts=bv, body_faces=bf, state=model.initial_state(x0), config=config
        )
        x_ours = eq.x.double().numpy()
        out.update(
            ours_equilibrium_frames=eq.steps,
            ours_equilibrium_s=round(eq.seconds, 2),
            ours_converged=eq.converged,
            ours_final_max_speed=round(eq.max_speed, 4),
        )
    mean, mx = pattern_edge_strain(garment, x_ours)
    out.update(ours_edge_strain_mean=round(mean, 4), ours_edge_strain_max=round(mx, 4))
    # (b) Newton's XPBD on the same sewn mesh, body and frame count
    if args.newton_python and Path(args.newton_python).exists():
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            faces = garment.sim_faces.numpy()
            x0n = x0.double().numpy()
            write_obj(tmp / "garment.obj", x0n, faces)
            write_obj(tmp / "rest.obj", x0n, faces)
            write_obj(tmp / "body.obj", body_verts.numpy(), body_faces.numpy())
            cmd = [args.newton_python, NEWTON_SCRIPT, "--garment", str(tmp / "garment.obj")]
            cmd += ["--rest", str(tmp / "rest.obj"), "--body", str(tmp / "body.obj"), "--solver", "xpbd"]
            cmd += ["--steps", str(args.frames), "--out", str(tmp / "final.obj")]
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.newton_timeout)
            if proc.returncode != 0:
                out["newton_error"] = proc.stderr.strip().splitlines()[-1:] or ["failed"]
            else:
                newton = json.loads(proc.stdout.strip().splitlines()[-1])
                out["newton"] = newton
                mean, mx = pattern_edge_strain(garment, read_obj_verts(tmp / "final.obj"))
                out.update(newton_edge_strain_mean=round(mean, 4), newton_edge_strain_max=round(mx, 4))
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--template", default="dress")
    p.add_argument("--spacings", type=float, nargs="+", default=[0.02, 0.015, 0.01], help="[m]")
    p.add_argument("--frames", type=int, default=30, help="frames timed on both sides (1/60 s each)")
    p.add_argument("--equilibrium", action="store_true", help="also drape ours to quasi-equilibrium")
    p.add_argument("--newton-python", default="/tmp/newton_venv/bin/python")
    p.add_argument("--newton-timeout", type=float, default=600.0, help="[s]")
    args = p.parse_args()
    torch.set_num_threads(1)
    from torch_diffavatar.body.anny_model import default_body_mesh

    body_verts, body_faces = default_body_mesh()
    for spacing in args.spacings:
        t = time.perf_counter()
        result = bench_spacing(spacing, args, body_verts, body_faces)
        result["total_s"] = round(time.perf_counter() - t, 1)
        print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
