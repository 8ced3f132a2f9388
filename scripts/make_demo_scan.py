"""Make the bundled example scan of `diffavatar demo` (torch_diffavatar/data/demo_scan.ply + ground truth).

A known answer to fit: the ``dress`` template with a changed design (skirt hem shortened by ``--hem-up``
and widened by ``--hem-widen``), sewn and draped with our simulator at a finer spacing than the fit's on
an Anny body with non-default phenotypes, in a cloth with a changed bending stiffness. The drape and the
visible body skin are sampled as a labelled point cloud (label 1 = garment, 0 = body) with Gaussian
noise, written as a small ASCII PLY, with the ground truth beside it:

* ``demo_scan.ply``: x y z label;
* ``demo_truth_pattern.json``: the changed pattern (GarmentCode);
* ``demo_truth.json``: phenotypes, body translation, material, spacing, noise, seed.

Usage: ``PYTHONPATH=. python scripts/make_demo_scan.py [--out torch_diffavatar/data]``
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

PHENOTYPES = {"gender": 0.5, "age": 0.5, "muscle": 0.5, "weight": 0.57, "height": 0.56, "proportions": 0.5}
BEND_STIFFNESS = 2.0e-5  # [N·m], 4× the default medium cotton


def area_sample(verts: np.ndarray, faces: np.ndarray, count: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(count, 3) points uniformly on a triangle mesh and the (count,) face of each."""
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(faces), count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return (bary[:, :, None] * tri[face]).sum(1), face


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", default="torch_diffavatar/data", help="output folder")
    parser.add_argument("--spacing", type=float, default=0.02, help="drape mesh spacing [m]")
    parser.add_argument("--hem-up", type=float, default=0.08, help="hem raised by [m]")
    parser.add_argument("--hem-widen", type=float, default=0.12, help="hem widened by [-]")
    parser.add_argument("--garment-points", type=int, default=14000)
    parser.add_argument("--body-points", type=int, default=12000)
    parser.add_argument("--noise", type=float, default=0.0015, help="Gaussian noise sigma [m]")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    torch.set_num_threads(1)

    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.geometry import vertex_normals
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.pattern import load_template, mesh_pattern, save_pattern
    from torch_diffavatar.pattern.design import changed_pattern
    from torch_diffavatar.scan import save_ply
    from torch_diffavatar.sim.forward_drape import sew_and_drape
    from torch_diffavatar.sim.material import ClothMaterial
    from torch_diffavatar.sim.placement import place_garment
    from torch_diffavatar.synthetic_scans import covered_by

    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    body = BodyModel(anny_model=load_anny(dtype=torch.float32))
    body.set_phenotypes(PHENOTYPES)
    with torch.no_grad():
        verts = body().vertices[0]
        body.translation[0, 1] -= verts[:, 1].min()  # feet on the floor
        verts = body().vertices[0]
        vn = vertex_normals(verts, body.faces)
    pattern = changed_pattern(load_template("dress"), args.hem_up, args.hem_widen)
    garment = place_garment(mesh_pattern(pattern, spacing=args.spacing), verts.double(), body.faces)
    material = ClothMaterial(bend_stiffness=BEND_STIFFNESS)
    result = sew_and_drape(garment, body_verts=verts, body_faces=body.faces, material=material)
    print(f"drape: {result.steps} frames, converged {result.converged}, {result.diagnostics}")
    cloth = result.x.double().numpy()
    g_pts, _ = area_sample(cloth, garment.sim_faces.numpy(), args.garment_points, rng)
    bv, bf = verts.double().numpy(), body.faces.numpy()
    b_pts, b_face = area_sample(bv, bf, args.body_points * 2, rng)
    b_n = vn.double().numpy()[bf[b_face]].mean(1)
    b_n /= np.linalg.norm(b_n, axis=1, keepdims=True)
    b_pts = b_pts[~covered_by(b_pts, b_n, cloth)][: args.body_points]
    points = np.concatenate([g_pts, b_pts]) + rng.normal(0.0, args.noise, (len(g_pts) + len(b_pts), 3))
    labels = np.concatenate([np.ones(len(g_pts), dtype=np.int64), np.zeros(len(b_pts), dtype=np.int64)])
    save_ply(out / "demo_scan.ply", points, int_properties={"label": labels})
    save_pattern(pattern, out / "demo_truth_pattern.json")
    truth = {
        "template": "dress",
        "design_change": {"hem_up_m": args.hem_up, "hem_widen": args.hem_widen},
        "phenotypes": dict(zip(body.phenotype_labels, body.phenotypes[0].tolist())),
        "body_translation_m": body.translation[0].tolist(),
        "material": {"bend_stiffness": BEND_STIFFNESS, "unit": "N*m"},
        "spacing_m": args.spacing,
        "noise_sigma_m": args.noise,
        "seed": args.seed,
        "points": {"garment": int(len(g_pts)), "body": int(len(b_pts))},
        "drape": {"frames": int(result.steps), "converged": bool(result.converged)},
    }
    (out / "demo_truth.json").write_text(json.dumps(truth, indent=1))
    size = (out / "demo_scan.ply").stat().st_size
    print(
        f"wrote {out / 'demo_scan.ply'} ({size / 1e6:.2f} MB, {len(points)} points) "
        f"in {time.perf_counter() - t0:.0f} s"
    )


if __name__ == "__main__":
    main()
