#!/usr/bin/env python
"""Contact detection with and without the contact cache (issue #32), on the fit's drapes of the dress.

The demo's set-up (as ``scripts/bench_fit.py``: body fit, garment openings of the bundled scan), the
``dress`` template meshed at ``--spacing`` and placed, the fit's first drape, then ``--iters`` fit
iterations (`Fitter.step`). Every contact detection of the static-body drapes runs twice, with the solver's
`collision.ContactCache` and without it (the full grid query of every cloth vertex), in alternating order,
timed in CPU seconds of this process; the two must give the same contacts (``torch.equal``, checked every
frame; the cached ones are used). Prints one JSON line: frames, the mean CPU ms per frame of each, their
ratio, and the mean share of the vertices queried (grid or candidates) and looked up among candidates.

    PYTHONPATH=. OMP_NUM_THREADS=1 python scripts/bench_contacts.py --spacing 0.015 --iters 2
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spacing", type=float, default=0.015)
    parser.add_argument("--iters", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(1)

    from torch_diffavatar.sim import collision

    fitter = _dress_fitter(args.spacing, args.iters)
    start = fitter._first_state()
    ev = fitter.evaluate(start)
    times = {"cached": [], "full": []}
    shares = {"queried": [], "among": []}
    detect = collision.detect_contacts

    def timed(kind, *a, **kw):
        c0 = time.process_time()
        out = detect(*a, **kw)
        times[kind].append(time.process_time() - c0)
        return out

    def both(x, body_verts, body_faces, band, *, cache=None, **kw):
        if cache is None:  # a moving body, or the cache is off: not measured
            return detect(x, body_verts, body_faces, band, **kw)
        kws = {"cached": dict(kw, cache=cache), "full": dict(kw, index=cache.index)}
        order = ("cached", "full") if len(times["full"]) % 2 else ("full", "cached")
        res = {k: timed(k, x, body_verts, body_faces, band, **kws[k]) for k in order}
        for name in ("vert", "tri", "bary"):
            if not torch.equal(getattr(res["cached"], name), getattr(res["full"], name)):
                raise AssertionError(f"the cached contacts differ ({name})")
        shares["queried"].append(cache.queried / x.shape[0])
        shares["among"].append(cache.among / x.shape[0])
        return res["cached"]

    collision.detect_contacts = both
    try:
        for _ in range(args.iters):
            ev, start, _ = fitter.step(ev, start)
            fitter.iteration += 1
    finally:
        collision.detect_contacts = detect
    n = len(times["full"])
    mean = {k: 1e3 * sum(v) / max(len(v), 1) for k, v in times.items()}
    print(
        json.dumps(
            {
                "spacing_m": args.spacing,
                "vertices": int(start.x.shape[0]),
                "iterations": args.iters,
                "frames": n,
                "full_cpu_ms_per_frame": round(mean["full"], 3),
                "cached_cpu_ms_per_frame": round(mean["cached"], 3),
                "ratio": round(mean["cached"] / mean["full"], 3) if n else None,
                "share_queried": round(sum(shares["queried"]) / max(n, 1), 3),
                "share_among_candidates": round(sum(shares["among"]) / max(n, 1), 3),
                "contacts_identical": True,
            }
        ),
        flush=True,
    )


def _dress_fitter(spacing: float, iters: int):
    """`Fitter` of the dress at ``spacing`` on the demo scan's set-up (as ``scripts/bench_fit.py``)."""
    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.commands.demo import DEMO_SCAN
    from torch_diffavatar.fit import Fitter, load_config
    from torch_diffavatar.fit_setup import match_boundaries, prepare
    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.sim.material import ClothMaterial
    from torch_diffavatar.sim.placement import place_garment

    anny = load_anny(dtype=torch.float32)
    base = load_config(garment="dress")
    setup = prepare(DEMO_SCAN, base, anny_model=anny)
    config = replace(base, spacing=spacing, iterations=iters)
    body = BodyModel(anny_model=anny)
    body.load_parameters_dict(setup["body_params"])
    with torch.no_grad():
        body_verts = body().vertices[0].double()
    garment = place_garment(mesh_pattern(load_template("dress"), spacing=spacing), body_verts, body.faces)
    target = setup["target"]
    scan_loops = {name: pts.numpy() for name, pts in target.boundaries.items()}
    target = replace(target, boundaries=match_boundaries(garment, scan_loops))
    material = ClothMaterial(bend_stiffness=config.initial_bend_stiffness)
    return Fitter(garment, target, config, body=body, material=material, progress=False)


if __name__ == "__main__":
    main()
