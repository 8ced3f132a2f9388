"""Frame conversion between the Anny body model and our world frame.

Anny is Z-up, faces −Y, +X is the body's left, metres. Our world (GarmentCode's) is Y-up, faces +Z,
+X is the body's left, metres, feet on y = 0. The map (x, y, z) → (x, z, −y) is a rotation of −90°
about X, so handedness and the body's left side are preserved.
"""

from __future__ import annotations

import torch

# Rows give world axes in Anny coordinates: world = ANNY_TO_WORLD @ anny.
ANNY_TO_WORLD = ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0))


def anny_to_world_rotation(like: torch.Tensor) -> torch.Tensor:
    """(3, 3) rotation taking Anny coordinates to world coordinates, on ``like``'s device and dtype."""
    return torch.tensor(ANNY_TO_WORLD, device=like.device, dtype=like.dtype)


def anny_to_world(points: torch.Tensor) -> torch.Tensor:
    """Rotate points from Anny's frame into ours (no translation). points: (..., 3) [m] -> (..., 3) [m]."""
    return points @ anny_to_world_rotation(points).T


def world_to_anny(points: torch.Tensor) -> torch.Tensor:
    """Inverse of `anny_to_world`. points: (..., 3) [m] -> (..., 3) [m]."""
    return points @ anny_to_world_rotation(points)
