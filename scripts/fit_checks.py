#!/usr/bin/env python
"""Two checks of the fit on a benchmark-suite scan: how far can it get, and is its gradient right?

``oracle GARMENT_DIR``: the fit's first drape started from the scan's TRUE pattern and bending stiffness
(``GARMENT_DIR/scan/truth/``), with the garment's fit config. Its Chamfer is what a perfect recovery of
the pattern and the material would score at the fit's spacing and XPBD settings: the floor of that
config, against which the template start and the fit's result can be read. ``--iterations N`` then runs
N fit iterations from there (does the fit stay at the truth?).

    PYTHONPATH=. python scripts/fit_checks.py oracle /tmp/suite/tshirt --set drape_substeps=10

``fd FIT_DIR``: a directional finite-difference check of the fit's gradient w.r.t. the cage handles at
the first drape, from a fit folder (its ``setup.pt`` and ``config.yaml``): the loss at the handles moved
by ±ε along the normalised gradient, central difference against the gradient's norm (equal when the
adjoint is exact and the drape is smooth in the pattern at that scale).

    PYTHONPATH=. python scripts/fit_checks.py fd /tmp/suite/tshirt/fit --set drape_substeps=40

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
    from torch_diffavatar.fit import config_from_dict
    from torch_diffavatar.fit_commands import fit_scan
    from torch_diffavatar.pattern import load_pattern

    scan_dir = Path(args.garment_dir) / "scan"
    truth = json.loads((scan_dir / "truth" / "truth.json").read_text())
    root = Path(__file__).resolve().parents[1]
    config = _config(root / "configs" / f"{truth['template']}.yaml", args.set)
    kb = float(truth["material"]["bend_stiffness"])
    config = config_from_dict({"initial_bend_stiffness": kb, "iterations": args.iterations}, base=config)
    out = Path(args.out)
    pattern = load_pattern(scan_dir / "truth" / "pattern.json")
    report = fit_scan(scan_dir / "scan.ply", config, out, progress=False, pattern=pattern)
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
        "chamfer_mm": mm,
        "boundary_chamfer_initial_mm": {
            k: round(1e3 * v, 1) for k, v in report["boundary_chamfer_initial"].items()
        },
        "bending_stiffness_ratio": ev["bending_stiffness_ratio"],
    }


def fd(args) -> dict:
    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.fit import SETUP, Fitter
    from torch_diffavatar.sim.material import ClothMaterial

    torch.set_num_threads(1)
    fit_dir = Path(args.fit_dir)
    config = _config(fit_dir / "config.yaml", args.set)
    setup = torch.load(fit_dir / SETUP, weights_only=False)
    body = BodyModel(anny_model=load_anny(dtype=torch.float32))
    body.load_parameters_dict(setup["body_params"])
    material = ClothMaterial(bend_stiffness=config.initial_bend_stiffness)
    fitter = Fitter(setup["garment"], setup["target"], config, body=body, material=material, progress=False)
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
    p = sub.add_parser("fd", help="finite-difference check of the cage gradient at the first drape")
    p.add_argument("fit_dir", help="a fit folder (setup.pt, config.yaml)")
    p.add_argument("--eps", type=float, nargs="+", default=[1e-3, 3e-3, 1e-2], help="steps [m]")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="FitConfig override")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print(json.dumps(oracle(args) if args.check == "oracle" else fd(args)))


if __name__ == "__main__":
    main()
