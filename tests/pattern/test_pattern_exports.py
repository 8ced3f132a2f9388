"""OBJ in/out, SVG/PNG pattern pictures, and the `diffavatar mesh` command."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch
from helpers_pattern import two_squares, write_json
from PIL import Image

from torch_diffavatar.cli import main
from torch_diffavatar.errors import InputError
from torch_diffavatar.mesh_io import read_obj, write_garment_obj, write_obj
from torch_diffavatar.pattern import load_template, mesh_pattern
from torch_diffavatar.pattern.svg import pattern_svg, save_pattern_png, stitch_colours


def test_obj_round_trip(tmp_path):
    g = torch.Generator().manual_seed(0)
    verts = torch.rand(6, 3, dtype=torch.float64, generator=g)
    faces = torch.tensor([[0, 1, 2], [2, 3, 4], [3, 5, 4]])
    uv = torch.rand(8, 2, dtype=torch.float64, generator=g)
    uv_faces = torch.tensor([[0, 1, 2], [5, 6, 7], [3, 4, 5]])
    normals = torch.nn.functional.normalize(torch.rand(6, 3, dtype=torch.float64, generator=g), dim=1)
    write_obj(tmp_path / "a.obj", verts, faces, uv=uv, uv_faces=uv_faces, normals=normals)
    m = read_obj(tmp_path / "a.obj")
    torch.testing.assert_close(m.verts, verts, atol=1e-8, rtol=0)
    assert (
        torch.equal(m.faces, faces)
        and torch.equal(m.uv_faces, uv_faces)
        and torch.equal(m.normal_faces, faces)
    )
    torch.testing.assert_close(m.uv, uv, atol=1e-8, rtol=0)
    torch.testing.assert_close(m.normals, normals, atol=1e-5, rtol=0)
    write_obj(tmp_path / "b.obj", verts, faces)
    m = read_obj(tmp_path / "b.obj")
    assert m.uv is None and torch.equal(m.faces, faces)


def test_read_obj_quads_negative_indices_and_errors(tmp_path):
    (tmp_path / "q.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf -4 -3 -2 -1\n")
    m = read_obj(tmp_path / "q.obj")
    assert m.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    (tmp_path / "bad.obj").write_text("v 0 0 0\nf 1 2 x\n")
    with pytest.raises(InputError, match="bad.obj:2"):
        read_obj(tmp_path / "bad.obj")
    with pytest.raises(InputError, match="not found"):
        read_obj(tmp_path / "missing.obj")


def test_garment_obj_keeps_rest_coordinates(tmp_path):
    g = mesh_pattern(load_template("skirt"), spacing=0.04)
    write_garment_obj(tmp_path / "skirt.obj", g)
    m = read_obj(tmp_path / "skirt.obj")
    assert len(m.verts) == g.sim_vert_count and len(m.uv) == g.vert_count
    assert torch.equal(m.faces, g.sim_faces) and torch.equal(m.uv_faces, g.tri_vertices)
    torch.testing.assert_close(m.uv, g.vert_uv, atol=1e-8, rtol=0)
    torch.testing.assert_close(m.verts, g.sim_positions(), atol=1e-8, rtol=0)


def test_svg_colours_both_edges_of_each_stitch_and_names_panels():
    p = load_template("dress")
    svg = pattern_svg(p)
    for name in p.panels:
        assert f">{name}</text>" in svg
    assert ">lower_interface</text>" in svg and ">left_armhole</text>" in svg
    strokes = re.findall(r'<polyline[^>]*stroke="(#[0-9a-f]{6})"', svg)
    for colour in stitch_colours(len(p.stitches)):
        assert strokes.count(colour) == 2


def test_png_preview(tmp_path):
    p = load_template("skirt")
    save_pattern_png(p, tmp_path / "skirt.png", px_per_cm=2)
    img = np.asarray(Image.open(tmp_path / "skirt.png").convert("RGB"))
    assert img.shape[0] > 50 and img.shape[1] > 100
    for colour in stitch_colours(len(p.stitches)):
        rgb = np.array([int(colour[i : i + 2], 16) for i in (1, 3, 5)])
        assert (np.abs(img.astype(int) - rgb).sum(axis=2) == 0).sum() > 20


def test_cli_mesh_json(tmp_path, capsys):
    out, svg, png = tmp_path / "s.obj", tmp_path / "s.svg", tmp_path / "s.png"
    code = main(
        [
            "mesh",
            "skirt",
            "--spacing",
            "0.03",
            "--out",
            str(out),
            "--svg",
            str(svg),
            "--png",
            str(png),
            "--json",
        ]
    )
    assert code == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    result = json.loads(lines[0])
    assert list(result) == [
        "panels",
        "vertices",
        "faces",
        "stitch_pairs",
        "boundary_loops",
        "min_angle_deg",
        "quality_min",
        "quality_mean",
        "max_stitch_count_mismatch",
    ]
    g = mesh_pattern(load_template("skirt"), spacing=0.03)
    assert result["panels"] == 2 and result["vertices"] == g.sim_vert_count and result["faces"] == g.tri_count
    assert result["boundary_loops"] == 2 and result["max_stitch_count_mismatch"] == 0
    assert result["min_angle_deg"] >= 25.0 and 0 < result["quality_min"] <= result["quality_mean"] <= 1
    assert out.exists() and svg.exists() and png.exists()


@pytest.mark.parametrize(
    "content,message",
    [
        (None, "not found"),
        ('{"pattern": [', "malformed JSON"),
        ("missing_edge", "missing edge 9"),
        ("twisted", "self-intersecting panel outline"),
    ],
)
def test_cli_bad_input_exits_2(tmp_path, capsys, content, message):
    path = tmp_path / "in.json"
    if content == "missing_edge":
        d = two_squares()
        d["pattern"]["stitches"][0][0]["edge"] = 9
        write_json(path, d)
    elif content == "twisted":
        d = two_squares()
        d["pattern"]["panels"]["back"]["vertices"] = [[0, 0], [20, 30], [0, 30], [20, 0]]
        write_json(path, d)
    elif content is not None:
        write_json(path, content)
    code = main(["mesh", str(path), "--json"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert message in err[0] and "in.json" in err[0]


def test_svg_writes_names_and_labels_as_text_never_markup():
    """Panel names and edge labels come from user files: in the SVG they are escaped text, and the file
    stays well-formed XML (a name with ``<script>`` and ``&`` once made it invalid, and an injection)."""
    import xml.etree.ElementTree as ET

    from torch_diffavatar.pattern import pattern_from_dict

    spec = two_squares()
    evil = '<script>alert("x")</script> & co'
    panels = spec["pattern"]["panels"]
    panels[evil] = panels.pop("front")
    panels[evil]["edges"][0]["label"] = "<b>hem</b> & 'cuff'"
    spec["pattern"]["stitches"][0][0]["panel"] = evil
    svg = pattern_svg(pattern_from_dict(spec))
    root = ET.fromstring(svg)
    texts = {el.text for el in root.iter("{http://www.w3.org/2000/svg}text")}
    assert evil in texts and "<b>hem</b> & 'cuff'" in texts
    assert "<script>" not in svg
