"""Small mesh helpers used by the body fit and segmentation: vertex normals and areas."""

from __future__ import annotations

import torch


def face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Face normals of length 2 × area. vertices: (..., V, 3) [m], faces: (F, 3) -> (..., F, 3) [m²]."""
    tri = vertices[..., faces, :]  # (..., F, 3, 3)
    return torch.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :], dim=-1)


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit vertex normals (area-weighted average of the adjacent faces' normals).

    Args:
        vertices: (V, 3) or (B, V, 3) [m].
        faces: (F, 3) int64, consistently oriented (outward normals for a closed body).

    Returns:
        same shape as ``vertices``, unit length.
    """
    fn = face_normals(vertices, faces)  # (..., F, 3)
    out = torch.zeros_like(vertices)
    for k in range(3):
        out = out.index_add(-2, faces[:, k], fn)
    return out / out.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def vertex_areas(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area attributed to each vertex: a third of the adjacent triangles' areas.

    Args:
        vertices: (V, 3) or (B, V, 3) [m].
        faces: (F, 3) int64.

    Returns:
        (V,) or (B, V) [m²]; sums to the surface area.
    """
    area = face_normals(vertices, faces).norm(dim=-1) / 6.0  # (..., F), a third of each face area
    out = torch.zeros_like(vertices[..., 0])
    for k in range(3):
        out = out.index_add(-1, faces[:, k], area)
    return out
