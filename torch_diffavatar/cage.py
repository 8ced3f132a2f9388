"""The pattern control cage (paper §4.2.2): a few handles per panel drive every rest coordinate.

Per panel, handles are picked automatically from the panel's boundary loop (`select_handles`): the
vertices on the convex hull of the outline plus those where the outline turns by more than a threshold
(10° by default). The handles, in boundary order, form the panel's *cage polygon*. Every panel vertex
``x`` gets mean value coordinates ``W(x)`` with respect to its panel's cage (`mean_value_coordinates`,
Hormann & Floater 2006), so the rest shape is the linear map ``rest_uv = W · ζ`` of the handle
positions ``ζ``, and ``W · ζ₀`` reproduces the template (``ζ₀`` = the handles' template positions).

`stitched_edges` recovers which pattern edges a `GarmentMesh`'s seams join (from ``stitch_pairs`` and
``edge_vertices``); the cage uses it to tie seams and `torch_diffavatar.losses` for the seam-length term.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from torch_diffavatar.pattern.garment_mesh import GarmentMesh

MIRROR = (-1.0, 1.0)  # the mirror map of tied left/right panels acts on panel coordinates as diag(-1, 1)


# ---------------------------------------------------------------------------------------------------------
# Pure functions


def select_handles(boundary_uv: np.ndarray, turning_angle_deg: float = 10.0, tol: float = 1e-9) -> np.ndarray:
    """Indices of the handle vertices of one closed panel outline.

    A boundary vertex is a handle if it is a corner of the outline's convex hull (strictly: collinear
    hull points are not corners) or if the outline turns there by more than ``turning_angle_deg``
    (the absolute angle between the incoming and the outgoing boundary edge).

    Args:
        boundary_uv: (L, 2) outline vertices [m] in loop order (either orientation), L >= 3.
        turning_angle_deg: turning-angle threshold [deg], in [0, 180).
        tol: relative tolerance of the collinearity test (fraction of the squared outline size).

    Returns:
        (h,) int64 increasing indices into ``boundary_uv`` (h >= 3 for a non-degenerate outline).
    """
    p = np.asarray(boundary_uv, dtype=np.float64)
    n = len(p)
    e_in = p - np.roll(p, 1, axis=0)
    e_out = np.roll(p, -1, axis=0) - p
    cross = e_in[:, 0] * e_out[:, 1] - e_in[:, 1] * e_out[:, 0]
    dot = (e_in * e_out).sum(axis=1)
    turning = np.degrees(np.abs(np.arctan2(cross, dot)))
    is_handle = turning > turning_angle_deg
    is_handle[_convex_hull_corners(p, tol)] = True
    if is_handle.sum() < 3:  # a degenerate outline: fall back to the three most turning vertices
        is_handle[np.argsort(-turning, kind="stable")[: min(3, n)]] = True
    return np.flatnonzero(is_handle).astype(np.int64)


def _convex_hull_corners(p: np.ndarray, tol: float) -> np.ndarray:
    """Indices of the strict corners of the convex hull of points (n, 2) (Andrew's monotone chain)."""
    scale = max(float(np.ptp(p, axis=0).max()) ** 2, 1e-300)
    eps = tol * scale
    order = np.lexsort((p[:, 1], p[:, 0]))

    def chain(idx):
        out: list[int] = []
        for i in idx:
            while len(out) >= 2:
                o, a = p[out[-2]], p[out[-1]]
                b = p[i]
                if (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]) <= eps:
                    out.pop()
                else:
                    break
            out.append(int(i))
        return out

    lower, upper = chain(order), chain(order[::-1])
    return np.unique(np.asarray(lower[:-1] + upper[:-1], dtype=np.int64))


def mean_value_coordinates(points: torch.Tensor, cage: torch.Tensor, tol: float = 1e-10) -> torch.Tensor:
    """Mean value coordinates of points w.r.t. a closed, possibly non-convex polygon.

    Hormann & Floater 2006, "Mean value coordinates for arbitrary planar polygons": with
    ``d_i = v_i − x``, ``r_i = |d_i|`` and ``α_i`` the signed angle from ``d_i`` to ``d_{i+1}``,
    ``w_i = (tan(α_{i−1}/2) + tan(α_i/2)) / r_i`` and ``W = w / Σ w``. Defined for every point of
    the plane (inside or outside the polygon); the coordinates reproduce linear functions:
    ``W @ cage == points``. Points on the polygon are handled explicitly (not as limits): a point at a
    vertex gets the one-hot row, a point on an edge the linear interpolation between its two ends.
    ``tan(α/2)`` is evaluated as ``A / (r_i r_{i+1} + D)`` when ``D >= 0`` and as
    ``(r_i r_{i+1} − D) / A`` when ``D < 0`` (``A`` = cross, ``D`` = dot of ``d_i, d_{i+1}``), which
    avoids cancellation on both sides.

    Args:
        points: (N, 2) query points [m].
        cage: (H, 2) polygon vertices [m] in loop order (either orientation), H >= 3.
        tol: relative tolerance: ``r_i <= tol · size`` is "at vertex i", ``|sin α_i| <= tol`` with
            ``D_i < 0`` is "on edge i".

    Returns:
        (N, H) coordinates (rows sum to 1), dtype/device of ``points``.
    """
    if points.dim() != 2 or points.shape[-1] != 2 or cage.dim() != 2 or cage.shape[-1] != 2:
        raise ValueError(
            f"points must be (N, 2) and cage (H, 2), got {tuple(points.shape)} and {tuple(cage.shape)}"
        )
    if cage.shape[0] < 3:
        raise ValueError(f"the cage needs at least 3 vertices, got {cage.shape[0]}")
    size = (cage.max(0).values - cage.min(0).values).max()
    d = cage[None, :, :] - points[:, None, :]  # (N, H, 2)
    dn = torch.roll(d, -1, dims=1)  # d_{i+1}
    r = torch.linalg.vector_norm(d, dim=-1)  # (N, H)
    rn = torch.roll(r, -1, dims=1)
    A = d[..., 0] * dn[..., 1] - d[..., 1] * dn[..., 0]
    D = (d * dn).sum(-1)
    rr = r * rn
    at_vertex = r <= tol * size  # (N, H)
    on_edge = (A.abs() <= tol * rr) & (D < 0) & ~at_vertex & ~torch.roll(at_vertex, -1, dims=1)
    special = at_vertex.any(1) | on_edge.any(1)  # (N,)

    safe_a = torch.where(A == 0, torch.ones_like(A), A)
    tan_half = torch.where(D >= 0, A / (rr + D).clamp_min(torch.finfo(rr.dtype).tiny), (rr - D) / safe_a)
    tan_half = torch.where(special[:, None], torch.zeros_like(tan_half), tan_half)
    safe_r = torch.where(special[:, None], torch.ones_like(r), r)
    w = (torch.roll(tan_half, 1, dims=1) + tan_half) / safe_r
    W = w / w.sum(1, keepdim=True)

    # points on an edge: linear interpolation between its two ends; at a vertex: one-hot
    lerp = rn / (r + rn).clamp_min(torch.finfo(r.dtype).tiny)  # weight of v_i on edge i
    first_edge = on_edge & (on_edge.cumsum(1) == 1)  # a point on two edges is at their shared vertex
    edge_part = torch.where(first_edge, lerp, torch.zeros_like(r)) + torch.roll(
        torch.where(first_edge, 1.0 - lerp, torch.zeros_like(r)), 1, dims=1
    )
    first_vertex = at_vertex & (at_vertex.cumsum(1) == 1)
    vertex_part = first_vertex.to(points.dtype)
    W = torch.where(on_edge.any(1, keepdim=True), edge_part, W)
    W = torch.where(at_vertex.any(1, keepdim=True), vertex_part, W)
    return W


@dataclass
class StitchedEdge:
    """The two pattern edges one seam joins, with their vertices aligned.

    Attributes:
        a_key, b_key: ``(panel_name, edge_index)`` of the two edges (keys of ``edge_vertices``).
        a: (n,) int64 panel vertices of edge A from its start to its end.
        b: (n,) int64 panel vertices of edge B such that ``a[i]`` and ``b[i]`` are sewn together
            (for a dart the tip is ``a[i] == b[i]``).
    """

    a_key: tuple[str, int]
    b_key: tuple[str, int]
    a: torch.Tensor
    b: torch.Tensor

    @property
    def is_dart(self) -> bool:
        return self.a_key[0] == self.b_key[0]


def stitched_edges(garment: GarmentMesh) -> list[StitchedEdge]:
    """The seams of a garment as pairs of aligned pattern edges.

    `GarmentMesh` keeps the seams as vertex pairs (``stitch_pairs``); this finds, for every seam, the two
    edges of ``edge_vertices`` whose vertices are pairwise stitched (a dart's tip, stitched to itself,
    is allowed at one end). The mesher gives the two edges of a stitch the same vertex count, so the
    match is exact.

    Returns:
        the stitched edge pairs, in the order of ``edge_vertices`` (A before B).

    Raises:
        ValueError: some stitch pairs are not explained by any pair of edges.
    """
    pairs = garment.stitch_pairs.tolist()
    partners: dict[int, set[int]] = {}
    for u, v in pairs:
        partners.setdefault(u, set()).add(v)
        partners.setdefault(v, set()).add(u)
    keys = list(garment.edge_vertices)
    verts = {k: garment.edge_vertices[k].tolist() for k in keys}
    at_vertex: dict[int, list[tuple[str, int]]] = {}
    for k in keys:
        for v in verts[k]:
            at_vertex.setdefault(v, []).append(k)
    rank = {k: i for i, k in enumerate(keys)}

    def aligned(a: list[int], b: list[int]) -> bool:
        same = [i for i in range(len(a)) if a[i] == b[i]]
        if len(same) > 1 or (same and same[0] not in (0, len(a) - 1)):
            return False
        return all(a[i] == b[i] or b[i] in partners.get(a[i], ()) for i in range(len(a)))

    out: list[StitchedEdge] = []
    covered: set[tuple[int, int]] = set()
    for ka in keys:
        a = verts[ka]
        mid = a[len(a) // 2]
        cands = {kb for p in partners.get(mid, ()) for kb in at_vertex.get(p, ())}
        cands |= {kb for kb in at_vertex.get(mid, ()) if len(a) <= 3}  # a dart tip in the middle
        for kb in sorted(cands, key=rank.__getitem__):
            if rank[kb] <= rank[ka] or len(verts[kb]) != len(a):
                continue
            b = verts[kb]
            for bb in (b[::-1], b):
                if aligned(a, bb):
                    out.append(
                        StitchedEdge(ka, kb, torch.as_tensor(a, dtype=torch.int64), torch.as_tensor(bb))
                    )
                    covered.update((min(x, y), max(x, y)) for x, y in zip(a, bb) if x != y)
                    break
    missing = {(min(u, v), max(u, v)) for u, v in pairs} - covered
    if missing:
        raise ValueError(
            f"{len(missing)} stitch pair(s) of the garment (e.g. {sorted(missing)[0]}) do not join two "
            "pattern edges with matching vertex counts; was the GarmentMesh built by mesh_pattern?"
        )
    return out


def seam_segments(garment: GarmentMesh) -> torch.Tensor:
    """(K, 4) int64 panel-vertex indices ``(a_i, a_{i+1}, b_i, b_{i+1})`` of every pair of sewn segments."""
    parts = [torch.stack([s.a[:-1], s.a[1:], s.b[:-1], s.b[1:]], dim=1) for s in stitched_edges(garment)]
    return torch.cat(parts) if parts else torch.zeros(0, 4, dtype=torch.int64)


# ---------------------------------------------------------------------------------------------------------
# The module


def _swap_side(name: str) -> str | None:
    """``left_x`` <-> ``right_x`` and ``x_l`` <-> ``x_r`` (token-wise on ``_``); None if no side token."""
    swap = {"left": "right", "right": "left", "l": "r", "r": "l"}
    tokens = name.split("_")
    out = [swap.get(t, t) for t in tokens]
    return "_".join(out) if out != tokens else None


def _mirror_match(pa: torch.Tensor, pb: torch.Tensor, tol: float) -> tuple[torch.Tensor | None, float]:
    """(best, mismatch): for handle positions ``pa``, ``pb`` (k, 2) [m], the handle of ``pa`` whose mirror
    image ``S pa + t`` (``t`` matching the means) lies on each handle of ``pb``, as (k,) indices into
    ``pa``, or None unless every one lies within ``tol`` [m] and each is used once; and the largest
    distance [m]."""
    mirrored = pa * pa.new_tensor(MIRROR)
    dist = torch.cdist(pb, mirrored + (pb.mean(0) - mirrored.mean(0)))  # (k, k)
    nearest = dist.min(1)
    best = nearest.indices
    ok = bool((nearest.values <= tol).all()) and len(set(best.tolist())) == len(pb)
    return (best if ok else None), float(nearest.values.max())


class ControlCage(nn.Module):
    """Handles ζ per panel whose mean value coordinates give every rest coordinate (paper §4.2.2).

    ``rest_uv = W · tie(ζ)`` with ``W`` (V, H) the mean value coordinates of each panel vertex w.r.t.
    its panel's cage polygon (block-diagonal over panels, stored as dense per-panel blocks: one small
    matmul per panel, ~1 ms forward + backward for 10k vertices), so ``forward()`` at the template
    handles ``ζ₀`` reproduces the template ``vert_uv`` (to ~1e-12 m in float64).

    Tying (optional) is a set of linear constraints ``C · vec(ζ − ζ₀) = 0``; ``tie`` is the orthogonal
    projection onto them, ``tie(ζ) = ζ₀ + P (ζ − ζ₀)``, applied to the parameter (or an override) in
    every forward pass, so the tied handles always satisfy them and gradients reach the raw
    parameter already projected:

    * ``tie_mirrored``: panels whose names differ only by ``left``/``right`` (or ``l``/``r``) tokens and
      whose handles are mirror images (same count, and each handle of one panel within 1e-6 m of a
      mirrored handle of the other) move as mirror images:
      ``ζ_right[j] = S · ζ_left[m(j)] + t`` with ``S = diag(−1, 1)`` (``x ↦ t_x − x``, ``y ↦ y + t_y``:
      the reflection across the vertical line ``x = t_x / 2`` of the panel frame, then a shift along it),
      ``m = handle_mirror`` and ``t`` the constant offset of the templates (``t = 0`` for the bundled
      ones: the reflection across the frame's y axis). Equivalently the two share one displacement,
      ``d_right = S · d_left``; the projection sets it to the mean of the two raw displacements.
    * ``tie_symmetric``: a panel that is its own mirror image (no side partner; its handles symmetric
      across a vertical line, as a skirt's front and back panels are) stays so, each handle moving as its
      partner's mirror image (``handle_mirror`` then points within the panel). The dress fits had made
      their skirt panels lopsided by up to 3.7 cm, which no scan of a symmetric garment asks for
      (docs/BENCHMARKS.md, "The hem's split and lopsided skirt panels").
    * ``tie_seams``: for every seam (see `stitched_edges`) the chords between the end vertices of its two
      edges (the handle pairs at the ends, when those are handles) change length together to first
      order: ``û_A · Δ(p_A,end − p_A,start) = û_B · Δ(p_B,end − p_B,start)`` with ``û`` the template chord
      directions and ``Δ`` the change from the template. Exact for motions along the chords; the seam
      length regularizer (`torch_diffavatar.losses.seam_length_loss`) does the rest.
    * ``tie_close``: handles of one panel that are consecutive on its cage and closer than this [m] share
      one displacement, so the short pattern edge between them moves rigidly. GarmentCode's tops have
      ~6 mm edges at the shoulder tips, where four panels meet; with their two ends free, every step of
      the fit (a few mm) could crush the few small triangles there (rest quality 0.56 → 0.17 in a T-shirt
      fit) and the drape then stretched them past any strain limit.

    Attributes:
        handles: (H, 2) nn.Parameter, raw handle positions [m] in their panels' frames.
        handle_rest: (H, 2) buffer, template handle positions ζ₀ [m].
        handle_vertices: (H,) int64 buffer, panel-vertex id of each handle.
        handle_panel: (H,) int64 buffer, panel id of each handle (handles of one panel are contiguous,
            in boundary-loop order).
        handle_mirror: (H,) int64 buffer, the mirror partner of each handle, −1 when not tied.
        weight_values: (Σ_p V_p·H_p,) buffer, the dense per-panel blocks ``W_p`` (V_p, H_p) of ``W``
            (block-diagonal, panels in order), flattened row-major and concatenated.
        vert_order: (V,) int64 buffer, panel vertices in block order (panel 0's vertices first …).
        tie_projector: (2H, 2H) buffer ``P`` acting on ``ζ.reshape(-1)`` (None without ties).

    Limitations: handles are boundary vertices only (no interior handles); the cage of a panel must be a
    simple polygon for the coordinates to be positive inside (they stay exact but may be negative).
    """

    def __init__(
        self,
        garment: GarmentMesh,
        *,
        turning_angle_deg: float = 10.0,
        tie_mirrored: bool = False,
        tie_symmetric: bool = False,
        tie_seams: bool = False,
        tie_close: float = 0.0,
    ):
        super().__init__()
        if not isinstance(garment, GarmentMesh):
            raise TypeError(f"garment must be a GarmentMesh, got {type(garment).__name__}")
        if not (isinstance(turning_angle_deg, int | float) and 0.0 <= turning_angle_deg < 180.0):
            raise ValueError(f"turning_angle_deg must be in [0, 180) degrees, got {turning_angle_deg!r}")
        if not (isinstance(tie_close, int | float) and 0.0 <= tie_close < float("inf")):
            raise ValueError(f"tie_close must be a finite length >= 0 [m], got {tie_close!r}")
        if len(garment.panel_boundary) != len(garment.panel_names):
            raise ValueError("garment.panel_boundary must hold one outline per panel")
        dtype = garment.vert_uv.dtype
        uv = garment.vert_uv.detach().to("cpu", torch.float64)
        vert_panel = garment.vert_panel.cpu()
        self.vert_count = garment.vert_count
        self.panel_names = list(garment.panel_names)

        handle_vertices, handle_panel, order, vals = [], [], [], []
        self._blocks: list[tuple[int, int, int, int]] = []  # (value offset, V_p, first handle, H_p)
        offset = 0
        h0 = 0
        for pid, boundary in enumerate(garment.panel_boundary):
            boundary = boundary.cpu()
            sel = torch.as_tensor(select_handles(uv[boundary].numpy(), turning_angle_deg))
            hv = boundary[sel]
            verts = torch.nonzero(vert_panel == pid).flatten()
            W = mean_value_coordinates(uv[verts], uv[hv])  # (n_p, h_p)
            self._blocks.append((offset, len(verts), h0, len(hv)))
            offset += W.numel()
            order.append(verts)
            vals.append(W.flatten())
            handle_vertices.append(hv)
            handle_panel.append(torch.full((len(hv),), pid, dtype=torch.int64))
            h0 += len(hv)
        hv_all = torch.cat(handle_vertices)
        self.register_buffer("handle_vertices", hv_all)
        self.register_buffer("handle_panel", torch.cat(handle_panel))
        self.register_buffer("handle_rest", uv[hv_all].to(dtype))
        vert_order = torch.cat(order)
        if not torch.equal(torch.sort(vert_order).values, torch.arange(self.vert_count)):
            raise ValueError("garment.vert_panel must give every panel vertex exactly one panel")
        self._identity_order = bool(torch.equal(vert_order, torch.arange(self.vert_count)))
        self.register_buffer("vert_order", vert_order)
        self.register_buffer("vert_block_index", torch.argsort(vert_order))
        self.register_buffer("weight_values", torch.cat(vals).to(dtype))
        self.handles = nn.Parameter(uv[hv_all].to(dtype))

        mirror, constraints = self._mirror_constraints(uv[hv_all], tie_mirrored, tie_symmetric)
        self.register_buffer("handle_mirror", mirror)
        if tie_seams:
            constraints.extend(self._seam_constraints(garment, uv, h0))
        if tie_close > 0:
            constraints.extend(self._close_constraints(uv[hv_all], h0, tie_close))
        projector = None
        if constraints:
            C = torch.as_tensor(np.concatenate(constraints))  # (m, 2H) float64
            _, sv, vt = torch.linalg.svd(C, full_matrices=False)
            basis = vt[: int((sv > 1e-10 * sv.max().clamp_min(1e-300)).sum())]  # (rank, 2H)
            projector = (torch.eye(2 * h0, dtype=torch.float64) - basis.T @ basis).to(dtype)
        self.register_buffer("tie_projector", projector)

    # -- construction helpers ---------------------------------------------------------------------------

    def _panel_handles(self, pid: int) -> torch.Tensor:
        return torch.nonzero(self.handle_panel == pid).flatten()

    def _mirror_constraints(
        self, rest: torch.Tensor, tie_mirrored: bool, tie_symmetric: bool
    ) -> tuple[torch.Tensor, list[np.ndarray]]:
        """(``handle_mirror`` (H,), constraint rows on vec(ζ − ζ₀)) of the mirror ties of mirrored panel pairs
        (``tie_mirrored``) and of panels that are their own mirror images (``tie_symmetric``), from the
        template handles ``rest`` (H, 2)."""
        h0 = len(rest)
        mirror = torch.full((h0,), -1, dtype=torch.int64)
        constraints: list[np.ndarray] = []
        if tie_mirrored:
            for a, b in self._mirror_pairs(rest):
                mirror[a], mirror[b] = b, a
                for ia, ib in zip(a.tolist(), b.tolist()):
                    row = np.zeros((2, 2 * h0))
                    row[0, 2 * ib], row[0, 2 * ia] = 1.0, -MIRROR[0]  # d_b,x + d_a,x = 0
                    row[1, 2 * ib + 1], row[1, 2 * ia + 1] = 1.0, -MIRROR[1]  # d_b,y − d_a,y = 0
                    constraints.append(row)
        if tie_symmetric:
            for a, b in self._self_mirror_pairs(rest):
                mirror[b] = a
                for ia, ib in zip(a.tolist(), b.tolist()):
                    row = np.zeros((1 if ia == ib else 2, 2 * h0))
                    row[0, 2 * ib] += 1.0  # d_b,x + d_a,x = 0 (on the axis, ia == ib: it stays there)
                    row[0, 2 * ia] += 1.0
                    if ia != ib:
                        row[1, 2 * ib + 1], row[1, 2 * ia + 1] = 1.0, -1.0  # d_b,y − d_a,y = 0
                    constraints.append(row)
        return mirror, constraints

    def _mirror_pairs(self, rest: torch.Tensor, tol: float = 1e-6) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Handle-index pairs (a (k,), b (k,)) of mirrored panels: ``rest[b] ≈ S rest[a] + t``."""
        out = []
        for pid, name in enumerate(self.panel_names):
            other = _swap_side(name)
            if other is None or other not in self.panel_names:
                continue
            qid = self.panel_names.index(other)
            if qid <= pid:
                continue
            ha, hb = self._panel_handles(pid), self._panel_handles(qid)
            if len(ha) != len(hb):
                warnings.warn(
                    f"tie_mirrored: panels {name!r} and {other!r} have {len(ha)} and {len(hb)} handles; "
                    "not tied",
                    stacklevel=3,
                )
                continue
            best, mismatch = _mirror_match(rest[ha], rest[hb], tol)
            if best is None:
                warnings.warn(
                    f"tie_mirrored: panels {name!r} and {other!r} are not mirror images (largest handle "
                    f"mismatch {mismatch:.3g} m); not tied",
                    stacklevel=3,
                )
                continue
            out.append((ha[best], hb))
        return out

    def _self_mirror_pairs(
        self, rest: torch.Tensor, tol: float = 1e-6
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Handle-index pairs (a (k,), b (k,)) of each panel that is its own mirror image (no left/right
        partner, and its handles symmetric across the vertical line through their mean within ``tol`` [m],
        as a skirt's front or back panel is): ``rest[b] ≈ S rest[a] + t``, a handle on the line its own
        partner. Other panels give none."""
        out = []
        for pid, name in enumerate(self.panel_names):
            if _swap_side(name) is not None:
                continue
            h = self._panel_handles(pid)
            best, _ = _mirror_match(rest[h], rest[h], tol)
            if best is not None:
                out.append((h[best], h))
        return out

    def close_handle_pairs(self, rest: torch.Tensor, distance: float) -> list[tuple[int, int]]:
        """Pairs (a, b) of handles consecutive on one panel's cage with template positions ``rest`` (H, 2)
        closer than ``distance`` [m]."""
        pairs = []
        for pid in range(len(self.panel_names)):
            idx = self._panel_handles(pid).tolist()
            if len(idx) < 2:
                continue
            for a, b in zip(idx, idx[1:] + idx[:1]):
                if a != b and float((rest[a] - rest[b]).norm()) < distance:
                    pairs.append((a, b))
        return pairs

    def _close_constraints(self, rest: torch.Tensor, h0: int, distance: float) -> list[np.ndarray]:
        """Two rows per close pair: equal displacements ``d_a − d_b = 0``."""
        rows = []
        for a, b in self.close_handle_pairs(rest, distance):
            row = np.zeros((2, 2 * h0))
            row[0, 2 * a], row[0, 2 * b] = 1.0, -1.0
            row[1, 2 * a + 1], row[1, 2 * b + 1] = 1.0, -1.0
            rows.append(row)
        return rows

    def _seam_constraints(self, garment: GarmentMesh, uv: torch.Tensor, h0: int) -> list[np.ndarray]:
        """One row per seam: first-order equal change of the two edges' end-to-end chord lengths."""
        W = self.weight_matrix().to_dense().double().numpy()

        def w_row(v: int) -> np.ndarray:  # (H,) row of W for panel vertex v
            return W[v]

        rows = []
        for s in stitched_edges(garment):
            row = np.zeros(2 * h0)
            ok = True
            for ends, sign in (((int(s.a[0]), int(s.a[-1])), 1.0), ((int(s.b[0]), int(s.b[-1])), -1.0)):
                chord = (uv[ends[1]] - uv[ends[0]]).numpy()
                length = float(np.linalg.norm(chord))
                if length < 1e-9:
                    ok = False
                    break
                u = chord / length
                dw = w_row(ends[1]) - w_row(ends[0])
                row[0::2] += sign * u[0] * dw
                row[1::2] += sign * u[1] * dw
            if ok and np.abs(row).max() > 0:
                rows.append(row[None])
        return rows

    # -- forward ----------------------------------------------------------------------------------------

    @property
    def handle_count(self) -> int:
        return int(self.handle_rest.shape[0])

    def tied_handles(self, handles: torch.Tensor | None = None) -> torch.Tensor:
        """(…, H, 2) handles [m] after tying (the raw parameter or ``handles`` when given)."""
        z = self.handles if handles is None else handles
        if self.tie_projector is None:
            return z
        d = (z - self.handle_rest).flatten(-2)  # (…, 2H)
        return self.handle_rest + (d @ self.tie_projector.T).unflatten(-1, (-1, 2))

    @torch.no_grad()
    def project_(self) -> None:
        """Write the tied handles back into the parameter (no-op without ties)."""
        self.handles.copy_(self.tied_handles())

    def weight_matrix(self) -> torch.Tensor:
        """``W`` as a sparse COO (V, H) tensor."""
        rows, cols = [], []
        for _, n, h0, h in self._blocks:
            r, c = torch.meshgrid(torch.arange(n), torch.arange(h0, h0 + h), indexing="ij")
            rows.append(r.flatten())
            cols.append(c.flatten())
        block_rows = torch.cat(rows) + torch.repeat_interleave(
            torch.as_tensor([0] + [n for _, n, _, _ in self._blocks[:-1]]).cumsum(0),
            torch.as_tensor([n * h for _, n, _, h in self._blocks]),
        )
        idx = torch.stack([self.vert_order.cpu()[block_rows], torch.cat(cols)]).to(self.weight_values.device)
        return torch.sparse_coo_tensor(
            idx, self.weight_values, (self.vert_count, self.handle_count), check_invariants=True
        ).coalesce()

    def forward(self, handles: torch.Tensor | None = None) -> torch.Tensor:
        """Rest coordinates of every panel vertex.

        Args:
            handles: optional (H, 2) or (B, H, 2) handle positions [m] overriding the parameter.

        Returns:
            (V, 2) or (B, V, 2) rest coordinates [m] in each panel's frame (dtype of the handles).
        """
        if handles is not None and (
            handles.dim() not in (2, 3) or handles.shape[-2:] != (self.handle_count, 2)
        ):
            raise ValueError(
                f"handles must have shape ({self.handle_count}, 2) or (B, {self.handle_count}, 2), "
                f"got {tuple(handles.shape)}"
            )
        z = self.tied_handles(handles)
        values = self.weight_values.to(z.dtype)
        parts = [
            values[o : o + n * h].view(n, h) @ z[..., h0 : h0 + h, :]  # (…, V_p, 2)
            for o, n, h0, h in self._blocks
        ]
        out = torch.cat(parts, dim=-2)  # (…, V, 2) in block order
        return out if self._identity_order else out.index_select(-2, self.vert_block_index)

    def extra_repr(self) -> str:
        tied = (
            ""
            if self.tie_projector is None
            else f", tied dof={int(round(float(self.tie_projector.trace())))}"
        )
        return (
            f"panels={len(self.panel_names)}, handles={self.handle_count}, vertices={self.vert_count}{tied}"
        )


class FreeVertices(nn.Module):
    """The pattern without a cage (the paper's "w/o cage" ablation): every panel vertex's rest coordinate
    is a parameter of its own.

    Same interface as `ControlCage` for the fit: ``handles`` (V, 2) nn.Parameter [m] (initialised to the
    template ``vert_uv``), ``handle_rest`` the template, ``forward(handles=None)`` → (V, 2) or (B, V, 2)
    rest coordinates [m]. Nothing ties mirrored panels or seams.
    """

    def __init__(self, garment: GarmentMesh):
        super().__init__()
        uv = garment.vert_uv.detach().clone()
        self.handles = nn.Parameter(uv.clone())
        self.register_buffer("handle_rest", uv)

    @property
    def handle_count(self) -> int:
        return self.handles.shape[0]

    def forward(self, handles: torch.Tensor | None = None) -> torch.Tensor:
        """Rest coordinates [m]: the parameter, or ``handles`` (V, 2) / (B, V, 2) overriding it."""
        z = self.handles if handles is None else handles
        if z.dim() not in (2, 3) or z.shape[-2:] != (self.handle_count, 2):
            raise ValueError(
                f"handles must have shape ({self.handle_count}, 2) or (B, {self.handle_count}, 2), "
                f"got {tuple(z.shape)}"
            )
        return z
