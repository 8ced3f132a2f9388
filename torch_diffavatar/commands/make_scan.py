"""`diffavatar make-scan`: a synthetic clothed scan with ground truth."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from torch_diffavatar.commands.out_paths import check_out_folder
from torch_diffavatar.errors import InputError, read_json_file
from torch_diffavatar.sim_newton import NewtonDrapeConfig
from torch_diffavatar.synthetic_scans import (
    POSE_SEED_OFFSET,
    SIMULATORS,
    below_floor_note,
    make_draped_scan,
    write_scan,
)

# ``--yaw random`` draws from (seed, this), apart from the scan's and the capture's draws.
YAW_SEED_OFFSET = 2001


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "make-scan",
        help="make a synthetic clothed scan with ground truth (changed template draped on an Anny body)",
        description="Drape a template with a changed hem on an Anny body, sample it as a noisy, holey "
        "labelled point cloud (scan.ply) and write the ground truth into --out/truth.",
    )
    p.add_argument("template", help="garment template name or GarmentCode JSON")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--phenotypes", default=None, help="e.g. 'weight=0.6,height=0.4' (others 0.5; default: all random)"
    )
    p.add_argument(
        "--pose",
        default="a",
        help="'a' (the A-pose, default), 'random' (a random plausible pose from --seed) or a JSON file "
        "{bone: [rx, ry, rz]} of axis-angles [rad] of the posed bones (others stay at the A-pose)",
    )
    p.add_argument("--bend-stiffness", type=float, default=2.0e-5, help="[N*m] (default 2e-5)")
    p.add_argument("--hem-up", type=float, default=0.05, help="hem raised by [m] (default 0.05)")
    p.add_argument("--hem-widen", type=float, default=0.1, help="hem widened by [-] (default 0.1)")
    p.add_argument("--spacing", type=float, default=0.02, help="drape mesh spacing [m] (default 0.02)")
    p.add_argument("--noise", type=float, default=0.003, help="noise sigma [m] (default 0.003)")
    p.add_argument("--holes", type=float, default=0.1, help="fraction cut away in holes (default 0.1)")
    p.add_argument("--no-underarm-holes", action="store_true", help="keep the points under the arms")
    p.add_argument("--missing-bottom", type=float, default=0.0, help="drop points below this height [m]")
    p.add_argument("--garment-points", type=int, default=40000, help="cloth samples before holes (40000)")
    p.add_argument("--body-points", type=int, default=30000, help="skin samples before holes (30000)")
    p.add_argument(
        "--simulator",
        choices=SIMULATORS,
        default="ours",
        help="who makes the truth's final drape: 'ours' (default) or 'newton' (NVIDIA Newton's VBD cloth "
        'with a random material from --seed; needs pip install -e ".[newton]")',
    )
    p.add_argument(
        "--waist-drop",
        type=float,
        default=None,
        help="with --simulator newton: a skirt / trousers sits this much lower on the body [m] (default: "
        "random in [0, 0.08] from --seed; 0 for other garments)",
    )
    p.add_argument(
        "--newton-iterations",
        type=int,
        default=None,
        help=f"with --simulator newton: VBD iterations per step (default {NewtonDrapeConfig.iterations}: a "
        "few mm from where more would bring the drape; at 10, the default before, it hung cm longer)",
    )
    p.add_argument(
        "--no-floor",
        action="store_true",
        help="drape without a floor at the soles: a garment longer than the legs hangs through it instead "
        "of piling on it (the truths before this option)",
    )
    p.add_argument("--json", action="store_true", help="print the ground-truth summary as one JSON line")
    _capture_args(p)
    p.set_defaults(func=_make_scan_command)


def _capture_args(p) -> None:
    """The simulated depth capture's options (`captured_scans`); ``--capture none`` keeps the sampled scan."""
    from torch_diffavatar.scan import UNITS, UP_AXES

    g = p.add_argument_group("depth capture (instead of the sampled scan)")
    g.add_argument(
        "--capture",
        default="none",
        choices=("none", "ring", "front"),
        help="'ring': --cameras depth cameras around the person, 'front': one in front; with a floor, "
        "stray points, colours and normals (default none: the sampled scan)",
    )
    g.add_argument("--cameras", type=int, default=4, help="ring cameras (default 4)")
    g.add_argument("--yaw", default="0", help="turn of the whole capture [deg], or 'random' (default 0)")
    g.add_argument("--scan-units", default="m", choices=tuple(UNITS), help="units of scan.ply (default m)")
    g.add_argument(
        "--scan-up",
        default="y",
        choices=tuple(UP_AXES),
        help="up axis of scan.ply (default y)",
    )
    g.add_argument("--camera-distance", type=float, default=2.2, help="[m], 1.5..3 (default 2.2)")
    g.add_argument("--resolution", default="640x480", help="depth image WxH [px] (default 640x480)")
    g.add_argument(
        "--flying-pixels",
        type=float,
        default=0.0,
        help="share of the pixels at a silhouette that return a depth between the two surfaces (default 0)",
    )
    g.add_argument(
        "--calibration-error",
        nargs=2,
        type=float,
        default=(0.0, 0.0),
        metavar=("MM", "DEG"),
        help="each camera's pose off by this translation [mm] and rotation [deg] (standard deviations; "
        "default 0 0)",
    )


def _capture_settings(args):
    """`CaptureSettings` from the arguments, or None for ``--capture none`` (InputError on bad values)."""
    import numpy as np

    from torch_diffavatar.capture import CaptureSettings

    changed = [
        flag
        for flag, value, default in (
            ("--cameras", args.cameras, 4),
            ("--yaw", args.yaw, "0"),
            ("--scan-units", args.scan_units, "m"),
            ("--scan-up", args.scan_up, "y"),
            ("--camera-distance", args.camera_distance, 2.2),
            ("--resolution", args.resolution, "640x480"),
            ("--flying-pixels", args.flying_pixels, 0.0),
            ("--calibration-error", tuple(args.calibration_error), (0.0, 0.0)),
        )
        if value != default
    ]
    if args.capture == "none":
        if changed:
            raise InputError(f"{', '.join(changed)} need --capture ring or --capture front")
        return None
    if args.yaw.lower() == "random":
        yaw = float(np.random.default_rng([args.seed, YAW_SEED_OFFSET]).uniform(0.0, 360.0))
    else:
        try:
            yaw = float(args.yaw)
        except ValueError as exc:
            raise InputError(f"--yaw: {args.yaw!r} is neither a number of degrees nor 'random'") from exc
    width, _, height = args.resolution.lower().partition("x")
    if not (width.isdigit() and height.isdigit()):
        raise InputError(f"--resolution: {args.resolution!r} is not WIDTHxHEIGHT, e.g. 640x480")
    settings = CaptureSettings(
        layout=args.capture,
        cameras=args.cameras,
        distance=args.camera_distance,
        width=int(width),
        height=int(height),
        yaw_deg=round(yaw, 3),
        units=args.scan_units,
        up=args.scan_up,
        flying_pixels=args.flying_pixels,
        calibration_m=1e-3 * args.calibration_error[0],
        calibration_deg=args.calibration_error[1],
    )
    settings.check()
    return settings


def _parse_phenotypes(text: str | None) -> dict[str, float] | None:
    """``"weight=0.6,height=0.4"`` -> a dict (phenotypes not named keep `BodyModel`'s default 0.5)."""
    if not text:
        return None
    labels = ("gender", "age", "muscle", "weight", "height", "proportions")
    values = {}
    for item in text.split(","):
        name, _, value = item.partition("=")
        if name.strip() not in labels:
            raise InputError(f"--phenotypes: unknown phenotype {name.strip()!r}; use {', '.join(labels)}")
        try:
            values[name.strip()] = float(value)
        except ValueError as exc:
            raise InputError(f"--phenotypes: {item!r} is not name=number") from exc
        if not 0.0 <= values[name.strip()] <= 1.0:
            raise InputError(f"--phenotypes: {item!r} must lie in [0, 1]")
    return values


def _parse_pose(text: str, seed: int) -> torch.Tensor | None:
    """``--pose``: None (the A-pose), a random pose seeded by ``seed``, or (1, K, 3) from a JSON file."""
    from torch_diffavatar.body.model import pose_from_bones
    from torch_diffavatar.body.synthetic import random_pose

    if text.lower() in ("a", "a-pose"):
        return None
    if text.lower() == "random":
        # A generator of its own, so that the phenotypes drawn from the seed stay those of the A-pose scan.
        return random_pose(torch.Generator().manual_seed(seed + POSE_SEED_OFFSET))
    bones = read_json_file(text, f"--pose: {text!r} is neither 'a', 'random' nor a JSON file")
    return pose_from_bones(bones, f"--pose {text}")[None]


def _newton_config(args):
    """`sim_newton.NewtonDrapeConfig` of ``--newton-iterations`` (None: not given)."""
    if args.newton_iterations is None:
        return None
    if args.simulator != "newton" or args.newton_iterations < 1:
        raise InputError(
            f"--newton-iterations needs --simulator newton and at least 1, got {args.newton_iterations} "
            f"with --simulator {args.simulator}"
        )
    return NewtonDrapeConfig(iterations=args.newton_iterations)


def _make_scan_command(args) -> dict:
    settings = _capture_settings(args)  # bad capture options fail before the drape
    check_out_folder(args.out)
    scan = make_draped_scan(
        args.template,
        seed=args.seed,
        phenotypes=_parse_phenotypes(args.phenotypes),
        pose=_parse_pose(args.pose, args.seed),
        bend_stiffness=args.bend_stiffness,
        hem_up=args.hem_up,
        hem_widen=args.hem_widen,
        spacing=args.spacing,
        noise=args.noise,
        hole_fraction=args.holes,
        underarm_holes=not args.no_underarm_holes,
        missing_bottom=args.missing_bottom,
        garment_points=args.garment_points,
        body_points=args.body_points,
        simulator=args.simulator,
        waist_drop=args.waist_drop,
        floor=not args.no_floor,
        newton_config=_newton_config(args),
    )
    captured = None
    if settings is not None:
        from torch_diffavatar.captured_scans import capture_draped_scan

        scan, captured = capture_draped_scan(scan, settings, args.seed)
    paths = write_scan(scan, args.out, capture=captured)
    note = below_floor_note(scan.info)
    if note is not None:
        print(f"diffavatar make-scan: warning: {note}", file=sys.stderr)
    summary = dict(scan.info, files=paths)
    if not args.json:
        print(f"scan: {paths['scan']} ({len(scan.points)} points); truth: {Path(paths['truth']).parent}")
    return summary
