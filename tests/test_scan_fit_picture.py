"""The scan on its fit (`scan_fit_picture`, ``scan_fit.png``): the distances both ways, the colours, and
the picture's views (the fit's front whatever way the body faces)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from torch_diffavatar.scan_fit_picture import (
    FULL_SCALE_M,
    distance_colours,
    render_scan_on_fit,
    scan_fit_distances,
)

GREEN, YELLOW, RED = distance_colours(np.array([0.0, FULL_SCALE_M / 2, FULL_SCALE_M]))


def _sheet(n: int = 21, half: float = 0.3, z: float = 0.1):
    """A flat garment in the plane z = ``z``, facing +Z: verts (n², 3), faces."""
    g = np.linspace(-half, half, n)
    xx, yy = np.meshgrid(g, g)
    verts = np.stack([xx.ravel(), yy.ravel() + 1.0, np.full(n * n, z)], 1)
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[:-1, 1:].ravel(), k[1:, 1:].ravel(), k[1:, :-1].ravel()
    return verts, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def test_colours_run_green_yellow_red_and_stay_red_beyond():
    colours = distance_colours(np.array([0.0, FULL_SCALE_M / 2, FULL_SCALE_M, 10 * FULL_SCALE_M, -1.0]))
    assert np.allclose(colours[0], colours[4]) and np.allclose(colours[2], colours[3])
    assert GREEN[1] > GREEN[0] and RED[0] > RED[1] and YELLOW[0] > 200 and YELLOW[1] > 150


def test_distances_both_ways_on_a_sheet():
    """Points on the sheet are 0 from it, a patch 2 cm in front 0.02; the sheet's far half, where the scan
    has no points, is far from the scan. Each point's distance is its neighbours' median: one stray point
    does not show."""
    verts, faces = _sheet()
    rng = np.random.default_rng(0)
    on = np.c_[rng.uniform(-0.3, 0.0, (2000, 2)) + [0, 1.0], np.full(2000, 0.1)]
    off = np.c_[rng.uniform(-0.3, -0.2, (300, 2)) + [0, 1.0], np.full(300, 0.12)]
    stray = on[:1] + [0.0, 0.0, 0.05]
    to_fit, to_scan = scan_fit_distances(np.concatenate([on, off, stray]), verts, faces)
    assert np.median(to_fit[:2000]) < 1e-3 and np.median(to_fit[2000:2300]) == pytest.approx(0.02, abs=2e-3)
    assert to_fit[-1] < 1e-3
    far = verts[:, 0] > 0.15  # 15 cm or more from the scan's half
    assert to_scan[far].min() > 0.1 and np.median(to_scan[verts[:, 0] < -0.05]) < 0.01


@pytest.mark.parametrize("yaw", [0.0, 120.0])
def test_picture_shows_a_miss_in_red_from_the_bodys_front(yaw):
    """A sheet in front of a box body, the scan on its left half and 4 cm in front of its right half; the
    whole scene turned by ``yaw``: the front view (``front_deg`` = yaw) shows green and red points, the
    back view only the body; the fit's panels are green where the scan lies on it."""
    verts, faces = _sheet()
    box = trimesh.creation.box(extents=(0.7, 1.8, 0.15))
    body_v, body_f = box.vertices + [0, 0.9, 0], box.faces
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.3, 0.3, (6000, 2))
    scan = np.c_[xy + [0, 1.0], np.where(xy[:, 0] > 0, 0.14, 0.1)]
    turn = torch.tensor(trimesh.transformations.rotation_matrix(np.radians(yaw), [0, 1, 0])[:3, :3])
    scan, verts, body_v = (torch.as_tensor(a, dtype=torch.float64) @ turn.T for a in (scan, verts, body_v))
    image = render_scan_on_fit(scan, verts, torch.as_tensor(faces), body_v, torch.as_tensor(body_f),
                               front_deg=yaw, size=96)  # fmt: skip
    assert image.shape == (96 * 5 // 4 + 34, 4 * 96, 3) and image.dtype == np.uint8
    front, back, fit_front = (image[: 96 * 5 // 4, k * 96 : (k + 1) * 96].reshape(-1, 3) for k in range(3))

    def share(pixels, colour):  # of the pixels, those of ``colour``'s hue (shaded: red or green dominant)
        r, g = pixels[:, 0].astype(int), pixels[:, 1].astype(int)
        return float(((r > g + 60) if colour is RED else (g > r + 40)).mean())

    assert share(front, RED) > 0.02 and share(front, GREEN) > 0.02
    assert share(back, RED) < 0.005 and share(back, GREEN) < 0.005  # the box hides the points
    assert share(fit_front, GREEN) > 0.02
