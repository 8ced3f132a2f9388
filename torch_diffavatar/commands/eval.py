"""`diffavatar eval`: a fit's assets measured against a make-scan ground truth."""

from __future__ import annotations

from pathlib import Path

from torch_diffavatar.evaluation import DRAPE_PICTURE, evaluate_assets, save_drape_comparison


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval",
        help="measure a fit's assets against a synthetic scan's ground truth",
        description="Chamfer distances, pattern, body and material errors and mesh quality of the assets "
        "in ASSETS_DIR (a 'diffavatar fit' output) against --gt (a 'diffavatar make-scan' output).",
    )
    p.add_argument("assets", help="the fit's output folder")
    p.add_argument("--gt", required=True, help="the make-scan output folder (scan.ply, truth/)")
    p.add_argument("--json", action="store_true", help="print the measures as one JSON line")
    p.add_argument(
        "--no-picture",
        action="store_true",
        help=f"do not write ASSETS_DIR/{DRAPE_PICTURE} (first drape, fitted and true drape, front and back)",
    )
    p.set_defaults(func=_eval_command)


def _eval_command(args) -> dict:
    out = evaluate_assets(args.assets, args.gt)
    if not args.no_picture:
        save_drape_comparison(args.assets, args.gt, Path(args.assets) / DRAPE_PICTURE)
    if not args.json:
        for key, value in out.items():
            print(f"{key}: {value}")
    return out
