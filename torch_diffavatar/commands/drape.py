"""`diffavatar drape`: mesh a pattern, wrap it around a body, sew and drape it, report and export.

Measures printed (one JSON object with ``--json``):

* ``vertices`` / ``faces``: sewn (seam-merged) cloth vertices and triangles.
* ``steps`` / ``seconds``: frames (sewing + draping) and wall time of the simulation [s].
* ``max_speed``: largest vertex speed at the end [m/s] (quasi-equilibrium when small).
* ``converged``: the drape met its speed criterion before running out of frames.
* ``penetrating_fraction``: share of cloth vertices inside the body (negative signed distance to the
  body surface, exact closest point).
* ``max_stitch_gap_m``: largest distance [m] between two panel vertices that a seam joins, at the end
  of the sewing phase (afterwards each such pair is one simulated vertex).
* ``inverted_triangles``: draped triangles that collapsed or flipped: 3D area below 1 % of the rest
  area, or a normal pointing against the mean normal of its three corners (area-weighted vertex
  normals of the draped mesh), i.e. a triangle folded over onto its neighbours.
* ``quality_min`` / ``quality_mean``: triangle quality 4√3·A/Σl² of the draped 3D mesh (1 = equilateral).
"""

from __future__ import annotations

import inspect
import sys
from pathlib import Path

import numpy as np
import torch

from torch_diffavatar.commands.out_paths import check_out_files
from torch_diffavatar.errors import InputError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "drape",
        help="sew and drape a sewing pattern (file or template name) on a body",
        description="Mesh a pattern, wrap it around a body, sew and drape it to rest; print measures.",
    )
    p.add_argument("pattern", help="GarmentCode *_specification.json file, or a template name (e.g. dress)")
    p.add_argument(
        "--body",
        default="default",
        help="'default' (Anny, default phenotypes, A-pose) or an OBJ/PLY body in metres, Y up, facing +Z",
    )
    p.add_argument(
        "--spacing", type=float, default=0.015, help="target cloth edge length [m] (default 0.015)"
    )
    p.add_argument(
        "--out", required=True, help="write the draped garment as OBJ (vt = 2D rest coordinates [m])"
    )
    p.add_argument("--png", help="write a front + back picture of the cloth on the body")
    p.add_argument("--max-steps", type=int, default=None, help="frames of the drape phase at most")
    p.add_argument("--sew-steps", type=int, default=None, help="frames of the sewing phase at most")
    p.add_argument(
        "--no-floor",
        action="store_true",
        help="no floor at the body's lowest point (default: a garment longer than the legs piles on it)",
    )
    p.add_argument("--json", action="store_true", help="print the result as one JSON line")
    p.set_defaults(func=run_drape)


def load_body(spec: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The body to drape on, ``"default"`` or a mesh file: verts (Vb, 3) float64 [m], faces (Fb, 3) int64."""
    if spec == "default":
        from torch_diffavatar.body.anny_model import default_body_mesh

        return default_body_mesh()
    path = Path(spec)
    if not path.is_file():
        raise InputError(f"--body {spec}: no such file (give 'default' or an OBJ/PLY mesh)")
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds of errors for unreadable files
        raise InputError(f"--body {spec}: cannot read the mesh ({exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"--body {spec}: the file holds no triangle mesh")
    verts = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float64)
    faces = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.int64)
    height = float(verts[:, 1].max() - verts[:, 1].min())
    if not 0.5 < height < 2.8:
        raise InputError(
            f"--body {spec}: the mesh is {height:.3g} units tall along +Y; expected a standing body in "
            "metres with Y up (convert it first)"
        )
    return verts, faces


def inverted_triangle_mask(x: torch.Tensor, faces: torch.Tensor, rest_area: torch.Tensor) -> torch.Tensor:
    """(F,) bool: triangles collapsed (area < 1 % of rest) or flipped against their corners' mean normal.

    Args:
        x: (Vs, 3) draped positions [m]; faces: (F, 3) int64; rest_area: (F,) rest areas [m²].
    """
    a, b, c = x[faces].unbind(1)
    cross = torch.linalg.cross(b - a, c - a)
    area = 0.5 * cross.norm(dim=1)
    vert_n = torch.zeros_like(x).index_add_(0, faces.reshape(-1), cross.repeat_interleave(3, dim=0))
    corner_n = vert_n[faces].sum(1)
    flipped = (cross * corner_n).sum(1) < 0
    return (area < 0.01 * rest_area) | flipped


def _rest_area(garment) -> torch.Tensor:
    uv = garment.vert_uv[garment.tri_vertices]  # (F, 3, 2)
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).abs()


def _check_args(args) -> None:
    """InputError for a ``--spacing`` that is not a positive length or a frame limit below 1."""
    if not args.spacing > 0:
        raise InputError(f"--spacing must be a positive length in metres, got {args.spacing}")
    for flag in ("max_steps", "sew_steps"):
        value = getattr(args, flag)
        if value is not None and value < 1:
            raise InputError(f"--{flag.replace('_', '-')} must be >= 1, got {value}")


def _drape_config(args):
    """The `DrapeConfig` with ``--max-steps`` / ``--sew-steps`` applied (the sewing ramp no longer than
    the sewing phase), on a floor unless ``--no-floor``."""
    from torch_diffavatar.sim.forward_drape import DrapeConfig

    overrides = {"floor": not args.no_floor}
    if args.max_steps is not None:
        overrides["max_steps"] = args.max_steps
    if args.sew_steps is not None:
        overrides["sew_max_steps"] = args.sew_steps
        overrides["sew_ramp_steps"] = min(DrapeConfig().sew_ramp_steps, args.sew_steps)
    return DrapeConfig(**overrides)


def _sew_and_drape(garment, body_verts: torch.Tensor, body_faces: torch.Tensor, config):
    """`sew_and_drape` on the body (float32), with a progress bar on stderr when it reports frames."""
    from torch_diffavatar.sim.forward_drape import sew_and_drape

    kwargs = {}
    bar = None
    if "progress" in inspect.signature(sew_and_drape).parameters:  # per-frame callback, when offered
        from tqdm import tqdm

        bar = tqdm(total=config.sew_max_steps + config.max_steps, desc="drape", unit="frame", file=sys.stderr)
        kwargs["progress"] = lambda *_, **__: bar.update(1)
    else:
        print(f"diffavatar drape: sewing and draping {garment.tri_count} triangles…", file=sys.stderr)
    try:
        return sew_and_drape(
            garment,
            body_verts=body_verts.to(torch.float32),
            body_faces=body_faces,
            config=config,
            **kwargs,
        )
    finally:
        if bar is not None:
            bar.close()


def _write_png(path, x: torch.Tensor, faces: torch.Tensor, body_verts, body_faces) -> None:
    """Front and back views of the cloth ``x`` (Vs, 3) [m] (faces (F, 3)) on the body, as a PNG."""
    from torch_diffavatar.render import CLOTH_COLOR, CLOTH_DEPTH_BIAS, RenderMesh, render_views, save_png

    image = render_views(
        [RenderMesh(body_verts, body_faces), RenderMesh(x, faces, CLOTH_COLOR, CLOTH_DEPTH_BIAS)],
        views=("front", "back"),
        width=512,
        height=640,
        supersample=2,
    )
    save_png(image, path)


def run_drape(args) -> dict:
    from torch_diffavatar.mesh_io import write_garment_obj
    from torch_diffavatar.metrics import triangle_quality
    from torch_diffavatar.pattern.library import resolve_pattern
    from torch_diffavatar.pattern.mesher import mesh_pattern
    from torch_diffavatar.sim.placement import body_signed_distance, place_garment

    _check_args(args)
    check_out_files(args, "out", "png")
    pattern = resolve_pattern(args.pattern)
    body_verts, body_faces = load_body(args.body)
    garment = mesh_pattern(pattern, spacing=args.spacing)
    garment = place_garment(garment, body_verts, body_faces)
    result = _sew_and_drape(garment, body_verts, body_faces, _drape_config(args))
    x = result.x.detach().to(torch.float64).cpu()
    faces = garment.sim_faces
    sd = body_signed_distance(x, body_verts, body_faces)
    quality = triangle_quality(x, faces)
    inverted = inverted_triangle_mask(x, faces, _rest_area(garment))
    diagnostics = result.diagnostics

    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_garment_obj(args.out, garment, sim_positions=x)
    if args.png:
        _write_png(args.png, x, faces, body_verts, body_faces)
    out = {
        "vertices": garment.sim_vert_count,
        "faces": garment.tri_count,
        "steps": int(result.steps + diagnostics.get("sew_steps", 0)),
        "seconds": round(float(result.seconds), 3),
        "max_speed": round(float(result.max_speed), 6),
        "converged": bool(result.converged),
        "penetrating_fraction": round(float((sd < 0).mean()), 6),
        "max_stitch_gap_m": round(float(diagnostics.get("max_stitch_gap_m", 0.0)), 6),
        "inverted_triangles": int(inverted.sum()),
        "quality_min": round(float(quality.min()), 4),
        "quality_mean": round(float(quality.mean()), 4),
    }
    if not args.json:
        for key, value in out.items():
            print(f"{key}: {value}")
    return out
