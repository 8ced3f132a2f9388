"""The headless rasteriser: silhouettes, visibility order, depth bias, views, PNG output."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from torch_diffavatar.render import (
    RenderMesh,
    look_at_camera,
    point_splats,
    render,
    render_views,
    save_png,
)

WHITE = (255, 255, 255)


def _quad(z: float, half: float = 0.5, shift: float = 0.0):
    """A square in the plane z = const, facing +Z: verts (4, 3), faces (2, 3)."""
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]]) + [shift, 0, 0]
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _covered(image: np.ndarray, background=WHITE) -> np.ndarray:
    return np.any(image != np.asarray(background, dtype=np.uint8), axis=2)


@pytest.mark.parametrize("view", ["front", "back", "left", "right", 30.0])
def test_unit_cube_silhouette_area(view):
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cam = look_at_camera(box.bounds[0], box.bounds[1], view, width=200, height=200)
    image = render([(box.vertices, box.faces, (200, 50, 50))], camera=cam, width=200, height=200)
    # orthographic: a face-on cube covers 1 m² → scale² pixels; at azimuth 30° its width is cos + sin
    az = {"front": 0.0, "back": 0.0, "left": 0.0, "right": 0.0}.get(view, 30.0)
    expected_area = (np.cos(np.radians(az)) + np.sin(np.radians(az))) * 1.0 * cam.scale**2
    area = _covered(image).sum()
    assert abs(area - expected_area) / expected_area < 0.02, (area, expected_area)


def test_two_quads_nearer_one_wins_whatever_the_draw_order():
    near_v, near_f = _quad(0.2, half=0.3)
    far_v, far_f = _quad(-0.2, half=0.5)
    red, green = (255, 0, 0), (0, 255, 0)
    for meshes in (
        [(near_v, near_f, red), (far_v, far_f, green)],
        [(far_v, far_f, green), (near_v, near_f, red)],
    ):
        image = render(meshes, view="front", width=100, height=100, ambient=1.0)
        center = image[50, 50]
        assert tuple(center) == red  # front camera on +Z sees the z = 0.2 quad
        assert tuple(image[50, 8]) == green  # only the far quad extends there
        back = render(meshes, view="back", width=100, height=100, ambient=1.0)
        assert tuple(back[50, 50]) == green  # from −Z the z = −0.2 quad is in front


def test_depth_bias_hides_coincident_body_without_speckles():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    cloth_v = sphere.vertices * (1.0 + 1e-4)  # 0.05 mm outside: pure z-fighting territory
    body_color, cloth_color = (200, 150, 120), (40, 80, 200)
    unbiased = render(
        [
            RenderMesh(sphere.vertices, sphere.faces, body_color),
            RenderMesh(cloth_v, sphere.faces, cloth_color),
        ],
        width=128,
        height=128,
        ambient=1.0,
    )
    biased = render(
        [
            RenderMesh(sphere.vertices, sphere.faces, body_color),
            RenderMesh(cloth_v, sphere.faces, cloth_color, depth_bias=0.002),
        ],
        width=128,
        height=128,
        ambient=1.0,
    )
    body_pixels = np.all(biased == body_color, axis=2).sum()
    cloth_pixels = np.all(biased == cloth_color, axis=2).sum()
    assert cloth_pixels > 0.7 * 128 * 128 * np.pi / 4 * 0.9
    assert body_pixels == 0
    # the sphere's silhouette is the same with and without the bias
    assert (_covered(unbiased) == _covered(biased)).mean() > 0.999


def test_perspective_makes_near_things_bigger():
    near_v, near_f = _quad(0.5, half=0.2, shift=-0.5)
    far_v, far_f = _quad(-0.5, half=0.2, shift=0.5)
    image = render(
        [(near_v, near_f, (255, 0, 0)), (far_v, far_f, (0, 0, 255))], perspective=True, width=200, height=200
    )
    red = (image[..., 0] > 100) & (image[..., 2] < 50)
    blue = (image[..., 2] > 100) & (image[..., 0] < 50)
    assert red.sum() > 1.3 * blue.sum() > 0


def test_render_views_side_by_side_and_png(tmp_path):
    box = trimesh.creation.box(extents=(0.4, 1.6, 0.3))
    image = render_views(
        [(box.vertices, box.faces, (120, 120, 120))], views=("front", "back", "left"), width=64, height=96
    )
    assert image.shape == (96, 192, 3) and image.dtype == np.uint8
    front, back, left = image[:, :64], image[:, 64:128], image[:, 128:]
    assert _covered(front).sum() == _covered(back).sum()  # same box, same scale, mirrored
    assert _covered(left).sum() < _covered(front).sum()  # narrower from the side
    path = save_png(image, tmp_path / "sub" / "views.png")
    from PIL import Image

    assert np.array_equal(np.asarray(Image.open(path)), image)


def test_supersampling_keeps_size_and_smooths_edges():
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    image = render([(ball.vertices, ball.faces, (0, 0, 0))], width=80, height=80, supersample=3)
    assert image.shape == (80, 80, 3)
    grey = (image[..., 0] > 0) & (image[..., 0] < 255)
    assert grey.any()  # partially covered edge pixels are blended


def test_invalid_inputs_are_rejected():
    v, f = _quad(0.0)
    with pytest.raises(ValueError, match=r"\(V, 3\)"):
        render([(v[:, :2], f, (0, 0, 0))])
    with pytest.raises(ValueError, match="face indices"):
        render([(v, f + 10, (0, 0, 0))])
    with pytest.raises(ValueError, match="unknown view"):
        render([(v, f, (0, 0, 0))], view="top")
    with pytest.raises(ValueError, match="uint8"):
        save_png(np.zeros((4, 4, 3)), "/tmp/never_written.png")


def test_per_face_colours_and_point_splats_in_front_of_a_surface():
    """A mesh's colour may be one RGB per face; points drawn as splats face the camera of any view and show
    where they are in front of a surface, in their own colours."""
    v, f = _quad(0.0)
    red, blue, grey = (255, 0, 0), (0, 0, 255), (128, 128, 128)
    halves = render([(v, f, np.array([red, blue]))], view="front", width=100, height=100, ambient=1.0)
    assert {tuple(halves[70, 60]), tuple(halves[30, 40])} == {red, blue}  # one face each side of the diagonal
    points = np.array([[-0.25, 0.0, 0.05], [0.25, 0.0, 0.05]])
    for view in ("front", 30.0):
        splats = point_splats(points, np.array([red, blue]), 0.05, view)
        assert splats.verts.shape == (6, 3) and splats.faces.shape == (2, 3)
        image = render([(v, f, grey), splats], view=view, width=100, height=100, ambient=1.0)
        colours = {tuple(c) for c in image.reshape(-1, 3)}
        assert red in colours and blue in colours and grey in colours
    behind = point_splats(points * [1, 1, -1], red, 0.05)  # one colour for all; hidden by the quad
    image = render([(v, f, grey), behind], view="front", width=100, height=100, ambient=1.0)
    assert red not in {tuple(c) for c in image.reshape(-1, 3)}
    with pytest.raises(ValueError, match="per face"):
        render([(v, f, np.array([red, blue, grey]))])
