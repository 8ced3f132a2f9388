"""Assets out: fitted pattern JSON reloads with our loader, OBJ UVs equal the rest coordinates, material
and report round-trip."""

from __future__ import annotations

import json

import pytest
import torch

from torch_diffavatar.assets import (
    fitted_pattern,
    material_dict,
    material_from_dict,
    pattern_deviation,
    write_assets,
)
from torch_diffavatar.mesh_io import read_obj
from torch_diffavatar.pattern import load_pattern, load_template, mesh_pattern
from torch_diffavatar.sim.material import ClothMaterial


@pytest.fixture(scope="module")
def dress():
    pattern = load_template("dress")  # lines, quadratic and cubic Béziers and arcs
    return pattern, mesh_pattern(pattern, spacing=0.05)


def _deformed_uv(garment) -> torch.Tensor:
    """A smooth per-panel deformation: stretch in y by 10 %, shear x by 5 % of y."""
    uv = garment.vert_uv.clone()
    return torch.stack([uv[:, 0] + 0.05 * uv[:, 1], 1.1 * uv[:, 1]], dim=1)


def test_fitted_pattern_follows_the_rest_coordinates(dress):
    pattern, garment = dress
    assert (
        pattern_deviation(fitted_pattern(pattern, garment, garment.vert_uv), garment, garment.vert_uv) < 1e-3
    )
    uv = _deformed_uv(garment)
    fitted = fitted_pattern(pattern, garment, uv)
    # an affine map keeps lines straight and Béziers Béziers: the export reproduces the mesh boundary
    # up to the polyline sampling of the curves
    assert pattern_deviation(fitted, garment, uv) < 3e-3  # [m]
    # the template itself is far from the deformed boundary
    assert pattern_deviation(pattern, garment, uv) > 0.02


@pytest.mark.parametrize("depth", [0.5, 1.4])
def test_an_arc_takes_the_depth_the_fit_gave_it(depth):
    """A neckline made shallower (or deeper) with its corners kept: the exported arc follows the rest
    vertices and keeps their length; scaling the template's radius with the unchanged chord did not (the
    suite's T-shirt: its neck exported 1.4 cm shorter than the fit's rest shape)."""
    pattern = load_template("tshirt")
    garment = mesh_pattern(pattern, spacing=0.02)
    ev = garment.edge_vertices[("right_ftorso", 1)]  # the front neckline, a circle edge
    assert pattern.panels["right_ftorso"].edges[1].kind == "circle"
    uv = garment.vert_uv.clone()
    a, b = uv[ev[0]], uv[ev[-1]]
    n = torch.stack([-(b - a)[1], (b - a)[0]]) / torch.linalg.norm(b - a)
    inner = uv[ev[1:-1]]
    off = ((inner - a) @ n)[:, None] * n  # each vertex's offset from the chord
    uv[ev[1:-1]] = inner - off + depth * off
    fitted = fitted_pattern(pattern, garment, uv)
    panel = fitted.panels["right_ftorso"]
    polyline = float(torch.linalg.norm(uv[ev[1:]] - uv[ev[:-1]], dim=1).sum())
    assert panel.edge_length(1) == pytest.approx(polyline, rel=0.01)
    assert pattern_deviation(fitted, garment, uv) < 3e-3  # [m]: a squashed circle is nearly one
    assert pattern_deviation(pattern, garment, uv) > 1e-2
    assert pattern.panels["right_ftorso"].edge_length(1) != pytest.approx(polyline, rel=0.05)


def test_write_assets_and_read_back(dress, tmp_path):
    pattern, garment = dress
    uv = _deformed_uv(garment)
    x = garment.sim_positions() + torch.tensor([0.0, -0.01, 0.0], dtype=torch.float64)
    body_verts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    body_faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    material = ClothMaterial(bend_stiffness=torch.tensor(1.5e-5))
    report = {"units": "m", "chamfer_initial": 0.02, "chamfer_final": 0.01, "iterations": 3}
    files = write_assets(
        tmp_path,
        pattern=pattern,
        garment=garment,
        rest_uv=uv,
        draped_x=x,
        body_verts=body_verts,
        body_faces=body_faces,
        body_params={"phenotypes": [[0.5] * 6]},
        material=material,
        report=report,
        before=(garment.sim_positions(), garment.sim_faces, body_verts, body_faces),
        scan_points=x[::3],
        png_size=64,
    )
    for key in ("pattern_json", "pattern_svg", "rest_obj", "draped_obj", "body_obj", "body_json",
                "material_json", "report_json", "before_after_png", "scan_fit_png",
                "draped_initial_obj"):  # fmt: skip
        assert key in files
    manifest = json.loads(open(files["manifest_json"]).read())
    assert "scan_fit.png" in json.dumps(manifest["files"])
    # pattern JSON loads with our loader and meshes
    loaded = load_pattern(files["pattern_json"])
    assert list(loaded.panels) == list(pattern.panels)
    assert len(loaded.stitches) == len(pattern.stitches)
    mesh_pattern(loaded, spacing=0.05)
    assert pattern_deviation(loaded, garment, uv) < 3e-3
    # rest OBJ: vt = the rest coordinates, faces = panel triangles
    rest = read_obj(files["rest_obj"])
    torch.testing.assert_close(rest.uv, uv.double(), rtol=0, atol=1e-8)
    assert torch.equal(rest.uv_faces, garment.tri_vertices)
    # draped OBJ: v = the drape (sim vertices), vt = the rest coordinates
    draped = read_obj(files["draped_obj"])
    torch.testing.assert_close(draped.verts, x, rtol=0, atol=1e-8)
    torch.testing.assert_close(
        draped.uv[draped.uv_faces], uv.double()[garment.tri_vertices], rtol=0, atol=1e-8
    )
    # the first drape, as draped.obj
    first = read_obj(files["draped_initial_obj"])
    torch.testing.assert_close(first.verts, garment.sim_positions().double(), rtol=0, atol=1e-8)
    # material and report
    data = json.loads(open(files["material_json"]).read())
    assert data["bend_stiffness"] == {"value": pytest.approx(1.5e-5), "unit": "N*m"}
    assert material_from_dict(data).bend_stiffness == pytest.approx(1.5e-5)
    assert material_dict(material_from_dict(data)) == data
    saved = json.loads(open(files["report_json"]).read())
    assert saved["chamfer_final"] == 0.01 and saved["units"] == "m"
    assert saved["pattern_export_max_deviation_m"] < 3e-3


def test_bad_rest_coordinates_are_rejected(dress):
    pattern, garment = dress
    with pytest.raises(ValueError, match="rest_uv must be"):
        fitted_pattern(pattern, garment, garment.vert_uv[:-1])
    bad = garment.vert_uv.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        fitted_pattern(pattern, garment, bad)


def test_an_exported_outline_that_crosses_itself_is_a_warning(dress, tmp_path):
    """`write_assets` says when a refitted panel outline crosses itself (`mesh_pattern` would refuse the
    exported pattern), in ``report.json``'s warnings, and whether the fit's rest outline crosses too or
    only the refitted curves; a sound export adds none."""
    from dataclasses import replace

    import numpy as np

    from torch_diffavatar.assets import crossed_outline_warnings

    pattern, garment = dress
    assert crossed_outline_warnings(pattern) == []
    name, panel = next(iter(pattern.panels.items()))
    verts = np.array(panel.vertices, copy=True)
    verts[[0, 1]] = verts[[1, 0]]  # two neighbouring corners swapped: a bow tie
    crossed = replace(pattern, panels={**pattern.panels, name: replace(panel, vertices=verts)})
    (message,) = crossed_outline_warnings(crossed)
    assert name in message and "crosses itself" in message
    (refit,) = crossed_outline_warnings(crossed, garment, garment.vert_uv.numpy())  # the rest shape is fine
    assert name in refit and "a refitted curve overshoots" in refit
    uv = garment.vert_uv.clone()
    corner = garment.edge_vertices[(name, 0)]
    uv[corner[0]], uv[corner[-1]] = garment.vert_uv[corner[-1]], garment.vert_uv[corner[0]]
    body_verts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    body_faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    files = write_assets(
        tmp_path,
        pattern=pattern,
        garment=garment,
        rest_uv=uv,
        draped_x=garment.sim_positions(),
        body_verts=body_verts,
        body_faces=body_faces,
        body_params={},
        material=ClothMaterial(),
        report={"warnings": ["kept"]},
    )
    warnings = json.loads(open(files["report_json"]).read())["warnings"]
    assert warnings[0] == "kept" and len(warnings) == 2
    assert (
        f"the fitted outline of {name} crosses itself" in warnings[1] and "passed each other" in warnings[1]
    )
