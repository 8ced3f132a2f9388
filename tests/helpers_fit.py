"""The tiny fit problem that the fit driver's tests and the objective's share (float64, no body)."""

from __future__ import annotations

import torch

from torch_diffavatar.fit_config import FitConfig
from torch_diffavatar.objective import ScanTarget

DT = torch.float64

# a stand-in body for asset files (a closed tetrahedron, outward normals) [m]
TETRA_V = torch.tensor(
    [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64
)
TETRA_F = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def skirt_problem():
    """(garment, start state, target): the skirt template at 10 cm spacing, sewn without a body, and the
    drape of the same skirt 20 % longer (its points and hem are the target)."""
    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.sim.forward_drape import DrapeConfig, drape_to_equilibrium, sew_and_drape

    garment = mesh_pattern(load_template("skirt"), spacing=0.1)
    cfg = DrapeConfig(max_steps=80, min_steps=80, sew_max_steps=120, sew_ramp_steps=60)
    base = sew_and_drape(garment, config=cfg, dtype=DT)
    truth_uv = garment.vert_uv.to(DT) * torch.tensor([1.0, 1.2], dtype=DT)
    truth = drape_to_equilibrium(base.model, truth_uv, config=cfg, state=base.state)
    hem = next(lp for lp in garment.boundary_loops if lp.name == "hem")
    target = ScanTarget(truth.x, {"hem": truth.x[hem.vertices]})
    return garment, base.state, target


def sewn_skirt():
    """(pattern, garment, `sew_and_drape` result): the skirt template at 10 cm spacing sewn without a body
    where the fit places it (the start of the membrane and waist tests, whose truths drape the same pattern
    with other physics)."""
    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.sim.forward_drape import DrapeConfig, sew_and_drape

    pattern = load_template("skirt")
    garment = mesh_pattern(pattern, spacing=0.1)
    cfg = DrapeConfig(max_steps=80, sew_max_steps=120, sew_ramp_steps=60)
    return pattern, garment, sew_and_drape(garment, config=cfg, dtype=DT)


def truth_drape_config(**fit_kw):
    """The drape config of a fit with ``fit_kw`` (`fit_config`), run long enough to settle a truth."""
    from dataclasses import replace

    from torch_diffavatar.fit_config import drape_config

    return replace(drape_config(fit_config(**fit_kw)), max_steps=400, min_steps=100)


def fit_config(**kw) -> FitConfig:
    """A short skirt fit (3 iterations, no images); ``kw`` overrides fields."""
    base = dict(template="skirt", iterations=3, lr_cage=0.01, lr_log_bend_stiffness=0.05, image_every=0)
    base.update(kw)
    return FitConfig(**base)


def write_truth_as_assets(scan, folder, **kw) -> None:
    """A fit output folder whose assets ARE the truth of the `DrapedScan` ``scan`` (its pattern, drape,
    body and material); ``kw`` goes to `assets.write_assets` (``before``, ``png_size``)."""
    from torch_diffavatar.assets import write_assets

    write_assets(
        folder,
        pattern=scan.pattern,
        garment=scan.garment,
        rest_uv=scan.garment.vert_uv,
        draped_x=torch.as_tensor(scan.cloth_x),
        body_verts=torch.as_tensor(scan.body_vertices),
        body_faces=torch.as_tensor(scan.body_faces),
        body_params=scan.body_params,
        material=scan.material,
        report={"inverted_rest_triangles": 0},
        **kw,
    )


def write_assets_on_default_body(
    out, anny_model, default_body, *, pattern, garment, rest_uv, draped_x, material
):
    """An asset folder of ``garment`` draped (``draped_x`` (Vs, 3) [m]) on the `default_body` fixture's body
    (verts, faces), whose parameters are Anny's defaults with the feet on y = 0 (as `animate` poses it)."""
    from torch_diffavatar.assets import write_assets
    from torch_diffavatar.body.model import BodyModel

    bv, bf = default_body
    body = BodyModel(anny_model)
    with torch.no_grad():
        body.translation[:, 1] = float(bv[:, 1].min() - body().vertices[0, :, 1].min())  # feet on y = 0
    write_assets(
        out,
        pattern=pattern,
        garment=garment,
        rest_uv=rest_uv,
        draped_x=draped_x,
        body_verts=bv,
        body_faces=bf,
        body_params=body.parameters_dict(),
        material=material,
        report={},
    )
    return out
