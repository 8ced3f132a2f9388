"""Geometry that the pattern, the simulator, the body and the losses share (layer 1: imports only torch,
numpy, scipy and the compiled extension): closest points on triangles and meshes, the Green strain of
triangles, and stitched-vertex merging.

The C++ op ``torch.ops.diffavatar.closest_point_on_mesh`` and `closest_point_on_mesh_torch` (its PyTorch
twin, `torch_diffavatar.sim.reference.closest_point_on_mesh`) return the same triangles, bit for bit on the
distances' ties aside; `closest_point_on_mesh` picks the op on CPU tensors when the extension is built.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torch_diffavatar._ext import has_extension

__all__ = [
    "closest_point_on_mesh",
    "closest_point_on_mesh_torch",
    "closest_point_on_triangles",
    "gather_rows",
    "green_strain",
    "merge_pairs",
    "triangle_green_strain",
]


def gather_rows(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(…, *index.shape, D) the rows ``x[..., index, :]`` of ``x`` (…, N, D) at the int64 ``index``.

    The same values as advanced indexing, through ``index_select``, whose backward (``index_add``) costs a
    third of advanced indexing's (``index_put`` with accumulation) and sums in the same order, so the
    gradient is the same bit for bit. The rest terms gather this way ~60 times a fit iteration.
    """
    return x.index_select(-2, index.reshape(-1).to(x.device)).unflatten(-2, index.shape)


# ------------------------------------------------------------------------------------- closest point


def closest_point_on_triangles(p, a, b, c):
    """Exact closest point on triangles (Ericson 5.1.5), broadcasting over leading dims.

    Args:
        p, a, b, c: (..., 3) query points and triangle corners.

    Returns:
        bary: (..., 3) barycentric coordinates of the closest point (weights of a, b, c).
    """
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = (ab * ap).sum(-1)
    d2 = (ac * ap).sum(-1)
    bp = p - b
    d3 = (ab * bp).sum(-1)
    d4 = (ac * bp).sum(-1)
    cp = p - c
    d5 = (ab * cp).sum(-1)
    d6 = (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    def safe_div(num, den):
        ok = den != 0
        return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))

    zero = torch.zeros_like(d1)
    one = torch.ones_like(d1)
    # interior (default), then regions overriding in reverse of Ericson's early-return order
    denom = va + vb + vc
    v = safe_div(vb, denom)
    w = safe_div(vc, denom)
    u = 1.0 - v - w
    # edge BC
    w_bc = safe_div(d4 - d3, (d4 - d3) + (d5 - d6))
    m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    u, v, w = torch.where(m, zero, u), torch.where(m, 1.0 - w_bc, v), torch.where(m, w_bc, w)
    # edge AC
    w_ac = safe_div(d2, d2 - d6)
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    u, v, w = torch.where(m, 1.0 - w_ac, u), torch.where(m, zero, v), torch.where(m, w_ac, w)
    # vertex C
    m = (d6 >= 0) & (d5 <= d6)
    u, v, w = torch.where(m, zero, u), torch.where(m, zero, v), torch.where(m, one, w)
    # edge AB
    v_ab = safe_div(d1, d1 - d3)
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    u, v, w = torch.where(m, 1.0 - v_ab, u), torch.where(m, v_ab, v), torch.where(m, zero, w)
    # vertex B
    m = (d3 >= 0) & (d4 <= d3)
    u, v, w = torch.where(m, zero, u), torch.where(m, one, v), torch.where(m, zero, w)
    # vertex A
    m = (d1 <= 0) & (d2 <= 0)
    u, v, w = torch.where(m, one, u), torch.where(m, zero, v), torch.where(m, zero, w)
    return torch.stack((u, v, w), dim=-1)


def closest_point_on_mesh_torch(
    points: torch.Tensor, verts: torch.Tensor, faces: torch.Tensor, max_dist: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closest point on a triangle mesh for each query point (brute force in chunks; no autograd).

    Args:
        points: (N, 3) query points [m].
        verts: (Vb, 3) mesh vertices [m].
        faces: (Fb, 3) int64 triangles.
        max_dist: search radius [m]; farther points get no triangle.

    Returns:
        tri: (N,) int64 closest triangle (-1 when none within ``max_dist``).
        bary: (N, 3) barycentric coordinates of the closest point on ``tri`` (zeros when -1).
        dist: (N,) unsigned distance [m] (inf when -1).
    """
    n = points.shape[0]
    tri = torch.full((n,), -1, dtype=torch.int64, device=points.device)
    bary = points.new_zeros(n, 3)
    dist = points.new_full((n,), float("inf"))
    if n == 0 or faces.shape[0] == 0:
        return tri, bary, dist
    with torch.no_grad():
        a, b, c = verts[faces].unbind(1)  # (Fb, 3) each
        lo = torch.minimum(torch.minimum(a, b), c) - max_dist
        hi = torch.maximum(torch.maximum(a, b), c) + max_dist
        chunk = max(1, 2_000_000 // faces.shape[0])
        for s in range(0, n, chunk):
            p = points[s : s + chunk]  # (P, 3)
            near = ((p[:, None] >= lo[None]) & (p[:, None] <= hi[None])).all(-1)  # (P, Fb)
            pi, fi = near.nonzero(as_tuple=True)
            if pi.numel() == 0:
                continue
            bc = closest_point_on_triangles(p[pi], a[fi], b[fi], c[fi])  # (M, 3)
            q = bc[:, :1] * a[fi] + bc[:, 1:2] * b[fi] + bc[:, 2:] * c[fi]
            d = (p[pi] - q).norm(dim=-1)
            best = p.new_full((p.shape[0],), float("inf")).scatter_reduce(0, pi, d, reduce="amin")
            is_best = d == best[pi]
            # one winner per point (ties: any)
            winner = torch.full((p.shape[0],), -1, dtype=torch.int64, device=p.device)
            cand = torch.nonzero(is_best).squeeze(1)
            winner[pi[cand]] = cand
            hit = (winner >= 0) & (best <= max_dist)
            rows = torch.nonzero(hit).squeeze(1)
            sel = winner[rows]
            tri[s + rows] = fi[sel]
            bary[s + rows] = bc[sel]
            dist[s + rows] = d[sel]
    return tri, bary, dist


def closest_point_on_mesh(
    points: torch.Tensor,
    verts: torch.Tensor,
    faces: torch.Tensor,
    max_dist: float,
    *,
    use_extension: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closest triangle, barycentrics and distance per point: the C++ op on CPU tensors when the extension
    is built (and ``use_extension``), else `closest_point_on_mesh_torch`. No autograd.

    Args:
        points: (N, 3) query points [m]; verts: (Vb, 3) [m]; faces: (Fb, 3) int64; max_dist: [m].

    Returns:
        tri (N,) int64 (-1 when farther than ``max_dist``), bary (N, 3), dist (N,) [m] (inf when -1).
    """
    if use_extension and points.device.type == "cpu" and has_extension():
        op = getattr(torch.ops.diffavatar, "closest_point_on_mesh", None)
        if op is not None:
            return op(points, verts, faces, float(max_dist))
    return closest_point_on_mesh_torch(points, verts, faces, float(max_dist))


# ------------------------------------------------------------------------------------- Green strain


def triangle_green_strain(corners: torch.Tensor, rest_inv: torch.Tensor) -> torch.Tensor:
    """``C = [E00, E11, E01]`` of the Green strain ``E = ½(FᵀF − I)``, ``F = D D̄⁻¹``, of triangles.

    Args:
        corners: (..., 3, 3) the triangles' corner positions [m] (D: edges from corner 2 to corners 0, 1).
        rest_inv: (..., 2, 2) inverse of the 2D rest edge matrix D̄ [1/m].

    Returns:
        (..., 3) dimensionless strain components.
    """
    c0, c1, c2 = corners.unbind(-2)
    d = torch.stack((c0 - c2, c1 - c2), dim=-1)  # (..., 3, 2)
    f = d @ rest_inv  # (..., 3, 2)
    f0, f1 = f[..., 0], f[..., 1]
    return torch.stack(
        (0.5 * ((f0 * f0).sum(-1) - 1.0), 0.5 * ((f1 * f1).sum(-1) - 1.0), 0.5 * (f0 * f1).sum(-1)), dim=-1
    )


def green_strain(x: torch.Tensor, tri_vertices: torch.Tensor, tri_rest_inv: torch.Tensor) -> torch.Tensor:
    """(F, 3) `triangle_green_strain` of the mesh triangles ``tri_vertices`` (F, 3) at ``x`` (V, 3) [m]."""
    return triangle_green_strain(x[tri_vertices], tri_rest_inv)


# ------------------------------------------------------------------------------------- merging


def merge_pairs(count: int, pairs: np.ndarray) -> tuple[np.ndarray, int]:
    """Merge ``count`` vertices joined by ``pairs`` (K, 2) into groups (connected components).

    Returns:
        labels: (count,) int64 group of each vertex, numbered in order of each group's first vertex.
        group_count: the number of groups.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(count, count))
    # components are labelled in order of their smallest vertex
    group_count, labels = connected_components(graph, directed=False)
    return labels.astype(np.int64), int(group_count)


def yaw_rotation(yaw_deg: float) -> np.ndarray:
    """(3, 3) float64 rotation by ``yaw_deg`` [deg] about +Y (counter-clockwise seen from above): it turns
    +Z (the way a body faces) to (sin yaw, 0, cos yaw)."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
