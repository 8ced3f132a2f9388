#!/usr/bin/env python
"""How strained an asset's drape is: the largest Green strain of its triangles, and where.

For each asset folder (`diffavatar fit` / `demo` / `export-template` output): the drape's per-triangle
largest |Green strain| component against the rest pattern, on the seam-merged mesh the simulator steps
(`solver.strained_triangles`, what `XPBDSolver`'s blow-up test measures), the triangles over 1 and over
``XPBDConfig.max_strain``, the rest area [cm²] and drape position [m] of the worst one, and the area the
triangles beyond ``max_strain`` cover against ``max_strain_area`` (docs/BENCHMARKS.md, "Slivers at the
shoulder tips").

    PYTHONPATH=. python scripts/asset_strains.py FIT_DIR [FIT_DIR ...] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys

import torch


def asset_strains(asset_dir) -> dict:
    """The strain summary of one asset folder (the module docstring)."""
    from torch_diffavatar.assets import load_assets
    from torch_diffavatar.sim.model import ClothModelBuilder
    from torch_diffavatar.sim.solver import XPBDConfig, strained_triangles

    assets = load_assets(asset_dir)
    builder = ClothModelBuilder(assets.material).add_garment(assets.garment, merge_seams=True)
    model = builder.finalize(dtype=torch.float64)
    rest = model.rest_data(assets.rest_uv.double())
    x = assets.draped_x.double()
    limit = XPBDConfig()
    e, over, area = strained_triangles(x, model, rest, limit.max_strain)
    worst = int(e.argmax())
    return {
        "asset": str(asset_dir),
        "triangles": int(e.numel()),
        "max_strain": float(e[worst]),
        "over_1": int((e > 1).sum()),
        "over_max_strain": int(over.sum()),
        "area_over_max_strain_cm2": 1e4 * area,
        "worst_rest_area_cm2": 1e4 * float(rest.tri_area[worst]),
        "median_rest_area_cm2": 1e4 * float(rest.tri_area.median()),
        "worst_at_m": [round(float(c), 3) for c in x[model.tri_vertices[worst]].mean(0)],
        "max_strain_limit": limit.max_strain,
        "max_strain_area_cm2": 1e4 * limit.max_strain_area,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("assets", nargs="+", help="asset folders")
    p.add_argument("--json", action="store_true", help="one JSON line per asset")
    args = p.parse_args(argv)
    from torch_diffavatar.errors import InputError

    failed = 0
    with torch.no_grad():
        for d in args.assets:
            try:
                s = asset_strains(d)
            except InputError as err:  # the others are still measured
                print(f"asset_strains: {err}", file=sys.stderr)
                failed += 1
                continue
            if args.json:
                print(json.dumps(s))
            else:
                print(
                    f"{d}: max strain {s['max_strain']:.2f} at {s['worst_at_m']} m (rest area "
                    f"{s['worst_rest_area_cm2']:.2f} cm², median {s['median_rest_area_cm2']:.2f}); "
                    f"{s['over_1']} of {s['triangles']} triangles over 1, {s['over_max_strain']} over "
                    f"{s['max_strain_limit']:g} ({s['area_over_max_strain_cm2']:.2f} cm², a blow-up beyond "
                    f"{s['max_strain_area_cm2']:g})"
                )
    return 2 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
