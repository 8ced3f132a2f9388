"""`diffavatar make-scan`: a synthetic clothed scan with ground truth."""

from __future__ import annotations

from pathlib import Path

import torch

from torch_diffavatar.errors import InputError, read_json_file
from torch_diffavatar.synthetic_scans import POSE_SEED_OFFSET, SIMULATORS, make_draped_scan, write_scan


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
    p.add_argument("--json", action="store_true", help="print the ground-truth summary as one JSON line")
    p.set_defaults(func=_make_scan_command)


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


def _make_scan_command(args) -> dict:
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
    )
    paths = write_scan(scan, args.out)
    summary = dict(scan.info, files=paths)
    if not args.json:
        print(f"scan: {paths['scan']} ({len(scan.points)} points); truth: {Path(paths['truth']).parent}")
    return summary
