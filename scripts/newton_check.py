#!/usr/bin/env python
"""Cross-simulator check: an exported asset folder draped by NVIDIA Newton's VBD cloth, in-process.

    PYTHONPATH=. python scripts/newton_check.py ASSET_DIR
    PYTHONPATH=. python scripts/newton_check.py ASSET_DIR --seams springs --membrane shear --json --out X.obj

Needs the ``newton`` extra (``pip install -e ".[newton]"``: Newton 1.8, Warp 1.19); without it, one line
says so. The Newton model is built from the exported files alone (`load_assets` +
`assets_newton.read_newton_material`): the material in Newton's units from ``material_newton.json``
(tri_ke / tri_ka, density, friction, radius, bending; docs/ASSETS.md "Material in Newton's units"),
body.obj as a static mesh, and the garment in one of two ways (``--seams``):

* ``welded`` (default): draped.obj's seam-merged triangles, each with its rest shape from rest.obj's
  ``vt``, and the exported per-edge ``edge_ke`` (bending across the seams too);
* ``springs``: rest.obj's unmerged panel meshes (one particle per panel vertex), sewn by zero-length
  springs (``--seam-ke`` N/m) on seams.json's ``stitch_pairs``, bending on the panels' own interior edges
  by the exported rule ``edge_ke = k_b 3|e|/(A1+A2)`` (none across a seam)
  (`assets_newton.unmerged_newton_export`). Newton's own VBD colouring leaves springs out, so the check
  colours the particles itself (`newton_units.vertex_coloring`).

The waist of a skirt or trousers (``held_vertices``) is pinned where our drape has it, the waistband as
long as its pattern makes it. It then settles with `sim_newton.newton_drape` (the machinery of ``make-scan
--simulator newton``, which pins a waist so too) from our drape (draped.obj), at rest: how far Newton's
physics moves our equilibrium. (Not from the panels' 3D placement, rest.obj ``v``: on the merged mesh each
seam vertex would start at the mean of its panel vertices, the triangles along the seams far from their
rest shape, and the settle blew up at frame 1 at 10 and 40 substeps on a 3 cm dress.)

Measured with our tools: penetration (cloth vertices behind their closest body triangle,
`penetration_diagnostics`), the surface Chamfer distance to our drape (`chamfer.surface_chamfer_m`), the
per-vertex displacement, the edge strain against the pattern for both drapes (`sim_newton.tri_edge_strain`),
the strain of the sewn seam edges and, with springs, the seam gaps (distance between stitched panel
vertices; the measures on the merged mesh then take each draped vertex at the mean of its panel
vertices). Wall and CPU time of the settle (Warp's CPU kernels: one core).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torch_diffavatar.errors import InputError


def seam_edge_strain(assets, x: torch.Tensor) -> np.ndarray:
    """(2 Se,) strain [-] of the sewn boundary edges (seams.json ``stitched_edges``, both sides) at ``x``
    (Vs, 3) [m] against their rest lengths in their panels."""
    se = assets.stitched_edges
    if not len(se):
        return np.zeros(0)
    pairs = torch.cat([se[:, :2], se[:, 2:]])  # (2 Se, 2) rest-vertex edges
    sim = assets.garment.vert_to_sim[pairs]
    uv = assets.rest_uv.double()
    length = (x[sim[:, 0]] - x[sim[:, 1]]).norm(dim=1)
    return (length / (uv[pairs[:, 0]] - uv[pairs[:, 1]]).norm(dim=1) - 1.0).numpy()


def measure(assets, export, x: torch.Tensor, samples: int = 20000) -> dict:
    """Newton's drape ``x`` (Vs, 3) [m] against ours (draped.obj): penetration, Chamfer, displacement,
    edge strain (both drapes) and seam-edge strain."""
    from torch_diffavatar.chamfer import sample_surface, surface_chamfer_m
    from torch_diffavatar.sim.forward_drape import penetration_diagnostics
    from torch_diffavatar.sim_newton import strain_summary, tri_edge_strain

    g, ours = assets.garment, assets.draped_x.double()
    faces = g.sim_faces
    pen = penetration_diagnostics(x, assets.body_verts.double(), assets.body_faces)
    ours_samples = sample_surface(ours, faces, samples, generator=torch.Generator().manual_seed(0))
    chamfer = surface_chamfer_m(x, faces, ours_samples)
    disp = (x - ours).norm(dim=1)
    cloth = export.cloth
    seam = seam_edge_strain(assets, x)
    return {
        "penetrating_vertices": int(pen["penetrating_count"]),
        "penetration_fraction": pen["penetrating_count"] / g.sim_vert_count,
        "chamfer_to_ours_m": chamfer["symmetric"],
        "chamfer_newton_to_ours_m": chamfer["mesh_to_points"],
        "chamfer_ours_to_newton_m": chamfer["points_to_mesh"],
        "displacement_mean_m": float(disp.mean()),
        "displacement_max_m": float(disp.max()),
        "lowest_point_drop_m": float(ours[:, 1].min() - x[:, 1].min()),
        "edge_strain": {
            "newton": strain_summary(tri_edge_strain(x, cloth.tri_vertices, cloth.tri_rest_uv)),
            "ours": strain_summary(tri_edge_strain(ours, cloth.tri_vertices, cloth.tri_rest_uv)),
        },
        "seam_edge_strain": strain_summary(seam) if len(seam) else None,
    }


SEAMS = ("welded", "springs")


def _merged(garment, x_panel: torch.Tensor) -> torch.Tensor:
    """(Vs, 3): each draped vertex at the mean of its panel vertices' positions ``x_panel`` (V, 3) [m]."""
    ones = torch.ones(len(x_panel), 1, dtype=x_panel.dtype)
    count = torch.zeros(garment.sim_vert_count, 1, dtype=x_panel.dtype).index_add_(
        0, garment.vert_to_sim, ones
    )
    total = torch.zeros(garment.sim_vert_count, 3, dtype=x_panel.dtype).index_add_(
        0, garment.vert_to_sim, x_panel
    )
    return total / count


def check_assets(
    asset_dir, *, membrane: str | None = None, seams: str = "welded", config=None, samples: int = 20000
) -> dict:
    """Drape the asset folder ``asset_dir`` with Newton (module docstring) and measure it.

    Args:
        asset_dir: a folder written by `assets.write_assets` (with ``material_newton.json``).
        membrane: ``"shear"`` or ``"stretch"``: the membrane conversion
            (`assets_newton.read_newton_material`); None: the export's (``parameters``).
        seams: ``"welded"`` (draped.obj's merged mesh, the exported edges) or ``"springs"`` (the unmerged
            panels sewn by zero-length springs on the stitch pairs, `assets_newton.unmerged_newton_export`).
        config: `sim_newton.NewtonDrapeConfig` (default its own).
        samples: surface samples of our drape for the Chamfer distance.

    Returns:
        JSON-friendly figures; ``"x"``: Newton's (Vs, 3) float64 drape [m] (a tensor, not JSON; with
        springs each draped vertex at the mean of its panel vertices).

    Raises:
        InputError: Newton is not installed, or the folder is not a complete asset.
        SimulationError: the settle blew up.
    """
    from torch_diffavatar import sim_newton as sn
    from torch_diffavatar.assets import load_assets
    from torch_diffavatar.assets_newton import read_newton_material, unmerged_newton_export

    sn.import_newton()  # before any work: the one-line error without it
    if seams not in SEAMS:
        raise InputError(f"unknown seams {seams!r}; use one of {', '.join(SEAMS)}")
    assets = load_assets(asset_dir)
    merged = read_newton_material(assets, membrane)
    export = merged if seams == "welded" else unmerged_newton_export(assets, merged)
    g = assets.garment
    x0 = assets.draped_x.double()
    x0 = x0 if seams == "welded" else x0[g.vert_to_sim]
    held = torch.from_numpy(export.held_vertices)
    targets = x0[held].numpy() if len(held) else None  # the waist where our drape holds it
    cpu0 = time.process_time()
    drape = sn.newton_drape(
        export.cloth, None, x0, assets.body_verts, assets.body_faces, export.material, config,
        attach_vertices=held, attach_targets=targets,
    )  # fmt: skip
    cpu = time.process_time() - cpu0
    x, gaps = drape.x, None
    if seams == "springs":
        pairs = g.stitch_pairs.reshape(-1, 2)
        gaps = (x[pairs[:, 0]] - x[pairs[:, 1]]).norm(dim=1)
        x = _merged(g, x)
    return {
        "assets": str(asset_dir),
        "garment": g.garment_type,
        "draped_vertices": g.sim_vert_count,
        "particles": int(len(drape.x)),
        "triangles": g.tri_count,
        "bending_edges": export.cloth.edge_count,
        "held_vertices": int(len(held)),
        "membrane": export.membrane_keep,
        "seams": seams,
        "newton_material": export.material.summary(),
        "settle": dict(drape.diagnostics(), cpu_seconds=round(cpu, 2)),
        "seam_gap_m": None if gaps is None else {"mean": float(gaps.mean()), "max": float(gaps.max())},
        **measure(assets, merged, x, samples),
        "x": x,
    }


def _summary(r: dict) -> str:
    s, e = r["settle"], r["edge_strain"]
    seam = r["seam_edge_strain"]
    state = "settled" if s["converged"] else "NOT settled"
    seams = (
        "none" if seam is None else f"mean |.| {100 * seam['mean_abs']:.2f} %, max {100 * seam['max']:.1f} %"
    )
    return (
        f"{r['garment']} ({r['draped_vertices']} vertices), Newton VBD from our drape, seams {r['seams']}, "
        f"membrane keeping our {r['membrane']}: "
        f"{state} in {s['frames']} frames, {s['seconds']:.1f} s wall / "
        f"{s['cpu_seconds']:.1f} s CPU; Chamfer to ours {1e3 * r['chamfer_to_ours_m']:.2f} mm, displacement "
        f"mean/max {1e3 * r['displacement_mean_m']:.1f}/{1e3 * r['displacement_max_m']:.1f} mm; "
        f"penetrating {r['penetrating_vertices']} ({100 * r['penetration_fraction']:.2f} %); edge strain "
        f"mean |.| Newton {100 * e['newton']['mean_abs']:.2f} % vs ours {100 * e['ours']['mean_abs']:.2f} % "
        f"(max {100 * e['newton']['max']:.1f} % vs {100 * e['ours']['max']:.1f} %); seam edges "
        + seams
        + (
            ""
            if r["seam_gap_m"] is None
            else f"; seam gap mean/max {1e3 * r['seam_gap_m']['mean']:.2f}/"
            f"{1e3 * r['seam_gap_m']['max']:.2f} mm"
        )
    )


def main(argv=None) -> int:
    from torch_diffavatar.errors import SimulationError
    from torch_diffavatar.sim_newton import NewtonDrapeConfig

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("assets", help="asset folder (asset.json, seams.json, OBJs, material_newton.json)")
    p.add_argument(
        "--membrane",
        choices=("shear", "stretch"),
        help="Newton's membrane conversion: keep our shear or our stretch (default: the export's, stretch)",
    )
    p.add_argument(
        "--seams",
        choices=SEAMS,
        default="welded",
        help="welded: draped.obj's merged mesh (default); springs: the panels sewn by zero-length springs",
    )
    p.add_argument(
        "--seam-ke", type=float, default=1.0e4, help="--seams springs: their stiffness [N/m] (default 1e4)"
    )
    p.add_argument("--max-frames", type=int, default=400, help="frames at most at 60 frames/s (default 400)")
    p.add_argument("--substeps", type=int, default=10, help="VBD steps per frame (default 10)")
    p.add_argument(
        "--iterations",
        type=int,
        default=NewtonDrapeConfig.iterations,
        help=f"VBD iterations per step (default {NewtonDrapeConfig.iterations}: fewer leave the drape "
        "hanging longer than its pattern, sim_newton.NewtonDrapeConfig)",
    )
    p.add_argument("--out", help="write Newton's drape here as OBJ (draped.obj layout, vt = pattern)")
    p.add_argument("--json", action="store_true", help="print one JSON line")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    try:
        config = NewtonDrapeConfig(
            max_frames=args.max_frames,
            min_frames=min(NewtonDrapeConfig.min_frames, args.max_frames),
            substeps=args.substeps,
            iterations=args.iterations,
            seam_ke=args.seam_ke,
        )
    except ValueError as exc:  # a setting out of range: one line, before Newton loads
        print(f"newton_check: {exc}", file=sys.stderr)
        return 2
    try:
        result = check_assets(args.assets, membrane=args.membrane, seams=args.seams, config=config)
    except (InputError, SimulationError) as exc:
        print(f"newton_check: {exc}", file=sys.stderr)
        return 2
    x = result.pop("x")
    if args.out:
        from torch_diffavatar.assets import load_assets
        from torch_diffavatar.mesh_io import write_garment_obj

        write_garment_obj(Path(args.out), load_assets(args.assets).garment, sim_positions=x)
        result["obj"] = str(args.out)
    print(json.dumps(result) if args.json else _summary(result))
    return 0 if result["settle"]["converged"] else 1


if __name__ == "__main__":
    sys.exit(main())
