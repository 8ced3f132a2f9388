"""Synthetic scans captured like real ones: `synthetic_scans.make_draped_scan`'s draped garment and body,
seen by simulated depth cameras (`capture.capture_scene`) on a floor, turned, in the asked units and axes.

The ground truth (``truth/``, `synthetic_scans.write_scan`) is written in the frame that the intake
(`scan_intake.intake_scan`) brings the scan into: the turned scene in metres, Y up, floor at y = 0 (the
intake converts units and axes and levels the floor at y = 0; it never turns nor shifts horizontally). So
the body and the drape in ``truth/`` are turned by the capture's yaw, and ``body.json``'s placement with
them; the pattern and material are unchanged. ``truth.json`` records the capture (``capture``: yaw, units,
up axis, cameras, noise, points per label), and `diffavatar eval` reads the scan file with its units and
axes.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from torch_diffavatar.capture import CapturedScan, CaptureSettings, SceneMesh, capture_scene
from torch_diffavatar.geometry import yaw_rotation
from torch_diffavatar.scan import UNITS, UP_AXES
from torch_diffavatar.synthetic_scans import DrapedScan

SKIN_COLOR = (222, 171, 140)
GARMENT_COLOR = (52, 86, 160)
# The capture draws from (seed, this), apart from `make_draped_scan`'s own draws.
CAPTURE_SEED_OFFSET = 2000


def turned_body_params(params: dict, yaw_deg: float) -> dict:
    """`BodyModel.parameters_dict` of the body turned by ``yaw_deg`` [deg] about +Y through the origin:
    world = R_yaw (s R(orient) x + t) = s (R_yaw R(orient)) x + R_yaw t."""
    rot = Rotation.from_matrix(yaw_rotation(yaw_deg))
    orient = rot * Rotation.from_rotvec(np.asarray(params["global_orient_axis_angle"], np.float64))
    out = dict(params)
    out["global_orient_axis_angle"] = orient.as_rotvec().tolist()
    out["translation_m"] = (
        np.asarray(params["translation_m"], np.float64) @ yaw_rotation(yaw_deg).T
    ).tolist()
    return out


def capture_draped_scan(
    scan: DrapedScan,
    settings: CaptureSettings,
    seed: int,
    *,
    garment_color: tuple[int, int, int] = GARMENT_COLOR,
    extra_meshes: tuple[SceneMesh, ...] = (),
) -> tuple[DrapedScan, CapturedScan]:
    """Capture the noise-free drape and body of ``scan`` with ``settings``, all draws from ``seed``.

    ``garment_color``: the garment's RGB; ``extra_meshes``: more of the scene in the body's frame (a second
    garment, e.g. `scripts/colour_segmentation.py`'s trousers), captured with it and turned alike.

    Returns:
        (``scan`` with the captured points and labels and its truth in the intake's frame (see the
        module docstring), the `CapturedScan` in the file's frame for `synthetic_scans.write_scan`).
    """
    meshes = [
        SceneMesh(scan.body_vertices, scan.body_faces, 0, SKIN_COLOR),
        SceneMesh(scan.cloth_x, scan.garment.sim_faces.numpy(), 1, garment_color),
        *extra_meshes,
    ]
    captured = capture_scene(meshes, settings, np.random.default_rng([seed, CAPTURE_SEED_OFFSET]))
    rot = yaw_rotation(settings.yaw_deg)
    truth_points = captured.points @ UP_AXES[settings.up].T * UNITS[settings.units]
    labels = captured.labels
    info = dict(scan.info, capture=captured.info)
    info["points"] = {"garment": int((labels == 1).sum()), "body": int((labels == 0).sum())}
    turned = replace(
        scan,
        points=truth_points,
        labels=labels,
        cloth_x=scan.cloth_x @ rot.T,
        body_vertices=scan.body_vertices @ rot.T,
        body_params=turned_body_params(scan.body_params, settings.yaw_deg),
        info=info,
    )
    return turned, captured
