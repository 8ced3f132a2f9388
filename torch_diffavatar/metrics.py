"""Mesh measures: triangle quality and angles (differentiable torch functions, any dtype/device)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


def _check_mesh(verts: torch.Tensor, faces: torch.Tensor) -> None:
    if verts.ndim != 2 or verts.shape[1] not in (2, 3):
        raise ValueError(f"verts must be (V, 2) or (V, 3), got {tuple(verts.shape)}")
    if not verts.is_floating_point():
        raise ValueError(f"verts must be a floating tensor, got {verts.dtype}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype not in (torch.int32, torch.int64):
        raise ValueError(f"faces must be (F, 3) int32/int64, got {tuple(faces.shape)} {faces.dtype}")


def _edges_and_area(verts: torch.Tensor, faces: torch.Tensor):
    """Edge vectors opposite each corner (F, 3, D) and triangle areas (F,)."""
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    e = torch.stack([c - b, a - c, b - a], dim=1)  # edge opposite corner i
    if verts.shape[1] == 2:
        area = 0.5 * (e[:, 2, 0] * (-e[:, 1, 1]) - e[:, 2, 1] * (-e[:, 1, 0])).abs()
    else:
        area = 0.5 * torch.linalg.vector_norm(torch.linalg.cross(e[:, 2], -e[:, 1]), dim=-1)
    return e, area


def triangle_quality(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Shewchuk's conditioning-based quality ``q = 4·√3·A / Σ l_i²`` (1 = equilateral, 0 = degenerate).

    Args:
        verts: (V, 2) rest or (V, 3) placed positions [m], floating.
        faces: (F, 3) int64 vertex indices.

    Returns:
        (F,) quality in [0, 1], same dtype as ``verts``; differentiable with respect to ``verts``.
    """
    _check_mesh(verts, faces)
    e, area = _edges_and_area(verts, faces)
    sq = (e * e).sum(dim=(1, 2))
    return 4.0 * math.sqrt(3.0) * area / sq.clamp_min(torch.finfo(verts.dtype).tiny)


def triangle_angles_deg(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(F, 3) interior angles [deg] at the three corners of each triangle."""
    _check_mesh(verts, faces)
    e, _ = _edges_and_area(verts, faces)
    # angle at corner i is between the two edges leaving it: -e[i+2] and e[i+1]
    u = -e[:, [2, 0, 1]]
    v = e[:, [1, 2, 0]]
    if verts.shape[1] == 2:
        cross = (u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]).abs()
    else:
        cross = torch.linalg.vector_norm(torch.linalg.cross(u, v, dim=-1), dim=-1)
    dot = (u * v).sum(-1)
    return torch.rad2deg(torch.atan2(cross, dot))


def min_angle_deg(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """() smallest interior angle [deg] over all triangles."""
    return triangle_angles_deg(verts, faces).min()


@dataclass
class QualitySummary:
    """Summary of `triangle_quality` and angles over a mesh (0-dim tensors)."""

    quality_min: torch.Tensor
    quality_mean: torch.Tensor
    min_angle_deg: torch.Tensor


def quality_summary(verts: torch.Tensor, faces: torch.Tensor) -> QualitySummary:
    """Min and mean quality and the smallest angle of a (V, 2) or (V, 3) mesh."""
    q = triangle_quality(verts, faces)
    return QualitySummary(q.min(), q.mean(), min_angle_deg(verts, faces))
