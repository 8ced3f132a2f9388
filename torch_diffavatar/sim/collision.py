"""Cloth–body collision: vertex–triangle contacts against any triangle mesh, with friction.

Detection (`detect_contacts`, no autograd) runs once per step: for every cloth vertex the closest body
triangle within a band. The response (`contact_frames`, `project_contacts`, `apply_friction`, in
`sim/contacts.py` and re-exported here) is plain, out-of-place torch and recomputes the contact point
(barycentric point on the stored triangle) and the face normal from the CURRENT ``body_verts`` each time,
so the projected positions are a differentiable function of the body vertices (paper eq. 6).
Limitations: no self-collision, no edge–edge contacts, one contact per cloth vertex (two in a valley with
``valley``, and the floor besides by a foot with ``floor``), the body is static within a step.

Ties: a vertex whose closest body point lies on a body edge (or vertex) is equally close to every face
sharing that feature, and the query picks one of them by rounding. The response uses the picked face's
plane, and those planes differ there (by up to ~3 mm on the Anny body at 3 mm thickness), so a frictionless
vertex sliding over the edge switched planes from frame to frame and the drape never came to rest.
`detect_contacts` therefore picks, among the faces sharing the closest feature, the one whose plane is
farthest from the vertex (the normal closest to the direction from the closest point): the plane distance
is then continuous as the vertex crosses the edge's region.

Valleys: a contact's plane extends past its triangle. Where the body folds inward (the armpit, the spine's
groove) the plane of one side runs into the other side, and a vertex held by one plane alone slides through
it: the next frame the other side is closest and pushes it back. Two vertices of a fitted dress's armpits
jumped 6.5–8.5 mm every frame so, and the drape never settled. With ``valley`` (`XPBDConfig.valley_contacts`)
a vertex within ``valley`` [m] of a triangle around its contact triangle that rises above the contact's plane
(a valley) gets a second contact with the closest such triangle, so that it is held by both sides.
"""

from __future__ import annotations

import torch

from torch_diffavatar.sim import ops, reference

# the differentiable response lives below the kernels (`sim/contacts.py`); re-exported for callers
from torch_diffavatar.sim.contacts import (  # noqa: F401
    Contacts,
    apply_friction,
    contact_frames,
    project_contacts,
    signed_distance_along_normal,
    unit_normals,
)


class BodyIndex:
    """The closest-point grid of a body mesh, built once for a body that does not move (no autograd).

    `detect_contacts` (``index=``) then skips the per-call grid build; the contacts are bit-identical to
    the ones without an index (`ops.closest_point_query`). Holds a copy of the mesh it was built from:
    `matches` tells whether it applies to a given (verts, faces). Without the C++ extension (or with
    ``use_extension=False``) it holds no grid and queries fall back to `ops.closest_point_on_mesh`.

    Args:
        body_verts: (Vb, 3) [m]; body_faces: (Fb, 3) int64.
        cell_size: grid cell edge [m]; None picks the op's default (mean triangle size). Only the speed
            depends on it.
    """

    def __init__(
        self,
        body_verts: torch.Tensor,
        body_faces: torch.Tensor,
        *,
        cell_size: float | None = None,
        use_extension=True,
    ):
        self.verts = body_verts.detach().clone().contiguous()
        self.faces = body_faces.detach().clone().contiguous()
        self.use_extension = use_extension
        self.grid = None
        self.features = _feature_faces(self.faces, self.verts.shape[0])  # shared: its tables outlive us
        if ops.closest_point_index_available(self.verts.device, use_extension):
            self.grid = ops.closest_point_index(
                self.verts, self.faces, 0.0 if cell_size is None else cell_size
            )

    def matches(self, body_verts: torch.Tensor, body_faces: torch.Tensor) -> bool:
        """True when (body_verts, body_faces) equal the mesh this index was built from."""
        return (
            body_verts.shape == self.verts.shape
            and body_faces.shape == self.faces.shape
            and body_verts.dtype == self.verts.dtype
            and body_verts.device == self.verts.device
            and torch.equal(body_faces, self.faces)
            and torch.equal(body_verts.detach(), self.verts)
        )

    def closest_point(self, points: torch.Tensor, max_dist: float, hint: torch.Tensor | None = None):
        """(tri, bary, dist) of `ops.closest_point_on_mesh` (points, verts, faces, max_dist). ``hint``: (N,)
        int64 triangles to test first (`ops.closest_point_query`; speed only, ignored without the grid)."""
        points = points.detach().contiguous()
        if self.grid is not None and points.device.type == "cpu":
            return ops.closest_point_query(points, self.verts, self.faces, self.grid, max_dist, hint)
        return ops.closest_point_on_mesh(
            points, self.verts, self.faces, max_dist, use_extension=self.use_extension
        )


class ContactCache:
    """What the last queries against one static body learnt about each cloth vertex, so that the next
    frame's detection queries only the vertices that can be in its band, and those mostly among a few
    triangles.

    Per vertex: its position at its last query, a lower bound of its distance to the body from there
    (the distance found, or the probe radius when nothing was closer) and the triangle found (-1: none);
    for a vertex found in the band, the triangles within (its distance + 2 ``margin``) of where it was
    (its candidates). Each frame:

    - a vertex whose lower bound minus how far it has moved since is beyond the band cannot be in contact:
      not queried;
    - a vertex within ``margin`` of where its candidates were collected: its closest triangle is among
      them (it is at most its old distance + ``margin`` from the body, and any triangle that close lies
      within old distance + 2 ``margin`` of the old position), found by `ops.closest_point_among`;
    - any other vertex: the grid query (`ops.closest_point_query`) in the full band, with last frame's
      triangle as its first candidate; new candidates are collected for it when it is in the band.

    All three give exactly the full query's result (the same distance test and tie-break), so the contacts
    equal those of `detect_contacts` without a cache: only the speed depends on the cache.

    Args:
        index: the `BodyIndex` of the body (the cache applies to it only; needs its C++ grid).
        probe: a vertex queried and found outside the band is probed again out to ``band + probe`` [m],
            to learn how far it is (a larger probe costs more per probe but skips the vertex for longer).
        margin: how far [m] a vertex may move before its candidates are collected again (larger: longer
            lists that last longer).
        max_radius: no candidates for a vertex farther than ``max_radius - 2 margin`` [m] from the body:
            its list would be long (a wide band while sewing), and it is grid-queried instead.
    """

    def __init__(
        self, index: BodyIndex, *, probe: float = 0.02, margin: float = 0.002, max_radius: float = 0.03
    ):
        if index.grid is None:
            raise ValueError("ContactCache needs a BodyIndex with its C++ grid")
        self.index = index
        self.probe = probe
        self.margin = margin
        self.max_radius = max_radius
        self.x: torch.Tensor | None = None  # (Vs, 3) float64 [m], at the last query
        self.lower: torch.Tensor | None = None  # (Vs,) float64 [m]
        self.tri: torch.Tensor | None = None  # (Vs,) int64
        self.x_cand: torch.Tensor | None = None  # (Vs, 3) float64 [m], where the candidates were collected
        self.cand: torch.Tensor | None = None  # (Vs, K) int64, -1 padded
        self.has_cand: torch.Tensor | None = None  # (Vs,) bool
        self.queried = 0  # vertices queried by the last `closest_point` (for benchmarks and tests)
        self.among = 0  # of which among their candidates

    def closest_point(self, x: torch.Tensor, band: float):
        """(tri (Vs,) int64, bary (Vs, 3)) of ``index.closest_point(x, band)``, bit for bit (-1 and zeros
        outside the band); x: (Vs, 3) [m]."""
        x = x.detach()
        x64 = x.to(torch.float64)
        n = x.shape[0]
        if self.x is None or self.x.shape != x64.shape or self.x.device != x.device:
            self._reset(x64)
        moved = (x64 - self.x).norm(dim=-1)
        # the C++ query decides on double distances: 1e-5 m covers their rounding and float32 distances
        # (NaN positions compare False: queried)
        active = torch.nonzero(~(self.lower - moved > band + _CACHE_SLACK)).squeeze(1)
        self.queried = int(active.numel())
        sub_tri, sub_bary, sub_dist = self._query(x, x64, active, band)
        tri = torch.full((n,), -1, dtype=torch.int64, device=x.device)
        bary = x.new_zeros(n, 3)
        tri[active], bary[active] = sub_tri, sub_bary
        self._remember(x, x64, active, band, sub_tri, sub_dist)
        return tri, bary

    def _reset(self, x64):
        n = x64.shape[0]
        self.x, self.x_cand = x64.clone(), x64.clone()
        self.lower = x64.new_zeros(n)
        self.tri = torch.full((n,), -1, dtype=torch.int64, device=x64.device)
        self.cand = torch.full((n, 1), -1, dtype=torch.int64, device=x64.device)
        self.has_cand = torch.zeros(n, dtype=torch.bool, device=x64.device)

    def _query(self, x, x64, active, band):
        """(tri, bary, dist) of the ``active`` vertices: among their candidates where they still hold,
        else the grid query (then new candidates for those in the band)."""
        index = self.index
        drift = (x64[active] - self.x_cand[active]).norm(dim=-1)
        near = self.has_cand[active] & (drift <= self.margin - _CACHE_SLACK)
        m = active.numel()
        tri = torch.full((m,), -1, dtype=torch.int64, device=x.device)
        bary, dist = x.new_zeros(m, 3), x.new_full((m,), torch.inf)
        fast, slow = torch.nonzero(near).squeeze(1), torch.nonzero(~near).squeeze(1)
        self.among = int(fast.numel())
        if fast.numel():
            ids = active[fast]
            tri[fast], bary[fast], dist[fast] = ops.closest_point_among(
                x[ids].contiguous(), index.verts, index.faces, self.cand[ids], band
            )
        if slow.numel():
            ids = active[slow]
            tri[slow], bary[slow], dist[slow] = index.closest_point(x[ids], band, self.tri[ids])
            hit = (tri[slow] >= 0) & (dist[slow] + 2 * self.margin <= self.max_radius)
            self.has_cand[ids] = hit
            self._collect(x, x64, ids[hit], dist[slow][hit])
        return tri, bary, dist

    def _collect(self, x, x64, ids, dist):
        """New candidates of vertices ``ids`` at distance ``dist`` [m] from the body."""
        if ids.numel() == 0:
            return
        radius = dist.to(torch.float64) + 2 * self.margin
        cand = ops.closest_point_candidates(
            x[ids].contiguous(), self.index.verts, self.index.faces, self.index.grid, radius
        )
        width = max(cand.shape[1], self.cand.shape[1])
        if self.cand.shape[1] < width:
            self.cand = torch.nn.functional.pad(self.cand, (0, width - self.cand.shape[1]), value=-1)
        self.cand[ids] = torch.nn.functional.pad(cand, (0, width - cand.shape[1]), value=-1)
        self.x_cand[ids] = x64[ids]

    def _remember(self, x, x64, active, band, sub_tri, sub_dist):
        """Store the queried vertices' positions, distance bounds and triangles; probe the misses."""
        lower = sub_dist.to(torch.float64)
        miss = torch.nonzero(sub_tri < 0).squeeze(1)
        if miss.numel():
            reach = band + self.probe
            far_tri, _, far_dist = self.index.closest_point(x[active[miss]], reach)
            sub_tri = sub_tri.clone()
            sub_tri[miss] = far_tri  # a hint for when the vertex comes closer
            lower[miss] = torch.where(
                far_tri >= 0, far_dist.to(torch.float64), torch.full_like(lower[miss], reach)
            )
        self.x[active] = x64[active]
        self.lower[active] = lower
        self.tri[active] = sub_tri


_CACHE_SLACK = 1e-5  # [m]


def detect_contacts(
    x: torch.Tensor,
    body_verts: torch.Tensor,
    body_faces: torch.Tensor,
    band: float,
    *,
    use_extension=True,
    index: BodyIndex | None = None,
    cache: ContactCache | None = None,
    valley: float | None = None,
    floor: tuple[int, float] | None = None,
) -> Contacts:
    """Closest body triangle of every cloth vertex within ``band`` [m] (no autograd).

    Args:
        x: (Vs, 3) cloth positions [m]; body_verts: (Vb, 3) [m]; body_faces: (Fb, 3) int64.
        index: a `BodyIndex` of exactly (body_verts, body_faces) to reuse (ValueError otherwise).
        cache: a `ContactCache` of that index (or of the body's, without ``index``): the same contacts,
            faster from frame to frame.
        valley: a contact vertex within this distance [m] of a valley partner of its triangle (one around
            it that rises above its plane) gets a second contact with the closest one, listed after every
            first contact (module docstring). None: one contact per vertex.
        floor: (first floor face, radius [m]): the faces from that one on are a floor (`sim.floor`). A
            vertex whose first contact is a body face within ``radius`` of the floor also gets the floor,
            listed last: where a foot's side meets the floor the two planes form a valley that shares no
            vertex. With one contact a vertex there was pushed below the floor by the foot's plane and back
            up by the floor's, frame after frame (a pile of trousers, 2.8 mm each way: it never settled).
    """
    with torch.no_grad():
        if cache is not None:
            if index is not None and cache.index is not index:
                raise ValueError("cache was built for another index")
            index = cache.index
        if index is not None:
            if not index.matches(body_verts, body_faces):
                raise ValueError("index was built for another body mesh")
            if cache is not None:
                tri, bary = cache.closest_point(x, band)
            else:
                tri, bary, _ = index.closest_point(x, band)
        else:
            tri, bary, _ = ops.closest_point_on_mesh(
                x.detach().contiguous(),
                body_verts.detach().contiguous(),
                body_faces.contiguous(),
                band,
                use_extension=use_extension,
            )
        vert = torch.nonzero(tri >= 0).squeeze(1)
        features = index.features if index is not None else _feature_faces(body_faces, body_verts.shape[0])
        tri, bary = features.outermost(x.detach()[vert], body_verts.detach(), tri[vert], bary[vert])
        first = vert
        if valley is not None and vert.numel():
            k, tri2, bary2 = features.valley_partners(
                x.detach()[vert], body_verts.detach(), tri, valley, use_extension=use_extension
            )
            vert, tri, bary = torch.cat((vert, vert[k])), torch.cat((tri, tri2)), torch.cat((bary, bary2))
        if floor is not None and first.numel():
            on_floor = (x.detach()[first], body_verts.detach(), body_faces, tri[: first.numel()])
            k, tri3, bary3 = _floor_contacts(*on_floor, *floor, use_extension)
            vert, tri, bary = torch.cat((vert, first[k])), torch.cat((tri, tri3)), torch.cat((bary, bary3))
    return Contacts(vert, tri, bary)


def _floor_contacts(x, body_verts, body_faces, tri, start: int, radius: float, use_extension):
    """`detect_contacts`' floor contacts: of the contacts at x (C, 3) on faces ``tri`` (C,), those on a body
    face (below ``start``) within ``radius`` [m] of the floor (faces ``start`` on), and their floor points.

    Returns:
        (k (P,) int64 ids of those contacts, tri (P,) their floor faces, bary (P, 3)).
    """
    height = body_verts[body_faces[start, 0], 1].to(x.dtype)
    rows = torch.nonzero((tri < start) & (x[:, 1] - height < radius)).squeeze(1)
    if rows.numel() == 0:
        return rows, rows, x.new_zeros(0, 3)
    cand = torch.arange(start, body_faces.shape[0], device=tri.device).expand(rows.numel(), -1)
    return _second_contacts(x, body_verts, body_faces, rows, cand, radius, use_extension)


def _second_contacts(x, body_verts, body_faces, rows, cand, radius: float, use_extension):
    """Second contacts of the contacts ``rows`` (R,) (at x (C, 3)): the closest of each row's candidate
    faces ``cand`` (R, K) (-1 padded) within ``radius`` [m], by the C++ op or its twin.

    Returns:
        (k (P,) int64 the rows that have one, tri (P,), bary (P, 3)).
    """
    fast = ops.closest_point_index_available(x.device, use_extension)
    among = ops.closest_point_among if fast else reference.closest_point_among
    points, bv = x[rows].contiguous(), body_verts.to(x.dtype).contiguous()
    tri, bary, _ = among(points, bv, body_faces.contiguous(), cand.contiguous(), float(radius))
    hit = tri >= 0
    return rows[hit], tri[hit], bary[hit].to(x.dtype)


# A valley partner's corners rise this much [m] above the contact plane: coplanar neighbours (flat to
# rounding) add nothing; any real fold, however shallow, does.
_VALLEY_RISE = 1e-5

_LAST_FEATURES: list = []  # [(faces, vert_count, _FeatureFaces)] of the last body topology


def _feature_faces(faces: torch.Tensor, vert_count: int) -> _FeatureFaces:
    """`_FeatureFaces` of ``faces``, reused while the same topology comes back: a moving body (animation,
    the trajectory adjoint's forward) has no `BodyIndex`, and the build costs ~7 ms on the Anny body,
    every frame otherwise; each of a fit's drapes builds a `BodyIndex`, and shares the valley table."""
    if _LAST_FEATURES:
        cached, count, features = _LAST_FEATURES[0]
        same = cached.shape == faces.shape and cached.device == faces.device and torch.equal(cached, faces)
        if count == vert_count and same:  # a copy is compared: faces edited in place are seen
            return features
    features = _FeatureFaces(faces, vert_count)
    _LAST_FEATURES[:] = [(faces.detach().clone(), vert_count, features)]
    return features


class _FeatureFaces:
    """Faces sharing a body edge or vertex, to break closest-face ties (see the module docstring).

    Args:
        faces: (Fb, 3) int64; vert_count: Vb.
    """

    def __init__(self, faces: torch.Tensor, vert_count: int):
        f = faces.detach().to(torch.int64)
        nf = f.shape[0]
        # across[f, i]: the face across the edge opposite corner i (f itself on a boundary edge)
        a, b = f[:, [1, 2, 0]], f[:, [2, 0, 1]]
        key = (torch.minimum(a, b) * vert_count + torch.maximum(a, b)).reshape(-1)
        order = torch.argsort(key)
        ks = key[order]
        owner = order // 3
        nxt = torch.cat((ks[1:] == ks[:-1], ks.new_zeros(1, dtype=torch.bool)))
        prv = torch.cat((ks.new_zeros(1, dtype=torch.bool), ks[1:] == ks[:-1]))
        mate = torch.where(nxt, torch.roll(owner, -1), torch.where(prv, torch.roll(owner, 1), owner))
        across = torch.empty_like(key)
        across[order] = mate
        self.across = across.reshape(nf, 3)
        # ring[u]: the faces around body vertex u, padded with -1
        corner_vert = f.reshape(-1)
        order = torch.argsort(corner_vert, stable=True)
        counts = torch.bincount(corner_vert, minlength=vert_count)
        start = torch.cumsum(counts, 0) - counts
        slot = torch.arange(corner_vert.numel(), device=f.device) - start[corner_vert[order]]
        ring = torch.full((vert_count, max(int(counts.max()), 1) if nf else 1), -1, dtype=torch.int64)
        ring = ring.to(f.device)
        ring[corner_vert[order], slot] = order // 3
        self.ring = ring
        self.faces = f
        # `valley_candidates`' [key, body verts, partner rows (Fb, P), rows done (Fb,)] of the last body
        self._valley: list | None = None

    def outermost(self, x, body_verts, tri, bary):
        """For contacts whose closest point is on an edge or vertex of face ``tri``: the face sharing that
        feature whose plane is farthest from x, and the point's barycentrics on it. (C, 3), (C,), (C, 3)."""
        zero = bary <= 0
        nz = zero.sum(-1)
        # only points on an edge or a vertex can change face: most contacts are inside their face
        on_feature = torch.nonzero(nz > 0).squeeze(1)
        if on_feature.numel() == 0:
            return tri, bary
        sub_tri, sub_bary = self._outermost(
            x[on_feature], body_verts, tri[on_feature], bary[on_feature], zero[on_feature], nz[on_feature]
        )
        tri, bary = tri.clone(), bary.clone()
        tri[on_feature], bary[on_feature] = sub_tri, sub_bary
        return tri, bary

    def _outermost(self, x, body_verts, tri, bary, zero, nz):
        """`outermost` for contacts on an edge (nz = 1 zero barycentric) or a vertex (nz = 2)."""
        cand = tri[:, None].expand(-1, self.ring.shape[1] + 1).clone()
        cand[:, 1:] = -1
        edge = nz == 1
        if bool(edge.any()):
            k = torch.argmax(zero[edge].to(torch.int8), dim=-1)
            cand[edge, 1] = self.across[tri[edge], k]
        corner = nz == 2
        if bool(corner.any()):
            k = torch.argmax((~zero[corner]).to(torch.int8), dim=-1)
            cand[corner, 1:] = self.ring[self.faces[tri[corner], k]]
        valid = cand >= 0
        corners = body_verts[self.faces[cand.clamp_min(0)]].to(x.dtype)  # (C, K, 3, 3)
        s = ((x[:, None, :] - corners[..., 0, :]) * unit_normals(corners)).sum(-1)
        s = torch.where(valid, s, torch.full_like(s, -torch.inf))
        best = torch.argmax(s, dim=-1)
        # keep the query's face unless another one's plane is strictly farther
        best = torch.where(s.gather(1, best[:, None])[:, 0] > s[:, 0], best, torch.zeros_like(best))
        new = cand.gather(1, best[:, None])[:, 0]
        moved = new != tri
        if not bool(moved.any()):
            return tri, bary
        # the closest point is a shared edge / vertex point: move its weights to the new face's corners
        old_c, new_c = self.faces[tri[moved]], self.faces[new[moved]]
        same = (old_c[:, :, None] == new_c[:, None, :]).to(bary.dtype)  # (M, 3 old, 3 new)
        # tri and bary are `outermost`'s own subsets: written in place
        bary[moved] = (bary[moved][:, :, None] * same).sum(1)
        tri[moved] = new[moved]
        return tri, bary

    def valley_partners(self, x, body_verts, tri, radius: float, *, use_extension=True):
        """Second contacts in valleys: for each contact (x (C, 3) on face ``tri`` (C,)), the closest of
        ``tri``'s valley partners (`valley_candidates`) when x is within ``radius`` [m] of it.

        Returns:
            (k (P,) int64 ids of the contacts that have one, tri (P,), bary (P, 3)).
        """
        cand = self.valley_candidates(body_verts, tri)
        rows = torch.nonzero(cand[:, 0] >= 0).squeeze(1)
        if rows.numel() == 0:
            empty = tri.new_zeros(0)
            return empty, empty, x.new_zeros(0, 3)
        return _second_contacts(x, body_verts, self.faces, rows, cand[rows], radius, use_extension)

    def valley_candidates(self, body_verts, tri) -> torch.Tensor:
        """(C, P) int64: for each face ``tri`` (C,), the faces sharing a vertex with it that rise more than
        `_VALLEY_RISE` above its plane (a fold inward), padded with -1 (partners first).

        Worked out per face on first use and kept while the body stays the same (a drape's frames ask for
        much the same faces: a few ms per drape on the Anny body instead of ~0.1 s for all its faces)."""
        key = (body_verts.shape, body_verts.dtype, body_verts.device)
        cache = self._valley
        if cache is None or cache[0] != key or not torch.equal(cache[1], body_verts):
            nf = self.faces.shape[0]
            rows = torch.full((nf, 1), -1, dtype=torch.int64, device=self.faces.device)
            done = torch.zeros(nf, dtype=torch.bool, device=self.faces.device)
            cache = self._valley = [key, body_verts.detach().clone(), rows, done]
        rows, done = cache[2], cache[3]
        need = torch.unique(tri[~done[tri]])
        if need.numel():
            part = self._partners(need, body_verts.detach().to(torch.float64))
            if part.shape[1] > rows.shape[1]:
                rows = torch.cat((rows, rows.new_full((rows.shape[0], part.shape[1] - rows.shape[1]), -1)), 1)
                cache[2] = rows
            rows[need, : part.shape[1]] = part
            done[need] = True
        return rows[tri]

    def _partners(self, ids, verts) -> torch.Tensor:
        """`valley_candidates` of the faces ``ids`` (K,) on the float64 body ``verts``, in chunks."""
        table = torch.full((ids.numel(), 1), -1, dtype=torch.int64, device=self.faces.device)
        for lo in range(0, ids.numel(), 4096):
            chunk = ids[lo : lo + 4096]
            cand = self.ring[self.faces[chunk]].reshape(chunk.numel(), -1)  # the faces around the corners
            c = verts[self.faces[chunk]]
            n = unit_normals(c)
            top = verts[self.faces[cand.clamp_min(0)]] - c[:, None, None, 0]
            rise = (top * n[:, None, None]).sum(-1).amax(-1)
            ok = (cand >= 0) & (cand != chunk[:, None]) & (rise > _VALLEY_RISE)
            if not bool(ok.any()):
                continue
            part = torch.where(ok, cand, -1).sort(dim=1, descending=True).values
            width = int(ok.sum(1).max())
            if width > table.shape[1]:
                table = torch.cat((table, table.new_full((ids.numel(), width - table.shape[1]), -1)), 1)
            table[lo : lo + chunk.numel(), :width] = part[:, :width]
        return table
