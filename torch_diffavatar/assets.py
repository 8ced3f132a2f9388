"""Assets out (the product of a fit): pattern JSON + SVG, rest and draped OBJ, body, material, report, PNG.

`fitted_pattern` turns optimised rest coordinates back into a GarmentCode pattern: every panel corner
takes the rest position of its panel vertex, Bézier control points are refitted by least squares to the
optimised edge vertices (at the template's curve parameters), and arcs are refitted to them too (the
circle through the two corners nearest the edge's vertices). `pattern_deviation` measures how far the
exported curves lie from the optimised mesh boundary. `write_assets` writes the whole set of files into
a folder.

Files written by `write_assets` (names in `ASSET_FILES`):

* ``pattern.json`` (GarmentCode specification, cm) and ``pattern.svg`` / ``pattern.png`` (pictures);
* ``rest.obj``: the panel meshes, ``v`` = each panel vertex placed by its panel's 3D rotation and
  translation, ``vt`` = the 2D rest coordinates [m] (one per panel vertex, faces ``f v/vt``);
* ``draped.obj``: the sewn garment at equilibrium (``v`` = sim vertices [m], ``vt`` = rest coordinates);
* ``body.obj`` + ``body.json`` (Anny parameters, phenotypes by name);
* ``material.json`` (every `ClothMaterial` field with its unit);
* ``material_newton.json``: the material in NVIDIA Newton's units (`assets_newton`);
* ``report.json`` (final metrics, see `torch_diffavatar.fit`);
* ``before_after.png``: front and back views of the first and the last drape on their bodies;
* ``scan_fit.png``: the scan's garment points on the fit and the fit against them, coloured by distance
  (`scan_fit_picture`);
* ``draped_initial.obj``: the first drape (the template on the initial body), to measure what the fit gained;
* ``seams.json``: the garment topology beside the OBJs (panel of each rest vertex, seam vertex pairs,
  stitched edge pairs, rest-vertex -> draped-vertex map, labels, openings);
* ``asset.json``: the manifest (format version, frame, units, files, material with meanings, counts).

`load_assets` reads such a folder back into our objects (`Assets`); docs/ASSETS.md documents the format.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import minimize_scalar

from torch_diffavatar.assets_newton import newton_material_dict
from torch_diffavatar.json_io import write_json
from torch_diffavatar.mesh_io import write_garment_obj, write_obj
from torch_diffavatar.pattern.garment_mesh import GarmentMesh
from torch_diffavatar.pattern.garmentcode import save_pattern
from torch_diffavatar.pattern.spec import (
    Edge,
    Pattern,
    _bezier_eval,
    _bezier_points,
    absolute_to_relative,
    outline_self_intersects,
    sample_edge,
)
from torch_diffavatar.sim.material import ClothMaterial

ASSET_FILES = {
    "pattern_json": "pattern.json",
    "pattern_svg": "pattern.svg",
    "pattern_png": "pattern.png",
    "rest_obj": "rest.obj",
    "draped_obj": "draped.obj",
    "body_obj": "body.obj",
    "body_json": "body.json",
    "material_json": "material.json",
    "material_newton_json": "material_newton.json",
    "report_json": "report.json",
    "before_after_png": "before_after.png",
    "scan_fit_png": "scan_fit.png",
    "draped_initial_obj": "draped_initial.obj",
    "seams_json": "seams.json",
    "manifest_json": "asset.json",
}

ASSET_FORMAT = "torch_diffavatar.assets"
ASSET_FORMAT_VERSION = 1

MATERIAL_UNITS = {
    "areal_density": "kg/m^2",
    "k_uu": "N/m",
    "k_vv": "N/m",
    "k_uv": "N/m",
    "poisson": "-",
    "bend_stiffness": "N*m",
    "damping": "1/s",
    "friction": "-",
    "thickness": "m",
}

MATERIAL_MEANINGS = {
    "areal_density": "mass per rest area; vertex masses are lumped from the rest triangle areas",
    "k_uu": "membrane stretch stiffness along the pattern's u axis (rest.obj vt first coordinate, warp): "
    "energy density 1/2 k_uu E00^2 per rest area, E = Green strain of the triangle w.r.t. its vt shape",
    "k_vv": "membrane stretch stiffness along the pattern's v axis (vt second coordinate, weft): "
    "1/2 k_vv E11^2",
    "k_uv": "in-plane shear stiffness: energy density 2 k_uv E01^2 (= 1/2 k_uv gamma^2, gamma = 2 E01)",
    "poisson": "coupling nu in [0, 1): energy term nu sqrt(k_uu k_vv) E00 E11",
    "bend_stiffness": "discrete-shell bending stiffness k_b: energy 1/2 k_b 3|e|^2/(A1+A2) (theta-theta0)^2 "
    "per interior edge of the draped mesh, theta0 = 0 (flat pattern, also across seams)",
    "damping": "velocity damping rate: v *= exp(-damping dt) every substep of dt seconds",
    "friction": "Coulomb friction coefficient cloth-body",
    "thickness": "collision offset: cloth vertices are kept this far outside the body surface",
}


def _check_rest_uv(rest_uv: torch.Tensor, garment: GarmentMesh) -> np.ndarray:
    if not isinstance(rest_uv, torch.Tensor) or tuple(rest_uv.shape) != (garment.vert_count, 2):
        shape = tuple(rest_uv.shape) if isinstance(rest_uv, torch.Tensor) else type(rest_uv).__name__
        raise ValueError(
            f"rest_uv must be a ({garment.vert_count}, 2) tensor of rest coordinates, got {shape}"
        )
    uv = rest_uv.detach().cpu().double().numpy()
    if not np.isfinite(uv).all():
        raise ValueError("rest_uv holds NaN or infinite coordinates")
    return uv


def _bezier_parameters(start, end, edge: Edge, points: np.ndarray, samples: int = 2049) -> np.ndarray:
    """(n,) Bézier parameters of the dense-sample points nearest to ``points`` (n, 2) on the template edge."""
    ctrl = _bezier_points(np.asarray(start, float), np.asarray(end, float), edge)
    s = np.linspace(0.0, 1.0, samples)
    dense = _bezier_eval(ctrl, s)  # (samples, 2)
    d = ((points[:, None, :] - dense[None]) ** 2).sum(-1)
    return s[d.argmin(1)]


def _refit_bezier(edge: Edge, s: np.ndarray, points: np.ndarray, start: np.ndarray, end: np.ndarray) -> Edge:
    """Least-squares interior control points of a Bézier edge through ``points`` at parameters ``s``."""
    order = len(edge.control) + 1  # 2 = quadratic, 3 = cubic
    coeffs = np.stack([_bernstein(order, j, s) for j in range(order + 1)], axis=1)  # (n, order+1)
    rhs = points - coeffs[:, :1] * start - coeffs[:, -1:] * end
    a = coeffs[:, 1:-1]
    if len(points) < order + 1 or np.linalg.matrix_rank(a) < a.shape[1]:
        return edge  # too few points to refit: keep the template's relative control points
    ctrl, *_ = np.linalg.lstsq(a, rhs, rcond=None)
    if float(np.linalg.norm(end - start)) < 1e-12:
        return edge
    rel = tuple(absolute_to_relative(start, end, c) for c in ctrl)
    return replace(edge, control=tuple((float(u), float(v)) for u, v in rel))


def _arc_sagitta(edge: Edge, start: np.ndarray, end: np.ndarray) -> float:
    """Signed sagitta [m] of a circle edge: how far its arc's midpoint lies from the chord's, > 0 on the
    left of start -> end."""
    chord = end - start
    mid = sample_edge(start, end, edge, np.array([0.5]))[0] - (start + end) / 2.0
    return float(chord[0] * mid[1] - chord[1] * mid[0]) / max(float(np.linalg.norm(chord)), 1e-300)


def _arc_with_sagitta(edge: Edge, start: np.ndarray, end: np.ndarray, sagitta: float) -> Edge:
    """The circle edge from ``start`` to ``end`` whose arc's midpoint lies ``sagitta`` [m] off the chord
    (> 0 on its left): radius (c²/4 + h²) / 2h, the larger arc beyond a half circle."""
    chord = float(np.linalg.norm(end - start))
    h = max(abs(sagitta), 1e-6 * chord)
    shaped = replace(edge, radius=(chord * chord / 4.0 + h * h) / (2.0 * h), large_arc=h > chord / 2.0)
    for right in (False, True):
        cand = replace(shaped, right=right)
        if _arc_sagitta(cand, start, end) * sagitta >= 0:
            return cand
    return shaped


def _refit_circle(edge: Edge, points: np.ndarray, start: np.ndarray, end: np.ndarray) -> Edge:
    """The circle edge through ``start`` and ``end`` nearest (least squares) to the edge's interior vertices
    ``points`` (n, 2): an arc keeps its corners' chord but takes the depth the fit gave it (a neckline the
    fit made shallower), which scaling the template's radius with its chord does not. ``edge`` unchanged
    without interior points, or when it already fits them best."""
    chord = float(np.linalg.norm(end - start))
    if len(points) == 0 or chord < 1e-12:
        return edge

    dense = np.linspace(0.0, 1.0, 257)

    def residual(cand: Edge) -> float:  # to the arc itself: the circle's other arc passes the points too
        arc = sample_edge(start, end, cand, dense)
        return float(((points[:, None, :] - arc[None]) ** 2).sum(-1).min(1).sum())

    grid = np.linspace(-chord, chord, 401)
    costs = [residual(_arc_with_sagitta(edge, start, end, h)) for h in grid]
    k = int(np.argmin(costs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    best = minimize_scalar(
        lambda h: residual(_arc_with_sagitta(edge, start, end, h)), bounds=(lo, hi), method="bounded"
    )
    cand = _arc_with_sagitta(edge, start, end, float(best.x))
    return cand if residual(cand) < residual(edge) else edge


def _bernstein(n: int, j: int, s: np.ndarray) -> np.ndarray:
    from math import comb

    return comb(n, j) * s**j * (1 - s) ** (n - j)


def fitted_pattern(pattern: Pattern, garment: GarmentMesh, rest_uv: torch.Tensor) -> Pattern:
    """The pattern whose panels follow the optimised rest coordinates.

    Args:
        pattern: the template the garment was meshed from (panel names and edges match the garment's).
        garment: the meshed template (its ``edge_vertices`` map pattern edges to panel vertices).
        rest_uv: (V, 2) optimised rest coordinates [m] of the panel vertices.

    Returns:
        a new `Pattern` (stitches, placement and labels unchanged): corners moved to the rest positions
        of their panel vertices; quadratic/cubic control points refitted (least squares, template curve
        parameters); arcs refitted (`_refit_circle`: the circle through the new corners nearest the
        edge's vertices).

    Raises:
        ValueError: ``rest_uv`` has the wrong shape or non-finite values, or the garment's edges do not
            match the pattern's.
    """
    uv = _check_rest_uv(rest_uv, garment)
    template_uv = garment.vert_uv.detach().cpu().double().numpy()
    panels = {}
    for name, panel in pattern.panels.items():
        verts = np.array(panel.vertices, dtype=np.float64, copy=True)
        edges = []
        for k, edge in enumerate(panel.edges):
            key = (name, k)
            if key not in garment.edge_vertices:
                raise ValueError(f"the garment has no vertices for edge {k} of panel {name!r}")
            ev = garment.edge_vertices[key].cpu().numpy()
            verts[edge.start] = uv[ev[0]]
            verts[edge.end] = uv[ev[-1]]
        for k, edge in enumerate(panel.edges):
            ev = garment.edge_vertices[(name, k)].cpu().numpy()
            new_start, new_end = verts[edge.start], verts[edge.end]
            if edge.kind in ("quadratic", "cubic"):
                old_start, old_end = panel.vertices[edge.start], panel.vertices[edge.end]
                s = _bezier_parameters(old_start, old_end, edge, template_uv[ev])
                edge = _refit_bezier(edge, s, uv[ev], new_start, new_end)
            elif edge.kind == "circle":
                old = float(np.linalg.norm(panel.vertices[edge.end] - panel.vertices[edge.start]))
                new = float(np.linalg.norm(new_end - new_start))
                if old > 1e-12:
                    edge = replace(edge, radius=float(edge.radius) * new / old)
                edge = _refit_circle(edge, uv[ev[1:-1]], new_start, new_end)
            edges.append(edge)
        panels[name] = replace(panel, vertices=verts, edges=edges)
    return replace(pattern, panels=panels, source=None)


def crossed_outline_warnings(
    pattern: Pattern, garment: GarmentMesh | None = None, rest_uv: np.ndarray | None = None
) -> list[str]:
    """Warnings (empty when none) about panel outlines of the exported ``pattern`` that cross themselves,
    which `mesh_pattern` refuses (`Pattern.validate`). Given the ``garment`` and its fitted ``rest_uv``
    (V, 2) [m], they say whether the fit's rest outline of the panel crosses itself too (two corners
    passed each other: on the suite's Newton dress, the legs of a back bodice dart) or only the refitted
    curves overshoot where the rest mesh is fine."""
    crossed = pattern.crossed_panels()
    if not crossed:
        return []
    in_rest = []
    if garment is not None and rest_uv is not None:
        outlines = {n: rest_uv[b.cpu().numpy()] for n, b in zip(garment.panel_names, garment.panel_boundary)}
        in_rest = [n for n in crossed if n in outlines and outline_self_intersects(outlines[n])]
    refit = [n for n in crossed if n not in in_rest]
    warnings = []
    if refit:
        warnings.append(
            f"the exported pattern's outline of {', '.join(refit)} crosses itself (a refitted curve "
            "overshoots): pattern.json cannot be meshed or cut as it is; rest.obj holds the fitted panels"
        )
    if in_rest:
        warnings.append(
            f"the fitted outline of {', '.join(in_rest)} crosses itself (two of its corners, such as a "
            "dart's legs, passed each other in the fit): neither pattern.json nor rest.obj's panels can be "
            "cut as they are"
        )
    return warnings


def pattern_deviation(pattern: Pattern, garment: GarmentMesh, rest_uv: torch.Tensor) -> float:
    """Largest distance [m] between ``pattern``'s edges and the rest coordinates of the edge vertices.

    Each edge's vertices are compared with the pattern curve sampled at their arc-length fractions along
    the vertex polyline (0 for a pattern that reproduces the mesh boundary exactly).
    """
    uv = _check_rest_uv(rest_uv, garment)
    worst = 0.0
    for name, panel in pattern.panels.items():
        for k, edge in enumerate(panel.edges):
            p = uv[garment.edge_vertices[(name, k)].cpu().numpy()]
            seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
            total = seg.sum()
            if total <= 0:
                continue
            t = np.concatenate([[0.0], np.cumsum(seg)]) / total
            q = sample_edge(panel.vertices[edge.start], panel.vertices[edge.end], edge, t)
            worst = max(worst, float(np.linalg.norm(q - p, axis=1).max()))
    return worst


def rest_mesh_positions(pattern: Pattern, garment: GarmentMesh, rest_uv: torch.Tensor) -> np.ndarray:
    """(V, 3) panel vertices placed by their panel's 3D rotation and translation (``Panel.to_world``)."""
    uv = _check_rest_uv(rest_uv, garment)
    out = np.zeros((garment.vert_count, 3))
    vert_panel = garment.vert_panel.cpu().numpy()
    for pid, name in enumerate(garment.panel_names):
        sel = vert_panel == pid
        out[sel] = pattern.panels[name].to_world(uv[sel])
    return out


def write_rest_obj(path, pattern: Pattern, garment: GarmentMesh, rest_uv: torch.Tensor) -> None:
    """Panel meshes as OBJ: ``v`` = panel vertices placed in 3D, ``vt`` = rest coordinates [m]."""
    pos = rest_mesh_positions(pattern, garment, rest_uv)
    write_obj(
        path, pos, garment.tri_vertices, uv=rest_uv.detach().cpu().double(), uv_faces=garment.tri_vertices
    )


def material_dict(material: ClothMaterial) -> dict:
    """JSON-friendly ``{field: {"value": float, "unit": str}}`` of a material (tensors become floats)."""
    out = {}
    for f in dataclasses.fields(material):
        value = getattr(material, f.name)
        value = float(value.detach()) if isinstance(value, torch.Tensor) else float(value)
        out[f.name] = {"value": value, "unit": MATERIAL_UNITS.get(f.name, "")}
    return out


def material_from_dict(data: dict) -> ClothMaterial:
    """Inverse of `material_dict` (plain ``{field: float}`` is accepted too)."""
    names = {f.name for f in dataclasses.fields(ClothMaterial)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"unknown material fields {sorted(unknown)}; valid: {sorted(names)}")
    values = {k: float(v["value"] if isinstance(v, dict) else v) for k, v in data.items()}
    return ClothMaterial(**values)


def render_before_after(
    before: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    after: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    *,
    size: int = 320,
) -> np.ndarray:
    """(size·5/4, 4·size, 3) uint8: front and back of ``before`` then of ``after``.

    Args:
        before, after: (cloth_x (Vs, 3), cloth_faces (F, 3), body_verts (Vb, 3), body_faces (Fb, 3)) [m].
    """
    from torch_diffavatar.render import CLOTH_COLOR, CLOTH_DEPTH_BIAS, RenderMesh, render_views

    panels = []
    for x, faces, bv, bf in (before, after):
        meshes = [
            RenderMesh(bv.detach().cpu(), bf.cpu()),
            RenderMesh(x.detach().cpu(), faces.cpu(), CLOTH_COLOR, CLOTH_DEPTH_BIAS),
        ]
        panels.append(render_views(meshes, views=("front", "back"), width=size, height=size * 5 // 4))
    return np.concatenate(panels, axis=1)


def _write_pictures(paths, garment, after, before, scan_points, front_deg, png_size) -> list[str]:
    """``before_after.png`` and ``draped_initial.obj`` (with ``before``), ``scan_fit.png`` (with
    ``scan_points``), as `write_assets` documents; the keys of what was written."""
    from torch_diffavatar.render import save_png

    written = []
    if scan_points is not None:
        from torch_diffavatar.scan_fit_picture import render_scan_on_fit

        picture = render_scan_on_fit(scan_points, *after, front_deg=front_deg, size=png_size)
        save_png(picture, paths["scan_fit_png"])
        written.append("scan_fit_png")
    if before is not None:
        save_png(render_before_after(before, after, size=png_size), paths["before_after_png"])
        write_garment_obj(
            paths["draped_initial_obj"], garment, sim_positions=before[0].detach().cpu().double()
        )
        written += ["before_after_png", "draped_initial_obj"]
    return written


def write_assets(
    out_dir: str | os.PathLike,
    *,
    pattern: Pattern,
    garment: GarmentMesh,
    rest_uv: torch.Tensor,
    draped_x: torch.Tensor,
    body_verts: torch.Tensor,
    body_faces: torch.Tensor,
    body_params: dict,
    material: ClothMaterial,
    report: dict,
    before: tuple | None = None,
    scan_points: torch.Tensor | None = None,
    front_deg: float = 0.0,
    png_size: int = 320,
) -> dict[str, str]:
    """Write every asset of a fit into ``out_dir`` (see the module docstring).

    Args:
        pattern: the template pattern (the fitted one is derived with `fitted_pattern`).
        garment: the meshed template; rest_uv: (V, 2) optimised rest coordinates [m].
        draped_x: (Vs, 3) final drape [m]; body_verts: (Vb, 3) [m]; body_faces: (Fb, 3) int64.
        body_params: `BodyModel.parameters_dict()` (plus anything to keep beside it).
        material: the fitted material.
        report: the metrics; ``pattern_export_max_deviation_m`` and ``files`` are added.
        before: optional (cloth_x, faces, body_verts, body_faces) of the first drape, for the PNG and
            ``draped_initial.obj``.
        scan_points: optional (P, 3) the scan's garment points [m], for ``scan_fit.png``.
        front_deg: the azimuth [deg] of the body's front in the pictures of ``scan_points``
            (`body.facing.body_facing_yaw`).
        png_size: width of one view in the PNGs [px].

    Returns:
        asset name -> path (the keys of `ASSET_FILES` that were written).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {k: out / v for k, v in ASSET_FILES.items()}
    uv = rest_uv.detach().cpu().double()
    fitted = fitted_pattern(pattern, garment, uv)
    save_pattern(fitted, paths["pattern_json"])
    from torch_diffavatar.pattern.svg import save_pattern_png, save_pattern_svg

    save_pattern_svg(fitted, paths["pattern_svg"])
    save_pattern_png(fitted, paths["pattern_png"])
    write_rest_obj(paths["rest_obj"], fitted, garment, uv)
    fitted_garment = replace(garment, vert_uv=uv)
    write_garment_obj(paths["draped_obj"], fitted_garment, sim_positions=draped_x.detach().cpu().double())
    write_obj(paths["body_obj"], body_verts.detach().cpu().double(), body_faces.cpu())
    write_json(paths["body_json"], body_params)
    write_json(paths["material_json"], material_dict(material))
    write_json(paths["material_newton_json"], newton_material_dict(garment, uv, material))
    write_json(paths["seams_json"], seams_dict(garment))
    optional = ("report_json", "before_after_png", "scan_fit_png", "draped_initial_obj", "manifest_json")
    written = [k for k in ASSET_FILES if k not in optional]
    after = (draped_x, garment.sim_faces, body_verts, body_faces)
    written += _write_pictures(paths, garment, after, before, scan_points, front_deg, png_size)
    written += ["report_json", "manifest_json"]
    report = dict(report)
    report["pattern_export_max_deviation_m"] = pattern_deviation(fitted, garment, uv)
    crossed = crossed_outline_warnings(fitted, garment, uv.numpy())
    report["warnings"] = list(report.get("warnings", [])) + crossed
    report["files"] = {k: str(paths[k]) for k in written}
    write_json(paths["report_json"], report)
    write_json(
        paths["manifest_json"],
        manifest_dict(garment, material, body_verts, body_faces, {k: ASSET_FILES[k] for k in written}),
    )
    return report["files"]


# ---------------------------------------------------------------------------------------------------
# The asset format for other simulators: seams.json + asset.json, and the loader
# ---------------------------------------------------------------------------------------------------

FILE_CONTENTS = {
    "pattern_json": "GarmentCode sewing pattern of the fitted garment (panels, curves, stitches) [cm]",
    "pattern_svg": "picture of the pattern",
    "pattern_png": "picture of the pattern",
    "rest_obj": "panel meshes, one vertex per panel vertex (seams NOT merged): v = panel placed in 3D "
    "by its panel rotation/translation [m], vt = 2D rest coordinates of the vertex in its panel [m]",
    "draped_obj": "the sewn garment at equilibrium on the body: v = seam-merged vertices [m]; faces "
    "'f v/vt' pair each corner's draped vertex with its rest vertex (vt indexes rest.obj's vertices)",
    "body_obj": "the body mesh the garment was draped on [m] (closed, outward normals)",
    "body_json": "Anny body parameters (BodyModel.parameters_dict: phenotypes, per-bone axis-angle "
    "[rad], global orientation [rad], translation [m], scale)",
    "material_json": "cloth material, every field with its SI unit",
    "material_newton_json": "the material in NVIDIA Newton's units (SolverVBD: tri_ke, tri_ka, per-edge "
    "edge_ke on draped.obj's interior edges, density, friction, radius), converted as docs/ASSETS.md says",
    "report_json": "metrics of the fit",
    "before_after_png": "first and final drape of the fit",
    "scan_fit_png": "the scan's garment points on the fit and the fit against them, coloured by distance",
    "draped_initial_obj": "the fit's first drape (template pattern on the initial body), as draped.obj",
    "seams_json": "garment topology: panel of each rest vertex, seam vertex pairs, stitched edge pairs, "
    "rest vertex -> draped vertex map, edge labels, openings",
    "manifest_json": "this manifest",
}


def stitched_edges(garment: GarmentMesh) -> np.ndarray:
    """(Se, 4) int64 pairs of sewn boundary edges ``(a0, a1, b0, b1)`` of the panel meshes.

    Boundary edge (a0, a1) of one panel is sewn to boundary edge (b0, b1) when a0–b0 and a1–b1 are both
    stitched vertex pairs (panel-vertex ids, i.e. rows of rest.obj). Each pair is listed once.
    """
    tri = garment.tri_vertices.cpu().numpy()
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    key, count = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)
    boundary = {(int(a), int(b)) for a, b in key[count == 1]}
    partners: dict[int, set[int]] = {}
    for a, b in garment.stitch_pairs.cpu().numpy().reshape(-1, 2):
        partners.setdefault(int(a), set()).add(int(b))
        partners.setdefault(int(b), set()).add(int(a))
    out = set()
    for a0, a1 in boundary:
        for b0 in partners.get(a0, ()):
            for b1 in partners.get(a1, ()):
                if b0 != b1 and (min(b0, b1), max(b0, b1)) in boundary:
                    first, second = (a0, a1), (b0, b1)
                    out.add((*first, *second) if first < (min(b0, b1), max(b0, b1)) else (*second, *first))
    return np.array(sorted(out), dtype=np.int64).reshape(-1, 4)


def seams_dict(garment: GarmentMesh) -> dict:
    """JSON-friendly garment topology (see ``FILE_CONTENTS["seams_json"]``); indices are 0-based."""

    def ints(t):
        return [int(i) for i in t.cpu().reshape(-1).tolist()]

    return {
        "panel_names": list(garment.panel_names),
        "garment_type": garment.garment_type,
        "spacing_m": float(garment.spacing),
        "panel_vertex_count": garment.vert_count,
        "sim_vertex_count": int(garment.sim_vert_count),
        "vert_panel": ints(garment.vert_panel),
        "vert_to_sim": ints(garment.vert_to_sim),
        "stitch_pairs": garment.stitch_pairs.cpu().reshape(-1, 2).tolist(),
        "stitched_edges": stitched_edges(garment).tolist(),
        "vert_labels": {k: ints(v) for k, v in garment.vert_labels.items()},
        "boundary_loops": [
            {"name": b.name, "sim_vertices": ints(b.vertices)} for b in garment.boundary_loops
        ],
        "panel_boundary": [ints(t) for t in garment.panel_boundary],
        "edge_vertices": [[name, int(k), ints(v)] for (name, k), v in garment.edge_vertices.items()],
    }


def manifest_dict(garment: GarmentMesh, material: ClothMaterial, body_verts, body_faces, files: dict) -> dict:
    """The ``asset.json`` manifest: format, frame, units, files, counts, material with meanings."""
    from torch_diffavatar.sim.forward_drape import DrapeConfig

    cfg = DrapeConfig()
    mat = material_dict(material)
    for name, entry in mat.items():
        entry["meaning"] = MATERIAL_MEANINGS.get(name, "")
    return {
        "format": ASSET_FORMAT,
        "version": ASSET_FORMAT_VERSION,
        "frame": {
            "up": "+Y",
            "forward": "+Z (the body faces +Z)",
            "left": "+X (the body's left side)",
            "ground": "feet on y = 0",
            "handedness": "right-handed",
        },
        "units": {"length": "m", "mass": "kg", "time": "s", "angle": "rad", "pattern_json": "cm"},
        "files": {k: {"path": v, "content": FILE_CONTENTS.get(k, "")} for k, v in files.items()},
        "garment": {
            "type": garment.garment_type,
            "panels": list(garment.panel_names),
            "rest_vertex_count": garment.vert_count,
            "draped_vertex_count": int(garment.sim_vert_count),
            "triangle_count": garment.tri_count,
            "stitch_pair_count": int(garment.stitch_pairs.reshape(-1, 2).shape[0]),
            "triangle_winding": "counter-clockwise seen from outside the garment (right-hand normal out)",
        },
        "material": mat,
        "body": {
            "model": "Anny (anny 0.6.2), topology anny-noeyes-notongue",
            "vertex_count": int(body_verts.shape[0]),
            "triangle_count": int(body_faces.shape[0]),
        },
        "simulation": {
            "note": "settings of our XPBD drape that produced draped.obj (for reference, not required)",
            "frame_dt_s": cfg.dt,
            "substeps": cfg.xpbd.substeps,
            "iterations": cfg.xpbd.iterations,
            "gravity_m_s2": list(cfg.xpbd.gravity),
            "velocity_scale_per_frame": cfg.drape_velocity_scale,
        },
    }


@dataclass
class Assets:
    """A simulation-ready asset folder read back by `load_assets`.

    Attributes:
        garment: the garment: ``vert_uv`` (V, 2) = rest coordinates [m], ``vert_pos`` (V, 3) = the drape
            at each rest vertex [m], seams, labels, openings (float64 / int64, CPU).
        rest_uv: (V, 2) float64 rest coordinates [m] (= ``garment.vert_uv``).
        rest_pos: (V, 3) float64 panels placed in 3D (rest.obj ``v``) [m].
        draped_x: (Vs, 3) float64 draped seam-merged vertices [m].
        body_verts: (Vb, 3) float64 [m]; body_faces: (Fb, 3) int64.
        body_params: body.json (`BodyModel.parameters_dict`, plus ``phenotypes_by_name``).
        material: the `ClothMaterial`.
        pattern: the fitted `Pattern` (pattern.json), or None when the file is absent.
        manifest: asset.json.
        stitched_edges: (Se, 4) int64 sewn boundary edge pairs (seams.json).
        path: the folder.
    """

    garment: GarmentMesh
    rest_uv: torch.Tensor
    rest_pos: torch.Tensor
    draped_x: torch.Tensor
    body_verts: torch.Tensor
    body_faces: torch.Tensor
    body_params: dict
    material: ClothMaterial
    pattern: Pattern | None
    manifest: dict
    stitched_edges: torch.Tensor
    path: Path


def _read_json(path: Path) -> dict:
    from torch_diffavatar.errors import read_json_file

    return read_json_file(path, f"{path}: missing (not an asset folder written by write_assets?)")


def load_assets(asset_dir: str | os.PathLike) -> Assets:
    """Read an asset folder written by `write_assets` (needs asset.json and seams.json, format v1).

    Raises:
        InputError: a missing or inconsistent file (the message names it).
    """
    from torch_diffavatar.errors import InputError
    from torch_diffavatar.mesh_io import read_obj
    from torch_diffavatar.pattern.garment_mesh import BoundaryLoop
    from torch_diffavatar.pattern.garmentcode import load_pattern

    root = Path(asset_dir)
    if not root.is_dir():
        raise InputError(f"{root}: no such asset folder")
    manifest = _read_json(root / ASSET_FILES["manifest_json"])
    if manifest.get("format") != ASSET_FORMAT or int(manifest.get("version", -1)) > ASSET_FORMAT_VERSION:
        raise InputError(
            f"{root / 'asset.json'}: format {manifest.get('format')!r} v{manifest.get('version')}, expected "
            f"{ASSET_FORMAT!r} v{ASSET_FORMAT_VERSION} or older"
        )
    files = {k: root / v["path"] for k, v in manifest["files"].items()}
    seams = _read_json(files["seams_json"])
    rest = read_obj(files["rest_obj"])
    draped = read_obj(files["draped_obj"])
    body = read_obj(files["body_obj"])
    V, Vs = int(seams["panel_vertex_count"]), int(seams["sim_vertex_count"])
    if rest.verts.shape[0] != V or rest.uv is None or rest.uv.shape[0] != V:
        raise InputError(f"{files['rest_obj']}: expected {V} vertices and {V} vt records (seams.json)")
    if draped.verts.shape[0] != Vs or draped.uv_faces is None:
        raise InputError(f"{files['draped_obj']}: expected {Vs} vertices with 'f v/vt' faces (seams.json)")
    tri = draped.uv_faces  # panel-vertex triangles
    if not torch.equal(tri, rest.faces):
        raise InputError(f"{files['draped_obj']}: its vt indices do not match the faces of rest.obj")
    vert_to_sim = torch.tensor(seams["vert_to_sim"], dtype=torch.int64)
    if not torch.equal(vert_to_sim[tri], draped.faces):
        raise InputError(f"{files['draped_obj']}: faces disagree with seams.json vert_to_sim")
    uv = rest.uv.to(torch.float64)
    garment = GarmentMesh(
        panel_names=list(seams["panel_names"]),
        vert_uv=uv,
        vert_panel=torch.tensor(seams["vert_panel"], dtype=torch.int64),
        vert_pos=draped.verts[vert_to_sim].clone(),
        tri_vertices=tri.clone(),
        stitch_pairs=torch.tensor(seams["stitch_pairs"], dtype=torch.int64).reshape(-1, 2),
        vert_to_sim=vert_to_sim,
        sim_vert_count=Vs,
        boundary_loops=[
            BoundaryLoop(b["name"], torch.tensor(b["sim_vertices"], dtype=torch.int64))
            for b in seams.get("boundary_loops", [])
        ],
        panel_boundary=[torch.tensor(t, dtype=torch.int64) for t in seams.get("panel_boundary", [])],
        edge_vertices={
            (name, int(k)): torch.tensor(v, dtype=torch.int64)
            for name, k, v in seams.get("edge_vertices", [])
        },
        vert_labels={k: torch.tensor(v, dtype=torch.int64) for k, v in seams.get("vert_labels", {}).items()},
        garment_type=seams.get("garment_type"),
        spacing=float(seams.get("spacing_m", 0.015)),
    )
    material = material_from_dict(_read_json(files["material_json"]))
    pattern = load_pattern(files["pattern_json"]) if files.get("pattern_json", Path()).is_file() else None
    return Assets(
        garment=garment,
        rest_uv=uv,
        rest_pos=rest.verts,
        draped_x=draped.verts,
        body_verts=body.verts,
        body_faces=body.faces,
        body_params=_read_json(files["body_json"]),
        material=material,
        pattern=pattern,
        manifest=manifest,
        stitched_edges=torch.tensor(seams.get("stitched_edges", []), dtype=torch.int64).reshape(-1, 4),
        path=root,
    )
