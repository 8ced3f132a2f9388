"""The whole job of ``diffavatar fit``: scan in, simulation-ready assets out.

`fit_scan` runs the set-up (`torch_diffavatar.fit_setup.prepare`, saved in ``DIR/setup.pt`` so that a resumed
run reuses it), the fit loop (`torch_diffavatar.fit.Fitter`, resumable from ``DIR/checkpoint.pt``) and writes
the assets (`torch_diffavatar.assets.write_assets`) with ``report.json``.

A folder is never a mix of two fits: while a fit runs, ``DIR/INCOMPLETE`` says so (it goes once the last
file is written); a new fit into a folder that holds another refuses unless ``force``, which first removes
the earlier fit's files; a resumed fit checks that the scan, the garment and the settings are the ones its
``setup.pt`` was made from (`fit_fingerprint`). What can refuse the input (that check, the scan's intake)
runs before the folder is touched, so a refused fit leaves it as it was.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

from torch_diffavatar.atomic_file import atomic_write_text
from torch_diffavatar.errors import InputError, SimulationError
from torch_diffavatar.json_io import write_json

INCOMPLETE = "INCOMPLETE"  # marker file of a fit folder whose fit has not finished writing


def _file_sha256(path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def fit_fingerprint(scan_path, config, **prepare_kw) -> dict:
    """What a fit's set-up was made from: the scan file's SHA-256, the config (its ``iterations`` aside: a
    resumed fit may run longer) and the set-up options ``prepare_kw`` (`fit_setup.prepare`'s), as plain
    data. The pattern and the body parameters enter as their JSON-like dicts."""
    from torch_diffavatar.fit_config import config_to_dict
    from torch_diffavatar.pattern.garmentcode import pattern_to_dict

    settings = config_to_dict(config)
    settings.pop("iterations")
    options = dict(prepare_kw)
    if options.get("pattern") is not None:
        options["pattern"] = pattern_to_dict(options["pattern"])
    return {"scan_sha256": _file_sha256(scan_path), "config": settings, "options": options}


def _changed_keys(a: dict, b: dict) -> list[str]:
    """The keys whose values differ between ``a`` and ``b`` (missing on one side included), sorted."""
    return sorted(k for k in {**a, **b} if a.get(k) != b.get(k))


def _with_new_defaults(settings: dict) -> dict:
    """A saved fingerprint's config with the `FitConfig` fields it predates at their defaults: a fit made
    before a field existed ran as its default does (the waist's height fixed, the membrane at 1, ...)."""
    from torch_diffavatar.fit_config import FitConfig, config_to_dict

    defaults = config_to_dict(FitConfig())
    defaults.pop("iterations")
    return {**defaults, **settings}


def _check_fingerprint(setup: dict, expected: dict, setup_path: Path) -> None:
    """InputError when the resumed set-up was made from another scan, garment or settings."""
    found = setup.get("fingerprint")
    if found is None:
        print(
            f"diffavatar fit: warning: {setup_path} predates the scan check; resuming it unchecked",
            file=sys.stderr,
        )
        return
    found = {**found, "config": _with_new_defaults(found["config"])}
    if found == expected:
        return
    if found["scan_sha256"] != expected["scan_sha256"]:
        what = "another scan file"
    else:
        keys = [k for part in ("config", "options") for k in _changed_keys(found[part], expected[part])]
        what = f"other settings ({', '.join(keys)})"
    raise InputError(
        f"--resume: {setup_path.parent} was made from {what}; resume with the same scan, garment and "
        "config, or start a new fit (another --out, or --force to replace it)"
    )


def prepare_out_folder(out: Path, *, resume: bool, force: bool) -> None:
    """Make ``out`` ready for a fit and mark it `INCOMPLETE`.

    Raises:
        InputError: ``out`` holds another fit (finished or not) and neither ``resume`` nor ``force``.
    """
    from torch_diffavatar.assets import ASSET_FILES
    from torch_diffavatar.evaluation import DRAPE_PICTURE
    from torch_diffavatar.fit_checkpoint import CHECKPOINT, SETUP
    from torch_diffavatar.fit_config import RESOLVED_CONFIG

    # the assets and what else a fit (and `diffavatar eval`) writes there: a forced rerun removes these only
    ours = [*ASSET_FILES.values(), SETUP, CHECKPOINT, RESOLVED_CONFIG, DRAPE_PICTURE, INCOMPLETE]
    earlier = [name for name in ours if (out / name).exists()]
    if earlier and not resume:
        if not force:
            state = "an unfinished fit" if (out / INCOMPLETE).exists() else "a fit"
            raise InputError(
                f"--out {out} holds {state} ({', '.join(earlier[:3])}…); pass --resume to continue it, "
                "--force to replace it, or choose another folder"
            )
        for name in earlier:  # only the files a fit writes: anything else of the user's stays
            (out / name).unlink()
        shutil.rmtree(out / "tb", ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(
        out / INCOMPLETE, "a fit is writing into this folder; it is not a finished asset folder\n"
    )


def resumed_setup(out: Path, fingerprint: dict) -> dict | None:
    """``out/setup.pt`` when it is there, checked against ``fingerprint`` (`fit_fingerprint`), else None.

    Raises:
        InputError: it was made from another scan, garment or settings.
    """
    from torch_diffavatar.fit_checkpoint import SETUP, safe_load

    setup_path = out / SETUP
    if not setup_path.is_file():
        return None
    setup = safe_load(setup_path)
    _check_fingerprint(setup, fingerprint, setup_path)
    return setup


def new_setup(
    scan_path, config, out: Path, fingerprint: dict, *, anny_model, loaded_scan=None, workers=1, **prepare_kw
):
    """`fit_setup.prepare` of the scan (``prepare_kw``: its options; ``loaded_scan``: the scan through the
    intake already; ``workers``: its body fit's, which change nothing in the set-up), saved as
    ``out/setup.pt`` with its ``fingerprint``."""
    from torch_diffavatar.fit_checkpoint import SETUP, atomic_save
    from torch_diffavatar.fit_setup import prepare

    setup = prepare(
        scan_path, config, anny_model=anny_model, loaded_scan=loaded_scan, workers=workers, **prepare_kw
    )
    setup["fingerprint"] = fingerprint
    atomic_save(setup, out / SETUP)
    return setup


def load_setup(scan_path, config, out: Path, *, resume: bool, anny_model, **prepare_kw) -> dict:
    """The fit's set-up: ``out/setup.pt`` with ``resume`` when it is there (made from the same scan and
    settings, `resumed_setup`), else a `new_setup` of the scan (``prepare_kw``: its options).

    Raises:
        InputError: the set-up to resume was made from another scan, garment or settings.
    """
    fingerprint = fit_fingerprint(scan_path, config, **prepare_kw)
    setup = resumed_setup(out, fingerprint) if resume else None
    if setup is None:
        setup = new_setup(scan_path, config, out, fingerprint, anny_model=anny_model, **prepare_kw)
    return setup


# a body fit this far from the scan (`fit_body`'s Chamfer, garment included) is a wrong body, not a loose
# garment: on our synthetic clothed scans body fits end 1.4-2.0 cm from the scan; on real captures the
# wrong-facing and floor-reaching ones ended at 3.3-7.5 cm
BODY_FIT_DOUBT_M = 0.03


def body_fit_warnings(chamfer_m: float | None) -> list[str]:
    """A warning when a body fit ended `BODY_FIT_DOUBT_M` or farther from the scan (none for None: a given
    body)."""
    if chamfer_m is None or chamfer_m <= BODY_FIT_DOUBT_M:
        return []
    return [
        f"the body fit ends {1e2 * chamfer_m:.1f} cm from the scan (good ones end within 2 cm): the body is "
        "probably wrong; check --up and --units, remove clutter from the scan, or give a body (--body)"
    ]


def first_sewing_advice(setup: dict) -> str:
    """What was likely wrong when a fit's first sewing failed (the body, the scan's openings or the
    template's placement), and what to try, from `fit_setup.prepare`'s ``setup``; one line."""
    garment = setup["garment"]
    missing = sorted({lp.name for lp in garment.boundary_loops} - set(setup["scan_boundaries"]))
    chamfer = setup.get("body_fit_chamfer_m")
    if chamfer is not None and chamfer > BODY_FIT_DOUBT_M:
        return (
            f"likely cause: the body fit, which ended {1e2 * chamfer:.1f} cm from the scan (good ones end "
            "within 2 cm): check --up and --units, remove the floor or clutter from the scan, or give "
            "a body with --body"
        )
    if missing:
        return (
            f"likely cause: the scan's segmentation, which found no {', '.join(missing)} opening: check "
            "--garment (or --garment-type) against the scan, or label the scan's garment points"
        )
    return (
        "likely cause: the template's placement on this body (the body fit and the openings look "
        "sound): try another --spacing, or a template closer to the garment (--garment)"
    )


def fit_scan(
    scan_path,
    config,
    out_dir,
    *,
    resume=False,
    force=False,
    units="m",
    up="y",
    progress=True,
    anny_model=None,
    pattern=None,
    garment_type=None,
    body_params=None,
    workers=1,
) -> dict:
    """Run the whole job (see the module docstring); returns the report (also ``out_dir/report.json``).

    ``pattern``: start from this `Pattern` instead of ``config.template``; ``garment_type`` and
    ``body_params`` (start from this body instead of fitting one): see `fit_setup.prepare`. ``force``:
    replace another fit in ``out_dir`` (else that is an error, `prepare_out_folder`). ``workers``:
    processes run side by side, one core each: the body fit's starting directions (`body.fit.fit_body`)
    and the candidates of the race of first drapes (`Fitter.run`); the same result for any number."""
    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.fit import Fitter
    from torch_diffavatar.fit_config import write_resolved_config
    from torch_diffavatar.fit_setup import load_fit_scan
    from torch_diffavatar.sim.material import ClothMaterial

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    out = Path(out_dir)
    prepare_kw = dict(units=units, up=up, pattern=pattern, garment_type=garment_type, body_params=body_params)
    # what can refuse the input goes before --out is touched: the set-up to resume (made from another
    # scan?) and the scan's intake (no person there?)
    fingerprint = fit_fingerprint(scan_path, config, **prepare_kw)
    setup = resumed_setup(out, fingerprint) if resume else None
    loaded_scan = load_fit_scan(scan_path, units=units, up=up) if setup is None else None
    prepare_out_folder(out, resume=resume, force=force)
    write_resolved_config(config, out)
    anny_model = load_anny(dtype=torch.float32) if anny_model is None else anny_model
    if setup is None:
        setup = new_setup(
            scan_path,
            config,
            out,
            fingerprint,
            anny_model=anny_model,
            loaded_scan=loaded_scan,
            workers=workers,
            **prepare_kw,
        )
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
    try:
        result = fitter.run(resume=resume, race_workers=workers)
    except SimulationError as exc:
        if fitter.first is not None:  # failed after the fit had started: the message says where
            raise
        raise SimulationError(f"{exc}; {first_sewing_advice(setup)}") from exc
    report = full_report(result.report, setup, scan_path, spacing, time.perf_counter() - t0)
    return write_fit_assets(out, setup, fitter, result, report)


def full_report(fit_report: dict, setup: dict, scan_path, spacing: float, seconds: float) -> dict:
    """``report.json`` of a fit: the fit loop's ``fit_report`` with the warnings about the scan and the
    body fit, and what the set-up (`fit_setup.prepare`'s ``setup``) found; ``spacing``: the mesh's [m];
    ``seconds``: this run's (a resumed one: since the resume)."""
    from torch_diffavatar.fit_report import floor_warnings, scan_warnings

    report = dict(fit_report)
    coverage = setup.get("scan_coverage")
    garment_points = setup["target"].garment_points
    report["warnings"] = (
        report["warnings"]
        + setup.get("scan_warnings", [])
        + body_fit_warnings(setup["body_fit_chamfer_m"])
        + scan_warnings(report, garment_points, coverage)
        + floor_warnings(setup.get("scan_floor"), garment_points)
    )
    report.update(
        scan=str(scan_path),
        scan_points=setup["scan_points"],
        scan_labelled=setup["labelled"],
        scan_boundaries=setup["scan_boundaries"],
        scan_coverage=coverage,
        scan_shift=setup.get("scan_shift"),
        spacing=spacing,
        upper_arm_angles_deg=setup.get("upper_arm_angles_deg"),
        hem_from_scan=setup.get("hem_from_scan"),
        body_fit_chamfer_m=setup["body_fit_chamfer_m"],
        setup_seconds=round(setup["setup_seconds"], 2),
        total_seconds=round(seconds, 2),
    )
    return report


def write_fit_assets(out: Path, setup: dict, fitter, result, report: dict) -> dict:
    """Write the assets of a fit (`assets.write_assets`: pattern, meshes, body, material, ``report``, the
    before/after picture, the scan on the fit) into ``out``; print the report's warnings on stderr;
    returns ``report.json``.

    Args:
        setup: `fit_setup.prepare`'s; fitter: the `Fitter` that ran; result: its `FitResult`.
    """
    from torch_diffavatar.assets import write_assets
    from torch_diffavatar.body.facing import body_facing_yaw
    from torch_diffavatar.fit_report import animation_warnings

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
        scan_points=setup["target"].garment_points,
        front_deg=body_facing_yaw(body.global_orient[0]),
    )
    (out / INCOMPLETE).unlink(missing_ok=True)  # every file is whole now
    written = json.loads(Path(files["report_json"]).read_text())  # with the export's warnings
    moved = animation_warnings(out, fitter.config.animation_check_s, body.anny)
    if moved:
        written["warnings"] = written["warnings"] + moved
        write_json(files["report_json"], written)
    for message in written["warnings"]:
        print(f"diffavatar fit: warning: {message}", file=sys.stderr)
    return written
