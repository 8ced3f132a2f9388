"""Nearest neighbours and (robust, one- or two-sided) Chamfer distances between point sets.

Nearest neighbours are found with scipy's ``cKDTree`` on detached NumPy copies; the distances are then
recomputed in torch from the gathered points, so gradients flow to both point sets (the neighbour
assignment itself is piecewise constant and carries no gradient, as in every Chamfer implementation).
Works on any dtype/device (the search runs on a CPU copy). Units: whatever the inputs use, [m] here.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

REDUCTIONS = ("mean", "sum", "none")
ROBUST_KERNELS = ("l2", "geman_mcclure", "huber")


def _check_reduction(reduction: str) -> None:
    if reduction not in REDUCTIONS:
        raise ValueError(f"reduction must be one of {REDUCTIONS}, got {reduction!r}")


def _check_robust(robust: str, scale: float) -> None:
    if robust not in ROBUST_KERNELS:
        raise ValueError(f"robust must be one of {ROBUST_KERNELS}, got {robust!r}")
    if robust != "l2" and not scale > 0:
        raise ValueError(f"the robust kernel {robust!r} needs a positive scale [m], got {scale}")


def _as_batched(points: torch.Tensor, name: str) -> torch.Tensor:
    if points.dim() == 2:
        points = points[None]
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (N, 3) or (B, N, 3), got {tuple(points.shape)}")
    if points.shape[1] == 0:
        raise ValueError(f"{name} is empty: it needs at least one point")
    return points


def nearest_indices(query: torch.Tensor | np.ndarray, points: torch.Tensor | np.ndarray) -> np.ndarray:
    """Index of the nearest point in ``points`` for every query point (exact, Euclidean, no gradient).

    Args:
        query: (N, 3) points (tensor or array) [m].
        points: (M, 3) points [m], M >= 1.

    Returns:
        (N,) int64 array of indices into ``points``.
    """
    q = query.detach().cpu().numpy() if isinstance(query, torch.Tensor) else np.asarray(query)
    p = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else np.asarray(points)
    _, idx = cKDTree(p).query(q, k=1)
    return idx.astype(np.int64)


def robust_penalty(sq_dist: torch.Tensor, robust: str = "l2", scale: float = 0.01) -> torch.Tensor:
    """Elementwise robust penalty of squared distances.

    ``"l2"``: d²; ``"geman_mcclure"``: s²·d² / (d² + s²) (saturates at s² for outliers);
    ``"huber"``: d² for d <= s, else s·(2d − s) (linear tails). All equal d² near zero.

    Args:
        sq_dist: (...) squared distances [m²].
        robust: kernel name, one of ``ROBUST_KERNELS``.
        scale: s [m], the distance where the kernel starts to flatten (ignored for ``"l2"``).

    Returns:
        (...) penalties [m²], same shape as ``sq_dist``.
    """
    _check_robust(robust, scale)
    if robust == "l2":
        return sq_dist
    s2 = scale * scale
    if robust == "geman_mcclure":
        return s2 * sq_dist / (sq_dist + s2)
    d = torch.sqrt(sq_dist.clamp_min(1e-24))
    return torch.where(d <= scale, sq_dist, scale * (2.0 * d - scale))


def one_sided_chamfer(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    robust: str = "l2",
    scale: float = 0.01,
    x_weights: torch.Tensor | None = None,
    reduction: str = "mean",
) -> torch.Tensor:
    """Penalized distance from every point of ``x`` to its nearest point in ``y``.

    Args:
        x: (N, 3) or (B, N, 3) source points [m].
        y: (M, 3) or (B, M, 3) target points [m] (a 2-D ``y`` is shared by the whole batch).
        robust: penalty kernel (see `robust_penalty`); ``"l2"`` gives squared distances [m²].
        scale: robust kernel scale [m].
        x_weights: optional (N,) or (B, N) non-negative per-point weights.
        reduction: ``"mean"`` (weighted mean over points, then mean over the batch → scalar),
            ``"sum"`` (sum over points and batch → scalar) or ``"none"`` ((B, N) per-point penalties).

    Returns:
        scalar, or (B, N) for ``reduction="none"`` [m²].
    """
    _check_reduction(reduction)
    _check_robust(robust, scale)
    xb = _as_batched(x, "x")
    yb = _as_batched(y, "y")
    if yb.shape[0] == 1 and xb.shape[0] > 1:
        yb = yb.expand(xb.shape[0], -1, -1)
    if yb.shape[0] != xb.shape[0]:
        raise ValueError(f"batch sizes differ: x has {xb.shape[0]}, y has {yb.shape[0]}")
    idx = torch.stack([torch.from_numpy(nearest_indices(xb[b], yb[b])) for b in range(xb.shape[0])]).to(
        xb.device
    )  # (B, N)
    nearest = torch.gather(yb, 1, idx[..., None].expand(-1, -1, 3))  # (B, N, 3)
    pen = robust_penalty(((xb - nearest) ** 2).sum(-1), robust, scale)  # (B, N)
    if x_weights is not None:
        w = x_weights if x_weights.dim() == 2 else x_weights[None]
        if w.shape[-1] != xb.shape[1]:
            raise ValueError(f"x_weights must have shape (N,) or (B, N) with N={xb.shape[1]}")
        pen = pen * w
    if reduction == "none":
        return pen
    if reduction == "sum":
        return pen.sum()
    if x_weights is None:
        return pen.mean()
    return (pen.sum(-1) / w.sum(-1).clamp_min(1e-12)).mean()


def chamfer_distance(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    robust: str = "l2",
    scale: float = 0.01,
    x_weights: torch.Tensor | None = None,
    y_weights: torch.Tensor | None = None,
    reduction: str = "mean",
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Two-sided Chamfer distance: ``one_sided(x → y) + one_sided(y → x)``.

    Args:
        x: (N, 3) or (B, N, 3) points [m].
        y: (M, 3) or (B, M, 3) points [m].
        robust, scale: penalty kernel and its scale [m] (see `robust_penalty`).
        x_weights, y_weights: optional per-point weights, (N,)/(B, N) and (M,)/(B, M).
        reduction: ``"mean"`` or ``"sum"`` → scalar sum of both directions [m²];
            ``"none"`` → the tuple ``((B, N) x→y, (B, M) y→x)`` of per-point penalties.
    """
    _check_reduction(reduction)
    kw = dict(robust=robust, scale=scale, reduction=reduction)
    xy = one_sided_chamfer(x, y, x_weights=x_weights, **kw)
    yx = one_sided_chamfer(y, x, x_weights=y_weights, **kw)
    if reduction == "none":
        return xy, yx
    return xy + yx


def sample_surface(
    verts: torch.Tensor, faces: torch.Tensor, count: int, generator: torch.Generator | None = None
) -> torch.Tensor:
    """(count, 3) points drawn uniformly by area on a triangle mesh (verts (V, 3), faces (F, 3))."""
    tri = verts[faces]  # (F, 3, 3)
    area = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
    face = torch.multinomial(area / area.sum(), count, replacement=True, generator=generator)
    u, v = torch.rand(2, count, 1, generator=generator, dtype=verts.dtype)
    flip = (u + v) > 1  # fold the unit square onto the triangle
    u, v = torch.where(flip, 1 - u, u), torch.where(flip, 1 - v, v)
    t = tri[face]
    return t[:, 0] + u * (t[:, 1] - t[:, 0]) + v * (t[:, 2] - t[:, 0])


def surface_chamfer_m(
    verts: torch.Tensor, faces: torch.Tensor, points: torch.Tensor, samples: int = 50000, seed: int = 0
) -> dict[str, float]:
    """Chamfer distance between a triangle mesh and a point cloud, measured on the surface (no gradient).

    ``points_to_mesh`` is the mean distance from each point to the closest point of the mesh surface;
    ``mesh_to_points`` the mean distance from ``samples`` area-uniform surface samples (seeded) to the
    nearest point. Neither depends on the mesh's resolution (a vertex-to-point Chamfer of a 3 cm mesh
    has a floor of about 1 cm); ``mesh_to_points`` still has the point cloud's own spacing as its floor.

    Args:
        verts: (V, 3) [m]; faces: (F, 3) int64; points: (N, 3) [m].

    Returns:
        ``{"points_to_mesh", "mesh_to_points", "symmetric"}`` [m], not squared; ``symmetric`` is the mean
        of the two.
    """
    from torch_diffavatar.geometry import closest_point_on_mesh

    v = verts.detach().double().cpu().contiguous()
    f = faces.detach().to(torch.int64).cpu().contiguous()
    p = points.detach().double().cpu().contiguous()
    extent = float((torch.cat([v, p]).amax(0) - torch.cat([v, p]).amin(0)).norm())
    _, _, dist = closest_point_on_mesh(p, v, f, 2.0 * extent + 1.0)
    gen = torch.Generator().manual_seed(seed)
    s = sample_surface(v, f, samples, generator=gen)
    d_mp = (s - p[torch.from_numpy(nearest_indices(s, p))]).norm(dim=1)
    pm, mp = float(dist.mean()), float(d_mp.mean())
    return {"points_to_mesh": pm, "mesh_to_points": mp, "symmetric": 0.5 * (pm + mp)}
