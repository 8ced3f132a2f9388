"""The simulated depth capture (`capture`): z-buffer, depth noise, grazing angles, floor, strays, and the
output's yaw, units and axes — on simple meshes (no Anny)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from torch_diffavatar.capture import (
    FLOOR_LABEL,
    STRAY_LABEL,
    CaptureSettings,
    DepthCamera,
    SceneMesh,
    capture_scene,
    rasterize,
)
from torch_diffavatar.errors import InputError
from torch_diffavatar.geometry import yaw_rotation
from torch_diffavatar.scan import UNITS, UP_AXES, load_scan, save_ply


def _column(radius=0.2, height=1.7) -> SceneMesh:
    """A vertical cylinder standing on the floor (a person's stand-in), label 0."""
    turn = trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0])
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=48, transform=turn)
    mesh.apply_translation([0.0, height / 2, 0.0])
    return SceneMesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), 0, (200, 150, 120))


def _wall(z=0.0) -> SceneMesh:
    """A 4 m × 2 m wall in the plane z = ``z``, facing +Z, label 1."""
    v = np.array([[-2, 0, z], [2, 0, z], [2, 2, z], [-2, 2, z]], np.float64)
    return SceneMesh(v, np.array([[0, 1, 2], [0, 2, 3]]), 1, (40, 80, 160))


def test_rasterize_matches_ray_casting():
    column = _column()
    cam = DepthCamera(position=(0.3, 1.1, 2.2), target=(0.0, 0.85, 0.0), width=160, height=120)
    depth, tri = rasterize(cam, column.vertices, column.faces)
    rays = cam.rays()
    mesh = trimesh.Trimesh(column.vertices, column.faces, process=False)
    origins = np.tile(np.asarray(cam.position), (len(rays), 1))
    loc, ray_id, _ = mesh.ray.intersects_location(origins, rays, multiple_hits=False)
    expected = np.full(len(rays), np.inf)
    expected[ray_id] = np.linalg.norm(loc - cam.position, axis=1)
    distance = depth / (rays @ cam.rotation()[2])
    assert (np.isfinite(expected) == np.isfinite(distance)).mean() > 0.999  # edge pixels may differ
    both = np.isfinite(expected) & np.isfinite(distance)
    assert both.sum() > 1000
    np.testing.assert_allclose(distance[both], expected[both], atol=1e-9)
    assert (tri >= 0).sum() == np.isfinite(depth).sum()


@pytest.mark.parametrize("distance", [1.5, 3.0])
def test_depth_noise_grows_with_distance(distance):
    s = CaptureSettings(
        layout="front", distance=distance, camera_height=1.0, floor_size=0.0, stray_fraction=0.0
    )
    captured = capture_scene([_wall()], s, np.random.default_rng(0))
    centre = (np.abs(captured.points[:, 0]) < 0.15) & (np.abs(captured.points[:, 1] - 1.0) < 0.15)
    sigma = captured.points[centre, 2].std()  # the wall is at z = 0, seen head-on there
    expected = s.noise_a + s.noise_b * distance**2
    assert centre.sum() > 300
    assert sigma == pytest.approx(expected, rel=0.15)


def test_grazing_returns_dropped_and_floor_labelled():
    """Floor points survive only where the view ray meets the floor steeper than ``min_cos``."""
    s = CaptureSettings(layout="front", camera_height=1.0, floor_size=3.0, min_cos=0.5, stray_fraction=0.0)
    captured = capture_scene([_column()], s, np.random.default_rng(1))
    floor = captured.points[captured.labels == FLOOR_LABEL]
    assert len(floor) > 1000
    assert np.abs(floor[:, 1]).max() < 0.05  # y = 0, up to the depth noise
    cam = s.camera_list(np.array([0.0, 0.85, 0.0]))[0]
    reach = np.hypot(floor[:, 0] - cam.position[0], floor[:, 2] - cam.position[2])
    # |cos| = h / sqrt(h² + r²) >= 0.5  <=>  r <= h·sqrt(3) (a little slack for the noise)
    assert reach.max() <= 1.0 * math.sqrt(3.0) + 0.03
    grazing = CaptureSettings(
        layout="front", camera_height=1.0, floor_size=3.0, min_cos=0.05, stray_fraction=0.0
    )
    assert (capture_scene([_column()], grazing, np.random.default_rng(1)).labels == FLOOR_LABEL).sum() > len(
        floor
    )


def test_yaw_units_and_axes_are_exact_transforms():
    """Draws come before the transforms: the same seed gives the same capture, turned and re-expressed."""
    ref = capture_scene([_column()], CaptureSettings(), np.random.default_rng(2))
    s = CaptureSettings(yaw_deg=120.0, units="cm", up="-y")
    out = capture_scene([_column()], s, np.random.default_rng(2))
    back = out.points @ UP_AXES["-y"].T * UNITS["cm"] @ yaw_rotation(120.0)  # to world, then un-turned
    np.testing.assert_allclose(back, ref.points, atol=1e-9)
    np.testing.assert_allclose(out.normals @ UP_AXES["-y"].T @ yaw_rotation(120.0), ref.normals, atol=1e-9)
    np.testing.assert_array_equal(out.labels, ref.labels)
    assert out.info["yaw_deg"] == 120.0 and out.info["units"] == "cm" and out.info["up"] == "-y"
    assert out.points[:, 1].min() < -150  # Y down, in cm: the head at about -170


def test_strays_colours_and_ply_round_trip(tmp_path):
    s = CaptureSettings(stray_fraction=0.01, units="mm")
    captured = capture_scene([_column()], s, np.random.default_rng(3))
    strays = captured.labels == STRAY_LABEL
    assert strays.sum() == round(0.01 * (~strays).sum())
    skin = captured.colors[captured.labels == 0].astype(float)
    assert np.abs(skin.mean(0) - (200, 150, 120)).max() < 2 and 2 < skin.std(0).mean() < 6
    np.testing.assert_allclose(np.linalg.norm(captured.normals, axis=1), 1.0, atol=1e-6)
    path = tmp_path / "capture.ply"
    save_ply(
        path,
        captured.points,
        colors=captured.colors,
        normals=captured.normals,
        binary=True,
        int_properties={"label": captured.labels},
    )
    loaded = load_scan(path, units="mm", check=False)
    np.testing.assert_allclose(loaded.points, captured.points * 1e-3, atol=1e-4)  # float32 in the file
    np.testing.assert_array_equal(loaded.labels, captured.labels)
    np.testing.assert_array_equal(loaded.colors, captured.colors)


def _quiet(**kw) -> CaptureSettings:
    """One camera in front, no depth noise, floor or strays (``kw``: other settings)."""
    base = dict(layout="front", camera_height=1.0, floor_size=0.0, stray_fraction=0.0)
    return CaptureSettings(**(base | dict(noise_a=0.0, noise_b=0.0) | kw))


def test_flying_pixels_lie_between_the_surfaces_at_a_silhouette():
    """A column 1 m in front of a wall: with mixed pixels some returns at the column's silhouette lie
    between the two surfaces, their colours between the two; without, none (and with the setting left at
    its default the capture is the one made with it at 0: its random draws come only when it is on)."""
    scene = [_column(radius=0.2), _wall(z=-1.0)]
    plain = capture_scene(scene, _quiet(), np.random.default_rng(5))
    mixed = capture_scene(scene, _quiet(flying_pixels=1.0), np.random.default_rng(5))
    assert len(plain.points) == len(mixed.points)

    def between(c):  # off the column (radius 0.2 about the y axis) and off the wall (z = -1)
        radius = np.hypot(c.points[:, 0], c.points[:, 2])
        return (radius > 0.23) & (c.points[:, 2] > -0.97)

    assert between(plain).sum() == 0
    flying = between(mixed)
    assert 100 < flying.sum() < 0.05 * len(mixed.points)
    blue = mixed.colors[flying].astype(float)  # the wall (40, 80, 160), the column (200, 150, 120)
    assert (blue[:, 0] > 40 + 3 * 4).mean() > 0.9 and (blue[:, 0] < 200 - 3 * 4).mean() > 0.9
    assert mixed.info["flying_pixels"] == 1.0
    ref = capture_scene(scene, CaptureSettings(layout="front", floor_size=0.0), np.random.default_rng(6))
    again = capture_scene(
        scene, CaptureSettings(layout="front", floor_size=0.0, flying_pixels=0.0), np.random.default_rng(6)
    )
    np.testing.assert_array_equal(ref.points, again.points)


def test_calibration_error_offsets_each_view_rigidly():
    """A camera's points move by one rigid motion (its pose error); two cameras that see the same wall, each
    off by its own, put it on two planes, and without the error on one."""
    column = [_column()]
    exact = capture_scene(column, _quiet(), np.random.default_rng(7))
    off = capture_scene(column, _quiet(calibration_m=0.005, calibration_deg=0.2), np.random.default_rng(7))
    moved = off.points - exact.points
    assert 0.001 < np.abs(moved).max() < 0.1
    affine = np.c_[exact.points, np.ones(len(exact.points))]
    fit, *_ = np.linalg.lstsq(affine, off.points, rcond=None)  # off = exact @ A + t
    np.testing.assert_allclose(affine @ fit, off.points, atol=1e-9)
    rot = fit[:3]
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-9)  # a rotation: rigid
    assert off.info["calibration_error"] == {"translation_m": 0.005, "rotation_deg": 0.2}

    ring = dict(cameras=2, camera_height=1.0, floor_size=0.0, stray_fraction=0.0, noise_a=0.0, noise_b=0.0)
    wall = [_wall(z=0.0)]
    both = capture_scene(wall, CaptureSettings(**ring), np.random.default_rng(8))
    shifted = capture_scene(wall, CaptureSettings(**ring, calibration_m=0.005), np.random.default_rng(8))
    front = len(capture_scene(wall, _quiet(), np.random.default_rng(8)).points)  # the ring's first camera
    assert np.abs(both.points[:, 2]).max() < 1e-9
    planes = [shifted.points[:front, 2].mean(), shifted.points[front:, 2].mean()]
    assert abs(planes[0] - planes[1]) > 5e-4
    assert max(shifted.points[:front, 2].std(), shifted.points[front:, 2].std()) < 1e-9


def test_coverage_of_front_and_ring():
    from torch_diffavatar.scan_intake import coverage

    for layout, cameras, expected in (("front", 1, range(3, 6)), ("ring", 4, range(8, 9))):
        s = CaptureSettings(layout=layout, cameras=cameras, floor_size=0.0, stray_fraction=0.0)
        captured = capture_scene([_column()], s, np.random.default_rng(4))
        assert coverage(captured.points)["sectors_seen"] in expected  # normals estimated
        assert coverage(captured.points, captured.normals)["sectors_seen"] in expected  # the sensor's


def test_bad_settings_are_one_line_errors():
    for bad in (
        dict(layout="top"),
        dict(distance=5.0),
        dict(units="inch"),
        dict(cameras=0),
        dict(noise_a=-1.0),
        dict(flying_pixels=1.5),
        dict(calibration_deg=-0.1),
        dict(calibration_m=0.5),
    ):
        with pytest.raises(InputError):
            CaptureSettings(**bad).check()


def test_make_scan_capture_options():
    """``make-scan --capture``'s options become `CaptureSettings` before any drape; misuse is one line."""
    from torch_diffavatar.cli import _join_signed_values, build_parser
    from torch_diffavatar.commands.make_scan import _capture_settings

    def settings(*extra):
        argv = ["make-scan", "tshirt", "--out", "o", "--seed", "5", *extra]
        return _capture_settings(build_parser().parse_args(_join_signed_values(argv)))

    s = settings("--capture", "ring", "--yaw", "random", "--scan-units", "cm", "--scan-up", "-y")
    assert (s.layout, s.units, s.up, s.width, s.height) == ("ring", "cm", "-y", 640, 480)
    assert 0.0 <= s.yaw_deg < 360.0 and settings("--capture", "ring", "--yaw", "random").yaw_deg == s.yaw_deg
    assert settings() is None  # the sampled scan, as before
    rig = settings("--capture", "ring", "--flying-pixels", "0.3", "--calibration-error", "2", "0.15")
    assert (rig.flying_pixels, rig.calibration_m, rig.calibration_deg) == (0.3, 0.002, 0.15)
    assert (s.flying_pixels, s.calibration_m, s.calibration_deg) == (0.0, 0.0, 0.0)
    for bad in (
        ("--yaw", "30"),
        ("--flying-pixels", "0.3"),
        ("--capture", "ring", "--calibration-error", "2", "45"),
        ("--capture", "front", "--yaw", "north"),
        ("--capture", "ring", "--resolution", "640"),
    ):
        with pytest.raises(InputError):
            settings(*bad)
