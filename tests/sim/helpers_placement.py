"""Shared by the placement tests."""

from __future__ import annotations

import numpy as np


def green_strain_max(garment, pos: np.ndarray) -> np.ndarray:
    """(F,) largest |Green strain| component of each placed triangle against its 2D rest shape."""
    t = garment.tri_vertices.numpy()
    uv = garment.vert_uv.numpy()
    rest = np.stack([uv[t[:, 0]] - uv[t[:, 2]], uv[t[:, 1]] - uv[t[:, 2]]], -1)
    cur = np.stack([pos[t[:, 0]] - pos[t[:, 2]], pos[t[:, 1]] - pos[t[:, 2]]], -1)
    f = cur @ np.linalg.inv(rest)
    e = 0.5 * (np.swapaxes(f, 1, 2) @ f - np.eye(2))
    return np.abs(e).reshape(len(t), -1).max(1)
