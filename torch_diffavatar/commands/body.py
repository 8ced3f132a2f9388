"""Sub-commands of the body area: `diffavatar fit-body` and `diffavatar segment`."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import numpy as np

from torch_diffavatar.commands.out_paths import check_out_folder
from torch_diffavatar.errors import InputError, ScanError, read_json_file
from torch_diffavatar.json_io import dumps_json, write_json
from torch_diffavatar.mesh_io import write_obj
from torch_diffavatar.scan import UNITS, UP_AXES

BODY_OBJ = "body.obj"
BODY_JSON = "body.json"


def register(subparsers) -> None:
    fit = subparsers.add_parser("fit-body", help="fit the Anny body (shape, pose, placement) to a scan")
    _scan_args(fit)
    fit.add_argument("--out", required=True, help="output directory (body.obj + body.json)")
    fit.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    fit.set_defaults(func=_stdout_to_stderr(fit_body_command))

    seg = subparsers.add_parser("segment", help="label a garment's points in an unlabelled scan")
    _scan_args(seg)
    seg.add_argument("--garment", required=True, help="dress, shirt, tshirt, polo, skirt or pants")
    seg.add_argument("--body", help="directory written by fit-body (default: fit the body now)")
    seg.add_argument("--out", required=True, help="output PLY of the garment points")
    seg.add_argument(
        "--no-colour", action="store_true", help="label by geometry alone, not by the scan's colours too"
    )
    seg.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    seg.set_defaults(func=_stdout_to_stderr(segment_command))


def _stdout_to_stderr(command):
    """Run ``command`` with stdout sent to stderr: warp (Anny's skinning backend) prints banners and
    kernel-load lines on stdout, which would break the one-JSON-line contract of ``--json``."""

    def run(args):
        with contextlib.redirect_stdout(sys.stderr):
            return command(args)

    run.__doc__ = command.__doc__
    return run


def add_frame_args(parser) -> None:
    """``--units`` and ``--up`` of a scan file, both inferred by the intake when not given
    (`scan_intake.intake_scan`)."""
    parser.add_argument(
        "--units",
        default=None,
        choices=tuple(UNITS),
        help="length unit of the scan file (default: from its height)",
    )
    parser.add_argument(
        "--up",
        default=None,
        choices=tuple(UP_AXES),
        help="up axis of the scan file (default: from the floor: y, -y when it is on top, z or -z when it "
        "lies under the person along Z)",
    )


def _scan_args(parser) -> None:
    parser.add_argument("scan", help="scan mesh or point cloud (PLY, OBJ, GLB)")
    add_frame_args(parser)
    parser.add_argument("--no-clean", action="store_true", help="skip floor, clutter and outlier removal")
    parser.add_argument(
        "--max-points",
        type=int,
        default=None,
        help="points of the scan used at most, a seeded random subset of a bigger scan (a PLY is thinned as "
        "it is read; default 2,000,000)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="processes of the body fit side by side, one core each (its two ways round); the same result "
        "for any number (default: the cores this process may use)",
    )


def workers_option(args) -> int:
    """``--workers`` (of `fit-body`, `segment` and `fit`), checked; the usable cores when not given."""
    from torch_diffavatar.forked import usable_cores

    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    return usable_cores() if args.workers is None else args.workers


def _load_clean_scan(args):
    """The scan through the intake (`scan_intake.intake_scan`), its decisions and warnings on stderr."""
    import warnings

    from torch_diffavatar.scan import ScanWarning
    from torch_diffavatar.scan_intake import MAX_POINTS, intake_scan

    kw = dict(
        units=args.units,
        up=args.up,
        clean=not args.no_clean,
        max_points=MAX_POINTS if args.max_points is None else args.max_points,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ScanWarning)
        scan, report = intake_scan(args.scan, **kw)
    for message in report.messages:
        print(f"diffavatar {args.command}: {message}", file=sys.stderr)
    for message in scan.warnings:
        print(f"diffavatar {args.command}: warning: {message}", file=sys.stderr)
    cov = report.coverage
    print(
        f"diffavatar {args.command}: coverage: {cov['sectors_seen']} of {cov['sectors']} sides seen",
        file=sys.stderr,
    )
    args.units, args.up, args.intake = report.units, report.up, report.as_dict()
    return scan


def _single_thread():
    import torch

    torch.set_num_threads(1)  # measured ~10x faster than 2 threads for Anny on small CPUs


def _floor_y(args) -> float | None:
    """The floor's height [m] after the intake (`_load_clean_scan`): 0 when it found and removed one."""
    return 0.0 if args.intake.get("floor") else None


def fit_body_command(args) -> dict:
    _single_thread()
    from torch_diffavatar.body.fit import fit_body
    from torch_diffavatar.fit_scan import body_fit_warnings

    out = Path(args.out)
    check_out_folder(out)
    workers = workers_option(args)
    scan = _load_clean_scan(args)
    result = fit_body(scan.points, floor_y=_floor_y(args), workers=workers)
    body = result.body
    verts = body().vertices[0].detach().cpu().numpy()
    phenotypes = dict(zip(body.phenotype_labels, body.phenotypes[0].detach().tolist()))
    summary = {
        "points": scan.point_count,
        "seconds": round(result.seconds, 2),
        "chamfer_m": result.chamfer_m,
        "height_m": result.height_m,
        "phenotypes": phenotypes,
        "yaw_deg": result.yaw_deg,
        "coverage": args.intake["coverage"],
        "warnings": args.intake["warnings"] + body_fit_warnings(result.chamfer_m),
    }
    for message in body_fit_warnings(result.chamfer_m):  # the intake's are printed already
        print(f"diffavatar fit-body: warning: {message}", file=sys.stderr)
    # the body parameters last: the summary's phenotypes by name must not replace their list, which
    # `BodyModel.load_parameters_dict` (fit --body, segment --body) reads back
    params = dict(summary, scan=str(args.scan), units=args.units, up=args.up, scan_shift=args.intake["shift"])
    params.update(body.parameters_dict())
    params["phenotypes_by_name"] = phenotypes
    dumps_json(params)  # a NaN refused before either file is written: never a body.obj alone
    out.mkdir(parents=True, exist_ok=True)
    write_obj(out / BODY_OBJ, verts, body.faces)
    write_json(out / BODY_JSON, params)
    return summary


def _body_from_dir(directory: str, anny_model) -> np.ndarray:
    """Fitted body vertices (Vb, 3) [m] from a fit-body output directory (its body.obj)."""
    from torch_diffavatar.scan import load_scan

    path = Path(directory) / BODY_OBJ
    if not path.exists():
        raise InputError(f"--body {directory}: no {BODY_OBJ} there (run `diffavatar fit-body` first)")
    body = load_scan(path, require_faces=True, check=False)
    expected = anny_model.template_vertices.shape[0]
    if body.point_count != expected:
        raise ScanError(f"{path}: {body.point_count} vertices, but the Anny body has {expected}")
    return body.points


def segment_command(args) -> dict:
    from torch_diffavatar.body.segment import garment_type

    kind = garment_type(args.garment)  # fail on a bad type or output before any heavy work
    check_out_folder(Path(args.out).parent)
    if Path(args.out).is_dir():
        raise InputError(f"--out {args.out} is a folder; give the PLY file to write")
    workers = workers_option(args)
    _single_thread()
    import torch

    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.body.parts import vertex_parts
    from torch_diffavatar.body.segment import segment_garment
    from torch_diffavatar.scan import save_ply

    anny_model = load_anny(dtype=torch.float32)
    body, body_verts = None, None  # body: its parameters, when known (its waist height helps trousers)
    if args.body:
        body_verts = _body_from_dir(args.body, anny_model)
        params = Path(args.body) / BODY_JSON
        if params.is_file():
            body = BodyModel(anny_model=anny_model)
            try:
                body.load_parameters_dict(read_json_file(params, f"{params}: missing"))
            except (KeyError, ValueError, TypeError, RuntimeError) as exc:  # the vertices suffice
                print(f"diffavatar segment: {params} not read ({exc}); no waist height", file=sys.stderr)
                body = None
    scan = _load_clean_scan(args)
    if not args.body:
        from torch_diffavatar.body.fit import fit_body

        body = fit_body(scan.points, anny_model=anny_model, floor_y=_floor_y(args), workers=workers).body
    waist = None
    if body is not None:
        with torch.no_grad():
            out = body()
        waist = body.waist_height(out.joints[0])
        if body_verts is None:  # the fitted body's (a --body folder's own vertices otherwise)
            body_verts = out.vertices[0].numpy()
    faces = anny_model.faces.cpu().numpy()
    parts = vertex_parts(anny_model).cpu().numpy()
    seg = segment_garment(
        scan.points,
        kind,
        body_verts,
        faces,
        parts,
        colors=scan.colors,
        support_top=waist,
        use_colour=not args.no_colour,
    )
    if scan.colors is not None and not args.no_colour:
        said = (
            "used" if seg.colour_separability is not None else "not used (it does not tell the garment apart)"
        )
        print(f"diffavatar segment: colour {said}", file=sys.stderr)
    if len(seg.garment_indices) == 0:
        raise ScanError(
            f"{args.scan}: no {kind} points found on this body (a bare body, or another garment?): check "
            "--garment, or give the fitted body with --body; nothing written"
        )
    loop_id = np.full(len(seg.garment_indices), -1, dtype=np.int64)
    for k, loop in enumerate(seg.loops):
        loop_id[loop.point_indices] = k
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
    colors = None if scan.colors is None else scan.colors[seg.garment_indices]
    save_ply(out, scan.points[seg.garment_indices], colors=colors, int_properties={"boundary_loop": loop_id})
    loops_json = [{"name": loop.name, "point_indices": loop.point_indices.tolist()} for loop in seg.loops]
    write_json(out.with_suffix(".boundaries.json"), {"garment": kind, "loops": loops_json}, indent=None)
    return {
        "points": scan.point_count,
        "garment_points": int(len(seg.garment_indices)),
        "boundary_loops": [{"name": loop.name, "points": len(loop.point_indices)} for loop in seg.loops],
    }
