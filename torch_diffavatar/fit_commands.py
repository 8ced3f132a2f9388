"""`diffavatar fit SCAN --garment TYPE [--config C] --out DIR [--iters N] [--resume] [--json]`.

The main job: scan in, simulation-ready assets out. Steps: load the scan (per-point garment labels used
when present), fit the Anny body to it (`body.fit.fit_body`), segment the garment when the scan is not
labelled (`body.segment.segment_garment`), find the garment's openings on the body (the segmentation's
boundary loops: neck, hem, cuffs, waist …) and match them to the template's named loops, mesh and place
the template (`sim.placement.place_garment`), then run the fit loop (`torch_diffavatar.fit.Fitter`) and
write the assets (`torch_diffavatar.assets.write_assets`). ``--json`` prints ``report.json`` as one line.

Everything the loop needs after the (slow) set-up is saved in ``DIR/setup.pt``; with ``--resume`` a
second run reuses it and continues from ``DIR/checkpoint.pt``.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torch_diffavatar.errors import InputError

# Template name -> segmentation garment type (`body.segment.GARMENT_TYPES`).
SEGMENT_TYPES = {
    "dress": "dress",
    "dress_pencil": "dress",
    "longsleeve": "shirt",
    "tshirt": "tshirt",
    "polo": "polo",
    "skirt": "skirt",
    "pants": "pants",
    "shorts": "pants",
}
# Segmentation loop name -> `GarmentMesh` loop name.
LOOP_NAMES = {
    "neck": "neck",
    "waist": "waist",
    "hem": "hem",
    "cuff.L": "cuff_left",
    "cuff.R": "cuff_right",
    "armhole.L": "cuff_left",
    "armhole.R": "cuff_right",
    "leg.L": "hem_left",
    "leg.R": "hem_right",
}
GARMENT_LABEL = 1  # label of the garment's points in a labelled scan (0 = body / not garment)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fit",
        help="fit body, sewing pattern and material to a scan; write simulation-ready assets",
        description="Recover the body, the garment's 2D sewing pattern and its bending stiffness from a scan "
        "by optimising through the differentiable drape; write pattern JSON/SVG, OBJs, body, material, "
        "report.json and a before/after PNG into --out.",
    )
    p.add_argument("scan", help="scan mesh or point cloud (PLY with an optional per-vertex 'label' property)")
    p.add_argument(
        "--garment", required=True, help="garment template: dress, longsleeve, polo, tshirt, skirt, pants"
    )
    p.add_argument("--config", help="YAML fit config (default: configs/<garment>.yaml)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--iters", type=int, default=None, help="iterations (overrides the config)")
    p.add_argument("--spacing", type=float, default=None, help="mesh spacing [m] (overrides the config)")
    p.add_argument("--resume", action="store_true", help="continue from --out's checkpoint")
    p.add_argument("--units", default="m", choices=("m", "cm", "mm"), help="length unit of the scan file")
    p.add_argument("--up", default="y", choices=("y", "-y", "z", "-z"), help="up axis of the scan file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print report.json as one JSON line")
    p.set_defaults(func=fit_command)


def fit_command(args) -> dict:
    from torch_diffavatar.fit import load_config

    if args.iters is not None and args.iters < 0:
        raise InputError(f"--iters must be >= 0, got {args.iters}")
    if args.spacing is not None and not args.spacing > 0:
        raise InputError(f"--spacing must be a positive length in metres, got {args.spacing}")
    if args.garment not in SEGMENT_TYPES:
        raise InputError(f"unknown --garment {args.garment!r}; use one of {', '.join(SEGMENT_TYPES)}")
    config = load_config(args.config, garment=args.garment, iterations=args.iters, spacing=args.spacing)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a directory")
    with contextlib.redirect_stdout(sys.stderr):  # warp prints on stdout; keep --json one clean line
        report = fit_scan(
            args.scan,
            config,
            out,
            resume=args.resume,
            units=args.units,
            up=args.up,
            progress=not args.no_progress,
        )
    if not args.json:
        for key in ("chamfer_initial", "chamfer_final", "iterations", "seconds", "rejected_steps"):
            print(f"{key}: {report[key]}")
        print(f"assets: {out}")
    return report


# ---------------------------------------------------------------------------------------------------------


def scan_boundaries(
    points: np.ndarray,
    garment_mask: np.ndarray,
    body_verts: np.ndarray,
    body_faces: np.ndarray,
    vertex_parts: np.ndarray,
    segment_type: str,
) -> dict[str, np.ndarray]:
    """The scan garment's openings, named as the segmentation names them (``neck``, ``cuff.L`` …).

    Uses the body package's boundary finder (loops of the covered body region, named by the body part
    just outside): segmentation name -> (k, 3) scan points [m] in loop order.
    """
    from scipy.spatial import cKDTree

    from torch_diffavatar.body import segment

    finder = getattr(segment, "boundary_loops", None) or segment._boundary_loops
    _, near = cKDTree(body_verts).query(points)
    loops = finder(points, garment_mask, near, body_verts, body_faces, vertex_parts, segment_type)
    garment_idx = np.flatnonzero(garment_mask)
    return {loop.name: points[garment_idx[loop.point_indices]] for loop in loops}


def match_boundaries(garment, scan_loops: dict[str, np.ndarray], max_distance: float = 0.2) -> dict:
    """Map scan openings to the garment's loop names.

    Names are translated with `LOOP_NAMES`; the scan openings left over are matched to the garment's
    unmatched loops (``opening_k`` …) by nearest centroid (placed garment, within ``max_distance`` [m]).

    Returns:
        garment loop name -> (k, 3) float64 tensor of scan points [m].
    """
    garment_names = [lp.name for lp in garment.boundary_loops]
    out, left = {}, {}
    for name, pts in scan_loops.items():
        mapped = LOOP_NAMES.get(name)
        if mapped in garment_names and mapped not in out:
            out[mapped] = torch.as_tensor(pts, dtype=torch.float64)
        else:
            left[name] = pts
    pos = garment.sim_positions().double()
    free = [lp for lp in garment.boundary_loops if lp.name not in out]
    for pts in left.values():
        if not free:
            break
        c = torch.as_tensor(pts, dtype=torch.float64).mean(0)
        dist = [float((pos[lp.vertices].mean(0) - c).norm()) for lp in free]
        k = int(np.argmin(dist))
        if dist[k] < max_distance:
            out[free.pop(k).name] = torch.as_tensor(pts, dtype=torch.float64)
    return out


def prepare(scan_path, config, *, units="m", up="y", anny_model=None, pattern=None) -> dict:
    """The slow set-up of a fit: scan, body fit, segmentation, openings, meshed and placed template.

    ``pattern`` (a `Pattern`) starts the fit from it instead of ``config.template``: an earlier fit's
    result, or a ground truth (`scripts/fit_checks.py` ``oracle``). It must have the template's panels
    and named boundary loops, which the scan's openings are matched to.

    Returns:
        a dict with ``garment`` (placed `GarmentMesh`), ``pattern``, ``target`` (`ScanTarget`),
        ``body_params`` (`BodyModel.parameters_dict` of the initial fit), ``body_fit_chamfer_m``,
        ``scan_points``, ``labelled`` and ``setup_seconds``.
    """
    import warnings

    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.fit import fit_body
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.body.parts import vertex_parts
    from torch_diffavatar.fit import ScanTarget
    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.scan import ScanWarning, load_scan, remove_outliers
    from torch_diffavatar.sim.placement import place_garment

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ScanWarning)
        scan = load_scan(scan_path, units=units, up=up)
    for message in scan.warnings:
        print(f"diffavatar fit: warning: {message}", file=sys.stderr)
    scan, _ = remove_outliers(scan)
    anny_model = load_anny(dtype=torch.float32) if anny_model is None else anny_model
    body = BodyModel(anny_model=anny_model)
    fitted = fit_body(scan.points, body)
    with torch.no_grad():
        body_verts = body().vertices[0].double()
    faces = body.faces.cpu().numpy()
    parts = vertex_parts(anny_model).cpu().numpy()
    seg_type = SEGMENT_TYPES.get(config.template, config.template)
    if scan.labels is not None:
        mask = scan.labels == GARMENT_LABEL
        labelled = True
    else:
        from torch_diffavatar.body.segment import segment_garment

        seg = segment_garment(scan.points, seg_type, body_verts.numpy(), faces, parts, colors=scan.colors)
        mask, labelled = seg.labels, False
    if mask.sum() < 50:
        raise InputError(f"{scan_path}: only {int(mask.sum())} garment points; cannot fit a garment")
    loops = scan_boundaries(scan.points, mask, body_verts.numpy(), faces, parts, seg_type)
    pattern = load_template(config.template) if pattern is None else pattern
    garment = mesh_pattern(pattern, spacing=config.spacing)
    garment = place_garment(garment, body_verts, body.faces)
    boundaries = match_boundaries(garment, loops)
    target = ScanTarget(
        garment_points=torch.as_tensor(scan.points[mask]),
        boundaries=boundaries,
        body_points=torch.as_tensor(scan.points[~mask]),
    )
    return {
        "garment": garment,
        "pattern": pattern,
        "target": target,
        "body_params": body.parameters_dict(),
        "body_fit_chamfer_m": fitted.chamfer_m,
        "scan_points": scan.point_count,
        "scan_boundaries": sorted(loops),
        "labelled": labelled,
        "setup_seconds": time.perf_counter() - t0,
    }


def fit_scan(
    scan_path,
    config,
    out_dir,
    *,
    resume=False,
    units="m",
    up="y",
    progress=True,
    anny_model=None,
    pattern=None,
) -> dict:
    """Run the whole job (see the module docstring); returns the report (also ``out_dir/report.json``).

    ``pattern``: start from this `Pattern` instead of ``config.template`` (see `prepare`)."""
    from torch_diffavatar.assets import write_assets
    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.fit import SETUP, Fitter, _atomic_save, write_resolved_config
    from torch_diffavatar.sim.material import ClothMaterial

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_resolved_config(config, out)
    anny_model = load_anny(dtype=torch.float32) if anny_model is None else anny_model
    setup_path = out / SETUP
    if resume and setup_path.is_file():
        setup = torch.load(setup_path, weights_only=False)
    else:
        setup = prepare(scan_path, config, units=units, up=up, anny_model=anny_model, pattern=pattern)
        _atomic_save(setup, setup_path)
    body = BodyModel(anny_model=anny_model)
    body.load_parameters_dict(setup["body_params"])
    garment, target = setup["garment"], setup["target"]
    material = ClothMaterial(bend_stiffness=config.initial_bend_stiffness)
    fitter = Fitter(garment, target, config, body=body, material=material, out_dir=out, progress=progress)
    result = fitter.run(resume=resume)
    report = dict(result.report)
    report.update(
        scan=str(scan_path),
        scan_points=setup["scan_points"],
        scan_labelled=setup["labelled"],
        scan_boundaries=setup["scan_boundaries"],
        body_fit_chamfer_m=setup["body_fit_chamfer_m"],
        setup_seconds=round(setup["setup_seconds"], 2),
        total_seconds=round(time.perf_counter() - t0 + (0.0 if resume else 0.0), 2),
    )
    final_material = ClothMaterial(bend_stiffness=float(result.params.log_bend_stiffness.detach().exp()))
    body_params = dict(body.parameters_dict())
    body_params["phenotypes_by_name"] = dict(zip(body.phenotype_labels, body.phenotypes[0].detach().tolist()))
    first = fitter.first
    before = None
    if first is not None and first["body_verts"] is not None:
        before = (first["x"], garment.sim_faces, first["body_verts"], body.faces)
    files = write_assets(
        out,
        pattern=setup["pattern"],
        garment=garment,
        rest_uv=result.rest_uv,
        draped_x=result.x,
        body_verts=result.body_verts,
        body_faces=body.faces,
        body_params=body_params,
        material=final_material,
        report=report,
        before=before,
    )
    return json.loads(Path(files["report_json"]).read_text())
