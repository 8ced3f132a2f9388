"""`diffavatar drape` in-process: JSON contract, OBJ/PNG outputs, bad input, the inverted-triangle measure."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from torch_diffavatar.cli import main
from torch_diffavatar.commands.drape import inverted_triangle_mask

KEYS = {
    "vertices",
    "faces",
    "steps",
    "seconds",
    "max_speed",
    "converged",
    "penetrating_fraction",
    "max_stitch_gap_m",
    "inverted_triangles",
    "quality_min",
    "quality_mean",
}


@pytest.mark.anny
@pytest.mark.slow
def test_drape_skirt_short_run(tmp_path, capsys):
    out, png = tmp_path / "skirt.obj", tmp_path / "skirt.png"
    # a coarse skirt and only a few frames: checks the plumbing, not the equilibrium (see docs/BENCHMARKS.md)
    code = main(
        ["drape", "skirt", "--spacing", "0.05", "--sew-steps", "12", "--max-steps", "2"]
        + ["--out", str(out), "--png", str(png), "--json"]
    )
    assert code == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(result) == KEYS
    assert 2 < result["steps"] <= 14 and result["faces"] > 100 and result["vertices"] > 50
    assert 0.0 <= result["penetrating_fraction"] < 0.005  # the placement starts outside the body
    assert result["inverted_triangles"] == 0
    assert 0.3 <= result["quality_min"] <= result["quality_mean"] <= 1.0
    text = out.read_text()
    assert text.count("\nvt ") > 0 and text.count("\nf ") == result["faces"]
    v = np.array(
        [[float(t) for t in line.split()[1:4]] for line in text.splitlines() if line.startswith("v ")]
    )
    assert len(v) == result["vertices"] and 0.3 < v[:, 1].min() < v[:, 1].max() < 1.2  # a skirt's heights
    from PIL import Image

    assert Image.open(png).size == (1024, 640)


def test_drape_bad_inputs(tmp_path, capsys):
    out = str(tmp_path / "x.obj")
    assert main(["drape", "no_such_template", "--out", out]) == 2
    assert "no_such_template" in capsys.readouterr().err
    assert main(["drape", "skirt", "--body", str(tmp_path / "missing.obj"), "--out", out]) == 2
    assert "missing.obj" in capsys.readouterr().err
    box = trimesh.creation.box(extents=(40.0, 170.0, 30.0))  # centimetres
    box.export(tmp_path / "cm_body.obj")
    assert main(["drape", "skirt", "--body", str(tmp_path / "cm_body.obj"), "--out", out]) == 2
    assert "metres" in capsys.readouterr().err
    assert main(["drape", "skirt", "--spacing", "-1", "--out", out]) == 2


def test_inverted_triangle_mask():
    # a flat strip of 4 triangles facing +Z
    x = torch.tensor([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])
    rest = torch.full((4,), 0.5, dtype=torch.float64)
    assert not inverted_triangle_mask(x, faces, rest).any()
    # fold vertex 5 across edge 1-2: triangle 2 flips against its corners' normals
    folded = x.clone()
    folded[5] = torch.tensor([1.5, -0.5, 0.0], dtype=torch.float64)
    assert inverted_triangle_mask(folded, faces, rest).tolist()[2]
    # collapse triangle 0 to a sliver
    squashed = x.clone()
    squashed[4] = torch.tensor([0.5, 0.001, 0.0], dtype=torch.float64)
    assert inverted_triangle_mask(squashed, faces, rest)[0]


def test_sewing_finishes_with_an_unbounded_pull(monkeypatch):
    """After the stiffness ramp, gaps under ``sew_finish_snap`` close without the bounded stitch pull."""
    from torch_diffavatar.pattern.library import load_template
    from torch_diffavatar.pattern.mesher import mesh_pattern
    from torch_diffavatar.sim import forward_drape as drape
    from torch_diffavatar.sim.model import ClothModelBuilder

    snaps = []

    class Spy(drape.XPBDSolver):
        def step(self, *args, **kwargs):
            snaps.append(self.config.stitch_snap)
            return super().step(*args, **kwargs)

    monkeypatch.setattr(drape, "XPBDSolver", Spy)
    garment = mesh_pattern(load_template("skirt"), spacing=0.08)
    model = ClothModelBuilder().add_garment(garment, merge_seams=False).finalize()
    config = drape.DrapeConfig(sew_max_steps=6, sew_ramp_steps=3, sew_finish_snap=0.02)
    drape.sew(model, garment.vert_uv.float(), config=config)
    bounded = config.sew_xpbd.stitch_snap
    assert snaps[:3] == [bounded] * 3 and set(snaps[3:]) == {0.02}


def test_drape_is_on_a_floor_unless_no_floor():
    from argparse import Namespace

    from torch_diffavatar.commands.drape import _drape_config

    args = Namespace(max_steps=None, sew_steps=12, no_floor=False)
    assert _drape_config(args).floor and _drape_config(args).sew_max_steps == 12
    assert not _drape_config(Namespace(max_steps=None, sew_steps=None, no_floor=True)).floor
