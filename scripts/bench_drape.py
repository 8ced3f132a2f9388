#!/usr/bin/env python
"""Drape benchmark: our XPBD simulator vs Newton's XPBD cloth solver on the same dress mesh, like for like.

For each spacing: mesh the ``dress`` template, wrap it around the default Anny body, sew it (our sewing
phase), then from the *same* sewn state (seams merged) run (a) our drape phase and (b) Newton's XPBD
(/work/shared/bench/newton_drape.py, in its own venv) for the same number of frames (1/60 s) on the same
body, and report time per frame and per substep (wall and process CPU time) and edge strain, for both.
Then (c) our drape runs from the sewn state to quasi-equilibrium (`drape_to_equilibrium` with
`DrapeConfig()` defaults): frames and seconds, converged or not (``--no-equilibrium`` skips it).

    PYTHONPATH=. python scripts/bench_drape.py                          # 2.0, 1.5 and 1.0 cm, 30 frames
    PYTHONPATH=. python scripts/bench_drape.py --spacings 0.02 --frames 20 --no-equilibrium
    PYTHONPATH=. python scripts/bench_drape.py --newton-rest sewn       # Newton's springs at the sewn lengths

Newton needs ``python3 -m venv /tmp/newton_venv && /tmp/newton_venv/bin/pip install warp-lang==1.19.0
newton==1.8.0``; without it (``--newton-python`` missing) only our side is measured.

**Edge strain** (the one measure, `EdgeRest.stats`, applied to the sewn start state and to both
simulators' final states): over every unique edge of the seam-merged mesh (interior, seam and boundary
edges alike), strain = |x_i − x_j| / l0 − 1, with l0 the edge's length in the 2D pattern (a seam edge's
two pattern lengths, one per panel, averaged). Reported: the signed mean, the mean of |strain|, the
99th and 99.9th percentiles and the maximum (largest stretch); the maximum over interior edges only
(``_max_interior``) and over edges not in a "small" triangle (shortest pattern edge below half the
spacing; ``_max_no_small``), and where the worst edge is.

What is compared:

* **Our settings.** ``ours`` is the `XPBDConfig` default (40 substeps × 1 iteration);
  ``ours_settings`` are the ``--ours`` SUBSTEPS:ITERATIONS settings (default 80:1, 120:1 and 160:1) and, with
  ``--ours-match-newton`` (default), ours at the substep count of Newton's reference setting. Each gets
  its ratios to Newton's reference (``ratio_newton_*``: CPU and wall, per substep and per frame).
* **Same rest state** (``--newton-rest pattern``, the default). Newton's script takes one rest mesh
  per vertex set and a merged seam vertex has two pattern positions, so it is given the sewn state as
  its rest mesh, and then a wrapper overwrites the rest data of the model it builds with ours: spring
  rest lengths = the pattern edge lengths l0 above, particle masses = our lumped masses (pattern area ×
  areal density / 3 per corner), bending rest angles = 0 (flat pattern, as ours). Both simulators
  therefore pull toward the same rest lengths. ``--newton-rest sewn`` keeps the script's rest data
  from the sewn state (its springs then hold the sewn state's strains, up to 9 % at 2 cm).
* Newton gets the same sewn mesh (positions and faces), the same body mesh, the same frame count and
  frame time, and our material's areal density, friction and thickness (``--density``, ``--mu``,
  ``--radius``; ``--newton-own-material`` keeps its script's defaults). Its material is its anchor
  setting: edge distance constraints at ``spring_ke`` N/m + dihedral bending, collision detection once
  per frame (5 cm band), frames replayed from a CPU capture graph. Ours is orthotropic StVK triangles
  + dihedral bending, Gauss–Seidel by colour, contacts detected once per frame.
* Newton is first run with its default 40 substeps × 1 iteration (our default budget too). Its Jacobi
  XPBD diverges once ``ke·dt²/m`` is too large (lighter vertices at finer spacing). A run "blew up"
  when it is non-finite, a vertex is faster than 50 m/s or an edge is stretched beyond 100 %; it is
  "unsettled" when its fastest vertex is still faster than ``--newton-max-speed`` (5 m/s; ours end
  below 0.6 m/s) after the frames; else "ok". If the default is not ok, the ``--newton-stable``
  settings are tried in order and the first ok one is the reference of the ratios (every run tried
  is reported).
* Newton's frame 1 (kernel load / compile) is excluded from its timings, as in its script; ours times
  every frame, including per-frame collision detection and the speed check.
* CPU time: ours is this process's ``time.process_time`` around the drape; Newton's is its process's
  ``time.process_time`` over the same timed window its script measures in wall time (the wrapper
  records both clocks at the script's own ``perf_counter`` calls).

Prints one JSON line per spacing (and one per Newton run to stderr).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

NEWTON_SCRIPT = "/work/shared/bench/newton_drape.py"

# Runs newton_drape.main() with the script's perf_counter calls also recording process CPU time, then
# prints {"cpu_window_s": ...} for the last (timed-frames) window. With BENCH_NEWTON_REST=<npz> set, the
# model its build() returns gets that file's spring rest lengths, particle masses and bending rest angles
# (after checking that its springs are the file's edges, in the same order).
NEWTON_WRAPPER = """\
import importlib.util, json, os, sys, time
import numpy as np
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
rest_file = os.environ.get("BENCH_NEWTON_REST")
if rest_file:
    _build = mod.build
    def build(args, rest, faces, *more, **kw):
        model = _build(args, rest, faces, *more, **kw)
        data = np.load(rest_file)
        springs = model.spring_indices.numpy().reshape(-1, 2)
        if not np.array_equal(np.sort(springs, axis=1), data["edges"]):
            sys.exit("BENCH_NEWTON_REST: the model's springs are not the file's edges")
        model.spring_rest_length.assign(data["rest_length"].astype(np.float32))
        mass = data["mass"].astype(np.float32)
        model.particle_mass.assign(mass)
        inv_mass = np.where(mass > 0, 1.0 / np.maximum(mass, 1e-30), 0.0)
        model.particle_inv_mass.assign(inv_mass.astype(np.float32))
        model.edge_rest_angle.assign(np.zeros(model.edge_count, dtype=np.float32))
        return model
    mod.build = build
sys.argv = [sys.argv[1]] + sys.argv[2:]
mod.main()
print(json.dumps({"cpu_window_s": marks[-1] - marks[-2], "perf_counter_calls": len(marks)}))
"""


class EdgeRest:
    """The unique edges of a garment's sewn (seam-merged) mesh with their 2D pattern rest lengths.

    Attributes:
        edges: (E, 2) int64 sim-vertex ids, each row sorted, rows in lexicographic order (the order of
            newton_drape.py's ``unique_edges``, hence of its springs).
        rest: (E,) rest length [m] from the panel vertices' 2D rest coordinates, averaged over the
            edge's triangles when they lie in different panels (a merged seam edge has one length per
            side; the mesher makes them nearly equal).
        boundary: (E,) bool edges with one triangle (garment openings: hem, neckline, armholes).
        in_small_tri: (E,) bool edges of a triangle whose shortest pattern edge is below
            ``small_frac`` × the mesh spacing (slivers, e.g. where several panels meet).
    """

    def __init__(self, garment, spacing: float, small_frac: float = 0.5):
        tri_p = garment.tri_vertices.numpy()
        tri_s = garment.sim_faces.numpy()
        uv = garment.vert_uv.numpy()
        sim_e = np.concatenate([tri_s[:, [0, 1]], tri_s[:, [1, 2]], tri_s[:, [2, 0]]])
        pan_e = np.concatenate([tri_p[:, [0, 1]], tri_p[:, [1, 2]], tri_p[:, [2, 0]]])
        rest = np.linalg.norm(uv[pan_e[:, 0]] - uv[pan_e[:, 1]], axis=1)
        self.edges, inv = np.unique(np.sort(sim_e, axis=1), axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        count = np.bincount(inv)
        self.rest = np.bincount(inv, weights=rest) / count
        self.boundary = count == 1
        tri_min = rest.reshape(3, -1).min(axis=0)  # (F,) shortest pattern edge of each triangle
        self.small_tri_count = int((tri_min < small_frac * spacing).sum())
        self.small_frac = small_frac
        self.min_pattern_edge = float(rest.min())
        small_half_edge = np.tile(tri_min < small_frac * spacing, 3)
        self.in_small_tri = np.bincount(inv, weights=small_half_edge, minlength=len(count)) > 0

    def strain(self, x: np.ndarray) -> np.ndarray:
        """(E,) signed edge strain ``|x_i − x_j| / rest − 1`` of sim-vertex positions ``x`` (Vs, 3) [m]."""
        return np.linalg.norm(x[self.edges[:, 0]] - x[self.edges[:, 1]], axis=1) / self.rest - 1.0

    def stats(self, x: np.ndarray) -> dict:
        """Edge-strain figures of ``x`` (Vs, 3) [m]: the one measure applied to both simulators.

        ``edge_strain_mean`` is the signed mean, ``_mean_abs`` the mean of |strain|, ``_p99`` / ``_p999``
        / ``_max`` the 99th / 99.9th percentile and the largest (signed, i.e. stretch) over all edges,
        seam and boundary edges included; ``_max_interior`` leaves out boundary edges and
        ``_max_no_small`` the edges of the small triangles; ``worst_edge`` is where the largest is.
        """
        s = self.strain(x)
        k = int(np.argmax(s))
        i, j = self.edges[k]
        return {
            "edge_strain_mean": round(float(s.mean()), 5),
            "edge_strain_mean_abs": round(float(np.abs(s).mean()), 5),
            "edge_strain_p99": round(float(np.percentile(s, 99)), 4),
            "edge_strain_p999": round(float(np.percentile(s, 99.9)), 4),
            "edge_strain_max": round(float(s[k]), 4),
            "edge_strain_max_interior": round(float(s[~self.boundary].max()), 4),
            "edge_strain_max_no_small": round(float(s[~self.in_small_tri].max()), 4),
            "worst_edge": {
                "midpoint_m": [round(float(c), 3) for c in 0.5 * (x[i] + x[j])],
                "rest_mm": round(1e3 * float(self.rest[k]), 1),
                "boundary": bool(self.boundary[k]),
            },
        }


def write_obj(path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    with open(path, "w") as fh:
        fh.writelines(f"v {a:.9g} {b:.9g} {c:.9g}\n" for a, b, c in verts)
        fh.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)


def read_obj_verts(path: Path) -> np.ndarray:
    with open(path) as fh:
        return np.array([[float(t) for t in line.split()[1:4]] for line in fh if line.startswith("v ")])


def run_newton(args, edge_rest: EdgeRest, tmp: Path, substeps: int, spring_ke: float, material) -> dict:
    """One Newton XPBD run on the OBJs in ``tmp``; returns its figures (or an error)."""
    cmd = [args.newton_python, str(tmp / "wrapper.py"), NEWTON_SCRIPT, "--garment", str(tmp / "garment.obj")]
    cmd += ["--rest", str(tmp / "garment.obj"), "--body", str(tmp / "body.obj"), "--solver", "xpbd"]
    cmd += ["--steps", str(args.frames), "--substeps", str(substeps), "--iterations", "1"]
    cmd += ["--spring-ke", str(spring_ke), "--out", str(tmp / "final.obj")]
    if not args.newton_own_material:
        cmd += ["--density", str(float(material.areal_density)), "--mu", str(float(material.friction))]
        cmd += ["--radius", str(float(material.thickness))]
    env = dict(os.environ)
    if args.newton_rest == "pattern":
        env["BENCH_NEWTON_REST"] = str(tmp / "rest.npz")
    out = {"substeps": substeps, "iterations": 1, "spring_ke": spring_ke, "rest": args.newton_rest}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.newton_timeout, env=env)
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
        mean_speed=newton["mean_speed"],
        finite=newton["finite"],
    )
    if newton["finite"]:
        out.update(edge_rest.stats(read_obj_verts(tmp / "final.obj")))
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


def parse_setting(text: str) -> tuple[int, float]:
    """``"SUBSTEPS:X"`` -> (substeps, X)."""
    sub, x = text.split(":")
    return int(sub), float(x)


def bench_spacing(spacing: float, args, body_verts, body_faces) -> dict:
    from torch_diffavatar.errors import SimulationError
    from torch_diffavatar.pattern.library import load_template
    from torch_diffavatar.pattern.mesher import mesh_pattern
    from torch_diffavatar.sim.forward_drape import DrapeConfig, drape_to_equilibrium, sew
    from torch_diffavatar.sim.model import ClothModelBuilder
    from torch_diffavatar.sim.placement import place_garment

    garment = place_garment(
        mesh_pattern(load_template(args.template), spacing=spacing), body_verts, body_faces
    )
    edge_rest = EdgeRest(garment, spacing)
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
        "edges": len(edge_rest.rest),
        "boundary_edges": int(edge_rest.boundary.sum()),
        "min_pattern_edge_mm": round(1e3 * edge_rest.min_pattern_edge, 2),
        "small_triangles": edge_rest.small_tri_count,
        "small_triangle_def": f"shortest pattern edge < {edge_rest.small_frac} x spacing",
        "edges_in_small_triangles": int(edge_rest.in_small_tri.sum()),
        "sew_frames": sewn.steps,
        "sew_s": round(sewn.seconds, 2),
        "sew_max_gap_m": round(sewn.diagnostics["max_stitch_gap_m"], 6),
        "sewn": edge_rest.stats(x0.double().numpy()),
        "frames": args.frames,
    }

    # (a) ours: a fixed frame count from the sewn state, the XPBDConfig default first, then --ours settings
    def run_ours(substeps: int, iterations: int) -> dict:
        xpbd = replace(config.xpbd, substeps=substeps, iterations=iterations)
        fixed = replace(config, xpbd=xpbd, max_steps=args.frames, min_steps=args.frames)
        res = {"substeps": substeps, "iterations": iterations}
        try:
            run, wall, cpu = timed(
                lambda: drape_to_equilibrium(
                    model, rest_uv, body_verts=bv, body_faces=bf, state=model.initial_state(x0), config=fixed
                )
            )
        except SimulationError as exc:
            res["error"] = str(exc)
            return res
        res.update(
            frame_ms=round(1e3 * wall / run.steps, 2),
            substep_ms=round(1e3 * wall / run.steps / substeps, 3),
            cpu_frame_ms=round(1e3 * cpu / run.steps, 2),
            cpu_substep_ms=round(1e3 * cpu / run.steps / substeps, 3),
            max_speed=round(run.max_speed, 4),
            penetrating=run.diagnostics.get("penetrating_count"),
            **edge_rest.stats(run.x.double().numpy()),
        )
        return res

    default_setting = (config.xpbd.substeps, config.xpbd.iterations)
    out["ours"] = run_ours(*default_setting)
    done = {default_setting}
    for text in args.ours:
        sub, it = parse_setting(text)
        if (sub, int(it)) not in done:
            done.add((sub, int(it)))
            out.setdefault("ours_settings", []).append(run_ours(sub, int(it)))

    # (b) Newton's XPBD on the same sewn mesh, body and frame count
    if args.newton_python and Path(args.newton_python).exists():
        args.current_spacing = spacing
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            (tmp / "wrapper.py").write_text(NEWTON_WRAPPER)
            write_obj(tmp / "garment.obj", x0.double().numpy(), garment.sim_faces.numpy())
            write_obj(tmp / "body.obj", body_verts.numpy(), body_faces.numpy())
            mass = model.rest_data(rest_uv).vert_mass.double().numpy()
            np.savez(tmp / "rest.npz", edges=edge_rest.edges, rest_length=edge_rest.rest, mass=mass)
            material = model.material
            default = run_newton(args, edge_rest, tmp, 40, 100.0, material)
            out["newton_default"] = default
            if default.get("status") != "ok":
                for setting in args.newton_stable:
                    sub, ke = parse_setting(setting)
                    stable = run_newton(args, edge_rest, tmp, sub, ke, material)
                    out.setdefault("newton_tried", []).append(stable)
                    if stable.get("status") == "ok":
                        out["newton_stable"] = stable
                        break

    # ours at the substep count of Newton's reference setting (× 1 iteration, as Newton), so that the two
    # also do the same number of substeps per frame
    ref = out.get("newton_stable") or out.get("newton_default")
    if args.ours_match_newton and ref and ref.get("status") == "ok" and (ref["substeps"], 1) not in done:
        done.add((ref["substeps"], 1))
        out.setdefault("ours_settings", []).append(run_ours(ref["substeps"], 1))

    # ratio ours / Newton per substep and per frame (against the setting that did not blow up), for
    # each of our settings
    if ref and ref.get("status") == "ok":
        for res in [out["ours"]] + out.get("ours_settings", []):
            if "substep_ms" in res:
                for key in ("substep_ms", "cpu_substep_ms", "frame_ms", "cpu_frame_ms"):
                    res[f"ratio_newton_{key}"] = round(res[key] / ref[key], 3)
                # issue #3's target: per-substep CPU time no more than Newton's, at mean and max edge
                # strain no worse
                res["meets_target"] = bool(
                    res["cpu_substep_ms"] <= ref["cpu_substep_ms"]
                    and all(res[k] <= ref[k] for k in ("edge_strain_mean_abs", "edge_strain_max"))
                )
        for key in ("substep_ms", "cpu_substep_ms", "frame_ms", "cpu_frame_ms"):
            if f"ratio_newton_{key}" in out["ours"]:
                out[f"ratio_ours_newton_{key}"] = out["ours"][f"ratio_newton_{key}"]

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
            out["equilibrium"] = {
                "frames": eq.steps,
                "max_frames": config.max_steps,
                "speed_tol": config.speed_tol,
                "wall_s": round(wall, 2),
                "cpu_s": round(cpu, 2),
                "converged": eq.converged,
                "final_max_speed": round(eq.max_speed, 4),
                "penetrating": eq.diagnostics.get("penetrating_count"),
                **edge_rest.stats(eq.x.double().numpy()),
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
    p.add_argument(
        "--ours",
        nargs="*",
        default=["80:1", "120:1", "160:1"],
        help="substeps:iterations settings of ours run besides the XPBDConfig default (40:1)",
    )
    p.add_argument(
        "--ours-match-newton",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also run ours at the substep count of Newton's reference setting (x 1 iteration)",
    )
    p.add_argument("--newton-python", default="/tmp/newton_venv/bin/python")
    p.add_argument(
        "--newton-rest",
        choices=["pattern", "sewn"],
        default="pattern",
        help="Newton's spring rest lengths, masses and bending rest angles: the 2D pattern's (like ours) or "
        "its script's, computed from the sewn state",
    )
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
