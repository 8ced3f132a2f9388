"""`diffavatar fit`'s garment argument: a bundled template or any GarmentCode pattern file."""

from __future__ import annotations

from pathlib import Path

import pytest

from torch_diffavatar.cli import main
from torch_diffavatar.fit_setup import SEGMENT_TYPES, TYPE_CONFIGS, infer_garment_type
from torch_diffavatar.pattern import load_pattern
from torch_diffavatar.pattern.library import load_template

GARMENTCODE = Path("/work/shared/garmentcode")
# GarmentCode's own files (not our templates) and what they are
PATTERN_FILES = {
    "shirt_long_sleeve": "shirt",
    "polo_collar_short_sleeve": "polo",
    "tshirt_short_sleeve": "tshirt",
    "skirt_aline": "skirt",
    "pants_shorts": "pants",
    "dress_fitted_sleeveless_aline": "dress",
    "dress_fitted_short_sleeve_pencil": "dress",
    "repo_examples/shirt_mean": "shirt",  # sleeves to mid-forearm
    "repo_examples/hoody_mean": "dress",  # sleeveless top with a hood: the dress's regions and armholes
    "repo_examples/js_mean_all": "jumpsuit",  # legs, and sleeves above the waist
}


@pytest.mark.parametrize("name", sorted(SEGMENT_TYPES))
def test_inferred_type_of_every_template_is_its_segmentation_type(name):
    assert infer_garment_type(load_template(name)) == SEGMENT_TYPES[name]


@pytest.mark.parametrize("folder", sorted(PATTERN_FILES))
def test_inferred_type_of_garmentcode_files(folder):
    specs = sorted((GARMENTCODE / folder).glob("*_specification.json"))
    if not specs:
        pytest.skip(f"{GARMENTCODE / folder} not on this machine")
    kind = infer_garment_type(load_pattern(specs[0]))
    assert kind == PATTERN_FILES[folder] and kind in TYPE_CONFIGS


def test_fit_rejects_a_garment_that_is_neither_template_nor_file(tmp_path, capsys):
    scan = tmp_path / "scan.ply"
    scan.write_text("ply\n")
    code = main(["fit", str(scan), "--garment", "cardigan", "--out", str(tmp_path / "out")])
    assert code == 2
    assert "not a template" in capsys.readouterr().err
    bad = tmp_path / "broken.json"
    bad.write_text("{not json")
    assert main(["fit", str(scan), "--garment", str(bad), "--out", str(tmp_path / "out")]) == 2


def test_fit_config_follows_the_garment(tmp_path, monkeypatch):
    """`fit --garment dress_pencil` fitted with the bare `FitConfig` defaults (a quick, weak fit), and
    `--config configs/dress.yaml --garment dress_pencil` fitted the plain dress (the file's template)."""
    import torch_diffavatar.commands.fit as commands
    from torch_diffavatar.fit import CONFIG_DIR, load_config

    seen = []
    monkeypatch.setattr(commands, "fit_scan", lambda scan, config, *a, **k: seen.append(config) or {})
    base = ["fit", str(tmp_path / "scan.ply"), "--out", str(tmp_path / "out"), "--json"]
    assert main([*base, "--garment", "dress_pencil"]) == 0
    assert main([*base, "--garment", "dress_pencil", "--config", str(CONFIG_DIR / "dress.yaml")]) == 0
    assert main([*base, "--garment", "shorts", "--iters", "3"]) == 0
    dress, pants = load_config(garment="dress"), load_config(garment="pants")
    assert seen[0].template == seen[1].template == "dress_pencil"
    assert seen[0].adjoint == seen[1].adjoint == dress.adjoint and seen[0].spacing == dress.spacing
    assert seen[2].template == "shorts" and seen[2].iterations == 3 and seen[2].spacing == pants.spacing


def test_body_parameters_are_read_from_a_file_or_a_folder(tmp_path):
    import json

    from torch_diffavatar.commands.fit import read_body_params
    from torch_diffavatar.errors import InputError

    params = {
        "phenotypes": [[0.5] * 6],
        "pose_bones": [],
        "pose_axis_angle": [[]],
        "global_orient_axis_angle": [[0.0, 0.0, 0.0]],
        "translation_m": [[0.0, 0.9, 0.0]],
        "scale": [1.0],
    }
    (tmp_path / "body.json").write_text(json.dumps(params))
    assert read_body_params(tmp_path) == params == read_body_params(tmp_path / "body.json")
    with pytest.raises(InputError, match="no body.json"):
        read_body_params(tmp_path / "nowhere")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        read_body_params(tmp_path / "bad.json")
    (tmp_path / "other.json").write_text(json.dumps({"phenotypes": [[0.5] * 6]}))
    with pytest.raises(InputError, match="missing pose_bones, pose_axis_angle"):
        read_body_params(tmp_path / "other.json")
    # the command says so on one line and exits 2, before any heavy work
    scan = tmp_path / "scan.ply"
    scan.write_text("ply\n")
    args = ["fit", str(scan), "--garment", "skirt", "--out", str(tmp_path / "out")]
    assert main([*args, "--body", str(tmp_path / "bad.json")]) == 2


@pytest.mark.anny
@pytest.mark.slow
def test_fit_set_up_on_a_given_body_does_not_fit_one(skirt_scan, anny_model, tmp_path, monkeypatch):
    import torch

    import torch_diffavatar.body.fit as body_fit
    from torch_diffavatar.fit import load_config
    from torch_diffavatar.fit_setup import prepare
    from torch_diffavatar.sim.placement import body_signed_distance
    from torch_diffavatar.synthetic_scans import write_scan

    def no_fit(*args, **kwargs):
        raise AssertionError("the body was fitted although one was given")

    monkeypatch.setattr(body_fit, "fit_body", no_fit)
    write_scan(skirt_scan, tmp_path / "scan")
    config = load_config(garment="skirt", spacing=0.05)
    truth = skirt_scan.body_params
    setup = prepare(tmp_path / "scan" / "scan.ply", config, anny_model=anny_model, body_params=truth)
    assert setup["body_fit_chamfer_m"] is None
    for key in ("phenotypes", "translation_m", "pose_axis_angle"):
        given = torch.tensor(setup["body_params"][key])
        torch.testing.assert_close(given, torch.tensor(truth[key]), atol=1e-6, rtol=0)
    # the template is placed around that body: outside it, and close to it at the waist
    garment = setup["garment"]
    dist = body_signed_distance(garment.vert_pos.numpy(), skirt_scan.body_vertices, skirt_scan.body_faces)
    assert dist.min() > 0.005 and dist.min() < 0.05
    assert setup["sewing_fallback"] is None  # an A-pose body: nothing else to try
    # on a posed body the fit also gets the way through the A-pose, placed for the same garment
    posed = dict(truth, pose_axis_angle=torch.tensor(truth["pose_axis_angle"]).add(0.1).tolist())
    setup = prepare(tmp_path / "scan" / "scan.ply", config, anny_model=anny_model, body_params=posed)
    route = setup["sewing_fallback"]
    assert route.vert_pos.shape == setup["garment"].vert_pos.shape
    assert route.body_path.shape[1:] == skirt_scan.body_vertices.shape
    dist = body_signed_distance(route.vert_pos.numpy(), route.body_path[0], skirt_scan.body_faces)
    assert dist.min() > 0.005


def test_a_hood_covers_the_head_and_no_other_garment_does():
    from torch_diffavatar.fit_setup import covers_head
    from torch_diffavatar.pattern import mesh_pattern

    hoody = sorted((GARMENTCODE / "repo_examples/hoody_mean").glob("*_specification.json"))
    if hoody:
        assert covers_head(mesh_pattern(load_pattern(hoody[0]), spacing=0.05))
    # the polo's collar too
    assert not any(covers_head(mesh_pattern(load_template(name), spacing=0.05)) for name in SEGMENT_TYPES)


@pytest.mark.anny
def test_the_body_fit_takes_a_hoods_points_on_the_head_for_cloth(anny_model, tmp_path, monkeypatch):
    """A hood covers the head, whose scan points the body fit otherwise takes for skin (`skin_parts`):
    the body came out 1.8-2.3 cm too tall on hoody scans, 0.7-1.1 cm without the head among them."""
    import numpy as np
    import trimesh

    import torch_diffavatar.body.fit as body_fit
    from torch_diffavatar.fit import load_config
    from torch_diffavatar.fit_setup import prepare

    class Fitted(Exception):
        pass

    seen = []

    def record(points, body, config=None, workers=1):
        seen.append(config.skin_parts)
        raise Fitted

    monkeypatch.setattr(body_fit, "fit_body", record)
    scan = tmp_path / "scan.ply"
    # a blob shaped like a standing person (the intake refuses a round one: `check_person_shape`)
    blob = np.random.default_rng(0).normal([0.0, 1.0, 0.0], [0.15, 0.35, 0.08], (2000, 3))
    trimesh.PointCloud(blob).export(scan)
    hoody = sorted((GARMENTCODE / "repo_examples/hoody_mean").glob("*_specification.json"))
    garments = ["polo", *(str(path) for path in hoody[:1])]
    for garment in garments:
        with pytest.raises(Fitted):
            prepare(scan, load_config(garment="polo", template=garment), anny_model=anny_model)
    assert "head" in seen[0] and "hand.L" in seen[0]
    if hoody:
        assert "head" not in seen[1] and "hand.L" in seen[1]


def test_arms_held_low_are_fitted_on_a_finer_mesh(tmp_path, monkeypatch):
    """A lowered arm presses the cloth flat, which a 2.5 cm mesh crushes (draped quality 0.24 and 0.20 on
    a T-shirt and a long sleeve with the arms 0.4 and 0.3 rad below the A-pose, 0.49 and 0.54 at 2 cm)."""
    from dataclasses import replace

    import torch_diffavatar.commands.fit as commands
    from torch_diffavatar.errors import InputError
    from torch_diffavatar.fit import config_from_dict, load_config
    from torch_diffavatar.fit_setup import arms_spacing

    a_pose, one_low = {"left": 41.7, "right": 41.7}, {"left": 41.7, "right": 19.0}
    for name in ("tshirt", "polo", "longsleeve"):
        config = load_config(garment=name)
        assert (config.spacing, config.arms_low_spacing) == (0.025, 0.02)
        assert arms_spacing(config, a_pose) == 0.025
        assert arms_spacing(config, one_low) == 0.02  # one arm is enough
    dress = load_config(garment="dress")  # fitted as well with its arms low at 3 cm (quality 0.56)
    assert dress.arms_low_spacing is None and arms_spacing(dress, one_low) == dress.spacing
    assert arms_spacing(replace(config, spacing=0.015), one_low) == 0.015  # never coarser than asked
    with pytest.raises(InputError, match="arms_low_spacing"):
        config_from_dict({"arms_low_spacing": -0.02})
    with pytest.raises(InputError, match="arms_low_angle"):
        config_from_dict({"arms_low_angle": 200})
    # --spacing is the user's choice, arms held low or not
    seen = []
    monkeypatch.setattr(commands, "fit_scan", lambda scan, config, *a, **k: seen.append(config) or {})
    base = ["fit", str(tmp_path / "scan.ply"), "--garment", "polo", "--out", str(tmp_path / "out"), "--json"]
    assert main(base) == 0 and main([*base, "--spacing", "0.03"]) == 0
    assert seen[0].arms_low_spacing == 0.02
    assert seen[1].spacing == 0.03 and seen[1].arms_low_spacing is None


@pytest.mark.anny
@pytest.mark.slow
def test_the_set_up_meshes_finer_under_arms_held_low(skirt_scan, anny_model, tmp_path):
    import torch

    from torch_diffavatar.fit import load_config
    from torch_diffavatar.fit_setup import prepare
    from torch_diffavatar.synthetic_scans import write_scan

    write_scan(skirt_scan, tmp_path / "scan")
    scan, config = (
        tmp_path / "scan" / "scan.ply",
        load_config(garment="skirt", spacing=0.05, arms_low_spacing=0.04),
    )
    truth = skirt_scan.body_params
    setup = prepare(scan, config, anny_model=anny_model, body_params=truth)
    assert setup["spacing"] == 0.05 and min(setup["upper_arm_angles_deg"].values()) > 40  # the A-pose
    pose = torch.tensor(truth["pose_axis_angle"])
    pose[0, truth["pose_bones"].index("upperarm01.L"), 1] += 0.4  # the left arm lowered toward the torso
    low = prepare(scan, config, anny_model=anny_model, body_params=dict(truth, pose_axis_angle=pose.tolist()))
    assert low["spacing"] == 0.04 and low["upper_arm_angles_deg"]["left"] < 20
    assert low["garment"].sim_vert_count > 1.3 * setup["garment"].sim_vert_count
    # the way through the A-pose is meshed alike
    assert low["sewing_fallback"].vert_pos.shape == low["garment"].vert_pos.shape
