#!/usr/bin/env python
"""The whole fit as a plain ``torch.optim`` loop, as a pipeline would write it around `FitObjective`.

The set-up of ``diffavatar fit`` (`fit_setup.prepare`: scan, body, openings, placed template), then
`FitParameters` + `FitObjective`, the first drape, and Adam with warm starts (the pattern held for the
config's ``pattern_delay`` iterations, as `Fitter` holds it). `Fitter`'s guards are left out
(step halving, proximal rest step, first-drape race, keeping the best iteration): with a config where they
do not act, this reaches the result of ``diffavatar fit`` (tests/test_objective.py).

    python scripts/fit_loop.py SCAN.ply --garment skirt --iters 5 --set rest_prox_iterations=0
"""

from __future__ import annotations

import argparse

import torch
import yaml

from torch_diffavatar.body.anny_model import load_anny
from torch_diffavatar.body.model import BodyModel
from torch_diffavatar.fit import lr_factor, param_groups
from torch_diffavatar.fit_config import load_config
from torch_diffavatar.fit_setup import prepare
from torch_diffavatar.fit_start import first_drape
from torch_diffavatar.objective import FitObjective, FitParameters
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.state import ClothState


def set_up(scan_path, config, anny_model, body_params=None):
    """``diffavatar fit``'s set-up of the scan (`fit_setup.prepare`) and its initial `BodyModel`."""
    setup = prepare(scan_path, config, anny_model=anny_model, body_params=body_params)
    body = BodyModel(anny_model=anny_model)
    body.load_parameters_dict(setup["body_params"])
    return setup, body


def fit_loop(
    garment, target, config, body=None, *, sewing_fallback=None, start_state=None, dtype=torch.float32
):
    """Fit ``config.iterations`` Adam steps; returns (the `FitParameters`, the last `ObjectiveOutput`).
    ``body``: a `BodyModel` (fitted too) or None; ``start_state``: a drape to settle instead of sewing."""
    params = FitParameters.from_config(garment, config, body, dtype)
    material = ClothMaterial(bend_stiffness=config.initial_bend_stiffness)
    objective = FitObjective.from_parameters(params, garment, target, config, material=material)
    groups = param_groups(params, config)
    optimizer = torch.optim.Adam(groups)  # a learning rate per kind of variable
    # cosine; the pattern's (the cage's) 0 for the first ``config.pattern_delay`` iterations
    factors = [lambda it, name=g["name"]: lr_factor(it, config, name) for g in groups]
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, factors)
    with torch.no_grad():  # the template sewn onto the body (or start_state) and settled
        start = first_drape(objective, params(), sewing_fallback=sewing_fallback, start_state=start_state)
    out = objective(params(), start)
    for it in range(config.iterations):
        optimizer.zero_grad()
        out.loss.backward()
        optimizer.step()
        schedule.step()
        start = ClothState(out.x.detach(), torch.zeros_like(out.x.detach()))  # warm start
        out = objective(params(), start)
        print(f"iteration {it + 1}: loss {float(out.loss.detach()):.6g}", flush=True)
    return params, out


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("scan")
    p.add_argument("--garment", default="skirt")
    p.add_argument("--iters", type=int, default=None)
    p.add_argument("--set", nargs="*", default=[], help="config fields, e.g. rest_prox_iterations=0")
    args = p.parse_args()
    overrides = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in args.set)}
    config = load_config(garment=args.garment, iterations=args.iters, **overrides)
    setup, body = set_up(args.scan, config, load_anny(dtype=torch.float32))
    _, out = fit_loop(
        setup["garment"], setup["target"], config, body, sewing_fallback=setup["sewing_fallback"]
    )
    terms = {k: float(v.detach()) for k, v in out.terms.items()}
    print(terms, "k_b", float(out.bend_stiffness.detach()), "N·m, membrane", float(out.stretch.detach()), "x")
