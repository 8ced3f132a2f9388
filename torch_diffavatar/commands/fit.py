"""`diffavatar fit SCAN --garment TEMPLATE|PATTERN.json [--config C] --out DIR [--body B] [--iters N]`.

The main job: scan in, simulation-ready assets out. Steps: load the scan (per-point garment labels used
when present), fit the Anny body to it (`body.fit.fit_body`; ``--body`` starts from a given body
instead), segment the garment when the scan is not labelled (`body.segment.segment_garment`), find the
garment's openings on the body (the segmentation's boundary loops: neck, hem, cuffs, waist …) and match
them to the template's named loops, mesh and place the template (`sim.placement.place_garment`), then
run the fit loop (`torch_diffavatar.fit.Fitter`) and write the assets
(`torch_diffavatar.assets.write_assets`). ``--json`` prints ``report.json`` as one line.

``--garment`` is a bundled template or any GarmentCode pattern file: the fit starts from that pattern with
the bundled config of its garment type (`infer_garment_type`, or ``--garment-type``).

Everything the loop needs after the (slow) set-up is saved in ``DIR/setup.pt``; with ``--resume`` a
second run reuses it and continues from ``DIR/checkpoint.pt``.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from dataclasses import replace
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
# Garment (segmentation) type -> the bundled config a GarmentCode file of that type is fitted with.
TYPE_CONFIGS = {
    "dress": "dress",
    "shirt": "longsleeve",
    "tshirt": "tshirt",
    "polo": "polo",
    "skirt": "skirt",
    "pants": "pants",
    # a jumpsuit hangs from its shoulders: the tops' 40 substeps (on a jumpsuit scan with pants.yaml's 10
    # the fit softened k_b to 0.13x and bent the sleeves: outline 2.78 / 5.81 cm, against 1.24 / 4.76)
    "jumpsuit": "longsleeve",
    "jumpsuit_sleeveless": "dress",
}
LONG_SLEEVE = 0.45  # [m] a sleeve reaching farther than this from the shoulder point is a long one
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
        "--garment",
        required=True,
        help=f"garment template ({', '.join(SEGMENT_TYPES)}) or a GarmentCode pattern JSON to start from",
    )
    p.add_argument(
        "--garment-type",
        choices=tuple(TYPE_CONFIGS),
        help="what the garment is, for the scan's segmentation and openings (default: the template's, or "
        "inferred from where a pattern file's panels go on the body)",
    )
    p.add_argument(
        "--config",
        help="YAML fit config (default: configs/<garment>.yaml, else its kind's: for a pattern file, its "
        "type's); --garment replaces the config's template",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--body",
        default=None,
        help="start from this body instead of fitting one: a body.json, or a folder holding one "
        "(`diffavatar fit-body --out`, an earlier fit's assets)",
    )
    p.add_argument("--iters", type=int, default=None, help="iterations (overrides the config)")
    p.add_argument(
        "--spacing",
        type=float,
        default=None,
        help="mesh spacing [m] (overrides the config's, and its arms_low_spacing for arms held low)",
    )
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
    template, garment_type, pattern = args.garment, args.garment_type, None
    overrides = {"template": args.garment}  # --garment says what to fit, whatever --config's template
    if args.garment not in SEGMENT_TYPES:
        from torch_diffavatar.pattern.library import resolve_pattern

        if not Path(args.garment).is_file():
            raise InputError(
                f"--garment {args.garment!r}: not a template ({', '.join(SEGMENT_TYPES)}) nor a pattern file"
            )
        pattern = resolve_pattern(args.garment)
        garment_type = garment_type or infer_garment_type(pattern)
        template, overrides = TYPE_CONFIGS[garment_type], {"template": str(Path(args.garment).resolve())}
    config = load_config(
        args.config, garment=template, iterations=args.iters, spacing=args.spacing, **overrides
    )
    if args.spacing is not None:  # the user's spacing, whatever the arms
        config = replace(config, arms_low_spacing=None)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a directory")
    body_params = None if args.body is None else read_body_params(args.body)
    with contextlib.redirect_stdout(sys.stderr):  # warp prints on stdout; keep --json one clean line
        report = fit_scan(
            args.scan,
            config,
            out,
            resume=args.resume,
            units=args.units,
            up=args.up,
            progress=not args.no_progress,
            pattern=pattern,
            garment_type=garment_type,
            body_params=body_params,
        )
    if not args.json:
        for key in (
            "chamfer_initial",
            "chamfer_final",
            "iterations",
            "result_iteration",
            "seconds",
            "rejected_steps",
        ):
            print(f"{key}: {report[key]}")
        print(f"assets: {out}")
    return report


# the keys `BodyModel.load_parameters_dict` reads
BODY_PARAM_KEYS = (
    "phenotypes",
    "pose_bones",
    "pose_axis_angle",
    "global_orient_axis_angle",
    "translation_m",
    "scale",
)


def read_body_params(path) -> dict:
    """Body parameters (`BodyModel.parameters_dict`) from a ``body.json`` or a folder holding one.

    Raises:
        InputError: no such file, not JSON, or not body parameters.
    """
    from torch_diffavatar.commands.body import BODY_JSON

    path = Path(path)
    if path.is_dir():
        path = path / BODY_JSON
    if not path.is_file():
        raise InputError(f"--body {path}: no body.json there (run `diffavatar fit-body` first)")
    try:
        params = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"--body {path}: not a JSON file ({exc})") from exc
    missing = [k for k in BODY_PARAM_KEYS if not isinstance(params, dict) or k not in params]
    if missing:
        raise InputError(f"--body {path}: not Anny body parameters (missing {', '.join(missing)})")
    return params


def infer_garment_type(pattern) -> str:
    """The garment type (a key of `TYPE_CONFIGS`) of a pattern, from where its panels go on the body.

    GarmentCode lays panels out around its mean body; `sim.placement` reads that layout into panel kinds
    (torso, arm, leg, collar-like panels attached to a partner). Legs: ``pants``, or ``jumpsuit`` (with
    sleeves) and ``jumpsuit_sleeveless`` when the panels reach above the waist too; nothing above the waist:
    ``skirt``; panels reaching below the crotch: ``dress`` (with or without sleeves); sleeves: ``polo``
    with an attached collar, else ``shirt`` when a sleeve reaches farther than `LONG_SLEEVE` from the
    shoulder point, else ``tshirt``; otherwise ``dress`` (a sleeveless top: the dress's body regions and
    armholes fit it). On the bundled templates it gives `SEGMENT_TYPES`.
    """
    from torch_diffavatar.pattern.mesher import mesh_pattern
    from torch_diffavatar.sim.placement import GC_BODY, _attachments, _panel_kinds

    garment = mesh_pattern(pattern, spacing=0.05)  # coarse: only the layout matters
    pos = garment.vert_pos.detach().cpu().numpy().astype(np.float64)
    kinds = _panel_kinds(garment, pos)
    panel_kind = np.array(kinds)[garment.vert_panel.cpu().numpy()]
    above_waist = pos[:, 1].max() >= GC_BODY["waist"] + 0.05
    arm = np.char.startswith(panel_kind.astype(str), "arm")
    if any(k.startswith("leg") for k in kinds):
        if not above_waist:
            return "pants"
        return "jumpsuit" if arm.any() else "jumpsuit_sleeveless"
    if not above_waist:
        return "skirt"
    if pos[:, 1].min() < GC_BODY["crotch"]:
        return "dress"
    if arm.any():
        if _attachments(garment, kinds):
            return "polo"
        reach = np.hypot(
            np.abs(pos[arm, 0]) - GC_BODY["shoulder_half_width"], pos[arm, 1] - GC_BODY["shoulder"]
        )
        return "shirt" if reach.max() > LONG_SLEEVE else "tshirt"
    return "dress"


def covers_head(garment, reach: float = 0.1) -> bool:
    """Whether a garment covers the head (a hood): ``garment``, a `GarmentMesh` as `mesh_pattern` lays it
    out around GarmentCode's mean body (before placement), reaches within ``reach`` [m] of the body's top
    (GarmentCode's hoody: 14 cm above it; a polo's collar, the highest of the others: 14 cm below)."""
    from torch_diffavatar.sim.placement import GC_BODY

    return float(garment.vert_pos[:, 1].max()) > GC_BODY["height"] - reach


# ---------------------------------------------------------------------------------------------------------


def scan_boundaries(
    points: np.ndarray,
    garment_mask: np.ndarray,
    body_verts: np.ndarray,
    body_faces: np.ndarray,
    vertex_parts: np.ndarray,
    segment_type: str,
) -> dict[str, np.ndarray]:
    """The scan garment's openings, named as the garment mesh names its own (``neck``, ``cuff_left`` …).

    Uses the body package's boundary finder (loops of the covered body region, named by the body part
    just outside): opening name -> (k, 3) scan points [m] in loop order.
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

    A scan opening goes to the garment loop of its name (the segmentation names openings as the garment
    mesh does); the scan openings left over are matched to the garment's unmatched loops (``opening_k``
    …) by nearest centroid (placed garment, within ``max_distance`` [m]).

    Returns:
        garment loop name -> (k, 3) float64 tensor of scan points [m].
    """
    garment_names = [lp.name for lp in garment.boundary_loops]
    out, left = {}, {}
    for name, pts in scan_loops.items():
        if name in garment_names:
            out[name] = torch.as_tensor(pts, dtype=torch.float64)
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


def arms_spacing(config, arm_angles: dict[str, float]) -> float:
    """The mesh spacing [m] of a fit: ``config.arms_low_spacing`` when it is set, finer than
    ``config.spacing``, and an upper arm stands less than ``config.arms_low_angle`` from the torso
    (``arm_angles``: `BodyModel.upper_arm_angles`, degrees); else ``config.spacing``."""
    finer = config.arms_low_spacing
    if finer is None or finer >= config.spacing or min(arm_angles.values()) >= config.arms_low_angle:
        return config.spacing
    return finer


def prepare(
    scan_path,
    config,
    *,
    units="m",
    up="y",
    anny_model=None,
    pattern=None,
    garment_type=None,
    body_params=None,
) -> dict:
    """The slow set-up of a fit: scan, body fit, segmentation, openings, meshed and placed template.

    ``config.template`` is a template name or a GarmentCode file. ``pattern`` (a `Pattern`) starts the fit
    from it instead: an earlier fit's result, or a ground truth (`scripts/fit_checks.py` ``oracle``).
    ``garment_type`` (a key of `TYPE_CONFIGS`) drives the scan's segmentation and openings; default: the
    template's (`SEGMENT_TYPES`), else `infer_garment_type` of the pattern. ``body_params`` (a
    `BodyModel.parameters_dict`, e.g. the ``body.json`` of ``diffavatar fit-body`` or of an earlier fit, in
    the scan's world frame) is the body to start from instead of fitting one to the scan.

    The pattern is meshed at ``config.spacing``, or at ``config.arms_low_spacing`` when the body holds an
    arm low (`arms_spacing`).

    Returns:
        a dict with ``garment`` (placed `GarmentMesh`), ``pattern``, ``target`` (`ScanTarget`),
        ``body_params`` (`BodyModel.parameters_dict` of the initial body), ``sewing_fallback`` (the
        garment's `a_pose_route` onto it, None in the A-pose), ``body_fit_chamfer_m`` (the body fit's
        residual [m]; None with ``body_params``),
        ``scan_points``, ``labelled``, ``spacing`` (the mesh's [m]), ``upper_arm_angles_deg`` (of the
        initial body, `BodyModel.upper_arm_angles`) and ``setup_seconds``.
    """
    import warnings

    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.fit import BodyFitConfig, fit_body
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.body.parts import vertex_parts
    from torch_diffavatar.fit import ScanTarget
    from torch_diffavatar.pattern import mesh_pattern
    from torch_diffavatar.scan import ScanWarning, load_scan, remove_outliers
    from torch_diffavatar.sim.placement import a_pose_route, place_garment

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ScanWarning)
        scan = load_scan(scan_path, units=units, up=up)
    for message in scan.warnings:
        print(f"diffavatar fit: warning: {message}", file=sys.stderr)
    scan, _ = remove_outliers(scan)
    anny_model = load_anny(dtype=torch.float32) if anny_model is None else anny_model
    body = BodyModel(anny_model=anny_model)
    if pattern is None:
        from torch_diffavatar.pattern.library import resolve_pattern

        pattern = resolve_pattern(config.template)
    mesh = mesh_pattern(pattern, spacing=config.spacing)
    if body_params is None:
        body_config = BodyFitConfig()
        if covers_head(mesh):  # a hood: the head's scan points are cloth, not skin
            body_config.skin_parts = tuple(p for p in body_config.skin_parts if p != "head")
        body_fit_chamfer_m = fit_body(scan.points, body, config=body_config).chamfer_m
    else:
        try:
            body.load_parameters_dict(body_params)
        except (KeyError, ValueError, TypeError, RuntimeError) as exc:
            raise InputError(f"the given body parameters do not fit this BodyModel: {exc}") from exc
        body_fit_chamfer_m = None
    with torch.no_grad():
        body_out = body()
        body_verts = body_out.vertices[0].double()
    arm_angles = body.upper_arm_angles(body_out.joints[0])
    spacing = arms_spacing(config, arm_angles)
    if spacing != config.spacing:
        print(
            f"diffavatar fit: an upper arm hangs {min(arm_angles.values()):.0f}° from the torso (below "
            f"{config.arms_low_angle:g}°): meshing at {spacing:g} m instead of {config.spacing:g} m, since "
            "a coarser mesh crushes where the lowered arm presses the cloth flat",
            file=sys.stderr,
        )
        mesh = mesh_pattern(pattern, spacing=spacing)
    faces = body.faces.cpu().numpy()
    parts = vertex_parts(anny_model).cpu().numpy()
    seg_type = garment_type or SEGMENT_TYPES.get(config.template) or infer_garment_type(pattern)
    if scan.labels is not None:
        mask = scan.labels == GARMENT_LABEL
        labelled = True
    else:
        from torch_diffavatar.body.segment import segment_garment

        waist = body.waist_height(body_out.joints[0])
        seg = segment_garment(
            scan.points, seg_type, body_verts.numpy(), faces, parts, colors=scan.colors, support_top=waist
        )
        mask, labelled = seg.labels, False
    if mask.sum() < 50:
        raise InputError(f"{scan_path}: only {int(mask.sum())} garment points; cannot fit a garment")
    loops = scan_boundaries(scan.points, mask, body_verts.numpy(), faces, parts, seg_type)
    garment = place_garment(mesh, body_verts, body.faces, arm_joints=body.arm_joints(body_out.joints[0]))
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
        "sewing_fallback": a_pose_route(mesh, body),
        "body_fit_chamfer_m": body_fit_chamfer_m,
        "scan_points": scan.point_count,
        "scan_boundaries": sorted(loops),
        "labelled": labelled,
        "spacing": spacing,
        "upper_arm_angles_deg": arm_angles,
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
    garment_type=None,
    body_params=None,
) -> dict:
    """Run the whole job (see the module docstring); returns the report (also ``out_dir/report.json``).

    ``pattern``: start from this `Pattern` instead of ``config.template``; ``garment_type`` and
    ``body_params`` (start from this body instead of fitting one): see `prepare`."""
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
        setup = prepare(
            scan_path,
            config,
            units=units,
            up=up,
            anny_model=anny_model,
            pattern=pattern,
            garment_type=garment_type,
            body_params=body_params,
        )
        _atomic_save(setup, setup_path)
    spacing = setup.get("spacing", config.spacing)
    if spacing != config.spacing:  # meshed finer for arms held low: the resolved config says so
        config = replace(config, spacing=spacing)
        write_resolved_config(config, out)
    body = BodyModel(anny_model=anny_model)
    body.load_parameters_dict(setup["body_params"])
    garment, target = setup["garment"], setup["target"]
    material = ClothMaterial(bend_stiffness=config.initial_bend_stiffness)
    fitter = Fitter(
        garment,
        target,
        config,
        body=body,
        material=material,
        sewing_fallback=setup.get("sewing_fallback"),
        out_dir=out,
        progress=progress,
    )
    result = fitter.run(resume=resume)
    report = dict(result.report)
    report.update(
        scan=str(scan_path),
        scan_points=setup["scan_points"],
        scan_labelled=setup["labelled"],
        scan_boundaries=setup["scan_boundaries"],
        spacing=spacing,
        upper_arm_angles_deg=setup.get("upper_arm_angles_deg"),
        body_fit_chamfer_m=setup["body_fit_chamfer_m"],
        setup_seconds=round(setup["setup_seconds"], 2),
        total_seconds=round(time.perf_counter() - t0, 2),  # this run's (a resumed one: since the resume)
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
    for message in report["warnings"]:
        print(f"diffavatar fit: warning: {message}", file=sys.stderr)
    return json.loads(Path(files["report_json"]).read_text())
