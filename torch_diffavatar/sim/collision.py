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

import weakref

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
        # the tensors last found equal to the mesh, with their version counters: a drape passes the same
        # two every frame, and comparing the body twice a frame was a fifth of its contact detection
        self._matched: tuple | None = None
        self.grid = None
        self.features = _feature_faces(self.faces, self.verts.shape[0])  # shared: its tables outlive us
        if ops.closest_point_index_available(self.verts.device, use_extension):
            self.grid = ops.closest_point_index(
                self.verts, self.faces, 0.0 if cell_size is None else cell_size
            )

    def matches(self, body_verts: torch.Tensor, body_faces: torch.Tensor) -> bool:
        """True when (body_verts, body_faces) equal the mesh this index was built from (compared once per
        pair of tensors while neither is modified in place: their version counters say so)."""
        inference = body_verts.is_inference() or body_faces.is_inference()  # no version counter: compared
        versions = None if inference else (body_verts._version, body_faces._version)
        last = self._matched  # weak references: the index must not keep a body (and its graph) alive
        if versions and last and last[0]() is body_verts and last[1]() is body_faces and last[2] == versions:
            return True
        ok = (
            body_verts.shape == self.verts.shape
            and body_faces.shape == self.faces.shape
            and body_verts.dtype == self.verts.dtype
            and body_verts.device == self.verts.device
            and torch.equal(body_faces, self.faces)
            and torch.equal(body_verts.detach(), self.verts)
        )
        if ok and versions:
            self._matched = (weakref.ref(body_verts), weakref.ref(body_faces), versions)
        return ok

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
    (its candidates, in rows of ``width``, widened when a list does not fit). Each frame:

    - a vertex whose lower bound minus how far it has moved since is beyond the band cannot be in contact:
      not queried;
    - a vertex within ``margin`` of where its candidates were collected: its closest triangle is among
      them (it is at most its old distance + ``margin`` from the body, and any triangle that close lies
      within old distance + 2 ``margin`` of the old position);
    - any other vertex: the grid query in the full band, with last frame's triangle as its first candidate;
      new candidates are collected for it when it is in the band.

    All three give exactly the full query's result (the same distance test and tie-break), so the contacts
    equal those of `detect_contacts` without a cache: only the speed depends on the cache. One frame is one
    C++ call (`ops.contact_cache_query_`; its twin `reference.contact_cache_query_` is the same rules in
    PyTorch).

    Args:
        index: the `BodyIndex` of the body (the cache applies to it only; needs its C++ grid).
        probe: a vertex queried and found outside the band is probed again out to ``band + probe`` [m],
            to learn how far it is (a larger probe costs more per probe but skips the vertex for longer).
        margin: how far [m] a vertex may move before its candidates are collected again (larger: longer
            lists that last longer).
        max_radius: no candidates for a vertex farther than ``max_radius - 2 margin`` [m] from the body:
            its list would be long (a wide band while sewing), and it is grid-queried instead.
        width: the most candidates a vertex keeps at first (grown when a list does not fit).
    """

    def __init__(
        self,
        index: BodyIndex,
        *,
        probe: float = 0.02,
        margin: float = 0.002,
        max_radius: float = 0.03,
        width: int = 64,
    ):
        if index.grid is None:
            raise ValueError("ContactCache needs a BodyIndex with its C++ grid")
        if width < 1:
            raise ValueError(f"ContactCache width must be >= 1, got {width}")
        self.index = index
        self.probe = probe
        self.margin = margin
        self.max_radius = max_radius
        self.width = width
        # (last_x (Vs, 3) f64 [m], lower (Vs,) f64 [m], last_tri (Vs,) i64, cand_x (Vs, 3) f64 [m],
        # cand (Vs, width) i64, -1 padded): the op's state, in place
        self.state: tuple[torch.Tensor, ...] | None = None
        self.queried = 0  # vertices queried by the last `closest_point` (for benchmarks and tests)
        self.among = 0  # of which among their candidates

    @property
    def has_cand(self) -> torch.Tensor:
        """(Vs,) bool: the vertices that hold candidates (none before the first query)."""
        if self.state is None:
            return torch.zeros(0, dtype=torch.bool)
        return self.state[4][:, 0] >= 0

    def closest_point(self, x: torch.Tensor, band: float):
        """(tri (Vs,) int64, bary (Vs, 3)) of ``index.closest_point(x, band)``, bit for bit (-1 and zeros
        outside the band); x: (Vs, 3) [m]."""
        x = x.detach().contiguous()
        n = x.shape[0]
        if self.state is None or self.state[0].shape[0] != n or self.state[0].device != x.device:
            x64 = x.to(torch.float64)
            never = torch.full((n,), -1, dtype=torch.int64, device=x.device)
            cand = torch.full((n, self.width), -1, dtype=torch.int64, device=x.device)
            self.state = (x64.clone(), x64.new_zeros(n), never, x64.clone(), cand)
        index = self.index
        query = (x, index.verts.to(x.dtype), index.faces, index.grid)
        limits = (band, self.probe, self.margin, self.max_radius)
        tri, bary, counts = ops.contact_cache_query_(*query, self.state, *limits)
        if int(counts[2]) > self.width:
            # lists too long for the rows: wider rows, and the frame again (the same result; those
            # vertices, left without candidates, collect them anew)
            self.width = max(2 * self.width, int(counts[2]))
            cand = self.state[4]
            cand = torch.nn.functional.pad(cand, (0, self.width - cand.shape[1]), value=-1)
            self.state = (*self.state[:4], cand)
            tri, bary, counts = ops.contact_cache_query_(*query, self.state, *limits)
        self.queried, self.among = int(counts[0]), int(counts[1])
        return tri, bary


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
        on = (x.detach()[vert], body_verts.detach(), tri[vert], bary[vert])
        tri, bary = features.outermost(*on, use_extension=use_extension)
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
        self.faces = f.contiguous()  # as the C++ ops take it
        # `valley_candidates`' [key, body verts, partner rows (Fb, P), rows done (Fb,)] of the last body
        self._valley: list | None = None

    def outermost(self, x, body_verts, tri, bary, *, use_extension=True):
        """For contacts whose closest point is on an edge or vertex of face ``tri``: the face sharing that
        feature whose plane is farthest from x, and the point's barycentrics on it. (C, 3), (C,), (C, 3).
        Planes in float64 (`ops.contact_outermost`)."""
        if tri.numel() == 0:
            return tri, bary
        return ops.contact_outermost(
            x.contiguous(), body_verts.to(x.dtype).contiguous(), self.faces, self.across,
            self.ring, tri.contiguous(), bary.contiguous(), use_extension=use_extension,
        )  # fmt: skip

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
