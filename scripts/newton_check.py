#!/usr/bin/env python
"""Cross-simulator check: our exported assets draped by NVIDIA Newton's XPBD cloth solver.

    PYTHONPATH=. python scripts/newton_check.py /tmp/demo_assets            # our Python (torch)
    PYTHONPATH=. python scripts/newton_check.py ASSETS --frames 120 --json

Two halves in one file. **Our side** (run with our interpreter) reads the folder with `load_assets`
and writes plain arrays (``.npz``) of what another simulator needs from the asset format alone: the
panel meshes with their 2D rest coordinates (rest.obj ``vt``), the seam vertex pairs (seams.json), the
material (material.json, SI) and the body (body.obj). It then runs this same file under Newton's
interpreter (``--newton-python``, default /tmp/newton_venv/bin/python, which has no torch) with
``--newton-side DIR``, which imports only numpy, warp and newton, builds the cloth and drapes it, and
writes the final positions back. Our side then measures the result with our own tools: penetration
(cloth vertices behind the body surface, `sim.forward_drape.penetration_diagnostics`), the surface Chamfer
distance to our drape (draped.obj) and the seam gaps.

The Newton model, built from the exported files only:

* particles = the rest.obj vertices (one per panel vertex, seams not merged), masses from
  ``areal_density`` [kg/m²] × the rest triangle areas (Newton computes them from the flat (u, v, 0)
  rest shape), raised to at least ``--min-mass`` (0.3) of the median particle mass, starting at our
  drape (draped.obj vertex of each rest vertex), at rest. The floor: at acute panel corners the lumped
  masses fall to ~3 % of the median (the T-shirt template at 2 cm), and the lightest particle sets the
  Jacobi XPBD's stability limit ``ke·dt²/m``; the T-shirt blew up at every setting without it, and with
  it 34 of its 2,818 particles are raised (+0.14 % of the total mass);
* stretch: Newton's XPBD has no triangle (StVK) constraint, so one distance constraint per panel
  mesh edge with rest length from the pattern, at ``--spring-ke`` N/m (its Jacobi XPBD diverges for
  ``ke·dt²/m`` above ~0.4, notes/warp-newton.md, so it cannot reach our k_uu ≈ 2·10⁴ N/m membrane);
* seams: zero-rest-length distance constraints between the seams.json ``stitch_pairs`` (same ke);
* bending: Newton's dihedral constraints at ``edge_ke`` = our ``bend_stiffness`` [N·m] × the mean of
  our per-edge weights ``3|e|²/(A1+A2)`` (Newton has one stiffness per edge, no area weighting);
* body: body.obj as a static mesh shape, friction ``friction``, contact radius ``thickness`` [m];
* gravity −9.81 m/s² along +Y's opposite (the asset frame is Y up), 60 frames/s, ``--substeps``.

If a run blows up (non-finite, a vertex faster than 50 m/s or an edge stretched beyond 100 %) or
does not come to rest (a vertex faster than 1 m/s at the end), the ``--fallback`` settings
(substeps:spring_ke) are tried in order and every run is reported.

Prints one JSON line (``--json``) or a short summary: per run the stability (finite, max speed at the
end [m/s], mean/max edge strain against the pattern), penetration fraction, max seam gap [m], and the
distance to our drape (surface Chamfer [m], mean/max per-vertex displacement [m]).
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

# ----------------------------------------------------------------------------------------------------
# Newton side: numpy + warp + newton only (runs in /tmp/newton_venv, which has no torch)
# ----------------------------------------------------------------------------------------------------


def _unique_edges(faces: np.ndarray) -> np.ndarray:
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def newton_side(work: Path) -> None:
    """Drape ``work/scene.npz`` with Newton's XPBD; write ``work/newton_out.npz`` and ``newton.json``."""
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # keep stdout free of Warp's banner
    import newton

    d = np.load(work / "scene.npz")
    cfg = json.loads((work / "scene.json").read_text())
    rest, init, tri = d["rest"], d["init"], d["tri"].astype(np.int32)
    stitches, body_v, body_f = d["stitches"], d["body_verts"], d["body_faces"].astype(np.int32)
    mat = cfg["material"]
    edges = _unique_edges(tri)
    rest_len = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)

    builder = newton.ModelBuilder(up_axis=newton.Axis.Y)  # gravity -9.81 m/s² along -Y
    builder.add_cloth_mesh(
        pos=wp.vec3(0.0, 0.0, 0.0),
        rot=wp.quat_identity(),
        scale=1.0,
        vel=wp.vec3(0.0, 0.0, 0.0),
        vertices=[wp.vec3(*p) for p in rest],  # the flat pattern: rest data of triangles / edges / masses
        indices=tri.flatten().tolist(),
        density=mat["areal_density"],
        edge_ke=cfg["edge_ke"],
        edge_kd=0.0,
        particle_radius=mat["thickness"],
    )
    ke = cfg["spring_ke"]
    for i, j in edges:
        builder.add_spring(int(i), int(j), ke, 0.0, control=0.0)
    first_stitch = (
        builder.spring_count if hasattr(builder, "spring_count") else len(builder.spring_indices) // 2
    )
    for i, j in stitches:
        builder.add_spring(int(i), int(j), ke, 0.0, control=0.0)
    builder.add_shape_mesh(
        body=-1,
        mesh=newton.Mesh(body_v.astype(np.float32), body_f.flatten(), compute_inertia=False),
        cfg=newton.ModelBuilder.ShapeConfig(mu=mat["friction"], ke=1.0e4, kd=1.0e-2),
    )
    model = builder.finalize(device="cpu")
    model.soft_contact_ke, model.soft_contact_kd, model.soft_contact_mu = 1.0e4, 1.0e-2, mat["friction"]
    if cfg.get("min_mass", 0.0) > 0.0:
        # the lightest particles (tiny corner triangles) set XPBD's stability limit ke·dt²/m
        mass = model.particle_mass.numpy()
        mass = np.maximum(mass, cfg["min_mass"] * float(np.median(mass[mass > 0])))
        model.particle_mass.assign(mass)
        model.particle_inv_mass.assign(1.0 / mass)
    model.particle_grid = None  # no particle-particle "self-contact" between neighbouring vertices
    model.particle_max_radius = 0.0
    # seams are zero-length: the builder took their rest lengths from the (apart) pattern positions
    spring_rest = model.spring_rest_length.numpy()
    spring_rest[first_stitch:] = 0.0
    model.spring_rest_length.assign(spring_rest)

    solver = newton.solvers.SolverXPBD(model, iterations=1)
    pipeline = newton.CollisionPipeline(model, soft_contact_gap=0.05)
    contacts = pipeline.contacts()
    control = model.control()
    s0, s1 = model.state(), model.state()
    s0.particle_q.assign(init.astype(np.float32))
    s1.particle_q.assign(init.astype(np.float32))
    substeps, frames = cfg["substeps"], cfg["frames"]
    dt = 1.0 / 60.0 / substeps
    speeds = []
    t0 = time.perf_counter()
    for _ in range(frames):
        pipeline.collide(s0, contacts)  # once per frame (5 cm band), as in the anchor configuration
        for _k in range(substeps):
            s0.clear_forces()
            solver.step(s0, s1, control, contacts, dt)
            s0, s1 = s1, s0
        qd = s0.particle_qd.numpy()
        speeds.append(float(np.linalg.norm(qd, axis=1).max()) if np.all(np.isfinite(qd)) else float("inf"))
    wall = time.perf_counter() - t0
    q = s0.particle_q.numpy().astype(np.float64)
    finite = bool(np.all(np.isfinite(q)))
    strain = np.linalg.norm(q[edges[:, 0]] - q[edges[:, 1]], axis=1) / rest_len - 1.0 if finite else None
    np.savez(work / "newton_out.npz", q=q)
    (work / "newton.json").write_text(
        json.dumps(
            {
                "particles": int(model.particle_count),
                "triangles": int(model.tri_count),
                "distance_constraints": int(model.spring_count),
                "bending_edges": int(model.edge_count),
                "frames": frames,
                "substeps": substeps,
                "spring_ke": ke,
                "edge_ke": cfg["edge_ke"],
                "wall_s": round(wall, 2),
                "finite": finite,
                "max_speed_end": speeds[-1],
                "max_speed_any": max(speeds),
                "edge_strain_mean": float(strain.mean()) if finite else None,
                "edge_strain_max": float(strain.max()) if finite else None,
            }
        )
    )


# ----------------------------------------------------------------------------------------------------
# Our side (torch): export arrays, run Newton, measure
# ----------------------------------------------------------------------------------------------------


# [m/s] a run whose fastest vertex is faster than this at the end has not come to rest: the next setting
# is tried
SETTLED_SPEED = 1.0


def export_scene(
    assets, work: Path, frames: int, substeps: int, spring_ke: float, min_mass: float = 0.0
) -> dict:
    """Write ``scene.npz`` / ``scene.json`` from the loaded asset folder (see the module docstring)."""
    import torch

    from torch_diffavatar.sim.model import ClothModelBuilder

    g = assets.garment
    rest = np.concatenate([assets.rest_uv.numpy(), np.zeros((g.vert_count, 1))], axis=1)  # (u, v, 0)
    init = assets.draped_x[g.vert_to_sim].numpy()
    model = ClothModelBuilder(assets.material).add_garment(g).finalize(dtype=torch.float64)
    edge_weight = model.rest_data(assets.rest_uv).edge_weight  # 3|e|²/(A1+A2) per interior edge
    mat = {k: float(getattr(assets.material, k)) for k in ("areal_density", "friction", "thickness")}
    mat["bend_stiffness"] = float(assets.material.bend_stiffness)
    cfg = {
        "material": mat,
        "edge_ke": mat["bend_stiffness"] * float(edge_weight.mean()),
        "spring_ke": spring_ke,
        "min_mass": min_mass,
        "substeps": substeps,
        "frames": frames,
    }
    np.savez(
        work / "scene.npz",
        rest=rest,
        init=init,
        tri=g.tri_vertices.numpy(),
        stitches=g.stitch_pairs.numpy().reshape(-1, 2),
        body_verts=assets.body_verts.numpy(),
        body_faces=assets.body_faces.numpy(),
    )
    (work / "scene.json").write_text(json.dumps(cfg))
    return cfg


def measure(assets, q: np.ndarray) -> dict:
    """Penetration, seam gaps and distance to our drape of Newton's final panel-vertex positions (V, 3)."""
    import torch

    from torch_diffavatar.chamfer import sample_surface, surface_chamfer_m
    from torch_diffavatar.sim.forward_drape import penetration_diagnostics

    g = assets.garment
    qt = torch.from_numpy(np.asarray(q, dtype=np.float64))
    pairs = g.stitch_pairs.reshape(-1, 2)
    seam_gap = float((qt[pairs[:, 0]] - qt[pairs[:, 1]]).norm(dim=1).max()) if len(pairs) else 0.0
    # the seam-merged mesh: each draped vertex at the mean of its panel vertices
    count = torch.zeros(g.sim_vert_count, dtype=torch.float64).index_add_(
        0, g.vert_to_sim, torch.ones(len(qt), dtype=torch.float64)
    )
    x = (
        torch.zeros(g.sim_vert_count, 3, dtype=torch.float64).index_add_(0, g.vert_to_sim, qt)
        / count[:, None]
    )
    pen = penetration_diagnostics(x, assets.body_verts, assets.body_faces)
    ours = assets.draped_x
    faces = g.sim_faces
    ours_samples = sample_surface(ours, faces, 20000, generator=torch.Generator().manual_seed(0))
    ch = surface_chamfer_m(x, faces, ours_samples)
    disp = (x - ours).norm(dim=1)
    return x, {
        "penetrating_vertices": pen["penetrating_count"],
        "penetration_fraction": pen["penetrating_count"] / g.sim_vert_count,
        "max_seam_gap_m": seam_gap,
        "chamfer_to_ours_m": ch["symmetric"],
        "chamfer_newton_to_ours_m": ch["mesh_to_points"],
        "chamfer_ours_to_newton_m": ch["points_to_mesh"],
        "displacement_mean_m": float(disp.mean()),
        "displacement_max_m": float(disp.max()),
        "hem_drop_m": float(ours[:, 1].min() - x[:, 1].min()),
    }


def run_newton(args, assets, substeps: int, spring_ke: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        export_scene(assets, work, args.frames, substeps, spring_ke, args.min_mass)
        cmd = [args.newton_python, str(Path(__file__).resolve()), "--newton-side", str(work)]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
        if proc.returncode != 0:
            err = (proc.stderr.strip().splitlines() or ["failed"])[-1]
            return {"substeps": substeps, "spring_ke": spring_ke, "error": err}
        out = json.loads((work / "newton.json").read_text())
        q = np.load(work / "newton_out.npz")["q"]
    blew = (
        not out["finite"]
        or out["max_speed_any"] > 50.0
        or out["edge_strain_max"] is None
        or out["edge_strain_max"] > 1.0
    )
    # finite but still jittering at the end (a template dress at 80 substeps ended at 14 m/s)
    out["status"] = "blew up" if blew else ("unsettled" if out["max_speed_end"] > SETTLED_SPEED else "ok")
    if not blew:  # a blown-up state has nothing to measure
        x, figures = measure(assets, q)
        out.update(figures)
        if args.out:
            from torch_diffavatar.mesh_io import write_garment_obj

            Path(args.out).mkdir(parents=True, exist_ok=True)
            path = Path(args.out) / f"newton_{substeps}sub_ke{spring_ke:g}.obj"
            write_garment_obj(path, assets.garment, sim_positions=x)
            out["obj"] = str(path)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("assets", nargs="?", help="asset folder (asset.json, seams.json, OBJs, material.json)")
    p.add_argument("--newton-side", help=argparse.SUPPRESS)  # internal: run the Newton half on DIR
    p.add_argument("--newton-python", default="/tmp/newton_venv/bin/python")
    p.add_argument("--frames", type=int, default=120, help="frames at 60 frames/s (default 120 = 2 s)")
    p.add_argument("--substeps", type=int, default=40)
    p.add_argument(
        "--spring-ke", type=float, default=100.0, help="Newton edge/seam constraint stiffness [N/m]"
    )
    p.add_argument(
        "--fallback",
        nargs="*",
        default=["80:100", "160:100", "160:50"],
        help="substeps:spring_ke settings tried in order when a run blows up",
    )
    p.add_argument(
        "--min-mass",
        type=float,
        default=0.3,
        help="raise every particle's mass to at least this fraction of the median particle mass "
        "(default 0.3; 0: the lumped masses as exported)",
    )
    p.add_argument("--timeout", type=float, default=900.0, help="[s] per Newton run")
    p.add_argument("--out", help="write Newton's final drape of every run here (OBJ, vt = rest coordinates)")
    p.add_argument("--json", action="store_true", help="print one JSON line")
    args = p.parse_args()
    if args.newton_side:
        newton_side(Path(args.newton_side))
        return 0
    if not args.assets:
        p.error("give the asset folder")
    if not Path(args.newton_python).exists():
        print(f"newton_check: no Newton interpreter at {args.newton_python} (see notes/warp-newton.md)")
        return 2
    import torch

    from torch_diffavatar.assets import load_assets

    torch.set_num_threads(1)
    assets = load_assets(args.assets)
    result = {
        "assets": str(args.assets),
        "garment": assets.garment.garment_type,
        "rest_vertices": assets.garment.vert_count,
        "draped_vertices": assets.garment.sim_vert_count,
        "stitch_pairs": int(assets.garment.stitch_pairs.reshape(-1, 2).shape[0]),
        "runs": [],
    }
    settings = [(args.substeps, args.spring_ke)] + [
        tuple(float(v) for v in s.split(":")) for s in args.fallback
    ]
    for substeps, ke in settings:
        run = run_newton(args, assets, int(substeps), float(ke))
        result["runs"].append(run)
        if run.get("status") == "ok":
            result["accepted"] = run
            break
    if args.json:
        print(json.dumps(result))
    else:
        for run in result["runs"]:
            if "error" in run:
                print(f"{run['substeps']} substeps, ke {run['spring_ke']}: error {run['error']}")
                continue
            line = f"{run['substeps']} substeps, ke {run['spring_ke']:g} N/m: {run['status']}"
            if run["status"] != "blew up":  # a blown-up run was not measured
                line += (
                    f"; end speed {run['max_speed_end']:.3f} m/s, strain mean/max "
                    f"{run['edge_strain_mean']:.4f}/"
                    f"{run['edge_strain_max']:.3f}, penetration {100 * run['penetration_fraction']:.2f} %, "
                    f"seam gap {1e3 * run['max_seam_gap_m']:.1f} mm, Chamfer to ours "
                    f"{1e3 * run['chamfer_to_ours_m']:.2f} mm, displacement mean/max "
                    f"{1e3 * run['displacement_mean_m']:.1f}/{1e3 * run['displacement_max_m']:.1f} mm"
                )
            print(line)
    return 0 if "accepted" in result else 1


if __name__ == "__main__":
    sys.exit(main())
