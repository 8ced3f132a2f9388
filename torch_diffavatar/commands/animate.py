"""`diffavatar animate` and `diffavatar export-template`: new motions for recovered assets."""

from __future__ import annotations

import torch

from torch_diffavatar.animate import animate, template_assets
from torch_diffavatar.commands.out_paths import check_out_folder
from torch_diffavatar.errors import InputError
from torch_diffavatar.sim.solver import XPBDConfig


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "animate",
        help="simulate a fitted garment on its body through a new motion (walk or keyframes)",
        description="Load an asset folder (from fit / demo / export-template), pose the body along a "
        "motion and simulate the garment; write one OBJ per frame (vt = rest coordinates), the body per "
        "frame (PLY), a preview GIF and animation.json.",
    )
    p.add_argument("assets", help="asset folder written by `diffavatar fit` / `demo` / `export-template`")
    p.add_argument("--motion", default="walk", help="'walk' (procedural walk cycle) or a keyframe JSON file")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--duration", type=float, default=None, help="seconds of motion (walk default 4)")
    p.add_argument("--fps", type=float, default=30.0, help="output frames per second (default 30)")
    p.add_argument(
        "--sim-fps", type=float, default=60.0, help="simulated frames per second, a multiple of --fps"
    )
    p.add_argument("--substeps", type=int, default=40, help="XPBD substeps per simulated frame")
    p.add_argument("--no-body-frames", action="store_true", help="do not write the body per frame")
    p.add_argument("--no-floor", action="store_true", help="no floor under the body's soles")
    p.add_argument("--no-gif", action="store_true", help="do not render the preview GIF")
    p.add_argument("--gif-size", type=int, default=240, help="width of one GIF view [px]")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    p.set_defaults(func=run_animate)

    t = subparsers.add_parser(
        "export-template",
        help="sew and drape a template on the default Anny body and write its asset folder",
        description="Mesh a template, place, sew and drape it on the default body (no fit) and write the "
        "same asset folder as `diffavatar fit`, e.g. to animate it.",
    )
    t.add_argument("template", help="template name (e.g. dress, tshirt)")
    t.add_argument("--out", required=True, help="output folder")
    t.add_argument("--spacing", type=float, default=0.02, help="target cloth edge length [m]")
    t.add_argument("--json", action="store_true", help="print the file map as one JSON line")
    t.set_defaults(func=run_export_template)


def run_animate(args) -> dict:
    from torch_diffavatar.assets import load_assets
    from torch_diffavatar.motion import load_motion

    torch.set_num_threads(1)
    check_out_folder(args.out)
    assets = load_assets(args.assets)
    motion = load_motion(args.motion, duration=args.duration)
    summary = animate(
        assets,
        motion,
        args.out,
        fps=args.fps,
        sim_fps=args.sim_fps,
        duration=args.duration,
        config=XPBDConfig(substeps=args.substeps),
        write_body=not args.no_body_frames,
        gif=not args.no_gif,
        gif_size=args.gif_size,
        progress=not args.json,
        floor=not args.no_floor,
    )
    short = {k: v for k, v in summary.items() if k != "per_frame"}
    if not args.json:
        print(
            f"animated {short['duration_s']:.2f} s ({short['sim_frames']} frames): max penetration "
            f"{100 * short['max_penetration_fraction']:.2f} % of the cloth vertices, max speed "
            f"{short['max_speed_m_s']:.2f} m/s, {short['wall_s']:.0f} s; {args.out}"
        )
    return short


def run_export_template(args) -> dict:
    if not args.spacing > 0:
        raise InputError(f"--spacing must be a positive length in metres, got {args.spacing}")
    torch.set_num_threads(1)
    files = template_assets(args.template, args.out, spacing=args.spacing)
    if not args.json:
        print(f"assets of {args.template!r}: {args.out}")
    return files
