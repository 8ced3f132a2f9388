"""The asset format for other simulators: asset.json + seams.json beside the OBJs, and `load_assets`
reading a folder back into the objects it was written from."""

from __future__ import annotations

import json

import pytest
import torch
from helpers_fit import TETRA_F, TETRA_V

from torch_diffavatar.assets import (
    MATERIAL_UNITS,
    load_assets,
    stitched_edges,
    write_assets,
)
from torch_diffavatar.errors import InputError
from torch_diffavatar.pattern import load_template, mesh_pattern
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    pattern = load_template("dress")
    garment = mesh_pattern(pattern, spacing=0.05)
    uv = garment.vert_uv.clone()
    uv = torch.stack([uv[:, 0] * 1.03 + 0.01 * uv[:, 1], uv[:, 1] * 0.98], dim=1)  # a "fitted" rest shape
    x = garment.sim_positions() + torch.tensor([0.0, -0.02, 0.01], dtype=torch.float64)
    material = ClothMaterial(bend_stiffness=torch.tensor(2.5e-5), friction=0.35)
    params = {"phenotypes": [[0.5] * 6], "pose_bones": ["head"], "translation_m": [[0.0, 0.9, 0.0]]}
    out = tmp_path_factory.mktemp("assets")
    files = write_assets(
        out,
        pattern=pattern,
        garment=garment,
        rest_uv=uv,
        draped_x=x,
        body_verts=TETRA_V,
        body_faces=TETRA_F,
        body_params=params,
        material=material,
        report={"chamfer_final": 0.01},
    )
    return out, files, garment, uv, x, material, params


def test_round_trip_restores_garment_material_and_body(written):
    out, _, garment, uv, x, material, params = written
    a = load_assets(out)
    g = a.garment
    torch.testing.assert_close(a.rest_uv, uv, atol=1e-8, rtol=0)  # %.9g in the OBJ
    torch.testing.assert_close(g.vert_uv, uv, atol=1e-8, rtol=0)
    torch.testing.assert_close(a.draped_x, x, atol=1e-8, rtol=0)
    torch.testing.assert_close(g.vert_pos, x[garment.vert_to_sim], atol=1e-8, rtol=0)
    for name in ("tri_vertices", "stitch_pairs", "vert_to_sim", "vert_panel"):
        assert torch.equal(getattr(g, name), getattr(garment, name)), name
    assert g.panel_names == garment.panel_names and g.sim_vert_count == garment.sim_vert_count
    assert g.garment_type == garment.garment_type and g.spacing == garment.spacing
    assert set(g.vert_labels) == set(garment.vert_labels)
    assert all(torch.equal(g.vert_labels[k], garment.vert_labels[k]) for k in garment.vert_labels)
    assert [b.name for b in g.boundary_loops] == [b.name for b in garment.boundary_loops]
    assert set(g.edge_vertices) == set(garment.edge_vertices)
    assert float(a.material.bend_stiffness) == pytest.approx(2.5e-5)
    assert float(a.material.friction) == pytest.approx(0.35)
    assert a.body_params == params
    torch.testing.assert_close(a.body_verts, TETRA_V)
    assert torch.equal(a.body_faces, TETRA_F)
    assert list(a.pattern.panels) == list(garment.panel_names)
    # the loaded garment builds the same simulation model as the original
    m0 = ClothModelBuilder(material).add_garment(garment).finalize(dtype=torch.float64)
    m1 = ClothModelBuilder(a.material).add_garment(g).finalize(dtype=torch.float64)
    for name in ("tri_vertices", "tri_panel_vertices", "edge_quads", "stitch_vertices", "attach_vertices"):
        assert torch.equal(getattr(m0, name), getattr(m1, name)), name
    torch.testing.assert_close(m0.rest_data(uv).vert_mass, m1.rest_data(a.rest_uv).vert_mass)


def test_manifest_names_files_frame_units_and_material_meanings(written):
    out, files, garment, *_ = written
    manifest = json.loads((out / "asset.json").read_text())
    assert manifest["frame"]["up"] == "+Y" and manifest["units"]["length"] == "m"
    for entry in manifest["files"].values():
        assert (out / entry["path"]).is_file() and entry["content"]
    assert set(manifest["material"]) == set(MATERIAL_UNITS)
    for name, entry in manifest["material"].items():
        assert entry["unit"] == MATERIAL_UNITS[name] and entry["meaning"]
    assert manifest["garment"]["rest_vertex_count"] == garment.vert_count
    assert manifest["garment"]["draped_vertex_count"] == garment.sim_vert_count
    assert "manifest_json" in files and "seams_json" in files


def test_stitched_edges_pair_sewn_boundary_edges(written):
    _, _, garment, *_ = written
    se = stitched_edges(garment)
    assert se.shape[0] > 0 and se.shape[1] == 4
    pairs = {tuple(sorted(p)) for p in garment.stitch_pairs.tolist()}
    v2s = garment.vert_to_sim
    for a0, a1, b0, b1 in se.tolist():
        assert tuple(sorted((a0, b0))) in pairs and tuple(sorted((a1, b1))) in pairs
        # a sewn edge pair collapses onto one edge of the draped (seam-merged) mesh
        assert {int(v2s[a0]), int(v2s[a1])} == {int(v2s[b0]), int(v2s[b1])}
    # every seam of the dress shows up: each stitched vertex lies on some stitched edge
    on_edges = set(se[:, :2].reshape(-1).tolist()) | set(se[:, 2:].reshape(-1).tolist())
    assert set(garment.stitch_pairs.reshape(-1).tolist()) <= on_edges


def test_load_assets_rejects_folders_without_a_manifest(written, tmp_path):
    out = written[0]
    with pytest.raises(InputError, match="asset.json"):
        load_assets(tmp_path)
    (tmp_path / "asset.json").write_text(json.dumps({"format": "other", "version": 1}))
    with pytest.raises(InputError, match="format"):
        load_assets(tmp_path)
    bad = json.loads((out / "seams.json").read_text())
    bad["sim_vertex_count"] += 1
    for f in out.iterdir():
        if f.is_file():
            (tmp_path / f.name).write_bytes(f.read_bytes())
    (tmp_path / "seams.json").write_text(json.dumps(bad))
    with pytest.raises(InputError, match="draped.obj"):
        load_assets(tmp_path)
