"""The whole job of ``diffavatar fit``: scan in, simulation-ready assets out.

`fit_scan` runs the set-up (`torch_diffavatar.fit_setup.prepare`, saved in ``DIR/setup.pt`` so that a resumed
run reuses it), the fit loop (`torch_diffavatar.fit.Fitter`, resumable from ``DIR/checkpoint.pt``) and writes
the assets (`torch_diffavatar.assets.write_assets`) with ``report.json``.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch


def load_setup(scan_path, config, out: Path, *, resume: bool, anny_model, **prepare_kw) -> dict:
    """The fit's set-up: ``out/setup.pt`` with ``resume`` when it is there, else `fit_setup.prepare` of the
    scan (``prepare_kw``: its options), saved there."""
    from torch_diffavatar.fit_checkpoint import SETUP, atomic_save, safe_load
    from torch_diffavatar.fit_setup import prepare

    setup_path = out / SETUP
    if resume and setup_path.is_file():
        return safe_load(setup_path)
    setup = prepare(scan_path, config, anny_model=anny_model, **prepare_kw)
    atomic_save(setup, setup_path)
    return setup


def fit_scan(
    scan_path,
    config,
    out_dir,
    *,
    resume=False,
    units="m",
    up="y",
    progress=True,
    anny_model=None,
    pattern=None,
    garment_type=None,
    body_params=None,
) -> dict:
    """Run the whole job (see the module docstring); returns the report (also ``out_dir/report.json``).

    ``pattern``: start from this `Pattern` instead of ``config.template``; ``garment_type`` and
    ``body_params`` (start from this body instead of fitting one): see `fit_setup.prepare`."""
    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.fit import Fitter
    from torch_diffavatar.fit_config import write_resolved_config
    from torch_diffavatar.sim.material import ClothMaterial

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_resolved_config(config, out)
    anny_model = load_anny(dtype=torch.float32) if anny_model is None else anny_model
    prepare_kw = dict(units=units, up=up, pattern=pattern, garment_type=garment_type, body_params=body_params)
    setup = load_setup(scan_path, config, out, resume=resume, anny_model=anny_model, **prepare_kw)
    spacing = setup.get("spacing", config.spacing)
    if spacing != config.spacing:  # meshed finer for arms held low: the resolved config says so
        config = replace(config, spacing=spacing)
        write_resolved_config(config, out)
    body = BodyModel(anny_model=anny_model)
    body.load_parameters_dict(setup["body_params"])
    fitter = Fitter(
        setup["garment"],
        setup["target"],
        config,
        body=body,
        material=ClothMaterial(bend_stiffness=config.initial_bend_stiffness),
        sewing_fallback=setup.get("sewing_fallback"),
        out_dir=out,
        progress=progress,
    )
    result = fitter.run(resume=resume)
    report = dict(result.report)
    report.update(
        scan=str(scan_path),
        scan_points=setup["scan_points"],
        scan_labelled=setup["labelled"],
        scan_boundaries=setup["scan_boundaries"],
        spacing=spacing,
        upper_arm_angles_deg=setup.get("upper_arm_angles_deg"),
        body_fit_chamfer_m=setup["body_fit_chamfer_m"],
        setup_seconds=round(setup["setup_seconds"], 2),
        total_seconds=round(time.perf_counter() - t0, 2),  # this run's (a resumed one: since the resume)
    )
    return write_fit_assets(out, setup, fitter, result, report)


def write_fit_assets(out: Path, setup: dict, fitter, result, report: dict) -> dict:
    """Write the assets of a fit (`assets.write_assets`: pattern, meshes, body, material, ``report``, the
    before/after picture) into ``out``; print the report's warnings on stderr; returns ``report.json``.

    Args:
        setup: `fit_setup.prepare`'s; fitter: the `Fitter` that ran; result: its `FitResult`.
    """
    from torch_diffavatar.assets import write_assets

    body, garment = fitter.params.body, setup["garment"]
    # the fitted k_b and membrane (the stretch factor times the base's k_uu, k_vv, k_uv)
    with torch.no_grad():
        params = result.params
        final_material = fitter.objective.material_at(params.log_bend_stiffness.exp(), params.stretch())
    body_params = dict(body.parameters_dict())
    body_params["phenotypes_by_name"] = dict(zip(body.phenotype_labels, body.phenotypes[0].detach().tolist()))
    first = fitter.first
    before = None
    if first is not None and first["body_verts"] is not None:
        before = (first["x"], garment.sim_faces, first["body_verts"], body.faces)
    files = write_assets(
        out,
        pattern=setup["pattern"],
        garment=garment,
        rest_uv=result.rest_uv,
        draped_x=result.x,
        body_verts=result.body_verts,
        body_faces=body.faces,
        body_params=body_params,
        material=final_material,
        report=report,
        before=before,
    )
    for message in report["warnings"]:
        print(f"diffavatar fit: warning: {message}", file=sys.stderr)
    return json.loads(Path(files["report_json"]).read_text())
