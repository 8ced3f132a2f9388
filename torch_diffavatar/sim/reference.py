"""PyTorch twins of the simulator's C++ kernels (the contract is /tmp/team/KERNELS.md, restated here).

Every function here has the same signature and semantics as the op ``torch.ops.diffavatar.<name>``
that ``csrc/`` registers; ``sim/ops.py`` picks between the two. The projection kernels work in place
on ``x`` and ``lam`` and return ``None``. They are written for clarity and vectorised over one colour
at a time (constraints of one colour share no vertex, so their corrections can be applied together).

Conventions shared with the C++ (test against these, not against the prose):

* **Stretch** (orthotropic StVK, one 3-vector block per triangle). ``D = [x0-x2, x1-x2]`` (3x2),
  ``F = D @ tri_rest_inv`` (3x2), ``E = (F^T F - I) / 2``, ``C = [E00, E11, E01]`` (E01 not doubled).
  ``dC_k/dD = P_k @ tri_rest_inv^T`` with ``P_0 = [f0, 0]``, ``P_1 = [0, f1]``, ``P_2 = [f1, f0] / 2``
  (``f_j`` the columns of F); ``dC_k/dx0``, ``dC_k/dx1`` are the two columns and
  ``dC_k/dx2 = -(col0 + col1)``. With ``G_i`` the 3x3 matrix whose row k is ``dC_k/dx_i``:
  ``A = sum_i w_i G_i G_i^T + alpha / dt^2`` (NOTE: ``G_i G_i^T``, the 3x3 Schur complement
  ``grad C  M^-1  grad C^T``; KERNELS.md's ``G_i^T G_i`` is a typo),
  ``dlam = A^-1 (-C - alpha/dt^2 lam)``, ``lam += dlam``, ``x_i += w_i G_i^T dlam``.
  Triangles whose three inverse masses are all 0 are skipped.
* **Bend** (signed dihedral angle per interior edge). ``n1 = (x1-x0) x (x2-x0)``,
  ``n2 = (x0-x1) x (x3-x1)`` (un-normalised normals of the triangles (v0,v1,v2) and (v1,v0,v3)),
  ``e = x1 - x0``, ``theta = atan2((n1 x n2) . e/|e|, n1 . n2)`` (0 when flat; moving v2 or v3 along
  its own triangle's normal decreases theta). The gradient below is the exact gradient of this theta
  (checked against autograd in tests/sim/test_reference.py)::

      dtheta/dx2 = -|e| n1/|n1|^2                       dtheta/dx3 = -|e| n2/|n2|^2
      dtheta/dx0 = -((x2-x1).e/|e|) n1/|n1|^2 - ((x3-x1).e/|e|) n2/|n2|^2
      dtheta/dx1 =  ((x2-x0).e/|e|) n1/|n1|^2 + ((x3-x0).e/|e|) n2/|n2|^2

  (Bridson et al. 2003 with the overall sign flipped for this orientation convention.)
  ``C = theta - rest``, ``dlam = (-C - alpha/dt^2 lam) / (sum_i w_i |dtheta/dx_i|^2 + alpha/dt^2)``,
  ``lam += dlam``, ``x_i += w_i dtheta/dx_i dlam``. Quads with ``|e| < 1e-12`` or
  ``|n1|^2, |n2|^2 < 1e-24`` are skipped (no change to x or lam).
* **Colour order**: ``order`` (K,) int64 lists constraint ids colour by colour, ``color_offsets``
  (n_colors+1,) int64 marks where each colour starts. Colours are processed in sequence, constraints
  of a colour simultaneously (they share no vertex). Constraints absent from ``order`` are not touched.
* **Jacobi** (``*_jacobi_``, no order/offsets, extra ``omega``): every constraint's dlam and dx are
  computed from the same x; ``lam += dlam`` for all; per vertex the dx are summed and
  ``x += omega * sum_dx / count`` where ``count`` is the number of non-skipped constraints that
  contain the vertex (vertices with count 0 do not move).
* **closest_point_on_mesh**: for each point the closest point on a triangle mesh, exact
  (Ericson, "Real-Time Collision Detection", 5.1.5); returns ``tri`` (-1 when none within
  ``max_dist``), barycentric ``bary`` (zeros when ``tri`` is -1) and unsigned ``dist`` (inf when -1).
* **closest_point_candidates** / **closest_point_among** (the contact cache, `collision.ContactCache`):
  the triangles within a radius of each point, and the closest among given candidates, with the grid
  query's distance test and tie-break (lowest id). The grid ops (``closest_point_index``,
  ``closest_point_query`` and its ``hint``) have ``closest_point_on_mesh`` as their twin.
* **max_abs_green_strain**: 0-dim tensor, the largest ``|C_k|`` of the stretch constraint vectors
  ``C = [E00, E11, E01]`` over all triangles (0 without triangles; NaN when any is NaN).
* **xpbd_substeps_** (fused): ``substeps`` × [predict, ``iterations`` × (stretch, bend, attachments,
  body contacts, stitches), friction, velocity update] in place on ``x`` and ``v``; its arguments are
  grouped by role (`sim/substep.py`, `SubstepInputs`). The maths is `xpbd_substeps`, the composition of
  the kernels above, `attach_project_`, `stitch_project_` and `sim.contacts`' ``push_out`` /
  ``apply_friction``. Multipliers start at 0 every substep.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import torch

# the closest-point twins live with the geometry that body and losses share; re-exported as this module's
from torch_diffavatar.geometry import closest_point_on_mesh_torch as closest_point_on_mesh  # noqa: F401
from torch_diffavatar.geometry import (
    closest_point_on_triangles,  # noqa: F401
    green_strain,
    triangle_green_strain,
)
from torch_diffavatar.sim.contacts import (
    Contacts,
    apply_friction,
    contact_frames,
    damp_bounce,
    push_out,
    unit_normals,
)
from torch_diffavatar.sim.substep import SubstepInputs


def closest_point_candidates(points, verts, faces, radius):
    """Twin of the C++ ``closest_point_candidates`` (brute force): (N, K) int64 ids of the triangles within
    ``radius`` (N,) [m] of each point (the op's slack, 1e-6 relative plus 1e-6 (1 + |p|) m, included),
    padded with -1, ascending."""
    n, nf = points.shape[0], faces.shape[0]
    p = points.to(torch.float64)
    a, b, c = (verts.to(torch.float64)[faces[:, k]] for k in range(3))
    bc = closest_point_on_triangles(p[:, None], a[None], b[None], c[None])  # (N, Fb, 3)
    q = bc[..., :1] * a + bc[..., 1:2] * b + bc[..., 2:] * c
    d2 = ((p[:, None] - q) ** 2).sum(-1)
    r = radius.to(torch.float64) * (1 + 1e-6) + 1e-6 * (1 + p.abs().amax(-1))
    inside = (d2 <= (r * r)[:, None]) & (radius[:, None] >= 0)
    ids = torch.where(inside, torch.arange(nf).expand(n, nf), torch.full((n, nf), nf))
    width = max(int(inside.sum(1).max()) if n else 0, 1)
    ids = ids.sort(1).values[:, :width]
    return torch.where(ids == nf, -1, ids)


def closest_point_among(points, verts, faces, cand, max_dist):
    """Twin of the C++ ``closest_point_among``: `closest_point_on_mesh` restricted to each point's
    candidates ``cand`` (N, K) int64 (each row's end at its first -1); ties to the lowest id."""
    n = points.shape[0]
    tri = torch.full((n,), -1, dtype=torch.int64, device=points.device)
    bary, dist = points.new_zeros(n, 3), points.new_full((n,), float("inf"))
    p = points.to(torch.float64)
    safe = cand.clamp_min(0)
    a, b, c = (verts.to(torch.float64)[faces[safe, k]] for k in range(3))  # (N, K, 3)
    bc = closest_point_on_triangles(p[:, None], a, b, c)
    d2 = ((p[:, None] - (bc[..., :1] * a + bc[..., 1:2] * b + bc[..., 2:] * c)) ** 2).sum(-1)
    listed = torch.cumprod((cand >= 0).to(torch.int64), 1) > 0  # up to the first -1
    d2 = torch.where(listed & (d2 <= max_dist * max_dist), d2, torch.inf)
    best = d2.min(1, keepdim=True).values
    # lowest id among the minima
    pick = torch.where(d2 == best, cand, torch.iinfo(torch.int64).max).argmin(1)
    hit = torch.isfinite(best[:, 0])
    rows = torch.nonzero(hit).squeeze(1)
    tri[rows] = cand[rows, pick[rows]]
    bary[rows] = bc[rows, pick[rows]].to(points.dtype)
    dist[rows] = best[rows, 0].sqrt().to(points.dtype)
    return tri, bary, dist


def _closest_among_all(points, verts, faces, max_dist):
    """The C++ grid query's (tri, bary, dist), brute force: `closest_point_among` over every face."""
    n, nf = points.shape[0], faces.shape[0]
    tri = torch.full((n,), -1, dtype=torch.int64, device=points.device)
    bary, dist = points.new_zeros(n, 3), points.new_full((n,), float("inf"))
    chunk = max(1, 2_000_000 // max(nf, 1))
    for s in range(0, n, chunk):
        every = torch.arange(nf, device=points.device).expand(min(chunk, n - s), nf)
        tri[s : s + chunk], bary[s : s + chunk], dist[s : s + chunk] = closest_point_among(
            points[s : s + chunk], verts, faces, every, max_dist
        )
    return tri, bary, dist


_CACHE_SLACK = 1e-5  # [m]: the C++ cache's (its distances in double, the positions float32 or float64)


def contact_cache_query_(
    points, verts, faces, header, cell_start, cell_items, last_x, lower, last_tri, cand_x, cand, band, probe,
    margin, max_radius,
):  # fmt: skip
    """Twin of the C++ ``contact_cache_query_`` (`collision.ContactCache`'s frame), brute force (the grid
    arguments are not read): in place on the state (last_x (N, 3) f64, lower (N,) f64, last_tri (N,) i64,
    cand_x (N, 3) f64, cand (N, K) i64, -1 padded); returns (tri (N,), bary (N, 3), counts (3,) i64: the
    points queried, of those the ones answered among their candidates, the longest list that did not fit
    in K)."""
    n, width = points.shape[0], cand.shape[1]
    p = points.to(torch.float64)
    tri = torch.full((n,), -1, dtype=torch.int64, device=points.device)
    bary = points.new_zeros(n, 3)
    moved = ((p - last_x) ** 2).sum(-1).sqrt()
    active = torch.nonzero(~(lower - moved > band + _CACHE_SLACK)).squeeze(1)
    drift = ((p[active] - cand_x[active]) ** 2).sum(-1).sqrt()
    near = (cand[active, 0] >= 0) & (drift <= margin - _CACHE_SLACK)
    fast, slow = active[near], active[~near]
    got_tri, got_bary, got_dist = (torch.cat(pair) for pair in zip(
        closest_point_among(points[fast], verts, faces, cand[fast], band),
        _closest_among_all(points[slow], verts, faces, band),
        strict=True,
    ))  # fmt: skip
    ids = torch.cat((fast, slow))
    cand[slow, 0] = -1
    radius = got_dist[fast.numel() :].to(torch.float64) + 2 * margin
    grow = (got_tri[fast.numel() :] >= 0) & (radius <= max_radius)
    found = closest_point_candidates(points[slow[grow]], verts, faces, radius[grow])
    count = (found >= 0).sum(1)
    fits = count <= width
    rows = slow[grow][fits]
    pad = (0, max(width - found.shape[1], 0))
    cand[rows] = torch.nn.functional.pad(found[fits][:, :width], pad, value=-1)
    cand_x[rows] = p[rows]
    hit = got_tri >= 0
    tri[ids[hit]], bary[ids[hit]] = got_tri[hit], got_bary[hit]
    lower[ids[hit]], last_tri[ids[hit]] = got_dist[hit].to(torch.float64), got_tri[hit]
    miss = ids[~hit]
    far_tri, _, far_dist = _closest_among_all(points[miss], verts, faces, band + probe)
    reach = torch.full_like(lower[miss], band + probe)
    lower[miss] = torch.where(far_tri >= 0, far_dist.to(torch.float64), reach)
    last_tri[miss] = far_tri
    last_x[active] = p[active]
    overflow = int(count[~fits].max()) if bool((~fits).any()) else 0
    counts = torch.tensor([active.numel(), fast.numel(), overflow], dtype=torch.int64, device=points.device)
    return tri, bary, counts


def contact_outermost(points, verts, faces, across, ring, tri, bary):
    """Twin of the C++ ``contact_outermost`` (`collision._FeatureFaces.outermost`): for contacts of the
    points (C, 3) whose closest point is on an edge or a vertex of face ``tri`` (C,), the face sharing that
    feature (``across`` (Fb, 3), ``ring`` (Vb, R) -1 padded) whose plane is strictly farther from the point
    (the first of the farthest), and the barycentrics ``bary`` (C, 3) moved to its corners. Planes in
    float64. Returns new (tri, bary)."""
    tri, bary = tri.clone(), bary.clone()
    zero = bary <= 0
    nz = zero.sum(-1)
    on = torch.nonzero((nz == 1) | (nz == 2)).squeeze(1)
    if on.numel() == 0:
        return tri, bary
    t, z = tri[on], zero[on]
    cand = torch.full((on.numel(), ring.shape[1] + 1), -1, dtype=torch.int64, device=tri.device)
    cand[:, 0] = t
    edge, corner = nz[on] == 1, nz[on] == 2
    cand[edge, 1] = across[t[edge], torch.argmax(z[edge].to(torch.int8), dim=-1)]
    cand[corner, 1:] = ring[faces[t[corner], torch.argmax((~z[corner]).to(torch.int8), dim=-1)]]
    corners = verts.to(torch.float64)[faces[cand.clamp_min(0)]]  # (C, K, 3, 3)
    s = ((points[on].to(torch.float64)[:, None] - corners[..., 0, :]) * unit_normals(corners)).sum(-1)
    s = torch.where(cand >= 0, s, -torch.inf)
    best = torch.argmax(s, dim=-1)
    best = torch.where(s.gather(1, best[:, None])[:, 0] > s[:, 0], best, torch.zeros_like(best))
    new = cand.gather(1, best[:, None])[:, 0]
    moved = torch.nonzero(new != t).squeeze(1)
    old_c, new_c = faces[t[moved]], faces[new[moved]]
    same = (old_c[:, :, None] == new_c[:, None, :]).to(bary.dtype)  # (M, 3 old, 3 new)
    rows = on[moved]
    bary[rows] = (bary[rows][:, :, None] * same).sum(1)
    tri[rows] = new[moved]
    return tri, bary


_BEND_EPS_LEN = 1e-12
_BEND_EPS_N2 = 1e-24


# --------------------------------------------------------------------------------------------- stretch


def _sym3_solve(a00, a01, a02, a11, a12, a22, r0, r1, r2):
    """Solve symmetric positive definite 3x3 systems by the adjugate (batched over the leading shape).

    A system whose largest diagonal entry exceeds cbrt(dtype max / 4) (float32: 4.4e12) is scaled down by
    that entry first: the determinant (three products ~ entry³) overflowed float32 at sub-millimetre
    triangles (entries ~1e13-1e14) and the solve returned NaN. Other systems are solved unscaled (scale
    1, as before); the C++ kernels do the same (`sym3_scale_limit`).
    """
    limit = (torch.finfo(a00.dtype).max / 4.0) ** (1.0 / 3.0)
    amax = torch.maximum(a00, torch.maximum(a11, a22))
    m = torch.where(amax > limit, 1.0 / amax, torch.ones_like(amax))
    a00, a01, a02, a11, a12, a22, r0, r1, r2 = (t * m for t in (a00, a01, a02, a11, a12, a22, r0, r1, r2))
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    return (
        (c00 * r0 + c01 * r1 + c02 * r2) / det,
        (c01 * r0 + c11 * r1 + c12 * r2) / det,
        (c02 * r0 + c12 * r1 + c22 * r2) / det,
    )


def _stretch_delta(x, lam_c, w, tri, rest_inv, compliance, dt):
    """Corrections of a set of stretch constraints evaluated at the same ``x``.

    Args:
        x: (Vs, 3) positions; lam_c: (K, 3) their multipliers; w: (Vs,) inverse masses;
        tri: (K, 3) int64 vertex ids; rest_inv: (K, 2, 2); compliance: (K, 3, 3); dt: float [s].

    Returns:
        dlam (K, 3), dx (K, 3, 3) per-vertex corrections (already multiplied by w_i), active (K,) bool.

    Closed form of the contract's matrices: with ``rest_inv = [[a, b], [c, d]]`` and, per triangle
    corner i, ``(p_i, q_i) = (a, b), (c, d), (-a-c, -b-d)``, the gradient rows are
    ``dC0/dx_i = p_i f0``, ``dC1/dx_i = q_i f1``, ``dC2/dx_i = (q_i f0 + p_i f1) / 2``, so
    ``A = sum_i w_i G_i G_i^T`` only needs ``f0.f0``, ``f1.f1``, ``f0.f1`` and
    ``W_pp = sum w p^2``, ``W_qq = sum w q^2``, ``W_pq = sum w p q`` (checked against autograd in tests).
    """
    xt = x[tri]  # (K, 3, 3)  [corner, xyz]
    wt = w[tri]  # (K, 3)
    d0 = xt[:, 0] - xt[:, 2]
    d1 = xt[:, 1] - xt[:, 2]
    a, b = rest_inv[:, 0, 0, None], rest_inv[:, 0, 1, None]
    c, d = rest_inv[:, 1, 0, None], rest_inv[:, 1, 1, None]
    f0 = d0 * a + d1 * c  # (K, 3)
    f1 = d0 * b + d1 * d
    s00 = (f0 * f0).sum(-1)
    s11 = (f1 * f1).sum(-1)
    s01 = (f0 * f1).sum(-1)
    c0, c1, c2 = 0.5 * (s00 - 1.0), 0.5 * (s11 - 1.0), 0.5 * s01
    p = torch.stack((a[:, 0], c[:, 0], -a[:, 0] - c[:, 0]), dim=1)  # (K, 3) per corner
    q = torch.stack((b[:, 0], d[:, 0], -b[:, 0] - d[:, 0]), dim=1)
    wpp = (wt * p * p).sum(-1)
    wqq = (wt * q * q).sum(-1)
    wpq = (wt * p * q).sum(-1)
    inv_dt2 = 1.0 / (dt * dt)
    al = compliance * inv_dt2  # (K, 3, 3)
    a00 = wpp * s00 + al[:, 0, 0]
    a11 = wqq * s11 + al[:, 1, 1]
    a22 = 0.25 * (wqq * s00 + 2.0 * wpq * s01 + wpp * s11) + al[:, 2, 2]
    a01 = wpq * s01 + al[:, 0, 1]
    a02 = 0.5 * (wpq * s00 + wpp * s01) + al[:, 0, 2]
    a12 = 0.5 * (wqq * s01 + wpq * s11) + al[:, 1, 2]
    l0, l1, l2 = lam_c[:, 0], lam_c[:, 1], lam_c[:, 2]
    r0 = -c0 - (al[:, 0, 0] * l0 + al[:, 0, 1] * l1 + al[:, 0, 2] * l2)
    r1 = -c1 - (al[:, 1, 0] * l0 + al[:, 1, 1] * l1 + al[:, 1, 2] * l2)
    r2 = -c2 - (al[:, 2, 0] * l0 + al[:, 2, 1] * l1 + al[:, 2, 2] * l2)
    active = (wt > 0).any(-1)
    one = torch.ones_like(a00)
    a00 = torch.where(active, a00, one)
    a11 = torch.where(active, a11, one)
    a22 = torch.where(active, a22, one)
    zero = torch.zeros_like(a00)
    a01, a02, a12 = (torch.where(active, t, zero) for t in (a01, a02, a12))
    dl0, dl1, dl2 = _sym3_solve(a00, a01, a02, a11, a12, a22, r0, r1, r2)
    dlam = torch.stack((dl0, dl1, dl2), dim=-1)
    dlam = torch.where(active[:, None], dlam, torch.zeros_like(dlam))
    dl0, dl1, dl2 = dlam[:, 0, None], dlam[:, 1, None], dlam[:, 2, None]
    # x_i += w_i * ((p_i dl0 + q_i dl2 / 2) f0 + (q_i dl1 + p_i dl2 / 2) f1)
    cf0 = wt * (p * dl0 + 0.5 * q * dl2)  # (K, 3) per corner
    cf1 = wt * (q * dl1 + 0.5 * p * dl2)
    dx = cf0[:, :, None] * f0[:, None, :] + cf1[:, :, None] * f1[:, None, :]  # (K, 3[corner], 3[xyz])
    return dlam, dx, active


def stretch_project_(
    x: torch.Tensor,
    lam: torch.Tensor,
    vert_inv_mass: torch.Tensor,
    tri_vertices: torch.Tensor,
    tri_rest_inv: torch.Tensor,
    tri_compliance: torch.Tensor,
    order: torch.Tensor,
    color_offsets: torch.Tensor,
    dt: float,
) -> None:
    """One colour-ordered Gauss–Seidel pass of the StVK stretch constraints, in place on x and lam.

    Args:
        x: (Vs, 3) positions [m], updated in place.
        lam: (F, 3) accumulated XPBD multipliers, updated in place.
        vert_inv_mass: (Vs,) inverse masses [1/kg] (0 = pinned).
        tri_vertices: (F, 3) int64 sim-vertex ids.
        tri_rest_inv: (F, 2, 2) inverse of the rest edge matrix ``[u0-u2, u1-u2]`` [1/m].
        tri_compliance: (F, 3, 3) SPD compliance of C (already divided by the rest area) [1/(N/m * m^2)].
        order: (K,) int64 triangle ids colour by colour.
        color_offsets: (n_colors + 1,) int64 start of each colour in ``order``.
        dt: substep [s].
    """
    offsets = color_offsets.tolist()
    for start, end in zip(offsets[:-1], offsets[1:]):
        if end <= start:
            continue
        ids = order[start:end]
        tri = tri_vertices[ids]
        dlam, dx, _ = _stretch_delta(
            x, lam[ids], vert_inv_mass, tri, tri_rest_inv[ids], tri_compliance[ids], dt
        )
        lam[ids] += dlam
        x.index_add_(0, tri.reshape(-1), dx.reshape(-1, 3))


def stretch_project_jacobi_(
    x: torch.Tensor,
    lam: torch.Tensor,
    vert_inv_mass: torch.Tensor,
    tri_vertices: torch.Tensor,
    tri_rest_inv: torch.Tensor,
    tri_compliance: torch.Tensor,
    dt: float,
    omega: float,
) -> None:
    """One Jacobi pass of all stretch constraints (arguments as `stretch_project_`; ``omega`` the
    relaxation factor): ``x += omega * sum_dx / count`` per vertex, ``lam += dlam`` for all triangles."""
    # lam.clone(): autograd saves the multipliers read here, and they are updated in place below
    dlam, dx, active = _stretch_delta(
        x, lam.clone(), vert_inv_mass, tri_vertices, tri_rest_inv, tri_compliance, dt
    )
    lam += dlam
    _jacobi_apply(x, tri_vertices, dx, active, omega)


def _jacobi_apply(x, ids, dx, active, omega):
    """x += omega * (sum of dx per vertex) / (number of active constraints containing the vertex)."""
    flat = ids.reshape(-1)
    total = torch.zeros_like(x).index_add_(0, flat, dx.reshape(-1, 3))
    count = torch.zeros_like(x[:, 0]).index_add_(
        0, flat, active[:, None].expand(ids.shape).reshape(-1).to(x.dtype)
    )
    x += omega * total / count.clamp_min(1.0)[:, None]


# ------------------------------------------------------------------------------------------------ bend


def dihedral_angle(x0, x1, x2, x3):
    """Signed dihedral angle [rad] of the quads (..., 3) x4 as defined in the module docstring."""
    e = x1 - x0
    n1 = torch.linalg.cross(e, x2 - x0)
    n2 = torch.linalg.cross(x0 - x1, x3 - x1)
    e_hat = e / e.norm(dim=-1, keepdim=True)
    return torch.atan2((torch.linalg.cross(n1, n2) * e_hat).sum(-1), (n1 * n2).sum(-1))


def _bend_delta(x, lam_c, w, quads, rest_angle, compliance, dt):
    """Corrections of a set of bend constraints evaluated at the same ``x``.

    Returns:
        dlam (K,), dx (K, 4, 3) per-vertex corrections (already multiplied by w_i), active (K,) bool.
    """
    xq = x[quads]  # (K, 4, 3)
    wq = w[quads]  # (K, 4)
    x0, x1, x2, x3 = xq.unbind(1)
    e = x1 - x0
    e_len = e.norm(dim=-1)
    n1 = torch.linalg.cross(e, x2 - x0)
    n2 = torch.linalg.cross(x0 - x1, x3 - x1)
    n1_sq = (n1 * n1).sum(-1)
    n2_sq = (n2 * n2).sum(-1)
    active = (e_len >= _BEND_EPS_LEN) & (n1_sq >= _BEND_EPS_N2) & (n2_sq >= _BEND_EPS_N2)
    one = torch.ones_like(e_len)
    e_len_s = torch.where(active, e_len, one)
    e_hat = e / e_len_s[:, None]
    m1 = n1 / torch.where(active, n1_sq, one)[:, None]
    m2 = n2 / torch.where(active, n2_sq, one)[:, None]
    theta = torch.atan2((torch.linalg.cross(n1, n2) * e_hat).sum(-1), (n1 * n2).sum(-1))
    g2 = -e_len_s[:, None] * m1
    g3 = -e_len_s[:, None] * m2
    g0 = -((x2 - x1) * e_hat).sum(-1, keepdim=True) * m1 - ((x3 - x1) * e_hat).sum(-1, keepdim=True) * m2
    g1 = ((x2 - x0) * e_hat).sum(-1, keepdim=True) * m1 + ((x3 - x0) * e_hat).sum(-1, keepdim=True) * m2
    g = torch.stack((g0, g1, g2, g3), dim=1)  # (K, 4, 3)
    alpha_t = compliance / (dt * dt)
    denom = (wq * (g * g).sum(-1)).sum(-1) + alpha_t
    c = theta - rest_angle
    ok = active & (denom > 0)
    dlam = torch.where(ok, (-c - alpha_t * lam_c) / torch.where(ok, denom, one), torch.zeros_like(c))
    dx = wq[..., None] * g * dlam[:, None, None]
    return dlam, dx, ok


def bend_project_(
    x: torch.Tensor,
    lam: torch.Tensor,
    vert_inv_mass: torch.Tensor,
    edge_quads: torch.Tensor,
    edge_rest_angle: torch.Tensor,
    edge_compliance: torch.Tensor,
    order: torch.Tensor,
    color_offsets: torch.Tensor,
    dt: float,
) -> None:
    """One colour-ordered Gauss–Seidel pass of the dihedral bending constraints, in place on x and lam.

    Args:
        x: (Vs, 3) positions [m], updated in place.
        lam: (E,) accumulated multipliers, updated in place.
        vert_inv_mass: (Vs,) inverse masses [1/kg].
        edge_quads: (E, 4) int64 (v0, v1, v2, v3): v0-v1 the shared edge, v2 opposite in (v0, v1, v2),
            v3 opposite in (v1, v0, v3).
        edge_rest_angle: (E,) rest dihedral angle [rad].
        edge_compliance: (E,) compliance [1/(N m)] (includes the geometric weight).
        order: (K,) int64 edge ids colour by colour; color_offsets: (n_colors + 1,) int64.
        dt: substep [s].
    """
    offsets = color_offsets.tolist()
    for start, end in zip(offsets[:-1], offsets[1:]):
        if end <= start:
            continue
        ids = order[start:end]
        quads = edge_quads[ids]
        dlam, dx, _ = _bend_delta(
            x, lam[ids], vert_inv_mass, quads, edge_rest_angle[ids], edge_compliance[ids], dt
        )
        lam[ids] += dlam
        x.index_add_(0, quads.reshape(-1), dx.reshape(-1, 3))


def bend_project_jacobi_(
    x: torch.Tensor,
    lam: torch.Tensor,
    vert_inv_mass: torch.Tensor,
    edge_quads: torch.Tensor,
    edge_rest_angle: torch.Tensor,
    edge_compliance: torch.Tensor,
    dt: float,
    omega: float,
) -> None:
    """One Jacobi pass of all bending constraints (arguments as `bend_project_`, plus ``omega``)."""
    # lam.clone(): as in `stretch_project_jacobi_`
    dlam, dx, active = _bend_delta(
        x, lam.clone(), vert_inv_mass, edge_quads, edge_rest_angle, edge_compliance, dt
    )
    lam += dlam
    _jacobi_apply(x, edge_quads, dx, active, omega)


# ------------------------------------------------------------------------------------- closest point


# ------------------------------------------------------------------------------- stitches, attachments


def stitch_project_(x, lam, w, pairs, alpha, h, max_move, snap):
    """Zero-length stitches ``C = x_a − x_b`` (3-vector), Jacobi-averaged per vertex, in place.

    Each pass moves a stitched vertex by at most ``max_move`` [m] unless its gap is under ``snap`` [m]:
    a wide-open seam then closes with a bounded pull that the membrane constraints can follow, instead
    of yanking single vertices out of their triangles (which the Green-strain constraints cannot
    recover from in a few iterations).

    Args:
        x: (Vs, 3) positions [m]; lam: (S, 3) multipliers; w: (Vs,) inverse masses [1/kg];
        pairs: (S, 2) int64 stitched vertices; alpha: compliance [m/N]; h: substep [s];
        max_move: [m]; snap: [m].
    """
    a, b = pairs[:, 0], pairs[:, 1]
    wa, wb = w[a], w[b]
    alpha_t = alpha / (h * h)
    c = x[a] - x[b]
    denom = (wa + wb + alpha_t)[:, None]
    dlam = (-c - alpha_t * lam) / denom
    move = torch.maximum(wa, wb) * dlam.norm(dim=-1)
    # seams already within ``snap`` close without limit (the body cannot hold them open)
    limit = torch.where(c.norm(dim=-1) < snap, move, torch.full_like(move, max_move)).clamp_min(max_move)
    dlam = dlam * (limit / move.clamp_min(limit))[:, None]
    lam += dlam
    idx = torch.cat((a, b))
    dx = torch.cat((wa[:, None] * dlam, -wb[:, None] * dlam))
    total = torch.zeros_like(x).index_add_(0, idx, dx)
    count = x.new_zeros(x.shape[0]).index_add_(0, idx, x.new_ones(idx.shape[0]))
    x += total / count.clamp_min(1.0)[:, None]


def attach_project_(x, lam, w, verts, height, alpha, h):
    """Soft height constraints ``C = y − y_target`` (waist attachments), in place.

    Args:
        x: (Vs, 3) [m]; lam: (A,); w: (Vs,) [1/kg]; verts: (A,) int64 distinct vertex ids;
        height: (A,) target y [m]; alpha: compliance [m/N]; h: substep [s].
    """
    wv = w[verts]
    alpha_t = alpha / (h * h)
    c = x[verts, 1] - height
    dlam = torch.where(wv > 0, (-c - alpha_t * lam) / (wv + alpha_t), torch.zeros_like(c))
    lam += dlam
    x[verts, 1] += wv * dlam


# ------------------------------------------------------------------------------------- fused substeps


def xpbd_substeps_(
    x: torch.Tensor,
    v: torch.Tensor,
    vert_inv_mass: torch.Tensor,
    stretch: list[torch.Tensor],
    bend: list[torch.Tensor],
    seams: list[torch.Tensor],
    body: list[torch.Tensor],
    coefficients: list[float],
    substeps: int,
    iterations: int,
    jacobi: bool,
    num_threads: int,
) -> None:
    """XPBD substeps of one frame, in place on ``x`` and ``v`` (twin of the fused C++ op).

    Args:
        x, v: (Vs, 3) positions [m] and velocities [m/s], updated in place.
        vert_inv_mass, stretch, bend, seams, body, coefficients, substeps, iterations, jacobi,
        num_threads: `SubstepInputs.op_args` (the tensor lists and scalars by role, see `sim/substep.py`;
        num_threads is used by the C++ op only).

    The maths is `xpbd_substeps`, run out of place under ``no_grad`` and copied into x and v.
    """
    inputs = SubstepInputs.from_op_args(
        vert_inv_mass, stretch, bend, seams, body, coefficients, substeps, iterations, jacobi, num_threads
    )
    with torch.no_grad():
        xs, vs = xpbd_substeps(x, v, inputs)
    x.copy_(xs)
    v.copy_(vs)


class KernelMembrane:
    """The stretch and bend passes of `xpbd_substeps` by the per-constraint kernels (in place, on a copy).

    Args:
        inputs: the call's `SubstepInputs`.
        kernels: an object with ``stretch_project_``, ``bend_project_``, ``stretch_project_jacobi_`` and
            ``bend_project_jacobi_``: this module's (default) or `sim.ops` (the C++ ops one at a time: the
            benchmark's former, unfused path).
    """

    def __init__(self, inputs: SubstepInputs, kernels=None):
        self.inputs = inputs
        self.kernels = _REFERENCE_KERNELS if kernels is None else kernels

    def start(self, x: torch.Tensor):
        """The multipliers of a new substep: (F, 3) and (E,) zeros."""
        face_count, edge_count = (
            self.inputs.stretch.tri_vertices.shape[0],
            self.inputs.bend.edge_quads.shape[0],
        )
        return x.new_zeros(face_count, 3), x.new_zeros(edge_count)

    def project(self, x: torch.Tensor, lam):
        """One stretch pass, then one bend pass; returns (x, lam) with x a new tensor (autograd may still
        need the old one)."""
        k, w, p = self.kernels, self.inputs.vert_inv_mass, self.inputs.params
        tri, edge = self.inputs.stretch, self.inputs.bend
        lam_tri, lam_edge = lam
        x = x.clone()
        if p.jacobi:
            k.stretch_project_jacobi_(
                x, lam_tri, w, tri.tri_vertices, tri.tri_rest_inv, tri.tri_compliance, p.dt, p.jacobi_omega
            )
            if lam_edge.numel():
                k.bend_project_jacobi_(
                    x, lam_edge, w, edge.edge_quads, edge.edge_rest_angle, edge.edge_compliance, p.dt,
                    p.jacobi_omega,
                )  # fmt: skip
        else:
            k.stretch_project_(
                x, lam_tri, w, tri.tri_vertices, tri.tri_rest_inv, tri.tri_compliance, tri.tri_order,
                tri.tri_color_offsets, p.dt,
            )  # fmt: skip
            if lam_edge.numel():
                k.bend_project_(
                    x, lam_edge, w, edge.edge_quads, edge.edge_rest_angle, edge.edge_compliance,
                    edge.edge_order, edge.edge_color_offsets, p.dt,
                )  # fmt: skip
        return x, lam


@dataclass(frozen=True)
class _ContactResponse:
    """A call's contact set with its frames, computed once per call (the body is static within it)."""

    contacts: Contacts
    point: torch.Tensor  # (C, 3) [m]
    normal: torch.Tensor  # (C, 3)
    movable: torch.Tensor  # (C,) 1 for free vertices, 0 for pinned ones
    thickness: float

    @staticmethod
    def of(inputs: SubstepInputs, x: torch.Tensor) -> _ContactResponse | None:
        contacts = inputs.body.contacts()
        if contacts is None:
            return None
        point, normal = contact_frames(inputs.body.body_verts, inputs.body.body_faces, contacts)
        movable = (inputs.vert_inv_mass.detach()[contacts.vert] > 0).to(x.dtype)
        return _ContactResponse(contacts, point, normal, movable, inputs.params.thickness)

    def project(self, x: torch.Tensor):
        return push_out(
            x, self.contacts.vert, self.point, self.normal, self.movable, self.thickness, self.contacts.layers
        )


def xpbd_substeps(x: torch.Tensor, v: torch.Tensor, inputs: SubstepInputs, membrane=None):
    """The XPBD substeps of `xpbd_substeps_`, out of place and differentiable in x, v and every tensor of
    ``inputs`` (the one frame that the reference twin, `trajectory.replay_frame` and `ReplayPlan` share).

    Per substep: ``v = (v · velocity_decay + gravity · dt) · [w > 0]``, ``x_start = x``, ``x += v · dt``,
    multipliers reset to 0; then ``iterations`` × (``membrane``'s stretch and bend passes, `attach_project_`,
    the contact projection (`contacts.push_out`, with the contact frames computed once per call), and
    `stitch_project_` last, so that a seam pressed onto the body still closes); then `contacts.apply_friction`
    with the summed contact depths (when ``friction`` > 0 and there are contacts); finally
    ``v = (x − x_start) / dt``, less the outward normal velocity of the pushed contacts that
    ``contact_bounce`` < 1 removes (`contacts.damp_bounce`).

    Args:
        x, v: (Vs, 3) positions [m] and velocities [m/s] (not modified).
        inputs: `SubstepInputs`.
        membrane: the stretch and bend passes: an object with ``start(x) -> lam`` (a substep's multipliers)
            and ``project(x, lam) -> (x, lam)`` (one pass of each, out of place); default
            `KernelMembrane` (this module's kernels). `ReplayPlan.membrane` is the batched variant.

    Returns:
        (x, v) at the end, (Vs, 3) each.
    """
    p = inputs.params
    membrane = KernelMembrane(inputs) if membrane is None else membrane
    movable = (inputs.vert_inv_mass.detach() > 0).to(x.dtype)[:, None]
    gravity_dt = x.new_tensor(p.gravity) * p.dt
    contact = _ContactResponse.of(inputs, x)
    for _ in range(p.substeps):
        x_start = x
        v = (v * p.velocity_decay + gravity_dt) * movable
        x, depth_sum = _iterations(x + v * p.dt, inputs, membrane, contact)
        if contact is not None and p.friction > 0:
            x = apply_friction(x, x_start, contact.contacts, contact.normal, depth_sum, p.friction)
        v = (x - x_start) / p.dt
        if contact is not None and p.contact_bounce < 1:
            v = damp_bounce(v, contact.contacts, contact.normal, depth_sum, p.contact_bounce)
    return x, v


def _iterations(x, inputs: SubstepInputs, membrane, contact: _ContactResponse | None):
    """The constraint iterations of one substep; returns (x, summed contact depths (C,) or None)."""
    p, seams, w = inputs.params, inputs.seams, inputs.vert_inv_mass
    lam = membrane.start(x)
    lam_attach = x.new_zeros(seams.attach_vertices.shape[0])
    lam_stitch = x.new_zeros(seams.stitch_vertices.shape[0], 3)
    depth_sum = None
    for _ in range(p.iterations):
        x, lam = membrane.project(x, lam)
        if lam_attach.numel():
            x = x.clone()
            attach_project_(
                x, lam_attach, w, seams.attach_vertices, seams.attach_height, p.attach_compliance, p.dt
            )
        if contact is not None:
            x, depth = contact.project(x)
            depth_sum = depth if depth_sum is None else depth_sum + depth
        if lam_stitch.numel():  # stitches last: a seam pressed onto the body still closes
            x = x.clone()
            stitch_project_(
                x,
                lam_stitch,
                w,
                seams.stitch_vertices,
                p.stitch_compliance,
                p.dt,
                p.stitch_max_move,
                p.stitch_snap,
            )
    return x, depth_sum


def max_abs_green_strain(
    x: torch.Tensor, tri_vertices: torch.Tensor, tri_rest_inv: torch.Tensor
) -> torch.Tensor:
    """Largest ``|E00|``, ``|E11|`` or ``|E01|`` of the Green strain (the solver's blow-up test).

    Args:
        x: (Vs, 3) [m]; tri_vertices: (F, 3) int64; tri_rest_inv: (F, 2, 2) [1/m].

    Returns:
        0-dim tensor of x's dtype (0 when F = 0).
    """
    if tri_vertices.shape[0] == 0:
        return x.new_zeros(())
    return green_strain(x, tri_vertices, tri_rest_inv).abs().max()


_REFERENCE_KERNELS = SimpleNamespace(
    stretch_project_=stretch_project_,
    bend_project_=bend_project_,
    stretch_project_jacobi_=stretch_project_jacobi_,
    bend_project_jacobi_=bend_project_jacobi_,
)


# ------------------------------------------------------------------------ element Hessians (adjoint)


def _stretch_energy_one(xt, rest_inv, area, stiffness):
    c = triangle_green_strain(xt, rest_inv)
    return 0.5 * area * (c @ stiffness @ c)


def _bend_energy_one(xq, weight, rest_angle, bend_stiffness):
    x0, x1, x2, x3 = xq.unbind(0)
    e = x1 - x0
    n1 = torch.linalg.cross(e, x2 - x0)
    n2 = torch.linalg.cross(x0 - x1, x3 - x1)
    theta = torch.atan2(torch.linalg.cross(n1, n2) @ (e / e.norm()), n1 @ n2)
    return 0.5 * bend_stiffness * weight * (theta - rest_angle) ** 2


def project_psd(h: torch.Tensor) -> torch.Tensor:
    """(K, n, n) symmetric blocks projected to PSD: eigenvalues clamped at 0 (``torch.linalg.eigh``)."""
    if h.shape[0] == 0:
        return h
    evals, evecs = torch.linalg.eigh(0.5 * (h + h.transpose(1, 2)))
    return (evecs * evals.clamp_min(0.0)[:, None, :]) @ evecs.transpose(1, 2)


def stretch_hessians(
    x: torch.Tensor,
    tri_vertices: torch.Tensor,
    tri_rest_inv: torch.Tensor,
    tri_area: torch.Tensor,
    stiffness: torch.Tensor,
    project: bool,
) -> torch.Tensor:
    """Per-triangle Hessians of the membrane energy ``Ā/2 Cᵀ K C`` (C as in the stretch kernel).

    Args:
        x: (Vs, 3) [m]; tri_vertices: (F, 3) int64; tri_rest_inv: (F, 2, 2) [1/m]; tri_area: (F,) [m²];
        stiffness: (3, 3) K [N/m]; project: clamp each block's negative eigenvalues to 0.

    Returns:
        (F, 9, 9) [N/m], dofs ordered 3·corner + axis (``torch.func.hessian``, then `project_psd`).
    """
    from torch.func import hessian, vmap

    h = vmap(hessian(_stretch_energy_one), in_dims=(0, 0, 0, None))(
        x[tri_vertices], tri_rest_inv, tri_area, stiffness.to(x.dtype)
    ).reshape(-1, 9, 9)
    return project_psd(h) if project else h


def bend_hessians(
    x: torch.Tensor,
    edge_quads: torch.Tensor,
    edge_weight: torch.Tensor,
    edge_rest_angle: torch.Tensor,
    bend_stiffness: float,
    project: bool,
) -> torch.Tensor:
    """Per-edge Hessians of the bending energy ``k_b w/2 (θ − θ̄)²`` (θ as in the bend kernel).

    Args:
        x: (Vs, 3) [m]; edge_quads: (E, 4) int64; edge_weight: (E,) [-]; edge_rest_angle: (E,) [rad];
        bend_stiffness: k_b [N·m]; project: clamp each block's negative eigenvalues to 0.

    Returns:
        (E, 12, 12) [N/m], dofs ordered 3·quad vertex + axis.
    """
    from torch.func import hessian, vmap

    kb = x.new_tensor(float(bend_stiffness))
    h = vmap(hessian(_bend_energy_one), in_dims=(0, 0, 0, None))(
        x[edge_quads], edge_weight, edge_rest_angle, kb
    ).reshape(-1, 12, 12)
    return project_psd(h) if project else h


# ------------------------------------------------------------------- block sparse Cholesky (adjoint)


def block_cholesky_analyze(
    crow: torch.Tensor, col: torch.Tensor, perm: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Symbolic block Cholesky of a CSR matrix with 3×3 block structure, in vertex ordering ``perm``.

    Args:
        crow: (n+1,) int64; col: (nnz,) int64 sorted per row, whole column triples, rows 3v..3v+2 alike.
        perm: (n/3,) int64 new → old vertex ordering.

    Returns:
        parent (n/3,) int64 elimination tree of the permuted vertex graph (−1 at roots), l_colptr
        (n/3+1,) int64 block column pointers of L (diagonal block included). Plain loops: small problems.
    """
    nb = (crow.shape[0] - 1) // 3
    c, cl = crow.tolist(), col.tolist()
    pinv = [0] * nb
    for i, p in enumerate(perm.tolist()):
        pinv[p] = i
    perm_l = perm.tolist()
    nbrs = [[pinv[cl[t] // 3] for t in range(c[3 * r], c[3 * r + 1], 3)] for r in perm_l]  # permuted rows
    parent = [-1] * nb
    for k in range(nb):  # Liu's algorithm: hang the root of each lower neighbour's subtree below k
        for i in nbrs[k]:
            if i >= k:
                continue
            while parent[i] not in (-1, k):
                i = parent[i]
            if parent[i] == -1:
                parent[i] = k
    count = [1] * nb
    for k in range(nb):
        seen = {k}
        for i in nbrs[k]:
            while i < k and i not in seen:
                seen.add(i)
                count[i] += 1
                i = parent[i]
    colptr = [0]
    for k in range(nb):
        colptr.append(colptr[-1] + count[k])
    return torch.tensor(parent, dtype=torch.int64), torch.tensor(colptr, dtype=torch.int64)


def block_cholesky_solve(
    crow: torch.Tensor,
    col: torch.Tensor,
    val: torch.Tensor,
    b: torch.Tensor,
    perm: torch.Tensor,
    parent: torch.Tensor,
    l_colptr: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve the SPD system ``H x = b`` by a Cholesky factorisation (dense here: small problems only).

    Args:
        crow, col, val: H in CSR (both triangles); b: (n,); perm, parent, l_colptr: from
        `block_cholesky_analyze` (unused by this dense twin, which needs no ordering).

    Returns:
        x (n,), info (4,) float64 = [0, |b − H x| / |b|, flag (0 ok, 3 H not positive definite),
        smallest pivot of the factorisation (squared diagonal of L; it depends on the ordering)].
    """
    h = _dense_lower(crow, col, val)
    info = torch.zeros(4, dtype=torch.float64)
    chol, err = torch.linalg.cholesky_ex(h)
    if int(err) != 0:
        info[1], info[2] = float("inf"), 3
        return torch.full_like(b, float("nan")), info
    x = torch.cholesky_solve(b.double()[:, None], chol)[:, 0]
    nb_ = float(b.double().norm())
    info[1] = float((b.double() - _dense(crow, col, val) @ x).norm()) / (nb_ if nb_ > 0 else 1.0)
    info[3] = float(chol.diagonal().min() ** 2)
    return x.to(b.dtype), info


def _dense(crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor) -> torch.Tensor:
    """(n, n) float64 dense matrix of the CSR (crow, col, val)."""
    n = crow.shape[0] - 1
    row = torch.repeat_interleave(torch.arange(n), crow[1:] - crow[:-1])
    h = torch.zeros(n, n, dtype=torch.float64)
    h[row, col] = val.double()
    return h


def _dense_lower(crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor) -> torch.Tensor:
    """(n, n) float64 symmetric matrix of the CSR's lower triangle (what the C++ factorisation reads)."""
    h = _dense(crow, col, val)
    return torch.tril(h) + torch.tril(h, -1).T


def block_cholesky_factor(
    crow: torch.Tensor,
    col: torch.Tensor,
    val: torch.Tensor,
    perm: torch.Tensor,
    parent: torch.Tensor,
    l_colptr: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Numeric block Cholesky ``P H Pᵀ = L Lᵀ`` of an SPD CSR matrix with 3×3 block structure (dense here:
    small problems only).

    Args:
        crow, col, val: H in CSR (both triangles); perm: (nb,) int64 new → old vertex ordering; parent,
        l_colptr: `block_cholesky_analyze` of that ordering.

    Returns:
        l_row (nnzl,) int64: the block row of each stored block of L, column by column (column j holds
        ``l_row[l_colptr[j]:l_colptr[j+1]]``: j itself first, then its rows below in increasing order);
        l_val (nnzl, 9) float64: those 3×3 blocks, row-major; info (4,) float64 = [0, 0, flag (0 ok, 3 not
        positive definite: l_val is NaN), smallest pivot].
    """
    nb = perm.shape[0]
    p = (3 * perm[:, None] + torch.arange(3)).reshape(-1)
    h = _dense_lower(crow, col, val)[p][:, p]
    info = torch.zeros(4, dtype=torch.float64)
    chol, err = torch.linalg.cholesky_ex(h)
    rows, cp = [[] for _ in range(nb)], l_colptr.tolist()
    # the structure of L: row k reaches up the elimination tree from each lower neighbour (cs_ereach)
    c, cl, par, pinv = crow.tolist(), col.tolist(), parent.tolist(), torch.argsort(perm).tolist()
    for k in range(nb):
        r = int(perm[k])
        seen = {k}
        for t in range(c[3 * r], c[3 * r + 1], 3):
            i = pinv[cl[t] // 3]
            while i < k and i not in seen:
                seen.add(i)
                rows[i].append(k)
                i = par[i]
    l_row = torch.tensor([x for j in range(nb) for x in [j, *sorted(rows[j])]], dtype=torch.int64)
    col_of = torch.repeat_interleave(torch.arange(nb), torch.tensor([cp[j + 1] - cp[j] for j in range(nb)]))
    blocks = chol.reshape(nb, 3, nb, 3).permute(0, 2, 1, 3)  # [row block, col block, 3, 3]
    l_val = blocks[l_row, col_of].reshape(-1, 9).contiguous()
    if int(err) != 0:
        info[2] = 3
        return l_row, torch.full_like(l_val, float("nan")), info
    info[3] = float(chol.diagonal().min() ** 2)
    return l_row, l_val, info


def block_cholesky_apply(
    l_row: torch.Tensor, l_val: torch.Tensor, perm: torch.Tensor, l_colptr: torch.Tensor, b: torch.Tensor
) -> torch.Tensor:
    """``x = Pᵀ L⁻ᵀ L⁻¹ P b`` (n,) in b's dtype, with a `block_cholesky_factor` (l_row, l_val, l_colptr) and
    its ordering ``perm`` (dense triangular solves: small problems only)."""
    nb = perm.shape[0]
    cp = l_colptr.tolist()
    col_of = torch.repeat_interleave(torch.arange(nb), torch.tensor([cp[j + 1] - cp[j] for j in range(nb)]))
    lower = torch.zeros(nb, nb, 3, 3, dtype=torch.float64)
    lower[l_row, col_of] = l_val.reshape(-1, 3, 3)
    lower = lower.permute(0, 2, 1, 3).reshape(3 * nb, 3 * nb)
    p = (3 * perm[:, None] + torch.arange(3)).reshape(-1)
    y = torch.linalg.solve_triangular(lower, b.double()[p][:, None], upper=False)
    z = torch.linalg.solve_triangular(lower.T, y, upper=True)[:, 0]
    x = torch.empty_like(z)
    x[p] = z
    return x.to(b.dtype)
