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
    for bad in (
        ("--yaw", "30"),
        ("--capture", "front", "--yaw", "north"),
        ("--capture", "ring", "--resolution", "640"),
    ):
        with pytest.raises(InputError):
            settings(*bad)
