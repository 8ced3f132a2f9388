"""`diffavatar eval`: a fit's assets measured against a make-scan ground truth."""

from __future__ import annotations

from pathlib import Path

from torch_diffavatar.evaluation import DRAPE_PICTURE, evaluate_assets, save_drape_comparison

# the keys the text report shows first, in its own units; everything else follows as "key: value"
_SHOWN = (
    "units",
    "pattern_outline_error_m",
    "pattern_outline_hausdorff_m",
    "pattern_outline_errors",
    "garment_measurements",
    "garment_measurement_max_error_cm",
    "garment_area_m2",
    "chamfer_truth_drape_m",
    "chamfer_truth_drape_initial_m",
    "chamfer_scan_m",
    "chamfer_scan_initial_m",
    "chamfer_scan_truth_m",
)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval",
        help="measure a fit's assets against a synthetic scan's ground truth",
        description="The pattern against the true one first (outline error, garment measurements: "
        "circumferences and lengths in cm), then Chamfer distances to the true drape and to the scan, then "
        "body and material errors and mesh quality of the assets in ASSETS_DIR (a 'diffavatar fit' "
        "output) against --gt (a 'diffavatar make-scan' output). --json keeps every measure in metres.",
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
    if not args.json:
        print("\n".join(report_lines(out)))
    if not args.no_picture:
        save_drape_comparison(args.assets, args.gt, Path(args.assets) / DRAPE_PICTURE)
    return out


def report_lines(out: dict) -> list[str]:
    """The text report of `evaluate_assets`' measures, truth first: the pattern (outline error, garment
    measurements [cm]), then the drape against the true drape and against the scan [mm], then the rest
    as ``key: value`` (metres, as in the JSON)."""
    outline, outline_max = 100 * out["pattern_outline_error_m"], 100 * out["pattern_outline_hausdorff_m"]
    lines = [
        "pattern vs the true pattern:",
        f"  outline error (worst panel, rigidly aligned): {outline:.2f} cm mean, {outline_max:.2f} cm max",
        "  per panel [cm, mean / max]: "
        + ", ".join(
            f"{name} {100 * e['mean_m']:.2f} / {100 * e['max_m']:.2f}"
            for name, e in out["pattern_outline_errors"].items()
        ),
    ]
    lines += _measurement_lines(out)
    mm = lambda key: f"{1000 * out[key]:.2f} mm"  # noqa: E731
    first = lambda key: f" (first drape {mm(key)})" if key in out else ""  # noqa: E731
    lines += [
        "drape:",
        f"  Chamfer to the true drape: {mm('chamfer_truth_drape_m')}{first('chamfer_truth_drape_initial_m')}",
        f"  Chamfer to the scan: {mm('chamfer_scan_m')}{first('chamfer_scan_initial_m')}; the true drape's "
        f"own, the floor: {mm('chamfer_scan_truth_m')}",
        "the rest (lengths in m):",
    ]
    lines += [f"  {key}: {value}" for key, value in out.items() if key not in _SHOWN]
    return lines


def _measurement_lines(out: dict) -> list[str]:
    """The garment measurements table [cm] and the pattern area [m²] (nothing for older results)."""
    table = out.get("garment_measurements")
    if not table:
        return []
    width = max(len(name) for name in table)
    lines = [f"  {'garment measurements [cm]':<{width + 2}} {'fitted':>8} {'true':>8} {'error':>8}"]
    for name, row in table.items():
        lines.append(
            f"    {name:<{width}} {row['fitted_cm']:8.2f} {row['true_cm']:8.2f} {row['error_cm']:+8.2f}"
        )
    lines.append(f"  largest measurement error: {out['garment_measurement_max_error_cm']:.2f} cm")
    area = out["garment_area_m2"]
    lines.append(
        f"  pattern area: {area['fitted_m2']:.4f} m² fitted, {area['true_m2']:.4f} m² true "
        f"({100 * area['error_m2'] / area['true_m2']:+.1f} %)"
    )
    return lines
