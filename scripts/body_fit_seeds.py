"""Report the initial body fit's accuracy over several random synthetic scans (issue #5's targets).

For each seed: a bare scan (random Anny phenotypes and plausible pose, 20k surface samples, 20 % cut
away in holes, 1 cm noise) and the same kind of scan under a stand-in dress layer. Prints one line per
scan with the height error, the mean vertex error, the fraction of covered body vertices inside the
garment layer, the colour-free segmentation recall/precision, and the CPU time of the fit (1 thread).
A third scan per seed (``--draped``) is a garment draped by our simulator (`synthetic_scans`); there
"inside" is the fraction of the cloth outside the fitted body.

    PYTHONPATH=. python scripts/body_fit_seeds.py --seeds 0 1 2 3 4
    PYTHONPATH=. python scripts/body_fit_seeds.py --bare-only --seeds 0 1 2 3 4 5 6 7 8 9
    PYTHONPATH=. python scripts/body_fit_seeds.py --missing-bottom 0.3  # scans that miss the feet
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torch_diffavatar.body.anny_model import load_anny
from torch_diffavatar.body.fit import fit_body
from torch_diffavatar.body.geometry import vertex_normals
from torch_diffavatar.body.segment import segment_garment
from torch_diffavatar.body.synthetic import make_scan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--garment", default="dress")
    parser.add_argument(
        "--draped",
        default="dress",
        help="template draped by the simulator for the third scan of each seed ('' to skip)",
    )
    parser.add_argument(
        "--bare-only", action="store_true", help="fit only the bare scan of each seed (no garment scans)"
    )
    parser.add_argument(
        "--missing-bottom",
        type=float,
        default=0.0,
        help="drop every scan's points below this height [m] above its lowest point (a capture that "
        "misses the feet)",
    )
    args = parser.parse_args()
    if args.bare_only:
        args.garment, args.draped = None, ""
    torch.set_num_threads(1)
    anny_model = load_anny(dtype=torch.float64)
    faces = anny_model.faces
    rows = []
    for seed in args.seeds:
        for garment in (None, args.garment) if args.garment else (None,):
            scan = make_scan(anny_model, seed=seed, garment=garment)
            keep = _kept(scan.points, args.missing_bottom)
            scan.points, scan.labels = scan.points[keep], scan.labels[keep]
            cpu = time.process_time()
            result = fit_body(scan.points, anny_model=anny_model)
            cpu = time.process_time() - cpu
            with torch.no_grad():
                verts = result.body().vertices[0].double().numpy()
            row = {
                "seed": seed,
                "scan": garment or "bare",
                "height_err_cm": 100 * (result.height_m - scan.height),
                "vertex_err_cm": 100 * np.linalg.norm(verts - scan.body_vertices, axis=1).mean(),
                "cpu_s": cpu,
                **_start_fields(result),
            }
            if garment is not None:
                normals = vertex_normals(torch.from_numpy(scan.body_vertices), faces).numpy()
                gap = ((scan.layer_vertices - verts) * normals).sum(1)[scan.covered]
                seg = segment_garment(
                    scan.points, garment, verts, faces.numpy(), result.body.vertex_parts.numpy()
                )
                truth = scan.labels == 1
                row["inside"] = float((gap >= 0).mean())
                row["seg_recall"] = float((seg.labels & truth).sum() / truth.sum())
                row["seg_precision"] = float((seg.labels & truth).sum() / max(seg.labels.sum(), 1))
            rows.append(row)
            _print_row(row)
        if args.draped:
            rows.append(_draped_row(anny_model, seed, args.draped, args.garment, args.missing_bottom))
            _print_row(rows[-1])
    kinds = ("bare",) + ((args.garment,) if args.garment else ())
    kinds += (f"draped {args.draped}",) if args.draped else ()
    for kind in kinds:
        sel = [r for r in rows if r["scan"] == kind]
        worst_h = max(abs(r["height_err_cm"]) for r in sel)
        worst_v = max(r["vertex_err_cm"] for r in sel)
        line = f"{kind}: worst |height err| {worst_h:.2f} cm, worst vertex err {worst_v:.2f} cm"
        if kind != "bare":
            line += f", worst inside {min(r['inside'] for r in sel):.3f}"
            line += f", worst seg recall {min(r['seg_recall'] for r in sel):.3f}"
        line += f", max cpu {max(r['cpu_s'] for r in sel):.1f} s"
        print(line)


def _kept(points: np.ndarray, missing_bottom: float) -> np.ndarray:
    """(N,) bool: the points higher than ``missing_bottom`` [m] above the lowest one (all if 0)."""
    return points[:, 1] >= points[:, 1].min() + missing_bottom


def _start_fields(result) -> dict:
    """Which start of the body fit won, and the pose-stage loss of each (`BodyFitConfig.head_start`)."""
    return {"start": result.start, **{k: v for k, v in result.losses.items() if k.startswith("pose_")}}


def _print_row(row: dict) -> None:
    text = (f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items())
    print("  ".join(text), flush=True)


def _draped_row(anny_model, seed: int, template: str, garment_type: str, missing_bottom: float) -> dict:
    """The same measures on a scan of ``template`` draped by our simulator (`make_draped_scan`: moderate
    random phenotypes, A-pose, 3 mm noise, 10 % holes plus underarm holes)."""
    from torch_diffavatar.sim.placement import body_signed_distance
    from torch_diffavatar.synthetic_scans import make_draped_scan

    scan = make_draped_scan(template, anny_model=anny_model, seed=seed, spacing=0.03)
    keep = _kept(scan.points, missing_bottom)
    points, labels = scan.points[keep], scan.labels[keep]
    cpu = time.process_time()
    result = fit_body(points, anny_model=anny_model)
    cpu = time.process_time() - cpu
    with torch.no_grad():
        verts = result.body().vertices[0].double()
    faces = torch.as_tensor(scan.body_faces)
    sd = np.asarray(body_signed_distance(torch.as_tensor(scan.cloth_x), verts, faces))
    seg = segment_garment(
        points, garment_type, verts.numpy(), scan.body_faces, result.body.vertex_parts.numpy()
    )
    truth = labels == 1
    return {
        "seed": seed,
        "scan": f"draped {template}",
        "height_err_cm": 100 * (result.height_m - scan.height),
        "vertex_err_cm": 100 * float(np.linalg.norm(verts.numpy() - scan.body_vertices, axis=1).mean()),
        "cpu_s": cpu,
        **_start_fields(result),
        "inside": float((sd >= -0.002).mean()),  # cloth outside the fitted body (within 2 mm)
        "seg_recall": float((seg.labels & truth).sum() / truth.sum()),
        "seg_precision": float((seg.labels & truth).sum() / max(seg.labels.sum(), 1)),
    }


if __name__ == "__main__":
    main()
