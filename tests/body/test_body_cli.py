import json

import pytest

from torch_diffavatar.cli import main
from torch_diffavatar.scan import save_ply

pytestmark = pytest.mark.anny


def _run(capsys, argv):
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out.strip(), out.err.strip()


@pytest.fixture(scope="module")
def dressed_scan(anny_model, tmp_path_factory):
    from torch_diffavatar.body.synthetic import make_scan

    scan = make_scan(anny_model, seed=5, point_count=8000, garment="tshirt")
    path = tmp_path_factory.mktemp("scan") / "scan.ply"
    save_ply(path, scan.points * 1000.0, colors=scan.colors)  # stored in millimetres
    return scan, path


def test_fit_body_cli_contract(capsys, tmp_path, dressed_scan, anny_model, monkeypatch):
    # The fit's accuracy is tested in test_body_fit.py; here a short schedule checks the plumbing.
    import torch_diffavatar.body.fit as fit_module

    short = fit_module.BodyFitConfig(placement_iters=3, pose_iters=3, final_rounds=1, final_iters=2)
    original = fit_module.fit_body
    monkeypatch.setattr(fit_module, "fit_body", lambda pts, **kw: original(pts, config=short, **kw))
    scan, path = dressed_scan
    code, out, _ = _run(capsys, ["fit-body", str(path), "--units", "mm", "--out", str(tmp_path), "--json"])
    assert code == 0
    summary = json.loads(out)
    assert list(summary) == [
        "points",
        "seconds",
        "chamfer_m",
        "height_m",
        "phenotypes",
        "yaw_deg",
        "coverage",
        "warnings",
    ]
    assert isinstance(summary["warnings"], list)
    assert summary["points"] > 0.9 * len(scan.points)
    assert set(summary["phenotypes"]) == {"gender", "age", "muscle", "weight", "height", "proportions"}
    assert 1.0 < summary["height_m"] < 2.3
    params = json.loads((tmp_path / "body.json").read_text())
    assert len(params["pose_axis_angle"][0]) == len(params["pose_bones"])
    obj = (tmp_path / "body.obj").read_text().splitlines()
    assert sum(line.startswith("f ") for line in obj) == 26692
    # body.json reads back (what `fit --body` and `segment --body` do) into the body of body.obj
    import numpy as np
    import torch

    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.commands.fit import read_body_params

    body = BodyModel(anny_model)
    body.load_parameters_dict(read_body_params(tmp_path))
    assert params["phenotypes_by_name"] == summary["phenotypes"]
    with torch.no_grad():
        verts = body().vertices[0].double().numpy()
    obj_verts = np.array([[float(t) for t in line.split()[1:4]] for line in obj if line.startswith("v ")])
    assert np.abs(verts - obj_verts).max() < 1e-6


@pytest.mark.parametrize("command", ["fit-body", "segment", "fit"])
def test_up_takes_a_negative_axis_as_its_value(command):
    """``--up -y`` (what the upside-down warning advises) parses like ``--up=-y``."""
    from torch_diffavatar.cli import _join_signed_values, build_parser

    extra = {"fit-body": [], "segment": ["--garment", "tshirt"], "fit": ["--garment", "tshirt"]}[command]
    for up in ("-y", "-z", "z"):
        argv = [command, "scan.ply", "--up", up, "--out", "o", *extra]
        assert build_parser().parse_args(_join_signed_values(argv)).up == up


def test_segment_cli_with_a_body_dir(capsys, tmp_path, dressed_scan, anny_model):
    scan, path = dressed_scan
    anny_faces = anny_model.faces.numpy()
    body_dir = tmp_path / "body"
    body_dir.mkdir()
    from torch_diffavatar.mesh_io import write_obj

    write_obj(body_dir / "body.obj", scan.body_vertices, anny_faces)
    out_ply = tmp_path / "garment.ply"
    argv = ["segment", str(path), "--units", "mm", "--garment", "T-shirt", "--body", str(body_dir)]
    code, out, _ = _run(capsys, argv + ["--out", str(out_ply), "--json"])
    assert code == 0
    summary = json.loads(out)
    assert list(summary) == ["points", "garment_points", "boundary_loops"]
    assert abs(summary["garment_points"] - int(scan.labels.sum())) < 0.1 * scan.labels.sum()
    assert {loop["name"] for loop in summary["boundary_loops"]} >= {"neck", "cuff_left", "cuff_right"}
    from torch_diffavatar.scan import load_scan

    garment = load_scan(out_ply, check=False)
    assert garment.point_count == summary["garment_points"]
    # a body.json beside it that cannot be read: said on stderr, the vertices still serve
    (body_dir / "body.json").write_text("{}")
    code, out, err = _run(capsys, argv + ["--out", str(out_ply), "--json"])
    assert code == 0 and "no waist height" in err
    assert json.loads(out)["garment_points"] == summary["garment_points"]
    # geometry alone (the scan has colours): still the T-shirt
    code, out, _ = _run(capsys, argv + ["--out", str(out_ply), "--json", "--no-colour"])
    assert code == 0
    assert abs(json.loads(out)["garment_points"] - int(scan.labels.sum())) < 0.1 * scan.labels.sum()


@pytest.mark.parametrize(
    "content, message",
    [("", "empty"), ("v 0 0 0\nv nan 1 0\nv 0 1 0\nf 1 2 3\n", "NaN")],
)
def test_bad_scans_give_one_line_and_exit_2(capsys, tmp_path, content, message):
    path = tmp_path / "scan.obj"
    path.write_text(content)
    code, out, err = _run(capsys, ["fit-body", str(path), "--out", str(tmp_path / "o"), "--json"])
    assert code == 2 and out == ""
    assert len(err.splitlines()) == 1 and message in err and err.startswith("diffavatar fit-body: error:")


def test_unknown_garment_and_faceless_body(capsys, tmp_path, dressed_scan):
    _, path = dressed_scan
    code, _, err = _run(
        capsys, ["segment", str(path), "--garment", "kimono", "--out", str(tmp_path / "g.ply")]
    )
    assert code == 2 and len(err.splitlines()) == 1 and "unknown garment type 'kimono'" in err
    body_dir = tmp_path / "body"
    body_dir.mkdir()
    (body_dir / "body.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    argv = ["segment", str(path), "--units", "mm", "--garment", "dress", "--body", str(body_dir)]
    code, _, err = _run(capsys, argv + ["--out", str(tmp_path / "g.ply")])
    assert code == 2 and len(err.splitlines()) == 1 and "no faces" in err
