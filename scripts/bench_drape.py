#!/usr/bin/env python
"""Drape benchmark: our XPBD simulator vs Newton's XPBD cloth solver on the same dress mesh.

For each spacing: mesh the ``dress`` template, wrap it around the default Anny body, sew it (our sewing
phase), then from the *same* sewn state run (a) our drape phase and (b) Newton's XPBD
(/work/shared/bench/newton_drape.py, in its own venv) for the same number of frames (1/60 s) on the same
body, and report time per frame and per substep (wall and process CPU time) and mean / max edge strain
against the 2D pattern's rest lengths, for both. Then (c) our drape runs from the sewn state to
quasi-equilibrium (`drape_to_equilibrium` with `DrapeConfig()` defaults, up to 600 frames): frames and
seconds, converged or not (``--no-equilibrium`` skips it).

    PYTHONPATH=. python scripts/bench_drape.py                          # 2.0, 1.5 and 1.0 cm, 30 frames
    PYTHONPATH=. python scripts/bench_drape.py --spacings 0.02 --frames 20 --no-equilibrium

Newton needs ``python3 -m venv /tmp/newton_venv && /tmp/newton_venv/bin/pip install warp-lang==1.19.0
newton==1.8.0``; without it (``--newton-python`` missing) only our side is measured.

Fairness notes:

* Newton gets the same sewn mesh (positions and faces, seams merged), the same body mesh, the same frame
  count and frame time, and our material's areal density, friction and thickness (``--density``,
  ``--mu``, ``--radius``; ``--newton-own-material`` keeps its script's defaults). Its rest shape is the
  sewn state (its script takes one rest mesh per vertex set, and a merged seam vertex has two pattern
  positions), so its edge strains are measured, like ours, against the pattern; the sewn state's own
  strain is reported as ``sewn_edge_strain_*``.
* Newton's material is its anchor setting: edge distance constraints at ``spring_ke`` N/m + dihedral
  bending, collision detection once per frame (5 cm band), frames replayed from a CPU capture graph.
  Ours is orthotropic StVK triangles + dihedral bending, Gauss–Seidel by colour, contacts per frame.
* Newton is first run with its default 40 substeps × 1 iteration (our budget too). Its Jacobi XPBD
  diverges once ``ke·dt²/m`` is too large (lighter vertices at finer spacing). A run "blew up" when it
  is non-finite, a vertex is faster than 50 m/s or an edge is stretched beyond 100 %; it is "unsettled"
  when its fastest vertex is still faster than ``--newton-max-speed`` (5 m/s; ours end below 0.5 m/s)
  after the frames; else "ok". If the default is not ok, the ``--newton-stable`` settings are tried in
  order and the first ok one is the reference of the ratios (every run tried is reported).
* Newton's frame 1 (kernel load / compile) is excluded from its timings, as in its script; ours times
  every frame, including per-frame collision detection and the speed check.
* CPU time: ours is this process's ``time.process_time`` around the drape; Newton's is its process's
  ``time.process_time`` over the same timed window its script measures in wall time (a small wrapper
  records both clocks at the script's own ``perf_counter`` calls).

Prints one JSON line per spacing (and one per Newton run to stderr).
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

# Runs newton_drape.main() with the script's perf_counter calls also recording process CPU time, then
# prints {"cpu_window_s": ...} for the last (timed-frames) window.
NEWTON_WRAPPER = """\
import importlib.util, json, sys, time
spec = importlib.util.spec_from_file_location("newton_drape", sys.argv[1])
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
marks = []
class _Clock:
    def __getattr__(self, name):
        return getattr(time, name)
    def perf_counter(self):
        marks.append(time.process_time())
        return time.perf_counter()
mod.time = _Clock()
sys.argv = [sys.argv[1]] + sys.argv[2:]
mod.main()
print(json.dumps({"cpu_window_s": marks[-1] - marks[-2], "perf_counter_calls": len(marks)}))
"""


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


def run_newton(args, garment, tmp: Path, substeps: int, spring_ke: float, material) -> dict:
    """One Newton XPBD run on the OBJs in ``tmp``; returns its figures (or an error)."""
    cmd = [args.newton_python, str(tmp / "wrapper.py"), NEWTON_SCRIPT, "--garment", str(tmp / "garment.obj")]
    cmd += ["--rest", str(tmp / "garment.obj"), "--body", str(tmp / "body.obj"), "--solver", "xpbd"]
    cmd += ["--steps", str(args.frames), "--substeps", str(substeps), "--iterations", "1"]
    cmd += ["--spring-ke", str(spring_ke), "--out", str(tmp / "final.obj")]
    if not args.newton_own_material:
        cmd += ["--density", str(float(material.areal_density)), "--mu", str(float(material.friction))]
        cmd += ["--radius", str(float(material.thickness))]
    out = {"substeps": substeps, "iterations": 1, "spring_ke": spring_ke}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.newton_timeout)
    if proc.returncode != 0:
        out["error"] = (proc.stderr.strip().splitlines() or ["failed"])[-1]
        return out
    lines = proc.stdout.strip().splitlines()
    newton, cpu = json.loads(lines[-2]), json.loads(lines[-1])
    n = newton["frames_timed"]
    out.update(
        frames=newton["frames"],
        frames_timed=n,
        frame_ms=round(1e3 * newton["wall_s"] / n, 2),
        substep_ms=round(1e3 * newton["wall_s"] / n / substeps, 3),
        cpu_frame_ms=round(1e3 * cpu["cpu_window_s"] / n, 2),
        cpu_substep_ms=round(1e3 * cpu["cpu_window_s"] / n / substeps, 3),
        warmup_frame_s=newton["warmup_frame_s"],
        max_speed=newton["max_speed"],
        finite=newton["finite"],
    )
    if newton["finite"]:
        mean, mx = pattern_edge_strain(garment, read_obj_verts(tmp / "final.obj"))
        out.update(edge_strain_mean=round(mean, 4), edge_strain_max=round(mx, 4))
    out["mean_speed"] = newton["mean_speed"]
    if not newton["finite"] or newton["max_speed"] > 50.0 or out["edge_strain_max"] > 1.0:
        out["status"] = "blew up"
    elif newton["max_speed"] > args.newton_max_speed:
        out["status"] = "unsettled"
    else:
        out["status"] = "ok"
    print(json.dumps({"spacing_m": args.current_spacing, "newton_run": out}), file=sys.stderr, flush=True)
    return out


def timed(fn):
    """(result, wall s, CPU s) of ``fn()``."""
    w, c = time.perf_counter(), time.process_time()
    result = fn()
    return result, time.perf_counter() - w, time.process_time() - c


def bench_spacing(spacing: float, args, body_verts, body_faces) -> dict:
    from torch_diffavatar.errors import SimulationError
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
    mean, mx = pattern_edge_strain(garment, x0.double().numpy())
    out = {
        "template": args.template,
        "spacing_m": spacing,
        "vertices": garment.sim_vert_count,
        "triangles": garment.tri_count,
        "sew_frames": sewn.steps,
        "sew_s": round(sewn.seconds, 2),
        "sew_max_gap_m": round(sewn.diagnostics["max_stitch_gap_m"], 6),
        "sewn_edge_strain_mean": round(mean, 4),
        "sewn_edge_strain_max": round(mx, 4),
        "frames": args.frames,
    }

    # (a) ours: a fixed frame count from the sewn state
    substeps = config.xpbd.substeps
    fixed = DrapeConfig(max_steps=args.frames, min_steps=args.frames)
    try:
        run, wall, cpu = timed(
            lambda: drape_to_equilibrium(
                model, rest_uv, body_verts=bv, body_faces=bf, state=model.initial_state(x0), config=fixed
            )
        )
    except SimulationError as exc:
        out["ours"] = {"error": str(exc)}
    else:
        mean, mx = pattern_edge_strain(garment, run.x.double().numpy())
        out["ours"] = {
            "substeps": substeps,
            "iterations": config.xpbd.iterations,
            "frame_ms": round(1e3 * wall / run.steps, 2),
            "substep_ms": round(1e3 * wall / run.steps / substeps, 3),
            "cpu_frame_ms": round(1e3 * cpu / run.steps, 2),
            "cpu_substep_ms": round(1e3 * cpu / run.steps / substeps, 3),
            "max_speed": round(run.max_speed, 4),
            "edge_strain_mean": round(mean, 4),
            "edge_strain_max": round(mx, 4),
            "penetrating": run.diagnostics.get("penetrating_count"),
        }

    # (b) Newton's XPBD on the same sewn mesh, body and frame count
    if args.newton_python and Path(args.newton_python).exists():
        args.current_spacing = spacing
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            (tmp / "wrapper.py").write_text(NEWTON_WRAPPER)
            write_obj(tmp / "garment.obj", x0.double().numpy(), garment.sim_faces.numpy())
            write_obj(tmp / "body.obj", body_verts.numpy(), body_faces.numpy())
            material = model.material
            default = run_newton(args, garment, tmp, 40, 100.0, material)
            out["newton_default"] = default
            if default.get("status") != "ok":
                for setting in args.newton_stable:
                    sub, ke = setting.split(":")
                    stable = run_newton(args, garment, tmp, int(sub), float(ke), material)
                    out.setdefault("newton_tried", []).append(stable)
                    if stable.get("status") == "ok":
                        out["newton_stable"] = stable
                        break

    # ratio ours / Newton per substep and per frame (against the setting that did not blow up)
    ref = out.get("newton_stable") or out.get("newton_default")
    if ref and "substep_ms" in out["ours"] and ref.get("status") == "ok":
        for key in ("substep_ms", "cpu_substep_ms", "frame_ms", "cpu_frame_ms"):
            out[f"ratio_ours_newton_{key}"] = round(out["ours"][key] / ref[key], 3)

    # (c) ours: time to equilibrium from the sewn state
    if args.equilibrium:
        try:
            eq, wall, cpu = timed(
                lambda: drape_to_equilibrium(
                    model, rest_uv, body_verts=bv, body_faces=bf, state=model.initial_state(x0), config=config
                )
            )
        except SimulationError as exc:
            out["equilibrium"] = {"error": str(exc)}
        else:
            mean, mx = pattern_edge_strain(garment, eq.x.double().numpy())
            out["equilibrium"] = {
                "frames": eq.steps,
                "max_frames": config.max_steps,
                "speed_tol": config.speed_tol,
                "wall_s": round(wall, 2),
                "cpu_s": round(cpu, 2),
                "converged": eq.converged,
                "final_max_speed": round(eq.max_speed, 4),
                "edge_strain_mean": round(mean, 4),
                "edge_strain_max": round(mx, 4),
                "penetrating": eq.diagnostics.get("penetrating_count"),
            }
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--template", default="dress")
    p.add_argument("--spacings", type=float, nargs="+", default=[0.02, 0.015, 0.01], help="[m]")
    p.add_argument("--frames", type=int, default=30, help="frames simulated on both sides (1/60 s each)")
    p.add_argument(
        "--equilibrium",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also drape ours from the sewn state to quasi-equilibrium",
    )
    p.add_argument("--newton-python", default="/tmp/newton_venv/bin/python")
    p.add_argument(
        "--newton-stable",
        nargs="*",
        default=["80:100", "80:50", "160:50", "160:25"],
        help="substeps:spring_ke settings tried in order when Newton's default (40:100) is not 'ok'",
    )
    p.add_argument(
        "--newton-max-speed",
        type=float,
        default=5.0,
        help="a Newton run whose fastest vertex is faster than this at the end is 'unsettled' [m/s]",
    )
    p.add_argument(
        "--newton-own-material",
        action="store_true",
        help="give Newton its script's density / friction / radius (0.2 kg/m², 0.3, 5 mm), not ours",
    )
    p.add_argument("--newton-timeout", type=float, default=900.0, help="[s]")
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
