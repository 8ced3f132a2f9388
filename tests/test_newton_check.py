"""The asset's material in Newton's units (material_newton.json) and scripts/newton_check.py draping an
exported asset in Newton. The drape needs the ``newton`` extra and Anny, and skips without them."""

from __future__ import annotations

import importlib.util
import json
import sys

import numpy as np
import pytest
import torch
from helpers_fit import TETRA_F, TETRA_V
from helpers_scripts import load_script

from torch_diffavatar.assets import load_assets, write_assets
from torch_diffavatar.assets_newton import read_newton_material
from torch_diffavatar.errors import InputError
from torch_diffavatar.pattern import load_template, mesh_pattern
from torch_diffavatar.sim import newton_units as nu
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder

requires_newton = pytest.mark.skipif(importlib.util.find_spec("newton") is None, reason="needs newton")


@pytest.fixture(scope="module")
def skirt_asset(tmp_path_factory):
    """(folder, garment, rest_uv, material): a coarse skirt with a "fitted" rest shape, on a stand-in body."""
    pattern = load_template("skirt")
    garment = mesh_pattern(pattern, spacing=0.05)
    uv = garment.vert_uv.clone()
    uv = torch.stack([uv[:, 0] * 1.03 + 0.01 * uv[:, 1], uv[:, 1] * 0.98], dim=1)
    material = ClothMaterial(bend_stiffness=torch.tensor(2.5e-5, requires_grad=True), friction=0.35)
    out = tmp_path_factory.mktemp("newton_asset")
    write_assets(
        out, pattern=pattern, garment=garment, rest_uv=uv, draped_x=garment.sim_positions(),
        body_verts=TETRA_V, body_faces=TETRA_F, body_params={}, material=material, report={},
    )  # fmt: skip
    return out, garment, uv, material


def test_exported_newton_material_is_the_conversion(skirt_asset):
    out, garment, uv, material = skirt_asset
    data = json.loads((out / "material_newton.json").read_text())
    manifest = json.loads((out / "asset.json").read_text())
    assert manifest["files"]["material_newton_json"]["path"] == "material_newton.json"
    export = read_newton_material(load_assets(out))
    model = ClothModelBuilder(ClothMaterial()).add_garment(garment).finalize(dtype=torch.float64)
    weight, length = nu.edge_geometry(model, uv)
    ours = ClothMaterial(bend_stiffness=2.5e-5, friction=0.35)
    expected = nu.material_to_newton(ours, weight, length, keep="stretch")  # the export's membrane
    m = export.material
    assert (m.tri_ke, m.tri_ka, m.density, m.soft_contact_mu, m.particle_radius) == pytest.approx(
        (
            expected.tri_ke,
            expected.tri_ka,
            expected.density,
            expected.soft_contact_mu,
            expected.particle_radius,
        )
    )
    np.testing.assert_allclose(m.edge_ke, expected.edge_ke, rtol=1e-6)  # k_b: a float32 tensor
    # edges in Newton's order (o0, o1, v0, v1) of our quads (v0, v1, o0, o1); rest lengths as ours
    np.testing.assert_array_equal(export.cloth.edge_indices, model.edge_quads.numpy()[:, [2, 3, 0, 1]])
    np.testing.assert_allclose(export.cloth.edge_rest_length, length, rtol=1e-12)
    # back to ours: the bending and everything but the orthotropic membrane come back exactly
    back = nu.material_from_newton(m, weight, length)
    assert back.bend_stiffness == pytest.approx(2.5e-5, rel=1e-6)
    assert (back.friction, back.thickness, back.areal_density) == pytest.approx((0.35, 0.003, 0.15))
    assert back.k_uu == pytest.approx(np.sqrt(2.0e4 * 1.5e4)) and back.poisson == pytest.approx(0.0)
    loss = data["membrane_conversion_loss"]
    assert loss["k_uu_relative_change"] == pytest.approx(np.sqrt(1.5 / 2.0) - 1.0)
    # the masses: lumped from the rest areas, as ours
    ours_mass = model.rest_data(uv, ClothMaterial()).vert_mass.numpy()
    np.testing.assert_allclose(export.cloth.vert_mass, ours_mass, rtol=1e-6)  # vt: %.9g
    np.testing.assert_array_equal(export.held_vertices, model.attach_vertices.numpy())
    assert len(export.held_vertices) > 0  # a skirt: its waist


def test_isotropic_material_round_trips_exactly_under_both_conversions():
    mu, lam = 700.0, 6.0e3
    material = ClothMaterial(**nu.membrane_from_newton(mu, lam))
    for keep in nu.MEMBRANE_KEEPS:
        args = (material.k_uu, material.k_vv, material.k_uv, material.poisson)
        assert nu.membrane_to_newton(*args, keep=keep) == pytest.approx((mu, lam))
        loss = nu.membrane_conversion_loss(material, keep)
        assert loss["stiffness_relative_error"] < 1e-12 and loss["k_uu_relative_change"] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="shear, stretch"):
        nu.membrane_to_newton(1.0, 1.0, 0.1, keep="bulk")


def test_uniaxial_stiffness_is_the_strip_s_and_newton_s_2d_young_modulus():
    """`material.uniaxial_stiffness`: √(k_uu k_vv) without coupling; on Newton's isotropic membrane the 2D
    Young's modulus 4μ(λ+μ)/(λ+2μ), as `membrane_conversion_loss` reports the strip's stiffness."""
    from torch_diffavatar.sim.material import uniaxial_stiffness

    assert uniaxial_stiffness(ClothMaterial()) == pytest.approx(np.sqrt(2.0e4 * 1.5e4))
    mu, lam = 108.0, 1685.0
    material = ClothMaterial(**nu.membrane_from_newton(mu, lam))
    assert uniaxial_stiffness(material) == pytest.approx(4 * mu * (lam + mu) / (lam + 2 * mu))
    loss = nu.membrane_conversion_loss(material, "shear")
    assert uniaxial_stiffness(material) == pytest.approx(loss["uniaxial_u_ours_N_per_m"])


def test_both_membranes_are_exported_with_what_they_lose(skirt_asset):
    data = json.loads((skirt_asset[0] / "material_newton.json").read_text())
    axial = np.sqrt(2.0e4 * 1.5e4)
    assert data["membrane_keep"] == "stretch"
    loss = data["membrane_conversion_loss"]
    assert loss["uniaxial_newton_N_per_m"] == pytest.approx(axial)  # ν = 0: no coupling, as ours
    assert loss["shear_newton_N_per_m"] == pytest.approx(axial / 2)  # the shear pays
    assert data["parameters"]["tri_ke"]["value"] == pytest.approx(axial / 2)
    assert data["parameters"]["tri_ka"]["value"] == pytest.approx(0.0)
    alt = data["membrane_alternative"]
    assert alt["keep"] == "shear" and alt["membrane_conversion_loss"]["shear_newton_N_per_m"] == 1.0e3
    assert alt["membrane_conversion_loss"]["uniaxial_newton_N_per_m"] < 0.3 * 1.5e4  # the stretch pays
    export = read_newton_material(load_assets(skirt_asset[0]), "shear")
    assert (export.material.tri_ke, export.material.tri_ka) == pytest.approx((1.0e3, axial - 2.0e3))
    assert export.membrane_keep == "shear"
    with pytest.raises(InputError, match="bulk"):
        read_newton_material(load_assets(skirt_asset[0]), "bulk")


def test_check_without_newton_says_how_to_install(skirt_asset, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "newton", None)  # `import newton` now raises ImportError
    code = load_script("newton_check").main([str(skirt_asset[0])])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and 'pip install -e ".[newton]"' in err[0]


@pytest.fixture(scope="module")
def draped_skirt_asset(anny_model, tmp_path_factory):
    """An asset folder whose garment is our coarse skirt draped on an Anny body."""
    from helpers_fit import write_truth_as_assets

    from torch_diffavatar.synthetic_scans import make_draped_scan

    scan = make_draped_scan(
        "skirt", anny_model=anny_model, seed=1, spacing=0.05, garment_points=2000, body_points=1000
    )
    folder = tmp_path_factory.mktemp("newton_check")
    write_truth_as_assets(scan, folder, png_size=64)
    return folder


@pytest.mark.parametrize("args", [["--iterations", "0"], ["--max-frames", "0"], ["--substeps", "-1"]])
def test_check_refuses_drape_settings_out_of_range(skirt_asset, capsys, args):
    code = load_script("newton_check").main([str(skirt_asset[0]), *args])
    (err,) = capsys.readouterr().err.strip().splitlines()
    assert (
        code == 2 and err.startswith("newton_check: NewtonDrapeConfig.") and "must be an integer >= 1" in err
    )


@requires_newton
@pytest.mark.anny
@pytest.mark.slow
@pytest.mark.parametrize("seams", ["welded", "springs"])
def test_newton_drapes_the_exported_asset_near_ours(draped_skirt_asset, seams):
    from torch_diffavatar.sim_newton import NewtonDrapeConfig

    check = load_script("newton_check")
    config = NewtonDrapeConfig(max_frames=60, min_frames=10, iterations=10)  # brief: a check, not a settle
    r = check.check_assets(draped_skirt_asset, seams=seams, config=config, samples=5000)
    x = r["x"]
    assert torch.isfinite(x).all() and r["held_vertices"] > 0 and x.shape == (r["draped_vertices"], 3)
    assert r["penetration_fraction"] < 0.02  # the body holds it
    assert r["lowest_point_drop_m"] < 0.05  # the pinned waist holds it: nothing slid down
    assert r["chamfer_to_ours_m"] < 0.04  # near our drape
    assert r["seam_edge_strain"]["max"] < 0.3  # seams hold (no torn seam edge)
    assert r["edge_strain"]["newton"]["mean_abs"] < 0.05
    if seams == "springs":  # one particle per panel vertex; the stitch springs keep the seams closed
        assert r["particles"] > r["draped_vertices"] and r["seam_gap_m"]["max"] < 0.005
    else:
        assert r["particles"] == r["draped_vertices"] and r["seam_gap_m"] is None
    json.dumps({k: v for k, v in r.items() if k != "x"}, allow_nan=False)  # strict JSON figures
