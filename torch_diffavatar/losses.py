"""Fit losses (paper §4.2.5): feature terms against the scan and regularizers of the 2D pattern.

* `boundary_loss`: the garment's labelled openings (hem, cuffs, neck, waist) vs the scan's [m²];
  `folded_collar_loop` gives a collar-covered neck's opening as the scan sees it, the collar's fold.
* `interior_loss`: Chamfer distance between the draped garment and the segmented scan garment [m²].
* `seam_length_loss`: the two sides of every seam keep equal segment lengths (eq. 7) [m⁴].
* `curvature_loss`: boundary curvature kept up to a per-vertex similarity transform (eq. 8) [m²].
* `rest_area_loss`: a barrier that keeps rest triangles from collapsing or inverting [-].

All are pure, differentiable functions in the style of pytorch3d's losses: ``reduction`` is one of
``"mean"``, ``"sum"``, ``"none"`` (checked up front) and optional per-item ``weights`` scale the items
being reduced. Nearest neighbours come from `torch_diffavatar.chamfer` (KD-tree on detached copies;
the distances are recomputed in torch, so gradients flow through the gathered points).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import torch

from torch_diffavatar.cage import seam_segments
from torch_diffavatar.chamfer import REDUCTIONS, chamfer_distance, one_sided_chamfer, robust_penalty
from torch_diffavatar.geometry import closest_point_on_mesh, gather_rows
from torch_diffavatar.pattern.garment_mesh import BoundaryLoop, GarmentMesh

# the thresholds of the rest triangles' hinges: `rest_area_loss` (area ratio) and `rest_distortion_loss`
REST_AREA_THRESHOLD = 0.5
REST_DISTORTION_THRESHOLD = 0.25


def _check_reduction(reduction: str) -> None:
    if reduction not in REDUCTIONS:
        raise ValueError(f"reduction must be one of {REDUCTIONS}, got {reduction!r}")


def _reduce(values: torch.Tensor, weights: torch.Tensor | None, reduction: str) -> torch.Tensor:
    """Reduce (…, K) item values with optional (K,) weights: weighted mean / weighted sum / as is."""
    if weights is not None:
        if weights.shape != values.shape[-1:]:
            raise ValueError(f"weights must have shape ({values.shape[-1]},), got {tuple(weights.shape)}")
        values = values * weights.to(values)
    if reduction == "none":
        return values
    if reduction == "sum":
        return values.sum(-1)
    if weights is None:
        return values.mean(-1)
    return values.sum(-1) / weights.to(values).sum().clamp_min(1e-12)


def _check_points(x: torch.Tensor, name: str, dim: int = 3) -> None:
    if not isinstance(x, torch.Tensor) or x.dim() != 2 or x.shape[-1] != dim or not x.is_floating_point():
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"{name} must be a float tensor of shape (N, {dim}), got {shape}")


def _check_rest_uv(rest_uv: torch.Tensor, garment: GarmentMesh) -> None:
    if (
        not isinstance(rest_uv, torch.Tensor)
        or rest_uv.dim() < 2
        or rest_uv.shape[-2:]
        != (
            garment.vert_count,
            2,
        )
    ):
        shape = tuple(rest_uv.shape) if isinstance(rest_uv, torch.Tensor) else type(rest_uv).__name__
        raise ValueError(
            f"rest_uv must have shape ({garment.vert_count}, 2) or (B, {garment.vert_count}, 2) "
            f"(one 2D rest coordinate per panel vertex), got {shape}"
        )


# ---------------------------------------------------------------------------------------------------------
# Feature terms


def _resample_loop(x: torch.Tensor, samples_per_edge: int) -> torch.Tensor:
    """(L, 3) closed loop -> (L·k, 3) points at fractions j/k along every loop edge."""
    if samples_per_edge == 1:
        return x
    t = torch.arange(samples_per_edge, dtype=x.dtype, device=x.device) / samples_per_edge  # (k,)
    nxt = torch.roll(x, -1, dims=0)
    return (x[:, None] + t[None, :, None] * (nxt - x)[:, None]).reshape(-1, 3)


def folded_collar_loop(
    garment_x: torch.Tensor,
    loop: BoundaryLoop,
    *,
    window_deg: float = 14.0,
    reach: float = 0.07,
    min_lift: float = 0.025,
    max_tilt_deg: float = 45.0,
) -> BoundaryLoop:
    """The top edge of a neckline whose loop is a folded collar's free edge; else ``loop`` itself.

    A scan's neck opening is the garment's top edge around the neck (`torch_diffavatar.body.segment`).
    On most garments that is the ``neck`` loop, but a folded collar (a polo's) lies over its own free
    edge, the loop, and the top edge is the fold, which no mesh edge marks (measured on the suite's
    polo: its true drape's loop lies 49 mm from the scan's neck rim, the fold 6 mm). Every loop vertex
    is lifted to the highest vertex (world +Y) within ``reach`` [m] of it and within ``window_deg`` of
    its angle about the vertical axis through the loop's centre. When the median lift exceeds
    ``min_lift`` [m] the loop is covered, and the lifted vertices (in loop order, repeats allowed) are
    the opening. Why 2.5 cm: on the suite's other tops the lift is a curved neckline's rise to a
    neighbouring loop vertex (median 0-8.5 mm, at most 24 mm); a polo's collar folds 3-6 cm above its
    free edge (median 36-45 mm).
    Only a loop around the neck is lifted: its plane (least-squares) lies within ``max_tilt_deg`` of
    horizontal (measured: 5-31 degrees on eight tops' necklines and collars). A hood's face opening, the
    ``neck`` loop of a hoody, stands upright (80-85 degrees), with the hood's crown above it.

    Args:
        garment_x: (Vs, 3) sim-vertex positions [m]; only read (the choice of vertices is not
            differentiated, as with a nearest neighbour).
        loop: the garment's neck opening.

    Returns:
        a `BoundaryLoop` of the same name on the chosen vertices.
    """
    with torch.no_grad():
        x = garment_x.detach()
        ring = x[loop.vertices.to(x.device)]  # (L, 3)
        centre = ring.mean(0)
        normal = torch.linalg.svd(ring - centre, full_matrices=False).Vh[-1]
        if float(normal[1].abs()) < math.cos(math.radians(max_tilt_deg)):
            return loop

        def angle(p):
            return torch.atan2(p[..., 0] - centre[0], p[..., 2] - centre[2])

        turn = angle(x)[None, :] - angle(ring)[:, None]  # (L, Vs)
        turn = torch.remainder(turn + math.pi, 2 * math.pi) - math.pi
        near = (turn.abs() < math.radians(window_deg)) & (torch.cdist(ring, x) < reach)
        top = (
            x[:, 1].expand_as(near).masked_fill(~near, -math.inf).argmax(1)
        )  # the loop vertex itself is always a candidate
        lift = x[top, 1] - ring[:, 1]
    if float(lift.median()) <= min_lift:
        return loop
    return BoundaryLoop(loop.name, top.to(loop.vertices))


def covered_loop_points(loop_x: torch.Tensor, scan_points: torch.Tensor, bin_length: float) -> torch.Tensor:
    """(L,) bool: the points of a garment opening ``loop_x`` (L, 3) [m] whose side of the opening the scan's
    points of it (P, 3) [m] cover.

    The loop is cut into angular sectors about its centre, in its least-squares plane, about
    ``bin_length`` [m] long at its mean radius; a sector is covered when a scan point falls in it. A scan
    opening is often a partial arc (a hole under the arm takes a cuff's underside, hands hide a hem's
    sides): pulled onto such an arc, the whole loop would shrink onto it (a fit from the true T-shirt
    narrowed its cuffs by 4 cm). Not differentiated, like a nearest neighbour. A loop of fewer than three
    points has no plane: all of it is covered.
    """
    if len(loop_x) < 3:
        return torch.ones(len(loop_x), dtype=torch.bool, device=loop_x.device)
    with torch.no_grad():
        x = loop_x.detach()
        centre = x.mean(0)
        axes = torch.linalg.svd(x - centre, full_matrices=False).Vh  # rows: in-plane, in-plane, normal
        radius = float(torch.linalg.norm((x - centre) @ axes[:2].T, dim=1).mean())
        bins = max(int(round(2 * math.pi * radius / bin_length)), 6)

        def sector(p):
            uv = (p - centre) @ axes[:2].T
            a = torch.remainder(torch.atan2(uv[:, 1], uv[:, 0]), 2 * math.pi)
            return (a / (2 * math.pi) * bins).long().clamp(max=bins - 1)

        hit = torch.zeros(bins, dtype=torch.bool, device=x.device)
        hit[sector(scan_points.to(x))] = True
        return hit[sector(x)]


def _opening_chamfer(
    garment_x: torch.Tensor,
    vertices: torch.Tensor,
    scan_points: torch.Tensor,
    seen: torch.Tensor | None,
    *,
    samples_per_edge: int,
    robust: str,
    scale: float,
    trim: float,
    gap_bin: float,
) -> torch.Tensor:
    """() `boundary_loss`'s term of one opening: the loop through ``vertices`` (L,) of ``garment_x`` vs its
    (P, 3) ``scan_points``, both directions trimmed; with ``seen`` the garment → scan direction only from
    the seen loop points (a resampled point between two loop vertices is seen when both are); with
    ``gap_bin`` > 0 only from the loop points that the scan's points cover (`covered_loop_points`)."""
    ids = vertices.to(garment_x.device)
    x = _resample_loop(garment_x[ids], samples_per_edge)
    y = scan_points.to(garment_x)
    xy, yx = chamfer_distance(x, y, robust=robust, scale=scale, reduction="none")
    value = _trimmed_mean(yx[0], trim)
    on = torch.ones(len(x), dtype=torch.bool, device=x.device)
    if seen is not None:
        on &= _resample_loop(seen[ids].to(garment_x)[:, None].expand(-1, 3), samples_per_edge)[:, 0] > 0.999
    if gap_bin > 0:
        on &= covered_loop_points(x, y, gap_bin)
    return value + _trimmed_mean(xy[0][on], trim) if bool(on.any()) else value


def boundary_loss(
    garment_x: torch.Tensor,
    loops: Sequence[BoundaryLoop],
    scan_boundaries: Mapping[str, torch.Tensor],
    *,
    samples_per_edge: int = 1,
    weights: torch.Tensor | None = None,
    reduction: str = "mean",
    robust: str = "l2",
    scale: float = 0.01,
    trim: float = 0.0,
    seen: torch.Tensor | None = None,
    gap_bin: float = 0.0,
) -> torch.Tensor:
    """Boundary feature matching: each named garment opening vs the scan's opening of the same name.

    For every loop whose name is a key of ``scan_boundaries`` (``"neck"``, ``"hem"``, ``"cuff_left"``,
    ``"waist"`` …), the symmetric Chamfer distance (mean squared nearest-neighbour distance garment →
    scan plus scan → garment) between the loop's points and the scan boundary points. Loops without a
    scan counterpart (and scan boundaries without a garment loop) are skipped.

    Args:
        garment_x: (Vs, 3) sim-vertex positions [m] (e.g. the drape).
        loops: the garment's openings (``GarmentMesh.boundary_loops``), on sim vertices.
        scan_boundaries: opening name -> (P, 3) scan boundary points [m], P >= 1.
        samples_per_edge: k >= 1 points per loop edge at fractions 0, 1/k, … (1 = the loop vertices
            only); more samples make the garment side denser than its vertex spacing.
        weights: optional (len(loops),) per-loop weights, aligned with ``loops``.
        reduction: ``"mean"`` (weighted mean over matched loops), ``"sum"`` or ``"none"`` ((K,) one value
            per matched loop, in the order of ``loops``).
        robust, scale: penalty kernel of the point distances and its scale [m]
            (`torch_diffavatar.chamfer.robust_penalty`; ``"l2"``: squared distances). Scan openings are
            broken where holes cut them and pick up the rims of those holes, so a kernel with linear tails
            (``"huber"``) keeps those points from dominating.
        trim: fraction in [0, 1) of the largest point penalties dropped in each direction of each loop
            (a trimmed mean, as in trimmed ICP): the stray hole-rim points of a scan opening and the
            garment points facing a gap in it are left out while the rest keep their full pull.
        seen: optional (Vs,) 0/1 per sim vertex (`seen_side_weights`): the garment → scan direction uses
            only the loop points on the sides a partial scan sees (a loop with none seen keeps the scan →
            garment direction alone), so the half of a hem the scan never saw is not pulled onto the half
            it did.
        gap_bin: > 0: the garment → scan direction only from the loop points on the sectors (about this
            long [m]) that the scan's opening covers (`covered_loop_points`): a scan opening broken by a
            hole or an unseen side does not pull the whole loop onto what is left of it. 0: off.

    Returns:
        scalar, or (K,) for ``"none"`` [m²].

    Raises:
        ValueError: bad shapes, or no loop name occurs in ``scan_boundaries`` (a likely naming mismatch).
    """
    _check_reduction(reduction)
    _check_points(garment_x, "garment_x")
    if not 0.0 <= trim < 1.0:
        raise ValueError(f"trim must be in [0, 1), got {trim}")
    if not (isinstance(samples_per_edge, int) and samples_per_edge >= 1):
        raise ValueError(f"samples_per_edge must be an integer >= 1, got {samples_per_edge!r}")
    for name, pts in scan_boundaries.items():
        _check_points(pts, f"scan_boundaries[{name!r}]")
    matched = [k for k, loop in enumerate(loops) if loop.name in scan_boundaries]
    if not matched:
        raise ValueError(
            f"no garment opening matches a scan boundary: garment has {[lp.name for lp in loops]}, "
            f"scan has {sorted(scan_boundaries)}"
        )
    if not (math.isfinite(gap_bin) and gap_bin >= 0):
        raise ValueError(f"gap_bin must be a finite length >= 0, got {gap_bin}")
    kw = dict(samples_per_edge=samples_per_edge, robust=robust, scale=scale, trim=trim, gap_bin=gap_bin)
    values = [
        _opening_chamfer(garment_x, loops[k].vertices, scan_boundaries[loops[k].name], seen, **kw)
        for k in matched
    ]
    values = torch.stack(values)  # (K,)
    if weights is not None:
        if weights.shape != (len(loops),):
            raise ValueError(
                f"weights must have shape ({len(loops)},) (one per loop), got {tuple(weights.shape)}"
            )
        weights = weights[torch.as_tensor(matched, device=weights.device)]
    return _reduce(values, weights, reduction)


def interior_loss(
    garment_x: torch.Tensor,
    scan_points: torch.Tensor,
    *,
    two_sided: bool = True,
    robust: str | None = None,
    scale: float = 0.01,
    weights: torch.Tensor | None = None,
    reduction: str = "mean",
    garment_faces: torch.Tensor | None = None,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Interior feature matching: Chamfer distance between the garment and the segmented scan garment.

    Nearest neighbours come from a KD-tree (`torch_diffavatar.chamfer`); the distances are recomputed
    in torch from the gathered points, so gradients flow to ``garment_x`` (and to ``scan_points`` if it
    requires grad), never through the neighbour assignment.

    Args:
        garment_x: (Vs, 3) sim-vertex positions [m].
        scan_points: (P, 3) points of the scan's garment segment [m].
        two_sided: add the scan → garment direction (catches garment parts missing from the scan fit);
            False gives garment → scan only.
        robust: None or ``"l2"`` (squared distances), ``"geman_mcclure"`` or ``"huber"`` (see
            `torch_diffavatar.chamfer.robust_penalty`) to damp scan outliers.
        scale: robust kernel scale [m].
        weights: optional (Vs,) per-garment-vertex weights (garment → scan direction).
        reduction: ``"mean"`` (sum over directions of the (weighted) mean over points), ``"sum"`` (sum
            over directions and points) or ``"none"`` (per-point penalties: (Vs,), or the tuple
            ``((Vs,), (P,))`` when two-sided).
        garment_faces: optional (F, 3) int64 triangles of ``garment_x``. With them the scan → garment
            direction is the distance to the garment's *surface* (closest point on a triangle, found
            without autograd, then rebuilt from its barycentrics so gradients reach the triangle's
            vertices) instead of to its nearest vertex, whose distance never falls below about half the
            mesh spacing even when the drape lies exactly on the scan.

    Returns:
        scalar [m²] (or per-point penalties for ``"none"``).
    """
    _check_reduction(reduction)
    _check_points(garment_x, "garment_x")
    _check_points(scan_points, "scan_points")
    if weights is not None and weights.shape != garment_x.shape[:1]:
        raise ValueError(f"weights must have shape ({garment_x.shape[0]},), got {tuple(weights.shape)}")
    kw = dict(robust="l2" if robust is None else robust, scale=scale, reduction=reduction)
    y = scan_points.to(garment_x)
    if two_sided and garment_faces is not None:
        xy = one_sided_chamfer(garment_x, y, x_weights=weights, **kw)
        yx = _point_to_surface(y, garment_x, garment_faces, kw["robust"], scale, reduction)
        return (xy[0], yx) if reduction == "none" else xy + yx
    if two_sided:
        out = chamfer_distance(garment_x, y, x_weights=weights, **kw)
        return (out[0][0], out[1][0]) if reduction == "none" else out
    out = one_sided_chamfer(garment_x, y, x_weights=weights, **kw)
    return out[0] if reduction == "none" else out


def seen_side_weights(x: torch.Tensor, faces: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
    """(Vs,) 1 for the garment vertices whose surface faces a side of the person the scan sees, else 0.

    A vertex's side is `scan_intake.side_sector` of its area-weighted normal (`body.geometry.
    vertex_normals`), the sectors of `scan_intake.coverage`'s ``seen``; a vertex whose normal is within 45°
    of vertical (a shoulder top) counts as seen. Without gradient: the weights only choose which garment
    points the garment → scan direction of `interior_loss` asks to find a scan point near them, so that a
    partial scan does not pull the cloth it never saw toward the points it did.

    Args:
        x: (Vs, 3) garment vertices [m]; faces: (F, 3) int64; seen: (S,) bool.
    """
    from torch_diffavatar.body.geometry import vertex_normals
    from torch_diffavatar.scan_intake import side_sector

    with torch.no_grad():
        side = side_sector(vertex_normals(x, faces).cpu().numpy(), seen.numel())
        side = torch.from_numpy(side).to(x.device)
        return (seen.to(x.device)[side.clamp(min=0)] | (side < 0)).to(x.dtype)


def skin_loss(
    body_verts: torch.Tensor,
    body_faces: torch.Tensor,
    skin_points: torch.Tensor,
    *,
    robust: str | None = None,
    scale: float = 0.01,
) -> torch.Tensor:
    """Body anchoring: mean penalized distance of the scan's skin points to the body's surface.

    The cloth terms reach the body only through the contacts, and they would rather move the body than
    the pattern (lifting the body lifts a hem that hangs too low): without a data term of its own the
    body drifted 1.6 cm up and 2 cm sideways in a T-shirt fit whose initial body fit was 0.3 cm off.

    Args:
        body_verts: (Vb, 3) body vertices [m] (differentiable).
        body_faces: (Fb, 3) int64 body triangles.
        skin_points: (Q, 3) scan points not labelled garment [m], Q >= 1.
        robust, scale: as `interior_loss` (segmentation errors put some cloth points among the skin).

    Returns:
        scalar [m²].
    """
    _check_points(body_verts, "body_verts")
    _check_points(skin_points, "skin_points")
    y = skin_points.to(body_verts)
    return _point_to_surface(y, body_verts, body_faces, "l2" if robust is None else robust, scale, "mean")


# ---------------------------------------------------------------------------------------------------------
# Pattern regularizers


def _trimmed_mean(values: torch.Tensor, trim: float) -> torch.Tensor:
    """Mean of (N,) ``values`` without the ``floor(trim·N)`` largest ones (at least one is kept)."""
    keep = max(values.shape[0] - int(trim * values.shape[0]), 1)
    if keep == values.shape[0]:
        return values.mean()
    return torch.topk(values, keep, largest=False, sorted=False).values.mean()


def _point_to_surface(
    points: torch.Tensor, verts: torch.Tensor, faces: torch.Tensor, robust: str, scale: float, reduction: str
) -> torch.Tensor:
    """Penalized distance of every point (P, 3) to the surface of the mesh (verts (V, 3), faces (F, 3)).

    The closest triangle and barycentrics come from `geometry.closest_point_on_mesh` on detached copies; the
    closest point is rebuilt as Σ bᵢ·verts[fᵢ], so the gradient is the point-to-plane one inside a
    triangle and the point-to-edge/vertex one on its border (the assignment itself is not
    differentiated, as for nearest neighbours). Returns a scalar [m²], or (P,) for ``"none"``.
    """
    if faces.dim() != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise ValueError(f"garment_faces must have shape (F, 3) with F >= 1, got {tuple(faces.shape)}")
    faces = faces.to(device=verts.device, dtype=torch.int64)
    with torch.no_grad():
        tri, bary, _ = closest_point_on_mesh(
            points.detach().contiguous(), verts.detach().contiguous(), faces.contiguous(), float("inf")
        )
    corners = verts[faces[tri]]  # (P, 3 corners, 3)
    closest = (bary.to(verts)[..., None] * corners).sum(1)
    pen = robust_penalty(((points - closest) ** 2).sum(-1), robust, scale)
    if reduction == "none":
        return pen
    return pen.sum() if reduction == "sum" else pen.mean()


def seam_length_loss(
    rest_uv: torch.Tensor,
    garment: GarmentMesh,
    *,
    segments: torch.Tensor | None = None,
    weights: torch.Tensor | None = None,
    reduction: str = "mean",
) -> torch.Tensor:
    """Seam-length regularizer (paper eq. 7): sewn segments keep equal lengths on both sides.

    For every seam joining edge A (points ``p_i``) and edge B (points ``p'_i``, aligned so ``p_i`` is
    sewn to ``p'_i``) the paper sums ``‖p_i − p_{i+1}‖² − ‖p'_i − p'_{i+1}‖²`` over the segments; that
    sum can be negative and lets long and short segments cancel, so here each segment's difference is
    **squared**: ``(‖p_i − p_{i+1}‖² − ‖p'_i − p'_{i+1}‖²)²`` >= 0, zero iff every sewn segment pair has
    equal length. Darts count as seams.

    Args:
        rest_uv: (V, 2) or (B, V, 2) rest coordinates [m] of the panel vertices.
        garment: the garment the coordinates belong to (its seams are read with `stitched_edges`).
        segments: optional (K, 4) int64 ``(a_i, a_{i+1}, b_i, b_{i+1})`` from
            `torch_diffavatar.cage.seam_segments` (computed from ``garment`` when None; pass it to skip
            that work in a loop).
        weights: optional (K,) per-segment weights.
        reduction: ``"mean"`` / ``"sum"`` over segments, or ``"none"`` → (…, K) per segment.

    Returns:
        () or (B,) [m⁴] (or (…, K) for ``"none"``); zero when the garment has no seams.
    """
    _check_reduction(reduction)
    _check_rest_uv(rest_uv, garment)
    seg = seam_segments(garment) if segments is None else segments
    if seg.dim() != 2 or seg.shape[-1] != 4:
        raise ValueError(f"segments must have shape (K, 4), got {tuple(seg.shape)}")
    seg = seg.to(rest_uv.device)
    if len(seg) == 0:
        return (
            rest_uv.sum((-2, -1)) * 0.0 if reduction != "none" else rest_uv.new_zeros(*rest_uv.shape[:-2], 0)
        )
    p = gather_rows(rest_uv, seg)  # (…, K, 4, 2)
    len_a = ((p[..., 1, :] - p[..., 0, :]) ** 2).sum(-1)
    len_b = ((p[..., 3, :] - p[..., 2, :]) ** 2).sum(-1)
    return _reduce((len_a - len_b) ** 2, weights, reduction)


def boundary_triplets(garment: GarmentMesh) -> torch.Tensor:
    """(Nb, 3) int64 ``(previous, vertex, next)`` panel vertices around every panel's boundary loop."""
    parts = [
        torch.stack([torch.roll(b, 1), b, torch.roll(b, -1)], dim=1)
        for b in garment.panel_boundary
        if len(b) >= 3
    ]
    return torch.cat(parts) if parts else torch.zeros(0, 3, dtype=torch.int64)


class CurvatureFrames(NamedTuple):
    """`curvature_frames`: ``triplets`` (Nb, 3) int64 (`boundary_triplets`); the template's two edges at
    each boundary vertex ``edges`` (Nb, 2, 2) [m], the same turned by 90° ``edges_perp`` (Nb, 2, 2) [m], and
    their summed squared lengths ``norm`` (Nb,) [m²]."""

    triplets: torch.Tensor
    edges: torch.Tensor
    edges_perp: torch.Tensor
    norm: torch.Tensor


def curvature_frames(template_uv: torch.Tensor, garment: GarmentMesh) -> CurvatureFrames:
    """The template's side of `curvature_loss`, which does not change during a fit: computed once by a caller
    that evaluates the term many times (a fit's proximal step, ~60 times an iteration).
    ``template_uv``: (V, 2) template rest coordinates [m]."""
    tri = boundary_triplets(garment).to(template_uv.device)
    q = template_uv[tri]  # (Nb, 3, 2)
    t = torch.stack([q[..., 2, :] - q[..., 1, :], q[..., 0, :] - q[..., 1, :]], dim=-2)  # (Nb, 2, 2)
    t_perp = torch.stack([-t[..., 1], t[..., 0]], dim=-1)
    norm = (t**2).sum((-2, -1)).clamp_min(torch.finfo(t.dtype).tiny)  # (Nb,)
    return CurvatureFrames(tri, t, t_perp, norm)


def curvature_loss(
    rest_uv: torch.Tensor,
    template_uv: torch.Tensor,
    garment: GarmentMesh,
    *,
    weights: torch.Tensor | None = None,
    reduction: str = "mean",
    frames: CurvatureFrames | None = None,
) -> torch.Tensor:
    """Boundary curvature regularizer (paper eq. 8): the outline keeps its template shape locally.

    At every boundary vertex ``i`` of every panel (its loop from ``garment.panel_boundary``), with the
    edges ``e_i1 = p_{i+1} − p_i`` and ``e_i2 = p_{i−1} − p_i`` (``ē`` the same on the template), the best
    similarity ``T_i = s_i R_i`` (rotation and uniform scale, no reflection) mapping the template edges
    to the current ones in the least-squares sense, ``min_T Σ_k ‖e_ik − T ē_ik‖²``, has the closed form
    ``T = [[a, −b], [b, a]]`` with ``a = Σ_k e_k·ē_k / Σ_k ‖ē_k‖²`` and ``b = Σ_k e_k·ē_k^⊥ / Σ_k ‖ē_k‖²``
    (``ē^⊥ = (−ē_y, ē_x)``; this is 2D Procrustes with scale). The loss per vertex is
    ``w_i ‖(e_i1 − T_i ē_i1) + (e_i2 − T_i ē_i2)‖²``: the discrete Laplacian ``e_i1 + e_i2`` must be the
    template's up to a local rotation and scale. Zero at the template and under any similarity transform
    of a whole panel; rigid motions of a panel leave it unchanged and a uniform scale ``s`` scales it by
    ``s²``.

    Args:
        rest_uv: (V, 2) or (B, V, 2) current rest coordinates [m].
        template_uv: (V, 2) template rest coordinates [m] (e.g. ``garment.vert_uv``).
        garment: the garment (for its panel boundary loops).
        weights: optional (Nb,) per-boundary-vertex weights ``w_i`` (default 1), in the order of
            `boundary_triplets` (panels in order, each loop in order).
        reduction: ``"mean"`` / ``"sum"`` over boundary vertices, or ``"none"`` → (…, Nb).
        frames: `curvature_frames` of ``template_uv`` and ``garment``, when already computed.

    Returns:
        () or (B,) [m²] (or (…, Nb) for ``"none"``).
    """
    _check_reduction(reduction)
    _check_rest_uv(rest_uv, garment)
    if template_uv.shape != (garment.vert_count, 2):
        raise ValueError(
            f"template_uv must have shape ({garment.vert_count}, 2), got {tuple(template_uv.shape)}"
        )
    if frames is None:
        frames = curvature_frames(template_uv.to(rest_uv), garment)
    tri, t, t_perp, norm = (f.to(rest_uv.device) for f in frames)
    t, t_perp, norm = t.to(rest_uv.dtype), t_perp.to(rest_uv.dtype), norm.to(rest_uv.dtype)
    p = gather_rows(rest_uv, tri)  # (…, Nb, 3, 2)
    e = torch.stack([p[..., 2, :] - p[..., 1, :], p[..., 0, :] - p[..., 1, :]], dim=-2)  # (…, Nb, 2, 2)
    a = (e * t).sum((-2, -1)) / norm  # (…, Nb)
    b = (e * t_perp).sum((-2, -1)) / norm
    fitted = a[..., None, None] * t + b[..., None, None] * t_perp  # T ē_k, (…, Nb, 2, 2)
    residual = (e - fitted).sum(-2)  # (…, Nb, 2)
    return _reduce((residual**2).sum(-1), weights, reduction)


def rest_area_loss(
    rest_uv: torch.Tensor,
    template_uv: torch.Tensor,
    tri_vertices: torch.Tensor,
    *,
    threshold: float = REST_AREA_THRESHOLD,
    reduction: str = "sum",
    template_area: torch.Tensor | None = None,
) -> torch.Tensor:
    """Keeps rest triangles from collapsing: ``Σ_f relu(threshold − A_f / Ā_f)²``.

    ``A_f`` is the signed area of rest triangle ``f`` and ``Ā_f`` its template area, so the term is 0
    while every triangle keeps more than ``threshold`` of its area and grows smoothly as one shrinks
    towards inversion (ratio ≤ 0). Handles of a control cage that pass each other would otherwise fold
    the pattern; a hard rejection of such steps stalls the fit instead.

    Args:
        rest_uv: (V, 2) or (B, V, 2) rest coordinates [m]; template_uv: (V, 2) [m];
        tri_vertices: (F, 3) int64 panel-vertex triangles (counter-clockwise or clockwise: the sign of
            the template's area is divided out).
        threshold: area ratio below which the penalty starts [-].
        reduction: ``"sum"`` / ``"mean"`` over triangles, or ``"none"`` → (…, F).
        template_area: optional (F,) `signed_rest_areas` of the template, computed once by a caller that
            evaluates the term many times (a fit's proximal step).

    Returns:
        () or (B,) dimensionless (or (…, F) for ``"none"``).
    """
    _check_reduction(reduction)
    if not 0.0 < threshold <= 1.0:
        raise ValueError(f"threshold must be in (0, 1], got {threshold}")
    if template_area is None:
        template_area = signed_rest_areas(template_uv.to(rest_uv), tri_vertices)

    def penalty(tri, area):
        return torch.relu(threshold - signed_rest_areas(rest_uv, tri) / area.to(rest_uv)) ** 2

    return _hinge_sum(penalty, tri_vertices, template_area, rest_uv, reduction)


def design_modes(template_uv: torch.Tensor, vert_panel: torch.Tensor) -> torch.Tensor:
    """(V, 4) per panel, an orthonormal basis (over that panel's vertices) of the displacement fields a
    design change makes, evaluated at each vertex: constant, linear in u and in v, and u·v.

    Applied to either coordinate of the displacement, these span a panel moved, scaled in width or length,
    sheared, and flared (its width changing linearly along its length): what GarmentCode's design
    parameters (length, width, flare) and `pattern.design.changed_pattern` do. A neckline dug deeper or an
    armhole reshaped is outside it. ``template_uv``: (V, 2) [m]; ``vert_panel``: (V,) int64.
    """
    modes = torch.zeros(len(template_uv), 4, dtype=template_uv.dtype, device=template_uv.device)
    for panel in torch.unique(vert_panel):
        rows = vert_panel == panel
        uv = template_uv[rows]
        uv = (uv - uv.mean(0)) / (uv - uv.mean(0)).abs().max().clamp(min=1e-12)  # conditioned basis
        basis = torch.stack([torch.ones_like(uv[:, 0]), uv[:, 0], uv[:, 1], uv[:, 0] * uv[:, 1]], dim=1)
        modes[rows] = torch.linalg.qr(basis).Q
    return modes


def pattern_change_loss(
    rest_uv: torch.Tensor,
    template_uv: torch.Tensor,
    vert_panel: torch.Tensor,
    *,
    modes: torch.Tensor | None = None,
    scale: float = 1.0e-3,
) -> torch.Tensor:
    """How far the pattern has moved from the template outside the design changes, as a robust (L1-like)
    distance [m].

    Per panel, the rest coordinates' displacement from the template less its projection on the panel's
    ``modes`` (`design_modes`: moves, scales, shears and flares are free); the term is the mean over
    vertices of the Charbonnier distance ``sqrt(|r|² + scale²) − scale`` of that remainder. Its gradient
    has a bounded size: a weight on it sets how strong the scan's evidence must be before the fit reshapes
    the panel, not how far it may go once the evidence is there (a quadratic prior would hold a true
    change back harder the larger it is).

    Args:
        rest_uv: (V, 2) or (B, V, 2) rest coordinates [m]; template_uv: (V, 2) [m].
        vert_panel: (V,) int64 panel index of each vertex.
        modes: (V, K) per-panel orthonormal displacement modes left free (default: `design_modes`;
            computed once by a caller that evaluates the term many times).
        scale: below this remainder [m] the term is quadratic (smooth at the template).

    Returns:
        () or (B,) [m].
    """
    if not scale > 0:
        raise ValueError(f"scale must be > 0 [m], got {scale}")
    modes = design_modes(template_uv, vert_panel) if modes is None else modes
    delta = rest_uv - template_uv
    panels = int(vert_panel.max()) + 1
    per_vertex = modes[:, :, None] * delta[..., :, None, :]  # (..., V, K, 2)
    coef = delta.new_zeros(*delta.shape[:-2], panels, *per_vertex.shape[-2:])
    coef = coef.index_add(-3, vert_panel, per_vertex)  # (..., P, K, 2): projection on each panel's modes
    remainder = delta - (modes[:, :, None] * coef.index_select(-3, vert_panel)).sum(-2)
    return (torch.sqrt((remainder**2).sum(-1) + scale**2) - scale).mean(-1)


def rest_distortion_loss(
    rest_uv: torch.Tensor,
    template_uv: torch.Tensor,
    tri_vertices: torch.Tensor,
    *,
    threshold: float = REST_DISTORTION_THRESHOLD,
    reduction: str = "sum",
    template_inverse: torch.Tensor | None = None,
) -> torch.Tensor:
    """Keeps rest triangles from turning into slivers: ``Σ_f relu(c_f − threshold)²``.

    ``c_f = ‖J_f‖²_F / (2 |det J_f|) − 1`` is the conformal distortion of the 2D map ``J_f`` from the
    template triangle to the rest triangle: 0 for a similarity (any scale and rotation), ``(r + 1/r)/2 − 1``
    for singular values in ratio ``r`` (0.25 at r = 2). `rest_area_loss` keeps areas; this keeps shapes:
    cage handles a few cm apart on a curved neckline, moved by a few mm each step, sheared the dress's
    rest triangles beside it to quality 0.23 (from 0.63) with every area intact.

    Args:
        rest_uv: (V, 2) or (B, V, 2) rest coordinates [m]; template_uv: (V, 2) [m];
        tri_vertices: (F, 3) int64 panel-vertex triangles.
        threshold: distortion below which the penalty is 0 [-].
        reduction: ``"sum"`` / ``"mean"`` over triangles, or ``"none"`` → (…, F).
        template_inverse: optional (F, 2, 2) `template_edge_inverse`, computed once by a caller that
            evaluates the term many times (a fit's proximal step).

    Returns:
        () or (B,) dimensionless (or (…, F) for ``"none"``).
    """
    _check_reduction(reduction)
    if not threshold >= 0.0:
        raise ValueError(f"threshold must be >= 0, got {threshold}")
    if template_inverse is None:
        template_inverse = template_edge_inverse(template_uv.to(rest_uv), tri_vertices)

    def penalty(tri, inverse):
        p = gather_rows(rest_uv, tri)  # (…, F, 3, 2)
        e = torch.stack([p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :]], dim=-1)  # columns
        jac = e @ inverse.to(rest_uv)  # (…, F, 2, 2)
        det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
        # a collapsing triangle is `rest_area_loss`'s (and the step guard's); keep this one finite there
        distortion = (jac**2).sum((-2, -1)) / (2.0 * det.abs().clamp_min(1e-3)) - 1.0
        return torch.relu(distortion - threshold) ** 2

    return _hinge_sum(penalty, tri_vertices, template_inverse, rest_uv, reduction)


def _hinge_sum(penalty, tri_vertices, per_tri, rest_uv, reduction) -> torch.Tensor:
    """`_reduce` of ``penalty(tri_vertices, per_tri)`` (…, F), a hinge that is 0 for most triangles: for a
    sum, evaluated with autograd only on the triangles where it is positive (any batch element), the rest
    found without a graph (a NaN counts as live, so it reaches the sum). The same value and gradient (a
    zero gets none), at about two thirds of the cost in a fit's proximal step, where these terms are
    evaluated ~60 times an iteration and mostly vanish."""
    if reduction != "sum" or not rest_uv.requires_grad or not torch.is_grad_enabled():
        return _reduce(penalty(tri_vertices, per_tri), None, reduction)
    with torch.no_grad():
        live = ~penalty(tri_vertices, per_tri).reshape(-1, tri_vertices.shape[0]).le(0).all(0)
    keep = torch.nonzero(live).squeeze(1)
    return penalty(tri_vertices[keep], per_tri[keep]).sum(-1)


def template_edge_inverse(template_uv: torch.Tensor, tri_vertices: torch.Tensor) -> torch.Tensor:
    """(F, 2, 2) inverse of each template triangle's edge matrix (columns: edges from corner 0) [1/m]."""
    q = template_uv[tri_vertices]  # (F, 3, 2)
    return torch.linalg.inv(torch.stack([q[..., 1, :] - q[..., 0, :], q[..., 2, :] - q[..., 0, :]], dim=-1))


def dart_triangles(garment: GarmentMesh, min_area: float = 1e-10) -> torch.Tensor:
    """(D, 3) int64 panel-vertex triangles across the garment's darts: for each stitch pair (a, b) of one
    panel's dart legs, (a, tip, b), the tip the outline vertex halfway between them. A dart is recognised
    on the outline alone: every vertex between a and b the short way round is sewn within the panel but
    the tip (a panel sewn to itself across its middle, a tube, gives none). Triangles of template area
    below ``min_area`` [m²] (at the tip) are left out.

    Why: `rest_area_loss` on these keeps a dart from closing past zero. Fitted dresses had inverted their
    bodice darts, the legs passing each other, and the exported pattern then crossed itself: 6 of about
    30 dress fits of Newton-made and our scans (docs/BENCHMARKS.md, "Darts that cross")."""
    panel = garment.vert_panel.cpu()
    pairs = garment.stitch_pairs.cpu()
    inside = pairs[(panel[pairs[:, 0]] == panel[pairs[:, 1]]) & (pairs[:, 0] != pairs[:, 1])]
    sewn = set(inside.flatten().tolist())
    tris = []
    for a, b in inside.tolist():
        ring = garment.panel_boundary[int(panel[a])].tolist()
        if a not in ring or b not in ring:
            continue
        ia, ib, n = ring.index(a), ring.index(b), len(ring)
        forward = (ib - ia) % n
        step, count = (1, forward) if forward <= n - forward else (-1, n - forward)
        if count < 2 or count % 2:
            continue
        between = [ring[(ia + step * k) % n] for k in range(1, count)]
        tip = between[len(between) // 2]
        if all(v in sewn for v in between if v != tip):
            tris.append((a, tip, b))
    tri = torch.tensor(tris, dtype=torch.int64).reshape(-1, 3)
    if len(tri):
        tri = tri[signed_rest_areas(garment.vert_uv.double().cpu(), tri).abs() > min_area]
    return tri


def signed_rest_areas(rest_uv: torch.Tensor, tri_vertices: torch.Tensor) -> torch.Tensor:
    """(…, F) signed areas [m²] of the rest triangles in their panel frames ((…, V, 2) coords, (F, 3) ids)."""
    p = gather_rows(rest_uv, tri_vertices)  # (…, F, 3, 2)
    e1, e2 = p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :]
    return 0.5 * (e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0])


def rest_area_ratio(
    rest_uv: torch.Tensor,
    template_uv: torch.Tensor,
    tri_vertices: torch.Tensor,
    *,
    template_area: torch.Tensor | None = None,
) -> torch.Tensor:
    """(…, F) signed rest area over the template's (1 = unchanged, <= 0 = inverted or collapsed);
    ``template_area``: the template's `signed_rest_areas` when already computed."""
    if template_area is None:
        template_area = signed_rest_areas(template_uv.to(rest_uv), tri_vertices)
    return signed_rest_areas(rest_uv, tri_vertices) / template_area.to(rest_uv)
