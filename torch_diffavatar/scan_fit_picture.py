"""The scan on its fit, as a picture (``scan_fit.png`` of a fit's assets): where the fitted garment misses
the scan, seen rather than read from a Chamfer distance.

Four views side by side, each on the fitted body: the front and the back of the scan's garment points, each
coloured by its distance to the fitted garment's surface (cloth the scan has and the fit has not: a hem
fitted short, a sleeve too narrow), then the front and the back of the fitted garment, each vertex coloured
by its distance to the nearest scan garment point (cloth the fit has and the scan has not: a hem fitted
long; also cloth the scan never saw, such as the far side of a partial scan). Green is on it, yellow
`FULL_SCALE_M` / 2 off, red `FULL_SCALE_M` or more; a line under the views says so. "Front" is the fitted
body's front (its global orientation), whatever way the person faced the cameras.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from torch_diffavatar.geometry import closest_point_on_mesh
from torch_diffavatar.render import (
    CLOTH_DEPTH_BIAS,
    RenderMesh,
    point_splats,
    render_views,
)

FULL_SCALE_M = 0.03  # [m] a distance drawn red
MAX_POINTS = 30_000  # scan points drawn (a seeded subset beyond): enough to cover a garment at ~5 mm
SPLAT_M = 0.008  # [m] a drawn point's size
NEIGHBOURS = 16  # a scan point's distance is the median over this many nearest points (its own included)
_STOPS = np.array([[40, 170, 60], [235, 200, 40], [215, 40, 40]], dtype=np.float64)  # green, yellow, red


def distance_colours(dist_m: np.ndarray, full_scale_m: float = FULL_SCALE_M) -> np.ndarray:
    """(N, 3) float RGB of distances (N,) [m]: green at 0, yellow at half ``full_scale_m``, red from it on."""
    t = np.clip(np.asarray(dist_m, dtype=np.float64) / full_scale_m, 0.0, 1.0) * 2.0
    low = np.minimum(t, 1.0)[:, None]
    high = np.clip(t - 1.0, 0.0, 1.0)[:, None]
    return np.where(
        t[:, None] <= 1.0,
        _STOPS[0] + low * (_STOPS[1] - _STOPS[0]),
        _STOPS[1] + high * (_STOPS[2] - _STOPS[1]),
    )


def scan_fit_distances(scan_points, cloth_x, cloth_faces) -> tuple[np.ndarray, np.ndarray]:
    """(scan → fit (P,), fit → scan (Vs,)) [m]: each scan garment point's distance to the fitted garment's
    surface (the median over its `NEIGHBOURS` nearest points: the scan's noise smoothed), and each fitted
    garment vertex's distance to the nearest scan garment point.

    Args:
        scan_points: (P, 3) [m]; cloth_x: (Vs, 3) [m]; cloth_faces: (F, 3) int.
    """
    points = torch.as_tensor(scan_points, dtype=torch.float64).detach().cpu().reshape(-1, 3).contiguous()
    x = torch.as_tensor(cloth_x, dtype=torch.float64).detach().cpu().reshape(-1, 3).contiguous()
    faces = torch.as_tensor(cloth_faces, dtype=torch.int64).cpu().contiguous()
    _, _, to_fit = closest_point_on_mesh(points, x, faces, float("inf"))
    tree = cKDTree(points.numpy())
    to_scan, _ = tree.query(x.numpy())
    # each point's median over its neighbours: the picture shows where the fit misses, not the scan's noise
    _, near = tree.query(points.numpy(), k=min(NEIGHBOURS, len(points)))
    near = near.reshape(len(points), -1)
    return np.median(to_fit.numpy()[near], axis=1), np.asarray(to_scan)


def render_scan_on_fit(
    scan_points,
    cloth_x,
    cloth_faces,
    body_verts,
    body_faces,
    *,
    front_deg: float = 0.0,
    size: int = 320,
) -> np.ndarray:
    """(size·5/4 + legend, 4·size, 3) uint8: the four views of the module docstring.

    Args:
        scan_points: (P, 3) the scan's garment points [m] (more than `MAX_POINTS`: a seeded subset drawn).
        cloth_x: (Vs, 3) the fitted drape [m]; cloth_faces: (F, 3) int.
        body_verts: (Vb, 3) the fitted body [m]; body_faces: (Fb, 3) int.
        front_deg: the azimuth [deg] of the body's front (`body.facing.body_facing_yaw`).
        size: a view's width [px].
    """
    points = torch.as_tensor(scan_points, dtype=torch.float64).detach().cpu().reshape(-1, 3)
    if len(points) > MAX_POINTS:
        points = points[np.random.default_rng(0).choice(len(points), MAX_POINTS, replace=False)]
    to_fit, to_scan = scan_fit_distances(points, cloth_x, cloth_faces)
    x = torch.as_tensor(cloth_x).detach().cpu().double().numpy()
    faces = torch.as_tensor(cloth_faces).cpu().numpy()
    body = RenderMesh(torch.as_tensor(body_verts).detach().cpu(), torch.as_tensor(body_faces).cpu())
    views, colours = (front_deg, front_deg + 180.0), distance_colours(to_fit)
    kw = dict(width=size, height=size * 5 // 4)
    points_seen = [render_views([body, point_splats(points, colours, SPLAT_M, v)], (v,), **kw) for v in views]
    cloth = RenderMesh(x, faces, distance_colours(to_scan[faces].mean(1)), CLOTH_DEPTH_BIAS)
    panels = [*points_seen, render_views([body, cloth], views, **kw)]
    return _with_legend(np.concatenate(panels, axis=1))


def _with_legend(image: np.ndarray) -> np.ndarray:
    """``image`` with a line of text and a colour bar under it (PIL's default font)."""
    from PIL import Image, ImageDraw

    height, width = 34, image.shape[1]
    strip = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(strip)
    half = width // 2
    draw.text((8, 4), "scan garment points: distance to the fitted garment (front, back)", fill=(0, 0, 0))
    text = "fitted garment: distance to the scan's garment points (red also where the scan saw no cloth)"
    draw.text((half + 8, 4), text, fill=(0, 0, 0))
    bar = distance_colours(np.linspace(0.0, FULL_SCALE_M, 200))
    for k, colour in enumerate(bar):
        draw.line([(8 + k, 20), (8 + k, 30)], fill=tuple(int(c) for c in colour))
    scale = f"0 - {100 * FULL_SCALE_M / 2:g} - {100 * FULL_SCALE_M:g} cm and more"
    draw.text((216, 19), scale, fill=(0, 0, 0))
    return np.concatenate([image, np.asarray(strip, dtype=np.uint8)], axis=0)
