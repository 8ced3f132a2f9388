"""Synthetic clothed scans (`diffavatar make-scan`) and the evaluation against their truth
(`diffavatar eval`)."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch

from torch_diffavatar.cli import main
from torch_diffavatar.evaluation import DRAPE_PICTURE, evaluate_assets, seam_length_mismatch
from torch_diffavatar.pattern.design import changed_pattern
from torch_diffavatar.pattern.garmentcode import load_pattern
from torch_diffavatar.pattern.library import load_template
from torch_diffavatar.synthetic_scans import make_draped_scan, write_scan


def test_changed_pattern_reproduces_the_demo_truth():
    """The demo's truth was made by raising the dress's skirt hem 8 cm and widening it 12 %."""
    from torch_diffavatar.commands.demo import DEMO_TRUTH_PATTERN

    changed = changed_pattern(load_template("dress"), hem_up=0.08, hem_widen=0.12)
    truth = load_pattern(DEMO_TRUTH_PATTERN)
    for name, panel in truth.panels.items():
        np.testing.assert_allclose(changed.panels[name].vertices, panel.vertices, atol=1e-9)


def test_changed_pattern_moves_only_the_hem_corners():
    base = load_template("tshirt")
    changed = changed_pattern(base, hem_up=0.04, hem_widen=0.0)
    moved = {n: np.abs(changed.panels[n].vertices - p.vertices).max() for n, p in base.panels.items()}
    assert all(moved[n] == pytest.approx(0.04) for n in moved if "torso" in n)
    assert all(moved[n] == 0.0 for n in moved if "sleeve" in n)
    # front and back shorten alike, so the side seams still match
    assert seam_length_mismatch(changed)["max_m"] == pytest.approx(
        seam_length_mismatch(base)["max_m"], abs=1e-9
    )
    # seam by seam: one entry per stitch; a panel grown 2 % moves exactly the seams it is on
    per_seam = seam_length_mismatch(base)["per_seam_m"]
    assert len(per_seam) == len(base.stitches)
    assert max(per_seam.values()) == seam_length_mismatch(base)["max_m"]
    grown = copy.deepcopy(base)
    grown.panels["right_sleeve_b"].vertices = 1.02 * grown.panels["right_sleeve_b"].vertices
    moved = {k for k, v in seam_length_mismatch(grown)["per_seam_m"].items() if abs(v - per_seam[k]) > 1e-6}
    assert moved and moved == {k for k in per_seam if "right_sleeve_b[" in k}


@pytest.mark.anny
@pytest.mark.slow
def test_make_scan_sews_a_long_sleeve_onto_a_large_body(anny_model):
    """Closing the shoulder tips, where four panels meet at 6 mm pattern edges, strains their small
    triangles past the solver's default limit (E = 3) for a frame; sewing must not call that a blow-up
    (`drape.SEW_MAX_STRAIN`). Before, this scan failed: "Green strain 3.36 > max_strain 3"."""
    scan = make_draped_scan(
        "longsleeve",
        anny_model=anny_model,
        seed=5,
        phenotypes=dict(weight=0.8, height=0.7, gender=0.8),
        garment_points=1000,
        body_points=1000,
    )
    drape = scan.info["drape"]
    assert drape["converged"] and drape["max_stitch_gap_m"] < 0.005
    assert scan.height > 1.75  # the large body the failure needed


@pytest.mark.anny
@pytest.mark.slow
def test_draped_scan_is_labelled_noisy_and_holey(skirt_scan):
    scan = skirt_scan
    labels = scan.labels
    assert set(np.unique(labels)) == {0, 1}
    assert scan.info["drape"]["converged"] and scan.info["drape"]["max_stitch_gap_m"] < 0.002
    # holes: 10 % in round holes plus the two under-arm holes
    assert len(scan.points) < 0.9 * 8000
    # noise: garment points lie ~2 mm off the noise-free drape
    from scipy.spatial import cKDTree

    d, _ = cKDTree(scan.cloth_x).query(scan.points[labels == 1])
    assert 0.0015 < np.median(d) < 0.03
    # no skin point is under the skirt: skin points are far from the cloth or outside it
    assert scan.points[labels == 0, 1].max() > 1.5 and scan.points[labels == 1, 1].max() < 1.2


@pytest.mark.anny
@pytest.mark.slow
def test_eval_of_the_truth_itself_is_exact(skirt_scan, tmp_path, capsys):
    """Assets that *are* the truth: every error is ~0 and the scan Chamfer is at the noise level."""
    from helpers_fit import write_truth_as_assets

    scan = skirt_scan
    write_scan(scan, tmp_path / "gt")
    write_truth_as_assets(
        scan,
        tmp_path / "fit",
        # the "first drape": the garment as placed, before any simulation
        before=(
            scan.garment.sim_positions(),
            scan.garment.sim_faces,
            torch.as_tensor(scan.body_vertices),
            torch.as_tensor(scan.body_faces),
        ),
        png_size=64,
    )
    out = evaluate_assets(tmp_path / "fit", tmp_path / "gt")
    assert out["chamfer_truth_drape_initial_m"] > 0.01 > 1e-4 > out["chamfer_truth_drape_m"]
    assert out["chamfer_scan_initial_m"] > out["chamfer_scan_m"] + 0.005
    assert out["pattern_outline_error_m"] < 1e-4 and out["pattern_outline_hausdorff_m"] < 1e-3
    assert out["chamfer_truth_drape_m"] < 1e-4
    assert out["bending_stiffness_ratio"] == pytest.approx(1.0)
    assert out["stretch_stiffness_ratio"] == pytest.approx(1.0)
    assert abs(out["body_height_error_m"]) < 1e-6 and out["body_mean_vertex_error_m"] < 1e-6
    assert 0.001 < out["chamfer_scan_m"] < 0.01  # the noise (2 mm) and the scan's point spacing
    assert out["chamfer_scan_truth_m"] == pytest.approx(out["chamfer_scan_m"], rel=1e-6)  # the floor
    assert out["draped_quality"]["min"] > 0.2 and out["rest_quality"]["min"] > 0.4
    seams, true_seams = out["seam_length_mismatch"], out["seam_length_mismatch_truth"]
    assert true_seams["per_seam_m"] == pytest.approx(seams["per_seam_m"], abs=1e-9)
    measured = out["garment_measurements"]
    assert {"waist_circumference", "hem_circumference", "garment_length"} <= set(measured)
    assert out["garment_measurement_max_error_cm"] < 1e-6
    # the text report leads with the truth: the pattern, then the true drape, then the scan
    assert main(["eval", str(tmp_path / "fit"), "--gt", str(tmp_path / "gt"), "--no-picture"]) == 0
    text = capsys.readouterr().out
    heads = ("outline error", "garment measurements [cm]", "Chamfer to the true drape", "Chamfer to the scan")
    assert [text.index(h) for h in heads] == sorted(text.index(h) for h in heads)
    # the command prints the same as one JSON line; a missing truth folder is one error line, exit 2
    assert main(["eval", str(tmp_path / "fit"), "--gt", str(tmp_path / "gt"), "--json"]) == 0
    assert main(["eval", str(tmp_path / "fit"), "--gt", str(tmp_path / "nowhere"), "--json"]) == 2
    # and draws the first drape, the result and the truth, front and back: here the last two are the same
    from PIL import Image

    picture = np.asarray(Image.open(tmp_path / "fit" / DRAPE_PICTURE))
    views = np.split(picture[16:], 6, axis=1)  # below the titles
    assert np.array_equal(views[2], views[4]) and np.array_equal(views[3], views[5])
    assert not np.array_equal(views[0], views[2]) and (views[2] < 250).any()
    truth = json.loads((tmp_path / "gt" / "truth" / "truth.json").read_text())
    assert truth["design_change"] == {"hem_up_m": 0.05, "hem_widen": 0.1}
    # from the fitted body's front and back: a body turned 90° about +Y (facing +X) is drawn from +X
    body_json = tmp_path / "fit" / "body.json"
    body_json.write_text(
        json.dumps({**json.loads(body_json.read_text()), "global_orient_axis_angle": [[0, 1.5708, 0]]})
    )
    assert main(["eval", str(tmp_path / "fit"), "--gt", str(tmp_path / "gt")]) == 0
    turned = np.split(np.asarray(Image.open(tmp_path / "fit" / DRAPE_PICTURE))[16:], 6, axis=1)
    assert not np.array_equal(turned[2], views[2]) and not np.array_equal(turned[3], views[3])

    def width(view):  # columns the drawing covers: a person is narrower seen from the side
        return int((view < 250).any(axis=(0, 2)).sum())

    assert width(turned[2]) < 0.8 * width(views[2])


def test_make_scan_rejects_bad_phenotypes(capsys):
    assert main(["make-scan", "skirt", "--out", "/tmp/unused", "--phenotypes", "wieght=0.3"]) == 2
    assert "unknown phenotype 'wieght'" in capsys.readouterr().err
    assert main(["make-scan", "skirt", "--out", "/tmp/unused", "--phenotypes", "weight=1.5"]) == 2


@pytest.mark.parametrize("kw", [{"garment_points": 10}, {"body_points": 2.5}, {"spacing": 0.0}])
def test_make_scan_rejects_bad_settings_before_any_work(kw):
    from torch_diffavatar.errors import InputError

    with pytest.raises(InputError, match=next(iter(kw))):
        make_draped_scan("skirt", **kw)


def test_make_scan_pose_option(tmp_path, capsys):
    """``--pose``: 'a' is no pose, 'random' is seeded (its own draws: the phenotypes stay the A-pose
    scan's), a JSON file sets the bones it names; bad files are one error line, exit 2."""
    from torch_diffavatar.body.model import POSE_BONES
    from torch_diffavatar.commands.make_scan import _parse_pose

    assert _parse_pose("a", 0) is None and _parse_pose("A-pose", 0) is None
    one, again, other = _parse_pose("random", 0), _parse_pose("random", 0), _parse_pose("random", 1)
    assert one.shape == (1, len(POSE_BONES), 3) and torch.equal(one, again) and not torch.equal(one, other)
    assert one.abs().max() > 0.1
    path = tmp_path / "pose.json"
    path.write_text(json.dumps({"lowerarm01.L": [0.0, 0.0, -0.6]}))
    pose = _parse_pose(str(path), 0)
    k = POSE_BONES.index("lowerarm01.L")
    assert pose[0, k].tolist() == [0.0, 0.0, -0.6] and pose.abs().sum() == pytest.approx(0.6)
    for text, message in (
        (json.dumps({"elbow.L": [0, 0, 1]}), "unknown bones ['elbow.L']"),
        (json.dumps({"head": [0, 1]}), "three numbers"),
        (json.dumps([0, 1, 2]), "a pose is an object"),
        ("{not json", "not valid JSON"),
    ):
        path.write_text(text)
        assert main(["make-scan", "skirt", "--out", str(tmp_path / "out"), "--pose", str(path)]) == 2
        assert message in capsys.readouterr().err
    assert main(["make-scan", "skirt", "--out", str(tmp_path / "out"), "--pose", "sitting"]) == 2
    assert "neither 'a', 'random' nor a JSON file" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.anny
@pytest.mark.slow
def test_posed_scan_records_its_pose(anny_model, skirt_scan):
    """A scan of a posed body: the truth holds the pose, and the skin follows it (a bent elbow moves
    the forearm's points)."""
    from torch_diffavatar.body.model import POSE_BONES

    pose = torch.zeros(1, len(POSE_BONES), 3, dtype=torch.float64)
    pose[0, POSE_BONES.index("lowerarm01.L")] = torch.tensor([0.0, 0.0, -0.6], dtype=torch.float64)
    phenotypes = dict(gender=0.5, age=0.5, muscle=0.5, weight=0.45, height=0.55, proportions=0.5)
    kw = dict(spacing=0.05, garment_points=4000, body_points=4000, noise=0.002, hole_fraction=0.1)
    posed = make_draped_scan("skirt", anny_model=anny_model, seed=3, phenotypes=phenotypes, pose=pose, **kw)
    assert list(posed.info["pose_rad"]) == ["lowerarm01.L"] and skirt_scan.info["pose_rad"] == {}
    assert torch.allclose(torch.as_tensor(posed.body_params["pose_axis_angle"]).double(), pose, atol=1e-6)
    moved = np.linalg.norm(posed.body_vertices - skirt_scan.body_vertices, axis=1)
    left_hand = skirt_scan.body_vertices[:, 0] > skirt_scan.body_vertices[:, 0].max() - 0.05
    right_hand = skirt_scan.body_vertices[:, 0] < skirt_scan.body_vertices[:, 0].min() + 0.05
    assert moved[left_hand].min() > 0.05 and moved[right_hand].max() < 1e-5


@pytest.mark.anny
@pytest.mark.slow
def test_trousers_longer_than_the_legs_pile_on_the_floor(anny_model, skirt_scan):
    """Trousers on a 1.32 m body (the held-out capture seed 343's) are 17 cm longer than its legs. Draped
    without a floor they hung 16.6 cm below the soles, a capture cut them off at the floor, and their fits
    shrank body and legs to match: truth.json records how far, and `make-scan --no-floor` warns
    (`below_floor_note`). On the floor (the default) they pile on it: nothing below it, no warning."""
    from torch_diffavatar.synthetic_scans import below_floor_note

    short = dict(gender=0.41, age=0.36, muscle=0.46, weight=0.42, height=0.35, proportions=0.59)
    kwargs = dict(anny_model=anny_model, seed=343, phenotypes=short, garment_points=1000, body_points=1000)
    scan = make_draped_scan("pants", floor=False, **kwargs)
    below = scan.info["drape"]["below_floor_m"]
    assert 0.10 < below < 0.25 and below == pytest.approx(-float(scan.cloth_x[:, 1].min()))
    note = below_floor_note(scan.info)
    assert "pants hangs 1" in note and "--no-floor" in note and not scan.info["drape"]["floor"]
    piled = make_draped_scan("pants", **kwargs)
    assert piled.info["drape"]["floor"] and piled.info["drape"]["converged"]
    assert piled.info["drape"]["below_floor_m"] == 0.0 and below_floor_note(piled.info) is None
    lowest = float(piled.cloth_x[:, 1].min())
    assert 0.0 < lowest < 0.004  # resting on the floor at the cloth's thickness (3 mm)
    assert int((piled.cloth_x[:, 1] < 0.01).sum()) > 50  # a pile, not a hem that just touches it
    assert skirt_scan.info["drape"]["below_floor_m"] == 0.0 and below_floor_note(skirt_scan.info) is None
