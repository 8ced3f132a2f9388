"""`diffavatar fit SCAN --garment TEMPLATE|PATTERN.json [--config C] --out DIR [--body B] [--iters N]`.

The main job: scan in, simulation-ready assets out (`torch_diffavatar.fit_scan.fit_scan`: the set-up of
`torch_diffavatar.fit_setup.prepare`, the fit loop of `torch_diffavatar.fit.Fitter`, the assets of
`torch_diffavatar.assets.write_assets`). ``--json`` prints ``report.json`` as one line.

``--garment`` is a bundled template or any GarmentCode pattern file: the fit starts from that pattern with
the bundled config of its garment type (`fit_setup.infer_garment_type`, or ``--garment-type``).

Everything the loop needs after the (slow) set-up is saved in ``DIR/setup.pt``; with ``--resume`` a
second run reuses it and continues from ``DIR/checkpoint.pt``.
"""

from __future__ import annotations

import contextlib
import sys
from dataclasses import replace
from pathlib import Path

from torch_diffavatar.commands.body import add_frame_args, workers_option
from torch_diffavatar.commands.out_paths import check_out_folder
from torch_diffavatar.errors import InputError, read_json_file
from torch_diffavatar.fit_scan import fit_scan
from torch_diffavatar.fit_setup import SEGMENT_TYPES, TYPE_CONFIGS, infer_garment_type


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
    p.add_argument(
        "--no-colour",
        action="store_true",
        help="segment an unlabelled scan by geometry alone, not by its colours too",
    )
    p.add_argument(
        "--workers",
        "--race-workers",
        dest="workers",
        type=int,
        default=None,
        help="processes run side by side, one core each: the body fit's two ways round and the race of "
        "first drapes (the tops' configs); the same result for any number (default: the cores this process "
        "may use)",
    )
    p.add_argument("--resume", action="store_true", help="continue from --out's checkpoint")
    p.add_argument("--force", action="store_true", help="replace another fit in --out (its files only)")
    add_frame_args(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print report.json as one JSON line")
    p.set_defaults(func=fit_command)


def fit_command(args) -> dict:
    from torch_diffavatar.fit_config import load_config

    if args.iters is not None and args.iters < 0:
        raise InputError(f"--iters must be >= 0, got {args.iters}")
    workers = workers_option(args)
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
    if args.no_colour:
        overrides["segment_colour"] = False
    config = load_config(
        args.config, garment=template, iterations=args.iters, spacing=args.spacing, **overrides
    )
    if args.spacing is not None:  # the user's spacing, whatever the arms
        config = replace(config, arms_low_spacing=None)
    check_pattern_size(pattern, config)
    out = Path(args.out)
    check_out_folder(out)
    body_params = None if args.body is None else read_body_params(args.body)
    with contextlib.redirect_stdout(sys.stderr):  # warp prints on stdout; keep --json one clean line
        report = fit_scan(
            args.scan,
            config,
            out,
            resume=args.resume,
            force=args.force,
            units=args.units,
            up=args.up,
            progress=not args.no_progress,
            pattern=pattern,
            garment_type=garment_type,
            body_params=body_params,
            workers=workers,
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


def check_pattern_size(pattern, config) -> None:
    """PatternError, before any heavy work, for a ``pattern`` (None: ``config.template``'s) with a panel
    smaller than the finest spacing the fit may mesh it at, or too many vertices there
    (`pattern.mesher.check_mesh_budget`)."""
    from torch_diffavatar.pattern.library import resolve_pattern
    from torch_diffavatar.pattern.mesher import check_mesh_budget

    pattern = resolve_pattern(config.template) if pattern is None else pattern
    check_mesh_budget(pattern, min(config.spacing, config.arms_low_spacing or config.spacing))


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
    params = read_json_file(path, f"--body {path}: no body.json there", where=f"--body {path}")
    missing = [k for k in BODY_PARAM_KEYS if not isinstance(params, dict) or k not in params]
    if missing:
        raise InputError(f"--body {path}: not Anny body parameters (missing {', '.join(missing)})")
    return params
