"""The cloth model: topology, stitches, attachments, colourings and material (fixed during a drape).

Built once from one or more `GarmentMesh` with `ClothModelBuilder`; ``finalize(device, dtype)`` validates,
precomputes the topology (interior edges, colourings) and freezes it. Whatever changes between fit
iterations (``rest_uv``, material tensors, body vertices) is NOT stored: `ClothModel.rest_data` is a
pure function of ``rest_uv`` and the material (see `sim/constraints.py`). Several garments added to one
builder become one model (disjoint vertex ranges): that is how a batch of garments is simulated.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from torch_diffavatar.pattern.garment_mesh import GarmentMesh
from torch_diffavatar.sim import constraints
from torch_diffavatar.sim.coloring import Coloring, greedy_coloring
from torch_diffavatar.sim.material import ClothMaterial, medium_cotton
from torch_diffavatar.sim.state import ClothState


@dataclass(frozen=True)
class ClothModel:
    """Static description of the cloth (Newton's ``Model``; the paper's §3.2 constraint set).

    Attributes:
        vert_count: number of simulated vertices ``Vs``.
        panel_vert_count: number of panel vertices ``V`` (rows of ``rest_uv``).
        vert_to_sim: (V,) int64 simulated vertex of each panel vertex.
        tri_vertices: (F, 3) int64 simulated-vertex ids (right-hand normal points out of the garment).
        tri_panel_vertices: (F, 3) int64 panel-vertex ids (where each triangle's rest shape comes from).
        edge_quads: (E, 4) int64 bending quads (v0, v1, v2, v3), see `sim/reference.py`.
        edge_tris: (E, 2) int64 the two triangles of each interior edge.
        edge_panel_vertices: (E, 4) int64 the edge's endpoints as panel vertices in triangle 1, then 2.
        stitch_vertices: (S, 2) int64 simulated vertices joined by zero-length stitch constraints
            (seams still open: only with ``merge_seams=False``).
        attach_vertices: (A,) int64 simulated vertices held at a height (waist of skirts / trousers).
        attach_height: (A,) target heights y [m] (their initial placement height).
        vert_pinned: (Vs,) bool vertices that never move (inverse mass 0).
        vert_init_pos: (Vs, 3) initial placement [m].
        tri_coloring, edge_coloring: colourings for the Gauss–Seidel kernels.
        material: default `ClothMaterial`.
        skipped_edge_count: interior edges without a bending constraint (non-manifold or flipped seams).
    """

    vert_count: int
    panel_vert_count: int
    vert_to_sim: torch.Tensor
    tri_vertices: torch.Tensor
    tri_panel_vertices: torch.Tensor
    edge_quads: torch.Tensor
    edge_tris: torch.Tensor
    edge_panel_vertices: torch.Tensor
    stitch_vertices: torch.Tensor
    attach_vertices: torch.Tensor
    attach_height: torch.Tensor
    vert_pinned: torch.Tensor
    vert_init_pos: torch.Tensor
    tri_coloring: Coloring
    edge_coloring: Coloring
    material: ClothMaterial = field(default_factory=medium_cotton)
    skipped_edge_count: int = 0

    @property
    def tri_count(self) -> int:
        return int(self.tri_vertices.shape[0])

    @property
    def edge_count(self) -> int:
        return int(self.edge_quads.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        return self.vert_init_pos.dtype

    @property
    def device(self) -> torch.device:
        return self.vert_init_pos.device

    def rest_data(
        self,
        rest_uv: torch.Tensor,
        material: ClothMaterial | None = None,
        attach_height: torch.Tensor | None = None,
    ) -> constraints.RestData:
        """Rest data from the panel rest coordinates (differentiable in ``rest_uv``, the material and
        ``attach_height``).

        Args:
            rest_uv: (V, 2) panel-vertex rest coordinates [m] (e.g. ``GarmentMesh.vert_uv``).
            material: overrides the model's material (e.g. with a bending stiffness being fitted).
            attach_height: (A,) target heights of the attached vertices [m], overriding
                ``attach_height`` (e.g. a waistband lowered by a fitted offset).
        """
        material = self.material if material is None else material
        if rest_uv.shape != (self.panel_vert_count, 2):
            raise ValueError(
                f"rest_uv must have shape ({self.panel_vert_count}, 2), got {tuple(rest_uv.shape)}"
            )
        if attach_height is None:
            attach_height = self.attach_height
        elif attach_height.shape != self.attach_height.shape:
            raise ValueError(
                f"attach_height must have shape {tuple(self.attach_height.shape)} (one height per attached "
                f"vertex), got {tuple(attach_height.shape)}"
            )
        rest_uv = rest_uv.to(device=self.device, dtype=self.dtype)  # differentiable cast
        rest_inv, area = constraints.tri_rest_geometry(rest_uv, self.tri_panel_vertices)
        weight = constraints.edge_bend_weight(rest_uv, self.edge_panel_vertices, self.edge_tris, area)
        mass = constraints.vert_lumped_mass(area, self.tri_vertices, self.vert_count, material)
        inv_mass = torch.where(self.vert_pinned | (mass <= 0), torch.zeros_like(mass), 1.0 / mass)
        return constraints.RestData(
            tri_rest_inv=rest_inv,
            tri_area=area,
            tri_compliance=constraints.tri_stretch_compliance(area, material),
            edge_rest_angle=torch.zeros_like(weight),  # flat pattern, also across merged seams
            edge_weight=weight,
            edge_compliance=constraints.edge_bend_compliance(weight, material),
            vert_mass=mass,
            vert_inv_mass=inv_mass,
            attach_height=attach_height.to(device=self.device, dtype=self.dtype),
            material=material,
        )

    def initial_state(self, x: torch.Tensor | None = None) -> ClothState:
        """A state at rest at ``x`` (Vs, 3) [m] (default: the pattern's placement)."""
        x = self.vert_init_pos if x is None else x
        return ClothState(x.clone(), torch.zeros_like(x))

    def sim_positions(self, panel_pos: torch.Tensor) -> torch.Tensor:
        """(Vs, 3) simulated-vertex positions as the mean of their panel vertices' (V, 3) positions."""
        out = panel_pos.new_zeros(self.vert_count, 3).index_add(0, self.vert_to_sim, panel_pos)
        count = panel_pos.new_zeros(self.vert_count).index_add(
            0, self.vert_to_sim, panel_pos.new_ones(panel_pos.shape[0])
        )
        return out / count.clamp_min(1)[:, None]


def interior_edges(tri_vertices: torch.Tensor):
    """Bending quads of a triangle mesh.

    Args:
        tri_vertices: (F, 3) int64 consistently oriented triangles.

    Returns:
        edge_quads (E, 4), edge_tris (E, 2), edge_local (E, 2) local edge index (0..2, edge k runs from
        corner k to corner k+1) in each triangle, skipped (int): edges shared by more than two triangles
        or by two triangles with the same direction (inconsistent orientation).
    """
    f = tri_vertices.detach().cpu()
    n = f.shape[0]
    a = f.reshape(-1)  # corner k
    b = f[:, [1, 2, 0]].reshape(-1)  # corner k+1
    tri = torch.arange(n).repeat_interleave(3)
    local = torch.arange(3).repeat(n)
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    key = lo * (int(f.max()) + 1 if n else 1) + hi
    uniq, inverse, counts = torch.unique(key, return_inverse=True, return_counts=True)
    pair_keys = counts == 2
    skipped = int((counts > 2).sum())
    sel = pair_keys[inverse]
    order = torch.argsort(inverse[sel], stable=True)
    idx = torch.nonzero(sel).squeeze(1)[order].reshape(-1, 2)  # (E, 2) half-edge ids
    ha, hb = idx[:, 0], idx[:, 1]
    opposite = a[ha] == b[hb]  # consistent orientation: second half-edge runs backwards
    skipped += int((~opposite).sum())
    ha, hb = ha[opposite], hb[opposite]
    t1, t2 = tri[ha], tri[hb]
    l1, l2 = local[ha], local[hb]
    v2 = f[t1, (l1 + 2) % 3]
    v3 = f[t2, (l2 + 2) % 3]
    quads = torch.stack((a[ha], b[ha], v2, v3), dim=1)
    return quads, torch.stack((t1, t2), 1), torch.stack((l1, l2), 1), skipped


class ClothModelBuilder:
    """Collects garments, then `finalize` builds a frozen `ClothModel`.

    Args:
        material: cloth material (default `medium_cotton()`).
    """

    def __init__(self, material: ClothMaterial | None = None):
        self.material = medium_cotton() if material is None else material
        self._garments: list[tuple[GarmentMesh, bool, tuple[str, ...], torch.Tensor | None]] = []

    def add_garment(
        self,
        garment: GarmentMesh,
        *,
        merge_seams: bool = True,
        attach_labels: tuple[str, ...] = ("lower_interface",),
        pinned: torch.Tensor | None = None,
    ) -> ClothModelBuilder:
        """Add a garment.

        Args:
            garment: the meshed, placed pattern.
            merge_seams: simulate on the seam-merged vertices (``vert_to_sim``) — the drape phase; with
                False every panel vertex is simulated and ``stitch_pairs`` become zero-length stitch
                constraints — the sewing phase.
            attach_labels: panel vertices with these labels (``GarmentMesh.vert_labels``) that are NOT on a
                stitch are held at their initial height by soft constraints. GarmentCode labels the waist of
                skirts and trousers ``lower_interface``; a dress's ``lower_interface`` is stitched to the
                bodice, so it gets no attachment.
            pinned: optional (k,) int64 panel vertices that never move (tests, hanging sheets).
        """
        if garment.vert_uv.ndim != 2 or garment.vert_uv.shape[1] != 2:
            raise ValueError(f"garment.vert_uv must be (V, 2), got {tuple(garment.vert_uv.shape)}")
        if garment.tri_count == 0:
            raise ValueError("garment has no triangles")
        self._garments.append((garment, merge_seams, tuple(attach_labels), pinned))
        return self

    def finalize(self, device=None, dtype: torch.dtype = torch.float32) -> ClothModel:
        """Validate, build topology and colourings, and move everything to ``device`` / ``dtype``."""
        if not self._garments:
            raise ValueError("ClothModelBuilder.finalize: add at least one garment first")
        parts = [_GarmentPart.of(*entry) for entry in self._garments]
        panel_offsets = torch.tensor([0] + [p.panel_vert_count for p in parts]).cumsum(0).tolist()
        sim_offsets = torch.tensor([0] + [p.sim_vert_count for p in parts]).cumsum(0).tolist()

        def cat(name, offsets=None):
            """The parts' ``name`` tensors concatenated; vertex ids shifted by their part's ``offsets``."""
            if offsets is None:
                return torch.cat([getattr(p, name) for p in parts])
            return torch.cat([getattr(p, name) + o for p, o in zip(parts, offsets)])

        tri_vertices = cat("tri_vertices", sim_offsets)
        tri_panel_vertices = cat("tri_panel_vertices", panel_offsets)
        quads, edge_tris, edge_local, skipped = interior_edges(tri_vertices)
        x0 = cat("vert_init_pos")
        if not torch.isfinite(x0).all():
            raise ValueError("garment.vert_pos contains NaN or inf")

        def ints(t):
            return t.to(device=device, dtype=torch.int64).contiguous()

        return ClothModel(
            vert_count=sim_offsets[-1],
            panel_vert_count=panel_offsets[-1],
            vert_to_sim=ints(cat("vert_to_sim", sim_offsets)),
            tri_vertices=ints(tri_vertices),
            tri_panel_vertices=ints(tri_panel_vertices),
            edge_quads=ints(quads),
            edge_tris=ints(edge_tris),
            edge_panel_vertices=ints(_edge_panel_vertices(tri_panel_vertices, edge_tris, edge_local)),
            stitch_vertices=ints(cat("stitch_vertices", sim_offsets).reshape(-1, 2)),
            attach_vertices=ints(cat("attach_vertices", sim_offsets)),
            attach_height=cat("attach_height").to(device=device, dtype=dtype),
            vert_pinned=cat("vert_pinned").to(device=device),
            vert_init_pos=x0.to(device=device, dtype=dtype).contiguous(),
            tri_coloring=greedy_coloring(tri_vertices).to(device),
            edge_coloring=greedy_coloring(quads).to(device),
            material=self.material,
            skipped_edge_count=skipped,
        )


@dataclass(frozen=True)
class _GarmentPart:
    """One garment's share of a `ClothModel`, with vertex ids local to the garment (CPU tensors).

    Attributes:
        panel_vert_count, sim_vert_count: its panel vertices V and simulated vertices Vs.
        vert_to_sim: (V,) int64; tri_vertices, tri_panel_vertices: (F, 3) int64; stitch_vertices: (S, 2)
        int64 (sim vertices); attach_vertices: (A,) int64; attach_height: (A,) float64 [m];
        vert_pinned: (Vs,) bool; vert_init_pos: (Vs, 3) float64 [m] (mean of the panel positions).
    """

    panel_vert_count: int
    sim_vert_count: int
    vert_to_sim: torch.Tensor
    tri_vertices: torch.Tensor
    tri_panel_vertices: torch.Tensor
    stitch_vertices: torch.Tensor
    attach_vertices: torch.Tensor
    attach_height: torch.Tensor
    vert_pinned: torch.Tensor
    vert_init_pos: torch.Tensor

    @staticmethod
    def of(garment: GarmentMesh, merge: bool, labels: tuple[str, ...], pinned) -> _GarmentPart:
        """The part of ``garment`` as `ClothModelBuilder.add_garment` describes it."""
        gv = garment.vert_count
        if merge:
            v2s = garment.vert_to_sim.cpu().to(torch.int64)
            n_sim = int(garment.sim_vert_count)
            st = v2s[garment.stitch_pairs.cpu()]
            st = st[st[:, 0] != st[:, 1]] if st.numel() else st.reshape(0, 2)
        else:
            v2s = torch.arange(gv)
            n_sim = gv
            st = garment.stitch_pairs.cpu().to(torch.int64).reshape(-1, 2)
        pos = garment.vert_pos.cpu().to(torch.float64)
        x0 = torch.zeros(n_sim, 3, dtype=torch.float64).index_add_(0, v2s, pos)
        count = torch.zeros(n_sim, dtype=torch.float64).index_add_(
            0, v2s, torch.ones(gv, dtype=torch.float64)
        )
        x0 /= count[:, None]
        attach = _attached(garment, v2s, labels)
        pin = torch.zeros(n_sim, dtype=torch.bool)
        if pinned is not None:
            pin[v2s[pinned.cpu().to(torch.int64)]] = True
        return _GarmentPart(
            panel_vert_count=gv,
            sim_vert_count=n_sim,
            vert_to_sim=v2s,
            tri_vertices=v2s[garment.tri_vertices.cpu()],
            tri_panel_vertices=garment.tri_vertices.cpu().to(torch.int64),
            stitch_vertices=st,
            attach_vertices=attach,
            attach_height=x0[attach, 1],
            vert_pinned=pin,
            vert_init_pos=x0,
        )


def _attached(garment: GarmentMesh, vert_to_sim: torch.Tensor, labels: tuple[str, ...]) -> torch.Tensor:
    """(A,) int64 sorted sim vertices of the panel vertices labelled ``labels`` that are not stitched."""
    stitched = torch.zeros(garment.vert_count, dtype=torch.bool)
    if garment.stitch_pairs.numel():
        stitched[garment.stitch_pairs.cpu().reshape(-1)] = True
    att = []
    for label in labels:
        if label in garment.vert_labels:
            pv = garment.vert_labels[label].cpu().to(torch.int64)
            att.append(vert_to_sim[pv[~stitched[pv]]])
    return torch.unique(torch.cat(att)) if att else torch.zeros(0, dtype=torch.int64)


def _edge_panel_vertices(tri_panel_vertices, edge_tris, edge_local) -> torch.Tensor:
    """(E, 4) int64: each interior edge's endpoints (v0, v1) as panel vertices of its first triangle,
    then of its second (they differ across a seam)."""
    l1, l2 = edge_local[:, 0], edge_local[:, 1]
    t1, t2 = edge_tris[:, 0], edge_tris[:, 1]
    return torch.stack(
        (
            tri_panel_vertices[t1, l1],
            tri_panel_vertices[t1, (l1 + 1) % 3],
            tri_panel_vertices[t2, (l2 + 1) % 3],
            tri_panel_vertices[t2, l2],
        ),
        dim=1,
    )
