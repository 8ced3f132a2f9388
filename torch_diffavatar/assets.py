"""Assets out (the product of a fit): pattern JSON + SVG, rest and draped OBJ, body, material, report, PNG.

`fitted_pattern` turns optimised rest coordinates back into a GarmentCode pattern: every panel corner
takes the rest position of its panel vertex, Bézier control points are refitted by least squares to the
optimised edge vertices (at the template's curve parameters), and arcs keep their shape relative to the
chord (radius scaled by the chord's change). `pattern_deviation` measures how far the exported curves
lie from the optimised mesh boundary. `write_assets` writes the whole set of files into a folder.

Files written by `write_assets` (names in `ASSET_FILES`):

* ``pattern.json`` (GarmentCode specification, cm) and ``pattern.svg`` / ``pattern.png`` (pictures);
* ``rest.obj``: the panel meshes, ``v`` = each panel vertex placed by its panel's 3D rotation and
  translation, ``vt`` = the 2D rest coordinates [m] (one per panel vertex, faces ``f v/vt``);
* ``draped.obj``: the sewn garment at equilibrium (``v`` = sim vertices [m], ``vt`` = rest coordinates);
* ``body.obj`` + ``body.json`` (Anny parameters, phenotypes by name);
* ``material.json`` (every `ClothMaterial` field with its unit);
* ``report.json`` (final metrics, see `torch_diffavatar.fit`);
* ``before_after.png``: front and back views of the first and the last drape on their bodies.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from torch_diffavatar.mesh_io import write_garment_obj, write_obj
from torch_diffavatar.pattern.garment_mesh import GarmentMesh
from torch_diffavatar.pattern.garmentcode import save_pattern
from torch_diffavatar.pattern.spec import (
    Edge,
    Pattern,
    _bezier_eval,
    _bezier_points,
    absolute_to_relative,
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
    "report_json": "report.json",
    "before_after_png": "before_after.png",
}

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
        parameters); arc radii scaled by the change of their chord length.

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
            edges.append(edge)
        panels[name] = replace(panel, vertices=verts, edges=edges)
    return replace(pattern, panels=panels, source=None)


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


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


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
        before: optional (cloth_x, faces, body_verts, body_faces) of the first drape for the PNG.
        png_size: width of one view in the PNG [px].

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
    _write_json(paths["body_json"], body_params)
    _write_json(paths["material_json"], material_dict(material))
    written = [k for k in ASSET_FILES if k not in ("report_json", "before_after_png")]
    if before is not None:
        from torch_diffavatar.render import save_png

        after = (draped_x, garment.sim_faces, body_verts, body_faces)
        save_png(render_before_after(before, after, size=png_size), paths["before_after_png"])
        written.append("before_after_png")
    written.append("report_json")
    report = dict(report)
    report["pattern_export_max_deviation_m"] = pattern_deviation(fitted, garment, uv)
    report["files"] = {k: str(paths[k]) for k in written}
    _write_json(paths["report_json"], report)
    return report["files"]
