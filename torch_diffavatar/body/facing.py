"""Which way a standing person in a scan faces, from the scan alone (a start for `body.fit.fit_body`).

Two cues, both about the horizontal (x, z) plane of a Y-up scan:

- the body's left-right axis: the principal horizontal axis of the hips slab (40–55 % of the height),
  wider from side to side than from front to back (and the hands of an A-pose hang beside it);
- front or back: the feet point forward. The mean of the feet slab (the lowest 6 cm) lies in front of the
  mean of the shins slab (15–35 cm up): toes reach about 18 cm before the ankle, heels 5 cm behind.

The facing direction is the normal of the left-right axis on the side the feet point to; with a round
hips slab (axis ratio under `MIN_ANISOTROPY`) the feet alone give it. Limitations: shoes are fine, but a
scan without feet, or with the feet crossed or turned out by more than 45°, gives a wrong sign
(`facing_yaw` returns None when the feet slab holds too few points).
"""

from __future__ import annotations

import math

import numpy as np

MIN_ANISOTROPY = 1.15  # hips slab: sqrt of the ratio of its horizontal variances
MIN_SLAB_POINTS = 30


def _slab(points: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(k, 2) horizontal (x, z) coordinates of the points with lo <= y < hi."""
    return points[(points[:, 1] >= lo) & (points[:, 1] < hi)][:, [0, 2]]


def facing_yaw(points: np.ndarray) -> float | None:
    """The person's facing direction as a yaw [deg] about +Y (0: facing +Z, 90: facing +X), or None.

    Args:
        points: (N, 3) scan points [m], Y up, the floor removed (the lowest points are the soles).

    Returns:
        the yaw [deg] in (-180, 180], or None when the feet or the shins hold fewer than 30 points.
    """
    y0, y1 = np.quantile(points[:, 1], [0.001, 0.999])
    height = y1 - y0
    feet = _slab(points, y0, y0 + 0.06)
    shins = _slab(points, y0 + 0.15, y0 + 0.35)
    if len(feet) < MIN_SLAB_POINTS or len(shins) < MIN_SLAB_POINTS:
        return None
    forward = feet.mean(0) - shins.mean(0)  # (x, z) towards the toes
    hips = _slab(points, y0 + 0.40 * height, y0 + 0.55 * height)
    if len(hips) >= MIN_SLAB_POINTS:
        evals, evecs = np.linalg.eigh(np.cov((hips - hips.mean(0)).T))
        if math.sqrt(evals[1] / max(evals[0], 1e-12)) >= MIN_ANISOTROPY:
            normal = evecs[:, 0]  # the minor axis: front-back
            forward = normal if normal @ forward >= 0 else -normal
    if not np.linalg.norm(forward) > 0:
        return None
    return math.degrees(math.atan2(forward[0], forward[1]))


def body_facing_yaw(global_orient) -> float:
    """The yaw [deg] about +Y of the direction a `BodyModel` faces: ``global_orient`` (3,) axis-angle
    [rad] turns its +Z (Anny's front in our frame, `frames`); 0: facing +Z, 90: facing +X."""
    from scipy.spatial.transform import Rotation

    rotvec = np.asarray(
        global_orient.detach().cpu().double() if hasattr(global_orient, "detach") else global_orient
    )
    front = Rotation.from_rotvec(rotvec.reshape(3)).apply([0.0, 0.0, 1.0])
    return math.degrees(math.atan2(front[0], front[2]))
