"""`diffavatar mesh`: mesh a sewing pattern (file or template name), report its quality, export it."""

from __future__ import annotations

from torch_diffavatar.commands.out_paths import check_out_files
from torch_diffavatar.errors import PatternError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "mesh",
        help="triangulate a sewing pattern (GarmentCode JSON or template name) and export it",
        description="Mesh a sewing pattern into a seam-merged garment; print quality measures.",
    )
    p.add_argument("pattern", help="GarmentCode *_specification.json file, or a template name (e.g. dress)")
    p.add_argument("--spacing", type=float, default=0.015, help="target edge length [m] (default 0.015)")
    p.add_argument("--min-angle", type=float, default=25.0, help="minimum triangle angle [deg] (default 25)")
    p.add_argument("--out", help="write the garment as OBJ (v = sewn vertices, vt = rest coordinates [m])")
    p.add_argument("--svg", help="write the pattern picture as SVG")
    p.add_argument("--png", help="write the pattern picture as PNG")
    p.add_argument("--json", action="store_true", help="print the result as one JSON line")
    p.set_defaults(func=run_mesh)


def run_mesh(args) -> dict:

    from torch_diffavatar.metrics import quality_summary
    from torch_diffavatar.pattern.library import resolve_pattern
    from torch_diffavatar.pattern.mesher import mesh_pattern, mesh_report

    if not args.spacing > 0:
        raise PatternError(f"--spacing must be a positive length in metres, got {args.spacing}")
    if not 0 < args.min_angle <= 34:
        raise PatternError(f"--min-angle must be in (0, 34] degrees, got {args.min_angle}")
    check_out_files(args, "out", "svg", "png")
    pattern = resolve_pattern(args.pattern)
    garment = mesh_pattern(pattern, spacing=args.spacing, min_angle=args.min_angle)
    report = mesh_report(pattern, garment)
    q = quality_summary(garment.vert_uv, garment.tri_vertices)
    if args.out:
        from torch_diffavatar.mesh_io import write_garment_obj

        write_garment_obj(args.out, garment)
    if args.svg or args.png:
        from torch_diffavatar.pattern.svg import save_pattern_png, save_pattern_svg

        if args.svg:
            save_pattern_svg(pattern, args.svg)
        if args.png:
            save_pattern_png(pattern, args.png)
    result = {
        "panels": len(garment.panel_names),
        "vertices": garment.sim_vert_count,
        "faces": garment.tri_count,
        "stitch_pairs": int(garment.stitch_pairs.shape[0]),
        "boundary_loops": len(garment.boundary_loops),
        "min_angle_deg": round(float(q.min_angle_deg), 4),
        "quality_min": round(float(q.quality_min), 4),
        "quality_mean": round(float(q.quality_mean), 4),
        "max_stitch_count_mismatch": report.max_stitch_count_mismatch,
    }
    if not args.json:
        loops = ", ".join(f"{b.name} ({len(b.vertices)})" for b in garment.boundary_loops)
        print(
            f"{args.pattern}: {result['panels']} panels, {result['vertices']} vertices, "
            f"{result['faces']} faces, {result['stitch_pairs']} stitch pairs; "
            f"min angle {result['min_angle_deg']:.2f} deg, quality "
            f"min {result['quality_min']:.3f} mean {result['quality_mean']:.3f}; openings: {loops}"
        )
    return result
