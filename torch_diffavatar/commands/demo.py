"""`diffavatar demo`: the main job on the bundled example scan.

The bundled scan (``torch_diffavatar/data/demo_scan.ply``, made by ``scripts/make_demo_scan.py``) is a
labelled point cloud of a dress with a changed design (hem raised and widened) draped by our simulator on
an Anny body with non-default phenotypes, in a stiffer cloth; its ground truth lies beside it. The demo
fits it from the plain ``dress`` template (`torch_diffavatar.fit_scan.fit_scan` with
``configs/dress.yaml``) and prints ``chamfer_initial → chamfer_final`` (plus the recovered bending
stiffness and phenotypes next to the truth). ``--no-fit`` keeps the old quick path: mesh, preview and
drape the template on the default body.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from torch_diffavatar.commands.out_paths import check_out_folder

DATA_DIR = Path(__file__).resolve().parent.parent / "data"
DEMO_SCAN = DATA_DIR / "demo_scan.ply"
DEMO_TRUTH = DATA_DIR / "demo_truth.json"
DEMO_TRUTH_PATTERN = DATA_DIR / "demo_truth_pattern.json"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo",
        help="fit the bundled example scan (dress) and write the assets",
        description="Fit body, sewing pattern and bending stiffness to the bundled example scan; write the "
        "assets to --out and print chamfer_initial -> chamfer_final.",
    )
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--iters", type=int, default=None, help="fit iterations (default: configs/dress.yaml)")
    p.add_argument("--resume", action="store_true", help="continue a previous demo run in --out")
    p.add_argument("--force", action="store_true", help="replace a previous demo run in --out")
    p.add_argument("--no-fit", action="store_true", help="only mesh, preview and drape the template")
    p.add_argument("--garment", default="dress", help="template for --no-fit (default: dress)")
    p.add_argument("--spacing", type=float, default=0.02, help="mesh spacing [m] for --no-fit (default 0.02)")
    p.add_argument("--no-drape", action="store_true", help="with --no-fit: only mesh and preview the pattern")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    p.set_defaults(func=run_demo)


def run_demo(args) -> dict:
    check_out_folder(args.out)
    if args.no_fit:
        return _preview(args)
    import contextlib
    import sys

    from torch_diffavatar.errors import InputError
    from torch_diffavatar.fit import load_config
    from torch_diffavatar.fit_scan import fit_scan
    from torch_diffavatar.forked import usable_cores

    if not DEMO_SCAN.is_file():
        raise InputError(f"the bundled scan {DEMO_SCAN} is missing (run scripts/make_demo_scan.py)")
    if args.iters is not None and args.iters < 0:
        raise InputError(f"--iters must be >= 0, got {args.iters}")
    config = load_config(garment="dress", iterations=args.iters)
    with contextlib.redirect_stdout(sys.stderr):
        report = fit_scan(
            DEMO_SCAN,
            config,
            args.out,
            resume=args.resume,
            force=args.force,
            progress=not args.no_progress,
            workers=usable_cores(),  # as `diffavatar fit`: the same result on any number of cores
        )
    truth = json.loads(DEMO_TRUTH.read_text()) if DEMO_TRUTH.is_file() else {}
    if DEMO_TRUTH_PATTERN.is_file():
        from torch_diffavatar.evaluation import compare_with_truth
        from torch_diffavatar.json_io import write_json

        true_kb = truth.get("material", {}).get("bend_stiffness")
        report.update(compare_with_truth(args.out, DEMO_TRUTH_PATTERN, true_kb))
        write_json(Path(args.out) / "report.json", report)
    summary = dict(report)
    summary["truth"] = truth
    if not args.json:
        print(
            f"chamfer: {1e3 * report['chamfer_initial']:.2f} mm -> {1e3 * report['chamfer_final']:.2f} mm "
            f"({report['iterations']} iterations, {report['seconds']:.0f} s fit, "
            f"{report['total_seconds']:.0f} s total)"
        )
        kb = report["material"]
        true_kb = truth.get("material", {}).get("bend_stiffness")
        print(
            f"bending stiffness: {kb['bend_stiffness_initial']:.3g} -> {kb['bend_stiffness_final']:.3g} N*m"
            + (f" (truth {true_kb:.3g})" if true_kb else "")
        )
        if "pattern_outline_error_m" in report:
            print(
                f"pattern outline error: {1e2 * report['pattern_outline_error_m']:.2f} cm mean, "
                f"{1e2 * report['pattern_outline_hausdorff_m']:.2f} cm max (worst panel)"
            )
        print(f"assets: {args.out}")
    return summary


def _preview(args) -> dict:
    """The forward pipeline only: mesh the template, write its pictures, drape it on the default body."""
    from torch_diffavatar.mesh_io import write_garment_obj
    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.pattern.svg import save_pattern_png, save_pattern_svg

    os.makedirs(args.out, exist_ok=True)
    start = time.perf_counter()
    pattern = load_template(args.garment)
    garment = mesh_pattern(pattern, spacing=args.spacing)
    files = {
        "pattern_svg": os.path.join(args.out, f"{args.garment}_pattern.svg"),
        "pattern_png": os.path.join(args.out, f"{args.garment}_pattern.png"),
        "rest_obj": os.path.join(args.out, f"{args.garment}_rest.obj"),
    }
    save_pattern_svg(pattern, files["pattern_svg"])
    save_pattern_png(pattern, files["pattern_png"])
    write_garment_obj(files["rest_obj"], garment)
    summary = {
        "garment": args.garment,
        "panels": len(garment.panel_names),
        "vertices": garment.sim_vert_count,
        "faces": garment.tri_count,
    }
    if not args.no_drape:
        summary.update(_drape(args, files))
    summary["seconds"] = round(time.perf_counter() - start, 2)
    summary["files"] = files
    if not args.json:
        for key, value in summary.items():
            print(f"{key}: {value}")
    return summary


def _drape(args, files: dict) -> dict:
    from types import SimpleNamespace

    from torch_diffavatar.commands.drape import run_drape

    files["drape_obj"] = os.path.join(args.out, f"{args.garment}_draped.obj")
    files["drape_png"] = os.path.join(args.out, f"{args.garment}_draped.png")
    drape_args = SimpleNamespace(
        pattern=args.garment,
        body="default",
        spacing=args.spacing,
        out=files["drape_obj"],
        png=files["drape_png"],
        max_steps=None,
        sew_steps=None,
        json=True,
    )
    result = run_drape(drape_args)
    return {f"drape_{k}": v for k, v in result.items()}
