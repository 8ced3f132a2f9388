"""Meshing a sewing pattern into a `GarmentMesh`: resampled seams, quality triangulation, merged seams.

Steps (`mesh_pattern`):

1. Every edge is resampled at equal arc-length steps close to ``spacing``; the two edges of a stitch get
   the same number of segments (the longer edge's count), corners are shared by the two edges meeting there.
   Edges much shorter than ``spacing`` (`SHORT_EDGE` × spacing, with every edge sewn to them) are
   collapsed to one point (`collapsed_edges`).
2. Each panel is triangulated with Shewchuk's Triangle (``p`` PSLG, ``q<min_angle>`` quality, ``a`` area
   bound of an equilateral triangle of side ``spacing``, ``Y`` = no Steiner points on the boundary, so the
   boundary samples stay exactly as resampled and stitched edges keep matching counts).
3. Triangles take the orientation of their panel's edge loop (GarmentCode: counter-clockwise for front
   panels, clockwise for back ones), so placed right-hand normals point out of the garment.
4. Stitched vertex pairs are merged transitively (union-find) into sim vertices; the boundary edges of
   the merged mesh are chained into loops and named by simple rules in the world frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import triangle
from scipy.cluster.hierarchy import DisjointSet

from torch_diffavatar.errors import PatternError
from torch_diffavatar.geometry import merge_pairs
from torch_diffavatar.pattern.garment_mesh import BoundaryLoop, GarmentMesh
from torch_diffavatar.pattern.garmentcode import GC_BODY
from torch_diffavatar.pattern.spec import EdgeRef, Pattern, polygon_signed_area

TOPS = ("dress", "tshirt", "longsleeve", "polo")
BOTTOMS = ("skirt", "pants")


GRADING = 0.4  # growth of the boundary sample spacing per unit arc length near short edges [m/m]
# edges shorter than this fraction of the spacing are collapsed to a point. A boundary segment of length
# l forces triangles of size ~l around it (min-angle quality), so a 1 mm edge in a 2 cm mesh leaves a
# patch of mm-sized triangles that a few cm of seam pull tears apart (GarmentCode's js_mean_all waist);
# 0.15 keeps every other bundled pattern's shortest edge (5.6 mm) above the threshold up to 3.7 cm spacing
SHORT_EDGE = 0.15


def collapsed_edges(pattern: Pattern, spacing: float) -> set[tuple[str, int]]:
    """Edges ``(panel_name, edge_index)`` that `mesh_pattern` collapses to a single point.

    An edge is collapsed when it is shorter than ``SHORT_EDGE * spacing`` and so is every edge joined to
    it through chains of stitches (both sides of a stitch then have one vertex, so they still match), and
    its panel keeps at least 3 edges that are not collapsed.
    """
    limit = SHORT_EDGE * spacing
    cand = {
        (name, k)
        for name, panel in pattern.panels.items()
        for k in range(len(panel.edges))
        if panel.edge_length(k) < limit
    }
    if not cand:
        return cand
    # edges joined through stitches: a group collapses all together or not at all
    groups = DisjointSet()
    for s in pattern.stitches:
        a, b = (s.a.panel, s.a.edge), (s.b.panel, s.b.edge)
        groups.add(a)
        groups.add(b)
        groups.merge(a, b)
    while True:
        keep = set(cand)
        for name, panel in pattern.panels.items():
            mine = {(name, k) for k in range(len(panel.edges))} & keep
            if len(panel.edges) - len(mine) < 3:
                keep -= mine
        bad_roots = {groups[key] for key in groups if key not in keep}
        keep = {key for key in keep if key not in groups or groups[key] not in bad_roots}
        if keep == cand:
            return keep
        cand = keep


def _graded_fractions(f0: float, f1: float, fmax: float, grading: float = GRADING) -> np.ndarray:
    """Arc-length fractions (n + 1,) from 0 to 1 whose step is ~``f0`` at the start, ~``f1`` at the end
    and at most ``fmax`` elsewhere, growing by at most ``grading`` per unit fraction (all in fractions of
    the edge length)."""
    grid = np.linspace(0.0, 1.0, 2049)
    h = np.minimum(np.minimum(fmax, f0 + grading * grid), f1 + grading * (1.0 - grid))
    inv = 1.0 / h
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (inv[1:] + inv[:-1]) * np.diff(grid))])
    n = max(1, math.ceil(cum[-1] - 1e-6))
    t = np.interp(np.arange(n + 1) * (cum[-1] / n), cum, grid)
    t[0], t[-1] = 0.0, 1.0
    return t


def edge_sample_fractions(pattern: Pattern, spacing: float) -> dict[tuple[str, int], np.ndarray]:
    """Arc-length fractions at which every edge is sampled, corners included.

    Steps are at most ``spacing``; next to an edge shorter than ``spacing`` they shrink to that edge's
    length and grow back gradually (so corner triangles can keep their quality without boundary Steiner
    points). The two edges of a stitch get the same number of samples (set by the longer edge) at
    matching fractions (mirrored for the default end-to-start seam). A collapsed edge (`collapsed_edges`)
    gets the single fraction ``[0.]``: it becomes one point, shared with its neighbours' corners, and its
    length does not shrink their steps.

    Returns:
        ``(panel_name, edge_index) -> (n + 1,) float64`` increasing fractions from 0 to 1.
    """
    collapsed = collapsed_edges(pattern, spacing)
    lengths: dict[tuple[str, int], float] = {}
    corner: dict[tuple[str, int], float] = {}  # target step [m] at each (panel, vertex) corner
    ends: dict[tuple[str, int], tuple[tuple[str, int], tuple[str, int]]] = {}
    for name, panel in pattern.panels.items():
        m = len(panel.edges)
        ls = [math.inf if (name, k) in collapsed else panel.edge_length(k) for k in range(m)]
        for k, edge in enumerate(panel.edges):
            lengths[(name, k)] = ls[k]
            ends[(name, k)] = ((name, edge.start), (name, edge.end))
            corner[(name, edge.start)] = min(spacing, ls[k], ls[k - 1])
    # corners that seams sew together (or a collapsed edge joins) become one point of the garment: give
    # them one step [m] (the smallest), propagated through chains of seams until nothing changes
    joins = [(ends[key][0], ends[key][1]) for key in sorted(collapsed)]
    for s in pattern.stitches:
        (a0, a1), (b0, b1) = ends[(s.a.panel, s.a.edge)], ends[(s.b.panel, s.b.edge)]
        joins += ((a0, b0), (a1, b1)) if s.right_wrong else ((a0, b1), (a1, b0))
    for _ in range(len(corner) + 1):
        changed = False
        for ca, cb in joins:
            step = min(corner[ca], corner[cb])
            if corner[ca] != step or corner[cb] != step:
                corner[ca] = corner[cb] = step
                changed = True
        if not changed:
            break
    out: dict[tuple[str, int], np.ndarray] = {key: np.zeros(1) for key in collapsed}
    for s in pattern.stitches:
        a, b = (s.a.panel, s.a.edge), (s.b.panel, s.b.edge)
        if a in collapsed:  # then so is b
            continue
        la, lb = lengths[a], lengths[b]
        (a0, a1), (b0, b1) = (corner[c] for c in ends[a]), (corner[c] for c in ends[b])
        # fractions along A; B's start meets A's end (default) or A's start (right_wrong)
        bs, be = (b0 / lb, b1 / lb) if s.right_wrong else (b1 / lb, b0 / lb)
        t = _graded_fractions(min(a0 / la, bs), min(a1 / la, be), spacing / max(la, lb))
        out[a] = t
        out[b] = t if s.right_wrong else 1.0 - t[::-1]
    for key, length in lengths.items():
        if key not in out:
            c0, c1 = (corner[c] for c in ends[key])
            out[key] = _graded_fractions(c0 / length, c1 / length, spacing / length)
    return out


def _triangulate_panel(boundary: np.ndarray, spacing: float, min_angle: float, name: str, source) -> tuple:
    """Quality-triangulate one closed outline (Lp, 2); returns (vertices (n, 2), triangles (f, 3))."""
    n = len(boundary)
    segments = np.stack([np.arange(n), (np.arange(n) + 1) % n], axis=1)
    max_area = math.sqrt(3.0) / 4.0 * spacing**2
    opts = f"pq{min_angle:g}a{max_area:.12f}YQ"
    out = triangle.triangulate({"vertices": boundary, "segments": segments}, opts)
    verts, tris = out.get("vertices"), out.get("triangles")
    where = f"{source}: " if source else ""
    if tris is None or len(tris) == 0:
        raise PatternError(f"{where}panel {name!r} could not be triangulated (degenerate outline?)")
    if len(verts) < n or not np.allclose(verts[:n], boundary):
        raise PatternError(f"{where}panel {name!r}: the triangulator moved boundary vertices")
    # with `Y` no Steiner point may land on the boundary: every boundary edge must be an input segment
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    uniq, cnt = np.unique(e, axis=0, return_counts=True)
    if int((cnt == 1).sum()) != n:
        raise PatternError(
            f"{where}panel {name!r}: triangulation boundary does not match the resampled outline "
            "(the outline may touch itself)"
        )
    return verts, tris.astype(np.int64)


def stitch_vertex_pairs(a: np.ndarray, b: np.ndarray, right_wrong: bool) -> np.ndarray:
    """(n, 2) vertex pairs joined by a stitch of two edges with equal vertex counts.

    Args:
        a, b: (n,) vertex indices along edge A and edge B, each from its start to its end.
        right_wrong: start joins start; otherwise (the default seam) the END of A joins the START of B.
    """
    a = np.asarray(a)
    return np.stack([a if right_wrong else a[::-1], np.asarray(b)], axis=1)


def _chain_boundary_loops(sim_faces: np.ndarray) -> list[np.ndarray]:
    """Boundary edges (used by one face) chained into closed loops of sim vertices.

    Loops follow the faces' orientation where it is consistent (directed boundary half-edges first).
    """
    half = np.concatenate([sim_faces[:, [0, 1]], sim_faces[:, [1, 2]], sim_faces[:, [2, 0]]])
    key = np.sort(half, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = half[counts[inverse.ravel()] == 1]
    out_edges: dict[int, list[int]] = {}
    adjacency: dict[int, list[int]] = {}
    for u, v in boundary.tolist():
        out_edges.setdefault(u, []).append(v)
        adjacency.setdefault(u, []).append(v)
        adjacency.setdefault(v, []).append(u)
    used: set[tuple[int, int]] = set()
    loops = []
    for u0, v0 in boundary.tolist():
        if (min(u0, v0), max(u0, v0)) in used:
            continue
        loop = [u0]
        used.add((min(u0, v0), max(u0, v0)))
        prev, cur = u0, v0
        while cur != u0:
            loop.append(cur)
            nxt = None
            for cand in out_edges.get(cur, []) + adjacency.get(cur, []):
                if (min(cur, cand), max(cur, cand)) not in used:
                    nxt = cand
                    break
            if nxt is None:  # open chain (non-manifold input); stop here
                break
            used.add((min(cur, nxt), max(cur, nxt)))
            prev, cur = cur, nxt
        del prev
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def name_boundary_loops(
    loops: list[np.ndarray],
    sim_pos: np.ndarray,
    garment_type: str | None,
    lower_interface: set[int],
) -> list[BoundaryLoop]:
    """Order loops top to bottom and name them by simple rules in the world frame (Y up, facing +Z).

    Tops and dresses: the highest loop is ``neck``; the lowest loop around the garment's centre plane
    (not wholly on one side of it) is ``hem``; of the others, a loop wholly on one side and far out
    (centroid beyond half the garment's half-width) is ``cuff_left`` (x > centre) or ``cuff_right``.
    When the two lowest loops lie below the crotch of GarmentCode's body (the layout's frame), each
    wholly on one side, on opposite sides, they are trouser legs (a jumpsuit): ``hem_left`` (x > centre)
    and ``hem_right``. Skirts and pants: the loop holding the most ``lower_interface`` vertices (else the
    highest) is ``waist``; a single other loop is ``hem``, else the two lowest are ``hem_left`` /
    ``hem_right``. Anything else is ``opening_<k>`` (k = position in the list). When ``garment_type`` is
    None the garment counts as a bottom if its highest loop holds ``lower_interface`` vertices.

    Args:
        loops: closed loops of sim-vertex indices.
        sim_pos: (Vs, 3) sim-vertex positions [m].
        garment_type: see ``GARMENT_TYPES``, or None.
        lower_interface: sim vertices on ``lower_interface`` edges.
    """
    if not loops:
        return []
    centroids = np.stack([sim_pos[lp].mean(axis=0) for lp in loops])
    order = np.argsort(-centroids[:, 1], kind="stable")
    loops = [loops[i] for i in order]
    centroids = centroids[order]
    names: list[str | None] = [None] * len(loops)
    li_count = [sum(int(v) in lower_interface for v in lp) for lp in loops]
    bottom = garment_type in BOTTOMS if garment_type is not None else li_count[0] > 0
    if bottom:
        waist = int(np.argmax(li_count)) if max(li_count) > 0 else 0
        names[waist] = "waist"
        rest = [i for i in range(len(loops)) if i != waist]
        if len(rest) == 1:
            names[rest[0]] = "hem"
        elif len(rest) >= 2:
            low = sorted(rest, key=lambda i: centroids[i, 1])[:2]
            left, right = sorted(low, key=lambda i: -centroids[i, 0])
            names[left], names[right] = "hem_left", "hem_right"
    else:
        names[0] = "neck"
        xc = 0.5 * (sim_pos[:, 0].max() + sim_pos[:, 0].min())
        half_width = 0.5 * (sim_pos[:, 0].max() - sim_pos[:, 0].min())
        side_of = [np.sign(sim_pos[lp, 0] - xc) for lp in loops]
        one_side = [bool(np.all(s == s[0])) for s in side_of]
        low = [len(loops) - 2, len(loops) - 1] if len(loops) >= 3 else []
        if (
            low
            and one_side[low[0]]
            and one_side[low[1]]
            and side_of[low[0]][0] * side_of[low[1]][0] < 0
            and (centroids[low, 1] < GC_BODY["crotch"]).all()
        ):
            # trouser legs (a jumpsuit; a cropped top's long sleeves end higher, in the A-pose)
            left, right = sorted(low, key=lambda i: -centroids[i, 0])
            names[left], names[right] = "hem_left", "hem_right"
        elif len(loops) > 1:
            around = [i for i in range(1, len(loops)) if not one_side[i]]
            names[around[-1] if around else -1] = "hem"
        for side, name in ((1.0, "cuff_left"), (-1.0, "cuff_right")):
            cands = [
                i
                for i in range(1, len(loops))
                if names[i] is None and one_side[i] and side * (centroids[i, 0] - xc) > 0.5 * half_width
            ]
            if cands:
                names[max(cands, key=lambda i: side * centroids[i, 0])] = name
    return [
        BoundaryLoop(n if n is not None else f"opening_{k}", torch.as_tensor(lp, dtype=torch.int64))
        for k, (n, lp) in enumerate(zip(names, loops))
    ]


@dataclass
class _PanelMeshes:
    """The panels triangulated side by side, before the seams are merged (see `mesh_pattern`).

    Attributes:
        vert_uv: (Vp, 2) float64 rest coordinates [m] of every panel vertex.
        vert_pos: (Vp, 3) float64 placed world positions [m].
        vert_panel: (Vp,) int64 panel index of each vertex.
        tri_vertices: (F, 3) int64 triangles, oriented like their panel's edge loop.
        panel_boundary: per panel, (Lp,) int64 its outline's vertices in loop order.
        edge_vertices: (panel, edge) -> (n,) int64 the edge's vertices from its start to its end.
    """

    vert_uv: np.ndarray
    vert_pos: np.ndarray
    vert_panel: np.ndarray
    tri_vertices: np.ndarray
    panel_boundary: list[torch.Tensor]
    edge_vertices: dict[tuple[str, int], torch.Tensor]


def _check_mesh_args(spacing, min_angle) -> None:
    if not (isinstance(spacing, int | float) and math.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing must be a positive length in metres, got {spacing!r}")
    if not (0 < min_angle <= 34):
        raise ValueError(
            f"min_angle must be in (0, 34] degrees (Triangle's guaranteed range), got {min_angle!r}"
        )


# More vertices than any garment of this project needs (a fit runs ~2-20k; a drape at 5 mm about 100k):
# a pattern beyond it is in the wrong units or asks for a spacing far too fine, and Triangle would take
# minutes and gigabytes before failing.
MAX_MESH_VERTICES = 1_000_000


def check_mesh_budget(pattern: Pattern, spacing: float) -> None:
    """PatternError, before any meshing, for a panel smaller than ``spacing`` [m] or a pattern whose mesh
    would exceed `MAX_MESH_VERTICES` (estimated from the panels' corner polygons: an equilateral mesh of
    edge ``spacing`` holds 2/√3 vertices per spacing², plus one per spacing of outline)."""
    estimate, area = 0.0, 0.0
    for name, panel in pattern.panels.items():
        corners = np.asarray(panel.vertices, dtype=np.float64)
        extent = float(np.linalg.norm(corners.max(0) - corners.min(0)))
        if extent < spacing:
            raise PatternError(
                f"panel {name!r} is {extent:.3g} m across, less than the mesh spacing {spacing:g} m: is the "
                "pattern in the right units? (else choose a smaller spacing)"
            )
        panel_area = abs(polygon_signed_area(corners))
        perimeter = float(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).sum())
        area += panel_area
        estimate += 2.0 / math.sqrt(3.0) * panel_area / spacing**2 + perimeter / spacing
    if estimate > MAX_MESH_VERTICES:
        raise PatternError(
            f"the pattern ({len(pattern.panels)} panels, {area:.3g} m²) meshes to about {estimate:,.0f} "
            f"vertices at spacing {spacing:g} m, more than the {MAX_MESH_VERTICES:,} meshed here: choose a "
            "larger spacing, or check the pattern's units"
        )


def _orient_like_loop(verts: np.ndarray, tris: np.ndarray, boundary: np.ndarray) -> None:
    """Flip in place the triangles (f, 3) of ``verts`` (n, 2) that turn against the outline (Lp, 2)."""
    loop_sign = np.sign(polygon_signed_area(boundary))
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    tri_sign = np.sign((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    flip = tri_sign != loop_sign
    tris[flip] = tris[flip][:, [0, 2, 1]]


def _mesh_panels(
    pattern: Pattern, fractions: dict[tuple[str, int], np.ndarray], spacing: float, min_angle: float
) -> _PanelMeshes:
    """Resample every panel's outline at ``fractions`` and triangulate it, panels numbered in order."""
    uv_parts, pos_parts, panel_ids, tri_parts = [], [], [], []
    panel_boundary: list[torch.Tensor] = []
    edge_vertices: dict[tuple[str, int], torch.Tensor] = {}
    offset = 0
    for pid, name in enumerate(pattern.panels):
        panel = pattern.panels[name]
        pts, starts = [], []
        for k in range(len(panel.edges)):
            starts.append(sum(len(p) for p in pts))
            # a collapsed edge adds no point: the previous edge runs on to the next edge's start
            pts.append(panel.sample_edge(k, fractions[(name, k)][:-1]).reshape(-1, 2))
        boundary = np.concatenate(pts, axis=0)
        lp = len(boundary)
        verts, tris = _triangulate_panel(boundary, spacing, min_angle, name, pattern.source)
        _orient_like_loop(verts, tris, boundary)
        for k in range(len(panel.edges)):
            idx = (starts[k] + np.arange(len(fractions[(name, k)]))) % lp + offset
            edge_vertices[(name, k)] = torch.as_tensor(idx, dtype=torch.int64)
        panel_boundary.append(torch.arange(offset, offset + lp, dtype=torch.int64))
        uv_parts.append(verts)
        pos_parts.append(panel.to_world(verts))
        panel_ids.append(np.full(len(verts), pid))
        tri_parts.append(tris + offset)
        offset += len(verts)
    return _PanelMeshes(
        vert_uv=np.concatenate(uv_parts),
        vert_pos=np.concatenate(pos_parts),
        vert_panel=np.concatenate(panel_ids),
        tri_vertices=np.concatenate(tri_parts),
        panel_boundary=panel_boundary,
        edge_vertices=edge_vertices,
    )


def _pattern_stitch_pairs(pattern: Pattern, edge_vertices: dict[tuple[str, int], torch.Tensor]) -> np.ndarray:
    """(S, 2) int64 panel-vertex pairs joined by the pattern's stitches (a dart tip not joined to itself)."""
    pairs = []
    for s in pattern.stitches:
        va = edge_vertices[(s.a.panel, s.a.edge)].numpy()
        vb = edge_vertices[(s.b.panel, s.b.edge)].numpy()
        p = stitch_vertex_pairs(va, vb, s.right_wrong)
        pairs.append(p[p[:, 0] != p[:, 1]])  # a dart tip joins itself
    return np.concatenate(pairs) if pairs else np.zeros((0, 2), dtype=np.int64)


def _check_no_collapse(sim_faces: np.ndarray, meshes: _PanelMeshes, pattern: Pattern) -> None:
    """PatternError when a triangle (sim faces (F, 3)) has a repeated sim vertex after the merge."""
    collapsed = (
        (sim_faces[:, 0] == sim_faces[:, 1])
        | (sim_faces[:, 1] == sim_faces[:, 2])
        | (sim_faces[:, 0] == sim_faces[:, 2])
    )
    if collapsed.any():
        pid = meshes.vert_panel[meshes.tri_vertices[collapsed][0, 0]]
        where = f"{pattern.source}: " if pattern.source else ""
        raise PatternError(
            f"{where}{int(collapsed.sum())} triangle(s) collapse when the seams are merged (first in panel "
            f"{list(pattern.panels)[pid]!r}); check the stitches of that panel"
        )


def _label_vertices(
    pattern: Pattern, edge_vertices: dict[tuple[str, int], torch.Tensor]
) -> dict[str, torch.Tensor]:
    """Edge label -> (n,) int64 sorted panel vertices of the edges with that label."""
    vert_labels: dict[str, torch.Tensor] = {}
    labels = sorted({e.label for p in pattern.panels.values() for e in p.edges if e.label is not None})
    for label in labels:
        refs: list[EdgeRef] = pattern.edges_with_label(label)
        idx = np.unique(np.concatenate([edge_vertices[(r.panel, r.edge)].numpy() for r in refs]))
        vert_labels[label] = torch.as_tensor(idx, dtype=torch.int64)
    return vert_labels


def _sim_loops(
    pattern: Pattern,
    sim_faces: np.ndarray,
    vert_to_sim: np.ndarray,
    sim_count: int,
    vert_pos: np.ndarray,
    vert_labels: dict[str, torch.Tensor],
) -> list[BoundaryLoop]:
    """The merged mesh's named openings (sim faces (F, 3), panel vertex -> sim vertex (Vp,)), named on
    the sim vertices placed at the mean of their panel vertices' positions (Vp, 3) [m]."""
    sim_pos = np.zeros((sim_count, 3))
    np.add.at(sim_pos, vert_to_sim, vert_pos)
    sim_pos /= np.bincount(vert_to_sim, minlength=sim_count)[:, None]
    lower = (
        set(vert_to_sim[vert_labels["lower_interface"].numpy()].tolist())
        if "lower_interface" in vert_labels
        else set()
    )
    return name_boundary_loops(_chain_boundary_loops(sim_faces), sim_pos, pattern.garment_type, lower)


def mesh_pattern(pattern: Pattern, spacing: float = 0.015, min_angle: float = 25.0) -> GarmentMesh:
    """Triangulate a sewing pattern into a placed, seam-merged `GarmentMesh`.

    Args:
        pattern: the sewing pattern (metres); `Pattern.validate` is run first.
        spacing: target edge length [m] along the boundary and inside panels (> 0).
        min_angle: minimum triangle angle [deg] asked of Triangle (0 < min_angle <= 34).

    Returns:
        the `GarmentMesh` (float64 / int64 on the CPU), see its docstring for every field.

    Raises:
        PatternError: a self-intersecting panel, a panel that cannot be triangulated, or seams that
            collapse a triangle when merged.
    """
    _check_mesh_args(spacing, min_angle)
    check_mesh_budget(pattern, spacing)
    pattern.validate()
    meshes = _mesh_panels(pattern, edge_sample_fractions(pattern, spacing), spacing, min_angle)
    stitch_pairs = _pattern_stitch_pairs(pattern, meshes.edge_vertices)
    # sim vertices numbered in order of first appearance (panel order, then position in panel)
    vert_to_sim, sim_count = merge_pairs(len(meshes.vert_uv), stitch_pairs)
    sim_faces = vert_to_sim[meshes.tri_vertices]
    _check_no_collapse(sim_faces, meshes, pattern)
    vert_labels = _label_vertices(pattern, meshes.edge_vertices)
    loops = _sim_loops(pattern, sim_faces, vert_to_sim, sim_count, meshes.vert_pos, vert_labels)
    return GarmentMesh(
        panel_names=list(pattern.panels),
        vert_uv=torch.as_tensor(meshes.vert_uv, dtype=torch.float64),
        vert_panel=torch.as_tensor(meshes.vert_panel, dtype=torch.int64),
        vert_pos=torch.as_tensor(meshes.vert_pos, dtype=torch.float64),
        tri_vertices=torch.as_tensor(meshes.tri_vertices, dtype=torch.int64),
        stitch_pairs=torch.as_tensor(stitch_pairs, dtype=torch.int64).reshape(-1, 2),
        vert_to_sim=torch.as_tensor(vert_to_sim, dtype=torch.int64),
        sim_vert_count=int(sim_count),
        boundary_loops=loops,
        panel_boundary=meshes.panel_boundary,
        edge_vertices=meshes.edge_vertices,
        vert_labels=vert_labels,
        garment_type=pattern.garment_type,
        spacing=float(spacing),
    )


@dataclass
class MeshReport:
    """Checks of a meshed pattern (see `mesh_report`).

    Attributes:
        max_stitch_count_mismatch: largest |vertices on edge A − vertices on edge B| (0 = equal).
        unmerged_stitch_pairs: stitch pairs whose two panel vertices did not become one sim vertex.
        seam_edges: sim edges that lie on a seam (between consecutive stitched vertices).
        open_seam_edges: seam edges that do not have exactly two triangles (0 = watertight seams).
        nonmanifold_edges: sim edges with more than two triangles.
        collapsed_faces: triangles with a repeated sim vertex.
    """

    max_stitch_count_mismatch: int
    unmerged_stitch_pairs: int
    seam_edges: int
    open_seam_edges: int
    nonmanifold_edges: int
    collapsed_faces: int


def mesh_report(pattern: Pattern, garment: GarmentMesh) -> MeshReport:
    """Measure seam consistency of ``garment`` (meshed from ``pattern``)."""
    mismatch = 0
    seam = set()
    v2s = garment.vert_to_sim
    for s in pattern.stitches:
        va = garment.edge_vertices[(s.a.panel, s.a.edge)]
        vb = garment.edge_vertices[(s.b.panel, s.b.edge)]
        mismatch = max(mismatch, abs(len(va) - len(vb)))
        for ev in (va, vb):
            sv = v2s[ev].tolist()
            seam.update((min(x, y), max(x, y)) for x, y in zip(sv[:-1], sv[1:]) if x != y)
    pairs = garment.stitch_pairs
    unmerged = int((v2s[pairs[:, 0]] != v2s[pairs[:, 1]]).sum()) if len(pairs) else 0
    faces = garment.sim_faces
    collapsed = int(
        ((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])).sum()
    )
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).sort(dim=1).values
    uniq, counts = torch.unique(e, dim=0, return_counts=True)
    count_of = {(int(a), int(b)): int(c) for (a, b), c in zip(uniq.tolist(), counts.tolist())}
    open_seam = sum(1 for key in seam if count_of.get(key, 0) != 2)
    return MeshReport(
        max_stitch_count_mismatch=int(mismatch),
        unmerged_stitch_pairs=unmerged,
        seam_edges=len(seam),
        open_seam_edges=int(open_seam),
        nonmanifold_edges=int((counts > 2).sum()),
        collapsed_faces=collapsed,
    )
