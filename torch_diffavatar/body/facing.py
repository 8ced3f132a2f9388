"""Which way a standing person in a scan faces, from the scan alone (a start for `body.fit.fit_body`).

Two cues, both about the horizontal (x, z) plane of a Y-up scan:

- the body's left-right axis: the principal horizontal axis of the hips slab (40–55 % of the height),
  wider from side to side than from front to back (and the hands of an A-pose hang beside it);
- front or back: the feet point forward. The mean of the feet slab (the lowest 6 cm) lies in front of the
  mean of the shins slab (15–35 cm up): toes reach about 18 cm before the ankle, heels 5 cm behind.

Neither cue says front from back for sure, so `facing_yaws` gives two opposite candidates, the feet's side
first, and the body fit decides (`body.fit.fit_body` runs its coarse stages facing each way and goes on
from the better fit by its final stage's measure): the normals of the left-right axis, or with a round
hips slab (axis ratio under `MIN_ANISOTROPY`) the feet's direction and its opposite. The feet alone were
wrong on a long dress captured from its side (seed 452: a 4.5 cm shift pointing backwards, its hem in the
shins slab), and the body was fitted facing backwards (docs/BENCHMARKS.md, "Front or back").
"""

from __future__ import annotations

import math

import numpy as np

MIN_ANISOTROPY = 1.15  # hips slab: sqrt of the ratio of its horizontal variances
MIN_SLAB_POINTS = 30
# [m] the feet slab's mean lies this far before the shins' at least when the feet are there. Measured:
# 6-10 cm on scans and captures with feet, 1-3.6 cm on scans cut 10-50 cm above the soles.
MIN_FEET_SHIFT = 0.045


def _slab(points: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(k, 2) horizontal (x, z) coordinates of the points with lo <= y < hi."""
    return points[(points[:, 1] >= lo) & (points[:, 1] < hi)][:, [0, 2]]


def feet_forward(points: np.ndarray) -> np.ndarray | None:
    """(2,) horizontal (x, z) shift [m] from the shins slab's mean to the feet slab's (towards the toes),
    or None when the scan shows no feet (a shift under `MIN_FEET_SHIFT`: a scan cut above them, or a long
    dress's hem; or too few points in a slab). ``points``: (N, 3) [m], Y up, the floor removed."""
    y0 = np.quantile(points[:, 1], 0.001)
    feet = _slab(points, y0, y0 + 0.06)
    shins = _slab(points, y0 + 0.15, y0 + 0.35)
    if len(feet) < MIN_SLAB_POINTS or len(shins) < MIN_SLAB_POINTS:
        return None
    forward = feet.mean(0) - shins.mean(0)
    return forward if np.linalg.norm(forward) >= MIN_FEET_SHIFT else None


def shows_feet(points: np.ndarray) -> bool:
    """Whether the scan ``points`` (N, 3) [m] (Y up, the floor removed) show the feet (`feet_forward`)."""
    return feet_forward(points) is not None


def facing_yaws(points: np.ndarray) -> list[float]:
    """The person's facing direction, front or back unknown: two opposite yaws [deg] about +Y (0: facing
    +Z, 90: facing +X).

    Args:
        points: (N, 3) scan points [m], Y up, the floor removed (the lowest points are the soles).

    Returns:
        the two normals of the hips axis, the one the feet point to first (the feet slab's mean at least
        `MIN_FEET_SHIFT` before the shins'; either first without feet); with a round hips slab the feet's
        direction and its opposite; [] with neither. Yaws in (-180, 180].
    """
    y0, y1 = np.quantile(points[:, 1], [0.001, 0.999])
    height = y1 - y0
    forward = feet_forward(points)
    normal = None
    hips = _slab(points, y0 + 0.40 * height, y0 + 0.55 * height)
    if len(hips) >= MIN_SLAB_POINTS:
        evals, evecs = np.linalg.eigh(np.cov((hips - hips.mean(0)).T))
        if math.sqrt(evals[1] / max(evals[0], 1e-12)) >= MIN_ANISOTROPY:
            normal = evecs[:, 0]  # the minor axis: front-back
    if normal is not None:
        front = normal if forward is None or normal @ forward >= 0 else -normal
    elif forward is not None:
        front = forward
    else:
        return []
    return [math.degrees(math.atan2(d[0], d[1])) for d in (front, -front)]


def body_facing_yaw(global_orient) -> float:
    """The yaw [deg] about +Y of the direction a `BodyModel` faces: ``global_orient`` (3,) axis-angle
    [rad] turns its +Z (Anny's front in our frame, `frames`); 0: facing +Z, 90: facing +X."""
    from scipy.spatial.transform import Rotation

    rotvec = np.asarray(
        global_orient.detach().cpu().double() if hasattr(global_orient, "detach") else global_orient
    )
    front = Rotation.from_rotvec(rotvec.reshape(3)).apply([0.0, 0.0, 1.0])
    return math.degrees(math.atan2(front[0], front[2]))
