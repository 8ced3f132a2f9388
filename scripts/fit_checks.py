#!/usr/bin/env python
"""Two checks of the fit on a benchmark-suite scan: how far can it get, and is its gradient right?

``oracle GARMENT_DIR``: the fit's first drape started from the scan's TRUE pattern and bending stiffness
(``GARMENT_DIR/scan/truth/``), with the garment's fit config. Its Chamfer is what a perfect recovery of
the pattern and the material would score at the fit's spacing and XPBD settings: the floor of that
config, against which the template start and the fit's result can be read. ``--iterations N`` then runs
N fit iterations from there (does the fit stay at the truth?); ``--true-body`` starts from the true body
(``truth/body.json``) instead of fitting one (how much does the body fit cost?).

    PYTHONPATH=. python scripts/fit_checks.py oracle /tmp/suite/tshirt --set drape_substeps=10

``fd FIT_DIR``: a directional finite-difference check of the fit's gradient w.r.t. the cage handles at
the first drape, from a fit folder (its ``setup.pt`` and ``config.yaml``): the loss at the handles moved
by ±ε along the normalised gradient, central difference against the gradient's norm (equal when the
adjoint is exact and the drape is smooth in the pattern at that scale).

    PYTHONPATH=. python scripts/fit_checks.py fd /tmp/suite/tshirt/fit --set drape_substeps=40

``spacing GARMENT_DIR --spacings 0.025 0.02``: how much the drape itself depends on the mesh: the
scan's TRUE pattern, material and body, meshed at each spacing and draped like the scan was (sewn from
the placement), and the same mesh started from the true drape (`placement.place_from_drape`: no sewing,
the scan's fold state), each against the true drape (symmetric mean surface distance). A fit at a coarser
spacing than its scan cannot come closer to the true drape than these, whatever pattern it finds. Also
``pattern_file_sewn_mm``: ``truth/pattern.json`` stores centimetres, and when its round trip moves a
vertex by an ulp and so meshes it otherwise at the scan's own spacing, that mesh's drape against the true
one (how chaotic the drape is; null when the file meshes exactly like the truth).

    PYTHONPATH=. python scripts/fit_checks.py spacing /tmp/suite/longsleeve --spacings 0.025 0.02

``body GARMENT_DIR --offsets 0 0.001 -0.001``: how much the drape depends on the body: the scan's TRUE
pattern at the scan's own spacing, sewn like the scan was on the true body grown along its normals by
each offset [m] (negative: thinner), against the true drape (``sewn_mm``) and against the scan
(``sewn_scan_mm``; the true drape's own: ``truth_scan_mm``). A fitted body is never exact (the suite's
are 1–3 mm off the true surface); where a millimetre moves the drape by more than a fit's target allows,
no fit of that body reaches it. Offset 0 reproduces the true drape (0.00 mm).

    PYTHONPATH=. python scripts/fit_checks.py body /tmp/suite/polo --offsets 0 0.001 -0.001

``--set key=value`` overrides any `FitConfig` field (``weights.name=value`` for a loss weight); values
are read as YAML. Prints one JSON line; lengths in mm.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _config(path, sets):
    from torch_diffavatar.fit import config_from_dict, load_config

    config = load_config(path)
    data: dict = {}
    for item in sets:
        key, _, value = item.partition("=")
        if key.startswith("weights."):
            data.setdefault("weights", {})[key.removeprefix("weights.")] = yaml.safe_load(value)
        else:
            data[key] = yaml.safe_load(value)
    return config_from_dict(data, base=config, source="--set") if data else config


def oracle(args) -> dict:
    from torch_diffavatar.evaluation import evaluate_assets
    from torch_diffavatar.fit import CONFIG_DIR, config_from_dict
    from torch_diffavatar.fit_scan import fit_scan
    from torch_diffavatar.pattern import load_pattern

    scan_dir = Path(args.garment_dir) / "scan"
    truth = json.loads((scan_dir / "truth" / "truth.json").read_text())
    config = _config(CONFIG_DIR / f"{truth['template']}.yaml", args.set)
    kb = float(truth["material"]["bend_stiffness"])
    config = config_from_dict({"initial_bend_stiffness": kb, "iterations": args.iterations}, base=config)
    out = Path(args.out)
    pattern = load_pattern(scan_dir / "truth" / "pattern.json")
    body_params = json.loads((scan_dir / "truth" / "body.json").read_text()) if args.true_body else None
    report = fit_scan(
        scan_dir / "scan.ply",
        config,
        out,
        progress=False,
        pattern=pattern,
        body_params=body_params,
        force=True,
    )
    ev = evaluate_assets(out, scan_dir)
    mm = {
        k.removesuffix("_m"): round(1e3 * ev[k], 2)
        for k in ev
        if k.startswith("chamfer_") and isinstance(ev[k], float)
    }
    return {
        "check": "oracle",
        "garment": truth["template"],
        "config": {"spacing": config.spacing, "drape_substeps": config.drape_substeps},
        "iterations": args.iterations,
        "body": "true" if args.true_body else "fitted",
        "chamfer_mm": mm,
        # against a fit's report.json (loss_final): does the fit's loss prefer the truth to its result?
        "loss_initial": report["loss_initial"],
        "loss_final": report["loss_final"],
        "boundary_chamfer_initial_mm": {
            k: round(1e3 * v, 1) for k, v in report["boundary_chamfer_initial"].items()
        },
        "bending_stiffness_ratio": ev["bending_stiffness_ratio"],
    }


class _TrueDrape:
    """The scan's truth (``GARMENT_DIR/scan/truth``): its pattern meshed exactly as the true drape, its body
    and material, and the scan's drape settings, to sew it again under a changed condition."""

    def __init__(self, garment_dir):
        from torch_diffavatar.fit import with_fit_strain_limit
        from torch_diffavatar.mesh_io import read_obj
        from torch_diffavatar.pattern import load_pattern, mesh_pattern
        from torch_diffavatar.pattern.design import changed_pattern
        from torch_diffavatar.pattern.library import resolve_pattern
        from torch_diffavatar.sim.forward_drape import DrapeConfig
        from torch_diffavatar.sim.material import ClothMaterial

        truth_dir = Path(garment_dir) / "scan" / "truth"
        self.truth = json.loads((truth_dir / "truth.json").read_text())
        body, self.draped = read_obj(truth_dir / "body.obj"), read_obj(truth_dir / "draped.obj")
        # The true drape's own mesh: pattern.json stores centimetres, and its round trip can move a vertex
        # by an ulp, which is enough to mesh it otherwise; the template with the design change is exact.
        design = self.truth["design_change"]
        candidates = (
            changed_pattern(resolve_pattern(self.truth["template"]), design["hem_up_m"], design["hem_widen"]),
            load_pattern(truth_dir / "pattern.json"),
        )
        self.meshes = [mesh_pattern(p, spacing=float(self.truth["spacing_m"])) for p in candidates]
        self.exact = [k for k, m in enumerate(self.meshes) if torch.equal(m.sim_faces, self.draped.faces)]
        if not self.exact:
            raise SystemExit(f"{truth_dir}/draped.obj is not the true pattern meshed at the scan's spacing")
        self.pattern, self.source = candidates[self.exact[0]], self.meshes[self.exact[0]]
        self.body_verts, self.body_faces = body.verts.float(), body.faces
        self.material = ClothMaterial(bend_stiffness=float(self.truth["material"]["bend_stiffness"]))
        # the scan's drape settings (make_draped_scan), with the fit's strain limit: sewing a coarse mesh
        # can pull a seam-corner triangle past the solver's default for a few frames
        self.config = with_fit_strain_limit(DrapeConfig())

    def to_truth(self, x, faces) -> float:
        """Symmetric mean surface distance of a drape to the true drape [mm]."""
        from torch_diffavatar.evaluation import mesh_distance_m

        return round(1e3 * mesh_distance_m(x.double(), faces, self.draped.verts, self.draped.faces), 2)

    def sewn(self, garment, body_verts=None):
        """``garment`` placed and sewn like the scan was, on the true body or on ``body_verts`` (V, 3) [m]."""
        from torch_diffavatar.sim.forward_drape import sew_and_drape
        from torch_diffavatar.sim.placement import place_garment

        body_verts = self.body_verts if body_verts is None else body_verts
        return sew_and_drape(
            place_garment(garment, body_verts.double(), self.body_faces),
            body_verts=body_verts,
            body_faces=self.body_faces,
            material=self.material,
            config=self.config,
        )


def spacing(args) -> dict:
    from torch_diffavatar.pattern import mesh_pattern
    from torch_diffavatar.sim.forward_drape import drape_to_equilibrium
    from torch_diffavatar.sim.model import ClothModelBuilder
    from torch_diffavatar.sim.placement import place_from_drape

    t = _TrueDrape(args.garment_dir)
    # the drape's own chaos: pattern.json meshed at the scan's spacing, when its ulp moved the mesh
    file_mesh = t.meshes[1]
    file_mm = None if 1 in t.exact else t.to_truth(t.sewn(file_mesh).x, file_mesh.sim_faces)

    rows = []
    for s in args.spacings:
        garment = mesh_pattern(t.pattern, spacing=s)
        from_placement = t.sewn(garment)
        # the model from the placed mesh, as `sew_and_drape` builds it (attachments keep placed heights)
        placed = place_from_drape(garment, t.source, t.draped.verts)
        model = ClothModelBuilder(t.material).add_garment(placed, merge_seams=True).finalize()
        kept = drape_to_equilibrium(
            model,
            garment.vert_uv.float(),
            body_verts=t.body_verts,
            body_faces=t.body_faces,
            state=model.initial_state(placed.sim_positions().float()),
            config=t.config,
        )
        rows.append(
            {
                "spacing_m": s,
                "vertices": garment.sim_vert_count,
                "sewn_mm": t.to_truth(from_placement.x, garment.sim_faces),
                "from_truth_mm": t.to_truth(kept.x, garment.sim_faces),
                "converged": bool(from_placement.converged and kept.converged),
            }
        )
    return {
        "check": "spacing",
        "garment": t.truth["template"],
        "scan_spacing_m": t.truth["spacing_m"],
        "pattern_file_sewn_mm": file_mm,
        "rows": rows,
    }


def grown(verts: torch.Tensor, faces: torch.Tensor, offset: float) -> torch.Tensor:
    """The body surface moved by ``offset`` [m] along its area-weighted vertex normals (outward > 0).

    Args:
        verts: (V, 3) [m]; faces: (F, 3) int64. Returns (V, 3) [m], the dtype of ``verts``.
    """
    from torch_diffavatar.body.geometry import vertex_normals

    v = verts.double()
    return (v + offset * vertex_normals(v, faces)).to(verts.dtype)


def body(args) -> dict:
    """The true pattern at the scan's own spacing, sewn on the true body grown by each offset."""
    from torch_diffavatar.chamfer import surface_chamfer_m
    from torch_diffavatar.scan import load_scan

    t = _TrueDrape(args.garment_dir)
    scan = load_scan(Path(args.garment_dir) / "scan" / "scan.ply")
    if scan.labels is None:
        raise SystemExit(f"{args.garment_dir}/scan/scan.ply has no labels: is it a make-scan output?")
    garment_points = torch.as_tensor(scan.points[scan.labels == 1])  # as `diffavatar eval` measures

    def to_scan(x) -> float:  # [mm]
        return round(1e3 * surface_chamfer_m(x, t.source.sim_faces, garment_points)["symmetric"], 2)

    rows = []
    for offset in args.offsets:
        result = t.sewn(t.source, grown(t.body_verts, t.body_faces, offset))
        rows.append(
            {
                "offset_mm": round(1e3 * offset, 3),
                "sewn_mm": t.to_truth(result.x, t.source.sim_faces),
                "sewn_scan_mm": to_scan(result.x),
                "converged": bool(result.converged),
            }
        )
    return {
        "check": "body",
        "garment": t.truth["template"],
        "truth_scan_mm": to_scan(t.draped.verts),
        "rows": rows,
    }


def fd(args) -> dict:
    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.fit import SETUP, Fitter
    from torch_diffavatar.fit_checkpoint import safe_load
    from torch_diffavatar.sim.material import ClothMaterial

    torch.set_num_threads(1)
    fit_dir = Path(args.fit_dir)
    config = _config(fit_dir / "config.yaml", args.set)
    setup = safe_load(fit_dir / SETUP)
    body = BodyModel(anny_model=load_anny(dtype=torch.float32))
    body.load_parameters_dict(setup["body_params"])
    material = ClothMaterial(bend_stiffness=config.initial_bend_stiffness)
    fitter = Fitter(
        setup["garment"],
        setup["target"],
        config,
        body=body,
        material=material,
        sewing_fallback=setup.get("sewing_fallback"),
        progress=False,
    )
    start = fitter._first_state()
    ev = fitter.evaluate(start)
    fitter.optimizer.zero_grad()
    ev.loss.backward()
    handles = [p for p in fitter.params.cage.parameters() if p.requires_grad]
    grads = [p.grad.detach().clone() for p in handles]
    norm = math.sqrt(sum(float((g**2).sum()) for g in grads))
    base = [p.detach().clone() for p in handles]
    rows = []
    for eps in args.eps:
        loss = []
        for sign in (1.0, -1.0):
            with torch.no_grad():
                for p, b, g in zip(handles, base, grads):
                    p.copy_(b + sign * eps * g / norm)
                loss.append(float(fitter.evaluate(start).loss))
        with torch.no_grad():
            for p, b in zip(handles, base):
                p.copy_(b)
        rows.append({"eps_mm": 1e3 * eps, "fd": (loss[0] - loss[1]) / (2 * eps), "adjoint": norm})
    return {
        "check": "fd",
        "config": {
            "spacing": config.spacing,
            "drape_substeps": config.drape_substeps,
            "adjoint": config.adjoint,
        },
        "loss": float(ev.loss.detach()),
        "directional_derivative": rows,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="check", required=True)
    p = sub.add_parser("oracle", help="first drape from the true pattern and material")
    p.add_argument("garment_dir", help="a benchmark-suite garment folder (with scan/ and scan/truth/)")
    p.add_argument("--out", default="oracle_out", help="fit output folder")
    p.add_argument("--iterations", type=int, default=0, help="fit iterations from the truth (default 0)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="FitConfig override")
    p.add_argument("--true-body", action="store_true", help="start from the true body, not a body fit")
    p = sub.add_parser("spacing", help="the true drape's own dependence on the mesh spacing")
    p.add_argument("garment_dir", help="a benchmark-suite garment folder (with scan/truth/)")
    p.add_argument("--spacings", type=float, nargs="+", default=[0.025], help="mesh spacings [m]")
    p = sub.add_parser("body", help="the true drape's own dependence on the body's surface")
    p.add_argument("garment_dir", help="a benchmark-suite garment folder (with scan/truth/)")
    p.add_argument(
        "--offsets", type=float, nargs="+", default=[0.0, 0.001, -0.001], help="normal offsets [m]"
    )
    p = sub.add_parser("fd", help="finite-difference check of the cage gradient at the first drape")
    p.add_argument("fit_dir", help="a fit folder (setup.pt, config.yaml)")
    p.add_argument("--eps", type=float, nargs="+", default=[1e-3, 3e-3, 1e-2], help="steps [m]")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="FitConfig override")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print(json.dumps({"oracle": oracle, "spacing": spacing, "body": body, "fd": fd}[args.check](args)))


if __name__ == "__main__":
    main()
