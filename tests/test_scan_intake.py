"""Scan intake (`scan_intake`): RANSAC floor on a tilted floor, the person as the largest cluster, units
from the height, the up axis from the floor, the frame check after the floor's removal — on simple point
sets; and one Anny body captured like a real scan, through the intake and `fit_body`."""

from __future__ import annotations

import math

import numpy as np
import pytest

from torch_diffavatar.errors import ScanError
from torch_diffavatar.geometry import yaw_rotation
from torch_diffavatar.scan import UP_AXES, Scan, check_scan_frame, save_ply
from torch_diffavatar.scan_intake import (
    find_floor,
    infer_units,
    intake_scan,
    largest_cluster,
    remove_floor_plane,
)

FOOT, LEG, FLOOR, NOISE = 0, 1, 2, 3  # kinds of the points of `_standing`


def _standing(rng, tilt_deg=0.0, floor=4000, noise=500, floor_side=2.0):
    """A stand-in person (a head of r = 13 cm on a trunk of r = 18 cm from 0.9 to 1.45 m on two legs of
    r = 6 cm, with 25 cm feet lying on the floor) on a square
    floor tilted by ``tilt_deg`` about X, with ``noise`` floor points 3–10 cm above it away from the feet.

    Returns: (N, 3) points [m] (the floor through the origin) and (N,) kinds (FOOT, LEG, FLOOR, NOISE).
    """
    parts, kinds = [], []
    for r, lo, hi in ((0.18, 0.9, 1.45), (0.13, 1.45, 1.7)):  # the trunk and the head
        a, y = rng.uniform(0, 2 * math.pi, 3000), rng.uniform(lo, hi, 3000)
        parts.append(np.stack([r * np.sin(a), y, r * np.cos(a)], 1))
        kinds.append(np.full(3000, LEG))
    for x in (-0.12, 0.12):
        a, y = rng.uniform(0, 2 * math.pi, 3000), rng.uniform(0.08, 0.9, 3000)
        parts.append(np.stack([x + 0.06 * np.sin(a), y, 0.06 * np.cos(a)], 1))
        kinds.append(np.full(3000, LEG))
        foot = np.stack(
            [x + rng.uniform(-0.05, 0.05, 800), rng.uniform(0.0, 0.08, 800), rng.uniform(-0.05, 0.2, 800)], 1
        )
        parts.append(foot)
        kinds.append(np.full(800, FOOT))
    xz = rng.uniform(-floor_side / 2, floor_side / 2, (floor, 2))
    parts.append(np.stack([xz[:, 0], rng.normal(0, 0.004, floor), xz[:, 1]], 1))
    kinds.append(np.full(floor, FLOOR))
    r, a = rng.uniform(0.45, 0.95, noise), rng.uniform(0, 2 * math.pi, noise)
    parts.append(np.stack([r * np.sin(a), rng.uniform(0.03, 0.10, noise), r * np.cos(a)], 1))
    kinds.append(np.full(noise, NOISE))
    points = np.concatenate(parts)
    c, s = math.cos(math.radians(tilt_deg)), math.sin(math.radians(tilt_deg))
    return points @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T, np.concatenate(kinds)


def test_ransac_floor_on_a_tilted_floor_keeps_the_feet():
    rng = np.random.default_rng(0)
    points, kind = _standing(rng, tilt_deg=4.0)
    floor = find_floor(points, rng=np.random.default_rng(1))
    assert floor is not None and floor.tilt_deg == pytest.approx(4.0, abs=0.5)
    scan, removed = remove_floor_plane(Scan(points=points, labels=kind), floor)
    left = np.bincount(scan.labels, minlength=4)
    total = np.bincount(kind, minlength=4)
    assert left[FLOOR] <= 0.005 * total[FLOOR]  # the floor's noise tail only
    assert left[NOISE] == 0  # 3-10 cm above the floor, away from the feet
    assert left[LEG] == total[LEG] and left[FOOT] >= 0.75 * total[FOOT]  # soles within 1.5 cm go
    assert removed == len(points) - scan.point_count
    assert abs(np.quantile(scan.points[:, 1], 0.001)) < 0.03  # the floor at y = 0 under the person


def test_no_floor_under_bare_soles():
    """Flat soles are not a floor: too small."""
    points, kind = _standing(np.random.default_rng(2), floor=0, noise=0)
    assert find_floor(points) is None


def test_largest_cluster_drops_stray_blob_and_dust():
    rng = np.random.default_rng(3)
    points, kind = _standing(rng, floor=0, noise=0)
    blob = rng.normal([0.8, 0.5, 0.3], 0.04, (400, 3))  # a bag on a chair
    dust = rng.uniform([-1.5, 0, -1.5], [1.5, 2.2, 1.5], (100, 3))
    scan = Scan(points=np.concatenate([points, blob, dust]))
    kept, removed = largest_cluster(scan)
    assert len(points) <= kept.point_count <= len(points) + 5  # dust within 5 cm of the person stays
    assert removed == scan.point_count - kept.point_count
    assert np.linalg.norm(kept.points - [0.8, 0.5, 0.3], axis=1).min() > 0.1


@pytest.mark.parametrize("gap", [0.08, 0.18])
def test_a_hand_a_hole_cut_off_stays_with_the_person(gap):
    # a hole across the wrist: the hand is a cluster of its own, ``gap`` from the forearm's end (18 cm: a
    # generator's 16 cm hole and a small piece between, our trousers 312)
    rng = np.random.default_rng(5)
    points, _ = _standing(rng, floor=0, noise=0)
    forearm = np.stack(
        [rng.uniform(0.18, 0.45, 600), rng.normal(1.3, 0.02, 600), rng.normal(0, 0.02, 600)], 1
    )
    centre = [0.45 + gap + 0.05, 1.3, 0.0]
    hand = rng.normal(centre, 0.02, (300, 3))
    hand = hand[np.linalg.norm(hand - centre, axis=1) < 0.05]
    blob = rng.normal([0.9, 0.5, 0.6], 0.04, (400, 3))  # a bag on a chair, half a metre away
    scan = Scan(points=np.concatenate([points, forearm, hand, blob]))
    kept, removed = largest_cluster(scan)
    assert len(blob) <= removed <= len(blob) + 3  # the bag, and a stray point of the forearm's noise
    assert np.linalg.norm(kept.points - [0.9, 0.5, 0.6], axis=1).min() > 0.1
    near_hand = lambda pts: int((np.linalg.norm(pts - centre, axis=1) < 0.05).sum())  # noqa: E731
    assert near_hand(kept.points) == near_hand(hand) > 100


@pytest.mark.parametrize("unit,scale", [("m", 1.0), ("cm", 100.0), ("mm", 1000.0)])
def test_units_inferred_from_the_height(tmp_path, unit, scale):
    points, _ = _standing(np.random.default_rng(4), floor=0, noise=0)
    assert infer_units(points * scale) == unit
    path = tmp_path / "scan.ply"
    save_ply(path, points * scale, binary=True)
    scan, report = intake_scan(path)
    assert report.units == unit and report.units_inferred and any("inferred" in m for m in report.messages)
    assert np.abs(scan.points[:, 1].max() - 1.7) < 0.02


def test_units_not_inferable_and_bad_options_are_one_line_errors(tmp_path):
    with pytest.raises(ScanError, match="--units"):
        infer_units(np.random.default_rng(5).uniform(0, 10.0, (100, 3)))
    path = tmp_path / "scan.ply"
    save_ply(path, np.random.default_rng(5).uniform(0, 1.7, (200, 3)), binary=True)
    with pytest.raises(ScanError, match="unknown units"):
        intake_scan(path, units="inch")


@pytest.mark.parametrize("up", ["-y", "z", "-z"])
def test_floor_heavy_scan_in_cm_up_found_from_the_floor(tmp_path, up):
    """Half the points on a wide floor: the frame check must not say "wrong --up" once it is removed, and
    the up axis (Y down; Z up, as Blender saves; Z down) is found from the floor under the person."""
    points, kind = _standing(np.random.default_rng(6), floor=12000, floor_side=3.0)
    assert any("wider" in w for w in check_scan_frame(points))  # what the check says before the intake
    path = tmp_path / "scan.ply"
    save_ply(path, points @ UP_AXES[up] * 100.0, int_properties={"label": kind}, binary=True)
    scan, report = intake_scan(path)
    assert report.up == up and report.units == "cm"
    assert any(m.startswith(f"up axis: {up} ") for m in report.messages)
    assert report.floor is not None and report.warnings == []
    assert not np.isin(scan.labels, [FLOOR, NOISE]).any()
    assert scan.points[:, 1].max() == pytest.approx(1.7, abs=0.02)


def test_a_person_holding_a_board_out_in_front_stays_y_up(tmp_path):
    """No floor, forearms 1 m forward holding a 30 × 50 cm board: along Z the board is a floor under a
    standing person's shape, but along Y the scan is a standing person, so Y stays (a posed Anny body in a
    T-shirt, saved as a mesh without a floor, was turned to -Z and its fit failed)."""
    rng = np.random.default_rng(10)
    parts = [_standing(rng, floor=0, noise=0)[0]]
    for x in (-0.12, 0.12):
        a, z = rng.uniform(0, 2 * math.pi, 2000), rng.uniform(0.0, 1.0, 2000)
        parts.append(np.stack([x + 0.04 * np.sin(a), 1.0 + 0.04 * np.cos(a), z], 1))
    board = rng.uniform(-0.5, 0.5, (3000, 2))
    parts.append(np.stack([0.3 * board[:, 0], 1.0 + 0.5 * board[:, 1], np.full(3000, 1.02)], 1))
    path = tmp_path / "scan.ply"
    save_ply(path, np.concatenate(parts), binary=True)
    scan, report = intake_scan(path)
    assert report.up == "y" and not any(m.startswith("up axis") for m in report.messages)


def test_a_person_along_z_with_no_floor_is_refused_naming_the_axis(tmp_path):
    """With no floor nothing tells up from down: Y stays, and the shape check names --up z (without
    --units the height along Y already fails, naming --up)."""
    points, _ = _standing(np.random.default_rng(8), floor=0, noise=0)
    path = tmp_path / "scan.ply"
    save_ply(path, points @ UP_AXES["z"], binary=True)
    with pytest.raises(ScanError, match="--up z"):
        intake_scan(path, units="m")
    with pytest.raises(ScanError, match="--up if the person is not along Y"):
        intake_scan(path)
    save_ply(path, points, binary=True)  # the same person, Y up, no floor: Y
    assert intake_scan(path)[1].up == "y"


@pytest.mark.parametrize("up", ["-y", "z", "-z"])
def test_a_front_capture_sees_its_front_whatever_its_up_axis(tmp_path, up):
    """The sensor's normals turn with the points: a front-only capture saved Y down (or Z up, Z down) is
    seen from the same sides as saved Y up. They did not turn, and a Y-down front capture was taken for
    one seen from behind, and its back pulled toward the scan."""
    import trimesh

    from torch_diffavatar.capture import CaptureSettings, SceneMesh, capture_scene

    turn = trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0])
    column = trimesh.creation.cylinder(radius=0.2, height=1.7, sections=48, transform=turn)
    column.apply_translation([0.0, 0.85, 0.0])
    person = SceneMesh(np.asarray(column.vertices), np.asarray(column.faces), 0, (200, 150, 120))
    seen = {}
    for axis in ("y", up):
        s = CaptureSettings(layout="front", units="cm", up=axis, yaw_deg=60.0, width=320, height=240)
        captured = capture_scene([person], s, np.random.default_rng(9))
        path = tmp_path / f"scan{axis}.ply"
        save_ply(path, captured.points, normals=captured.normals, binary=True)
        scan, report = intake_scan(path)
        assert report.up == axis
        seen[axis] = report.coverage["seen"]
    assert 3 <= sum(seen["y"]) <= 5 and seen[up] == seen["y"]


@pytest.mark.anny
@pytest.mark.slow
def test_ring_capture_turned_in_cm_y_down_fits(anny_model, tmp_path):
    """An Anny body captured by a ring of 4 depth cameras, turned 120°, in cm, Y down, with a floor and
    strays: the intake and `fit_body` give its height within 1.5 cm and its surface within 1 cm."""
    import torch

    from torch_diffavatar.body.fit import fit_body
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.capture import CaptureSettings, SceneMesh, capture_scene
    from torch_diffavatar.evaluation import mesh_distance_m

    body = BodyModel(anny_model=anny_model, dtype=torch.float64)
    body.set_phenotypes(torch.tensor([[0.6, 0.4, 0.5, 0.45, 0.6, 0.5]], dtype=torch.float64))
    with torch.no_grad():
        body.translation[0, 1] -= body().vertices[0][:, 1].min()  # feet on the floor
        verts, height = body().vertices[0].numpy(), float(body.standing_height()[0])
    faces = body.faces.numpy()
    s = CaptureSettings(yaw_deg=120.0, units="cm", up="-y", width=320, height=240)
    captured = capture_scene([SceneMesh(verts, faces, 0, (222, 171, 140))], s, np.random.default_rng(7))
    path = tmp_path / "scan.ply"
    save_ply(
        path, captured.points, colors=captured.colors, int_properties={"label": captured.labels}, binary=True
    )
    scan, report = intake_scan(path)
    assert (report.units, report.up, report.coverage["sectors_seen"]) == ("cm", "-y", 8)
    assert (scan.labels == 0).mean() > 0.99
    fitted = fit_body(scan.points, anny_model=anny_model)
    with torch.no_grad():
        fit_verts = fitted.body().vertices[0].double()
    truth = torch.from_numpy(verts @ yaw_rotation(120.0).T)
    surface = mesh_distance_m(fit_verts, fitted.body.faces, truth, body.faces)
    assert abs(fitted.height_m - height) < 0.015
    assert surface < 0.01


def test_level_arms_are_not_a_floor(tmp_path):
    """Arms held out level near the top are long and flat, but narrow: a Y-up scan without a floor
    stays Y up (no floor found below, none on top either)."""
    rng = np.random.default_rng(8)
    points, _ = _standing(rng, floor=0, noise=0)
    a, x = rng.uniform(0, 2 * math.pi, 4000), rng.choice([-1.0, 1.0], 4000) * rng.uniform(0.18, 0.9, 4000)
    arms = np.stack([x, 1.45 + 0.04 * np.sin(a), 0.04 * np.cos(a)], 1)
    path = tmp_path / "scan.ply"
    save_ply(path, np.concatenate([points, arms]) @ yaw_rotation(30.0).T, binary=True)
    scan, report = intake_scan(path, units="m")
    assert report.up == "y" and report.floor is None


@pytest.mark.parametrize(("floor", "up"), [(0, "y"), (8000, "y"), (8000, "-y")])
def test_arms_held_forward_are_no_floor_upside_down(tmp_path, floor, up):
    """Both arms held forward at shoulder height: seen upside down, their tops are a plane 65 cm long and
    50 cm across at the lowest 35 cm, with a standing person's shape beyond it, so a Y-up scan without a
    floor was turned Y down; the head under that plane tells it from a floor. With a floor, either way up
    is found from it."""
    rng = np.random.default_rng(11)
    parts = [_standing(rng, floor=floor, noise=0)[0]]
    for x in (-0.22, 0.22):
        a, z = rng.uniform(0, 2 * math.pi, 3000), rng.uniform(0.05, 0.7, 3000)
        parts.append(np.stack([x + 0.045 * np.sin(a), 1.40 + 0.045 * np.cos(a), z], 1))
    points = np.concatenate(parts)
    assert find_floor(points * [1.0, -1.0, 1.0]) is None  # fails before: the arms' tops were a floor
    path = tmp_path / "scan.ply"
    save_ply(path, points @ UP_AXES[up], binary=True)
    scan, report = intake_scan(path)
    assert report.up == up and (report.floor is None) == (floor == 0)
    assert scan.points[:, 1].max() == pytest.approx(1.7, abs=0.02)  # the head on top


@pytest.mark.parametrize("yaw", [0.0, 120.0, -75.0])
def test_facing_from_hips_and_feet(yaw):
    """The stand-in's feet point to +Z: its facing is found turned with it, first of the two opposite
    candidates; cut above the feet, both directions of the hips' axis are candidates."""
    from torch_diffavatar.body.facing import facing_yaws

    points, _ = _standing(np.random.default_rng(9), floor=0, noise=0)
    turned = points @ yaw_rotation(yaw).T
    found, back = facing_yaws(turned)
    assert abs((found - yaw + 180.0) % 360.0 - 180.0) < 5.0
    assert abs((back - found) % 360.0 - 180.0) < 1e-6
    both = facing_yaws(turned[turned[:, 1] > 0.3])
    # (a round trunk over the stand-in's legs: its hips axis is looser than a body's)
    assert len(both) == 2 and min(abs((b - yaw + 180.0) % 360.0 - 180.0) for b in both) < 10.0


def test_feet_are_seen_only_on_a_scan_that_has_them():
    """`shows_feet` decides whether the body fit also starts from the head (`BodyFitConfig.head_start`):
    the stand-in shows its feet, turned or not; cut 30 cm above its soles it does not."""
    from torch_diffavatar.body.facing import shows_feet

    points, _ = _standing(np.random.default_rng(9), floor=0, noise=0)
    for yaw in (0.0, 120.0):
        turned = points @ yaw_rotation(yaw).T
        assert shows_feet(turned)
        assert not shows_feet(turned[turned[:, 1] > 0.3])


def test_a_huge_scan_is_thinned_before_the_clean_up(tmp_path):
    points, _ = _standing(np.random.default_rng(6), floor=0, noise=0)
    path = tmp_path / "scan.ply"
    save_ply(path, points, binary=True)
    scan, report = intake_scan(path, max_points=5000)
    assert scan.point_count <= 5000
    assert any(f"{len(points):,} points: more than the 5,000 used" in m for m in report.messages)
    again, _ = intake_scan(path, max_points=5000)
    np.testing.assert_array_equal(again.points, scan.points)  # seeded: the same subset every time
