"""`GarmentMesh`: a sewing pattern turned into a simulation mesh.

Two vertex sets live side by side:

* **panel vertices** (``V``): one per vertex of each panel's own triangulation. A vertex on a seam
  exists once per side, each with its own 2D rest coordinate in its panel's frame. Rest shape,
  gradients w.r.t. the pattern (`rest_uv`, V×2) and exports with UVs use these.
* **sim vertices** (``Vs``): after merging every stitched pair (transitively) into one vertex. The
  seam-merged topology is what the cloth is simulated on; triangle rest shapes still come from the
  panel vertices, so a merged vertex can have a different rest coordinate in each adjacent panel.

All tensors are on the CPU in float64 / int64 as built; `to()` moves them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import torch


@dataclass
class BoundaryLoop:
    """One opening of the sewn garment (hem, cuff, neck, waist …).

    Attributes:
        name: ``"neck"``, ``"hem"``, ``"waist"``, ``"cuff_left"``, ``"cuff_right"``, ``"hem_left"``,
            ``"hem_right"``, or ``"opening_<k>"`` when no rule names it.
        vertices: (L,) int64 sim-vertex indices in order around the loop (closed: the last joins the first).
    """

    name: str
    vertices: torch.Tensor


@dataclass
class GarmentMesh:
    """Triangulated, placed sewing pattern with seams.

    Attributes:
        panel_names: panel name per panel id (order defines ``vert_panel`` ids).
        vert_uv: (V, 2) float64 rest coordinates [m] in each panel's own 2D frame.
        vert_panel: (V,) int64 panel id of each panel vertex.
        vert_pos: (V, 3) float64 initial 3D placement [m] (world frame: Y up, facing +Z).
        tri_vertices: (F, 3) int64 panel-vertex indices; the right-hand normal of a placed triangle
            points out of the garment (the same orientation as its panel's edge loop).
        stitch_pairs: (S, 2) int64 panel-vertex pairs that seams join (darts included).
        vert_to_sim: (V,) int64 sim-vertex index of each panel vertex (seam-merged topology).
        sim_vert_count: number of sim vertices ``Vs``.
        boundary_loops: openings of the sewn garment, ordered, on sim vertices.
        panel_boundary: per panel, (Lp,) int64 panel-vertex indices of its outline in loop order.
        edge_vertices: ``(panel_name, edge_index) -> (n,) int64`` panel vertices along that pattern
            edge from its start to its end vertex, both corners included.
        vert_labels: edge label (e.g. ``"lower_interface"``) -> (k,) int64 panel vertices on those edges.
        garment_type: template's garment type (``"dress"``, ``"tshirt"`` …) or None.
        spacing: target edge spacing [m] the mesh was built with.
    """

    panel_names: list[str]
    vert_uv: torch.Tensor
    vert_panel: torch.Tensor
    vert_pos: torch.Tensor
    tri_vertices: torch.Tensor
    stitch_pairs: torch.Tensor
    vert_to_sim: torch.Tensor
    sim_vert_count: int
    boundary_loops: list[BoundaryLoop] = field(default_factory=list)
    panel_boundary: list[torch.Tensor] = field(default_factory=list)
    edge_vertices: dict[tuple[str, int], torch.Tensor] = field(default_factory=dict)
    vert_labels: dict[str, torch.Tensor] = field(default_factory=dict)
    garment_type: str | None = None
    spacing: float = 0.015

    @property
    def vert_count(self) -> int:
        return int(self.vert_uv.shape[0])

    @property
    def tri_count(self) -> int:
        return int(self.tri_vertices.shape[0])

    @property
    def sim_faces(self) -> torch.Tensor:
        """(F, 3) int64 faces on sim vertices (same order and orientation as ``tri_vertices``)."""
        return self.vert_to_sim[self.tri_vertices]

    def sim_positions(self, vert_pos: torch.Tensor | None = None) -> torch.Tensor:
        """(Vs, 3) positions of sim vertices: the mean of the panel vertices merged into each.

        Args:
            vert_pos: (V, 3) panel-vertex positions [m]; defaults to the initial placement.
        """
        pos = self.vert_pos if vert_pos is None else vert_pos
        out = pos.new_zeros(self.sim_vert_count, 3).index_add_(0, self.vert_to_sim, pos)
        count = pos.new_zeros(self.sim_vert_count).index_add_(0, self.vert_to_sim, pos.new_ones(len(pos)))
        return out / count[:, None]

    def to(self, device=None, dtype=None) -> GarmentMesh:
        """A copy with float tensors cast to ``dtype`` and all tensors moved to ``device``."""

        def move(t: torch.Tensor) -> torch.Tensor:
            return t.to(device=device, dtype=dtype if t.is_floating_point() and dtype else None)

        changes = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, torch.Tensor):
                changes[f.name] = move(value)
        changes["boundary_loops"] = [BoundaryLoop(b.name, move(b.vertices)) for b in self.boundary_loops]
        changes["panel_boundary"] = [move(t) for t in self.panel_boundary]
        changes["edge_vertices"] = {k: move(v) for k, v in self.edge_vertices.items()}
        changes["vert_labels"] = {k: move(v) for k, v in self.vert_labels.items()}
        return replace(self, **changes)
