"""GarmentCode JSON pattern specifications in and out.

Format (see /work/shared/garmentcode/README.md): ``{"pattern": {"panels", "stitches", "panel_order"},
"properties": {"units_in_meter", "curvature_coords", ...}, ...}``. Files are usually in cm
(``units_in_meter: 100``); a `Pattern` is in metres. Extra top-level keys (e.g. our ``"garment_type"``)
are kept and written back.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from torch_diffavatar.errors import PatternError
from torch_diffavatar.json_io import write_json
from torch_diffavatar.pattern.spec import (
    GARMENT_TYPES,
    Edge,
    EdgeRef,
    Panel,
    Pattern,
    Stitch,
    absolute_to_relative,
)

# GarmentCode's mean_all body [m], from body/mean_all.yaml (floor at 0): height; crotch = hip level −
# crotch_hip_diff; waist level = height − head_l − waist_line; neck base = height − head_l; acromion =
# neck base − (shoulder_w/2 − neck_w/2)·tan(shoulder_incl); the arm pose angle below horizontal [deg].
GC_BODY = {
    "height": 1.7199,
    "crotch": 0.7648,
    "waist": 1.0877,
    "shoulder": 1.4219,
    "neck": 1.4566,
    "shoulder_half_width": 0.1823,
    "arm_angle_deg": 45.48,
}


_KNOWN_TOP_KEYS = ("pattern", "properties", "garment_type")
_DEFAULT_PROPERTIES = {
    "curvature_coords": "relative",
    "normalize_panel_translation": False,
    "normalized_edge_loops": True,
    "units_in_meter": 100,
}


def load_pattern(path: str | os.PathLike) -> Pattern:
    """Read a GarmentCode pattern specification.

    Args:
        path: the ``*_specification.json`` file.

    Returns:
        the `Pattern` in metres. Self-intersecting outlines are accepted here; `Pattern.validate`
        (called by the mesher) rejects them.

    Raises:
        PatternError: missing file, malformed JSON, or an inconsistent pattern (the message names the
            file and the problem).
    """
    path = Path(path)
    if not path.exists():
        raise PatternError(f"{path}: pattern file not found")
    if path.is_dir():
        raise PatternError(f"{path}: is a directory, expected a pattern JSON file")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise PatternError(f"{path}: malformed JSON: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise PatternError(f"{path}: not a text JSON file ({exc})") from exc
    except RecursionError as exc:
        raise PatternError(f"{path}: JSON nested too deeply to be a sewing pattern") from exc
    return pattern_from_dict(data, source=str(path))


def save_pattern(pattern: Pattern, path: str | os.PathLike) -> None:
    """Write a `Pattern` as GarmentCode JSON (units from ``pattern.properties``, cm by default)."""
    write_json(path, pattern_to_dict(pattern))


# Panels of a pattern read here: the templates and GarmentCode's examples have at most 12; 10,000 asked
# the drape for gigabytes and the fit for 128 GB (issue #33)
MAX_PANELS = 200


def _fail(source: str | None, msg: str):
    raise PatternError(f"{source or '<pattern>'}: {msg}")


def _number(value, source, what) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        _fail(source, f"{what} must be a finite number, got {value!r}")
    return float(value)


def _point(value, source, what, dim=2) -> np.ndarray:
    if not isinstance(value, list | tuple) or len(value) != dim:
        _fail(source, f"{what} must be a list of {dim} numbers, got {value!r}")
    return np.array([_number(v, source, what) for v in value], dtype=np.float64)


def _parse_edge(raw, verts_file: np.ndarray, scale: float, absolute: bool, source, where) -> Edge:
    if not isinstance(raw, dict) or "endpoints" not in raw:
        _fail(source, f"{where}: an edge must be an object with 'endpoints'")
    ends = raw["endpoints"]
    n = len(verts_file)
    if (
        not isinstance(ends, list | tuple)
        or len(ends) != 2
        or not all(isinstance(i, int) and not isinstance(i, bool) and 0 <= i < n for i in ends)
    ):
        _fail(source, f"{where}: endpoints {ends!r} must be two vertex indices in [0, {n})")
    start, end = int(ends[0]), int(ends[1])
    if start == end:
        _fail(source, f"{where}: edge starts and ends at the same vertex {start}")
    label = raw.get("label")
    if label is not None and not isinstance(label, str):
        _fail(source, f"{where}: label must be a string, got {label!r}")
    curv = raw.get("curvature")
    if curv is None:
        return Edge(start, end, label=label)
    s_file, e_file = verts_file[start], verts_file[end]

    def rel(p):
        pt = _point(p, source, f"{where}: control point")
        return absolute_to_relative(s_file, e_file, pt) if absolute else (float(pt[0]), float(pt[1]))

    if isinstance(curv, list | tuple):  # legacy: a bare [u, v] is a quadratic control point
        return Edge(start, end, "quadratic", control=(rel(curv),), label=label)
    if not isinstance(curv, dict) or "type" not in curv or "params" not in curv:
        _fail(source, f"{where}: curvature must be {{'type': ..., 'params': ...}} or a legacy [u, v]")
    kind, params = curv["type"], curv["params"]
    if kind == "quadratic":
        if not isinstance(params, list) or len(params) != 1:
            _fail(source, f"{where}: quadratic curvature needs params [[u, v]], got {params!r}")
        return Edge(start, end, "quadratic", control=(rel(params[0]),), label=label)
    if kind == "cubic":
        if not isinstance(params, list) or len(params) != 2:
            _fail(source, f"{where}: cubic curvature needs params [[u1, v1], [u2, v2]], got {params!r}")
        return Edge(start, end, "cubic", control=(rel(params[0]), rel(params[1])), label=label)
    if kind == "circle":
        if not isinstance(params, list) or len(params) != 3:
            _fail(
                source, f"{where}: circle curvature needs params [radius, large_arc, right], got {params!r}"
            )
        radius = _number(params[0], source, f"{where}: circle radius")
        if radius <= 0:
            _fail(source, f"{where}: circle radius must be positive, got {radius}")
        return Edge(
            start,
            end,
            "circle",
            radius=radius / scale,
            large_arc=bool(params[1]),
            right=bool(params[2]),
            label=label,
        )
    _fail(source, f"{where}: unknown curvature type {kind!r} (valid: quadratic, cubic, circle)")


def _check_loop(name: str, edges: list[Edge], source) -> None:
    """Edges must form one closed loop, edge k ending where edge k + 1 starts."""
    if len(edges) < 2:
        _fail(source, f"panel {name!r}: needs at least 2 edges to form a closed loop, got {len(edges)}")
    for k, e in enumerate(edges):
        nxt = edges[(k + 1) % len(edges)]
        if e.end != nxt.start:
            _fail(
                source,
                f"panel {name!r}: edge loop is not closed: edge {k} ends at vertex {e.end} but edge "
                f"{(k + 1) % len(edges)} starts at vertex {nxt.start}",
            )
    starts = [e.start for e in edges]
    if len(set(starts)) != len(starts):
        _fail(source, f"panel {name!r}: the edge loop visits a vertex twice (it must be one simple loop)")


def _parse_ref(raw, panels: dict[str, Panel], source, where) -> EdgeRef:
    if not isinstance(raw, dict) or "panel" not in raw or "edge" not in raw:
        _fail(source, f"{where}: each side must be {{'panel': name, 'edge': index}}, got {raw!r}")
    name, k = raw["panel"], raw["edge"]
    if name not in panels:
        _fail(source, f"{where}: names a missing panel {name!r} (panels: {', '.join(panels)})")
    n = len(panels[name].edges)
    if not isinstance(k, int) or isinstance(k, bool) or not 0 <= k < n:
        _fail(source, f"{where}: names a missing edge {k!r} of panel {name!r} (it has edges 0..{n - 1})")
    return EdgeRef(name, int(k))


def _parse_units(props, source) -> tuple[float, bool]:
    """(file units per metre, True for absolute curvature coordinates) from the 'properties' object."""
    units = props.get("units_in_meter", 100)
    units = _number(units, source, "properties.units_in_meter")
    if units <= 0:
        _fail(source, f"properties.units_in_meter must be positive, got {units}")
    coords = props.get("curvature_coords", "relative")
    if coords not in ("relative", "absolute"):
        _fail(source, f"properties.curvature_coords must be 'relative' or 'absolute', got {coords!r}")
    return units, coords == "absolute"


def _parse_panel(name: str, raw, units: float, absolute: bool, source) -> Panel:
    """One panel from its GarmentCode object (file units; ``units`` per metre), in metres."""
    where = f"panel {name!r}"
    if not isinstance(raw, dict):
        _fail(source, f"{where}: must be an object")
    for key in ("vertices", "edges"):
        if not isinstance(raw.get(key), list) or not raw[key]:
            _fail(source, f"{where}: missing or empty '{key}' list")
    verts_file = np.stack([_point(v, source, f"{where}: vertex {i}") for i, v in enumerate(raw["vertices"])])
    edges = [
        _parse_edge(e, verts_file, units, absolute, source, f"{where}, edge {k}")
        for k, e in enumerate(raw["edges"])
    ]
    _check_loop(name, edges, source)
    label = raw.get("label")
    if label is not None and not isinstance(label, str):
        _fail(source, f"{where}: label must be a string")
    return Panel(
        name=name,
        vertices=verts_file / units,
        edges=edges,
        translation=_point(raw.get("translation", [0, 0, 0]), source, f"{where}: translation", 3) / units,
        rotation=_point(raw.get("rotation", [0, 0, 0]), source, f"{where}: rotation", 3),
        label=label,
    )


def _parse_stitches(raw_stitches, panels: dict[str, Panel], source) -> list[Stitch]:
    """The stitches from 'pattern.stitches'; each panel edge may take part in one stitch only."""
    if not isinstance(raw_stitches, list):
        _fail(source, "pattern.stitches must be a list")
    stitches: list[Stitch] = []
    used: dict[EdgeRef, int] = {}
    for i, raw in enumerate(raw_stitches):
        where = f"stitch {i}"
        if not isinstance(raw, list) or len(raw) not in (2, 3):
            _fail(
                source, f"{where}: must be [side A, side B] or [side A, side B, 'right_wrong'], got {raw!r}"
            )
        right_wrong = False
        if len(raw) == 3:
            if raw[2] != "right_wrong":
                _fail(source, f"{where}: unknown stitch flag {raw[2]!r} (only 'right_wrong' is known)")
            right_wrong = True
        a = _parse_ref(raw[0], panels, source, where)
        b = _parse_ref(raw[1], panels, source, where)
        if a == b:
            _fail(source, f"{where}: joins edge {a.edge} of panel {a.panel!r} to itself")
        for ref in (a, b):
            if ref in used:
                _fail(
                    source,
                    f"{where}: edge {ref.edge} of panel {ref.panel!r} is already in stitch {used[ref]} "
                    "(an edge can take part in one stitch only)",
                )
            used[ref] = i
        stitches.append(Stitch(a, b, right_wrong))
    return stitches


def pattern_from_dict(data: dict, source: str | None = None) -> Pattern:
    """Build a `Pattern` from the parsed GarmentCode JSON; see `load_pattern`."""
    if not isinstance(data, dict) or not isinstance(data.get("pattern"), dict):
        _fail(source, "not a GarmentCode pattern: missing the top-level 'pattern' object")
    props = data.get("properties", {}) or {}
    if not isinstance(props, dict):
        _fail(source, "'properties' must be an object")
    units, absolute = _parse_units(props, source)
    raw_panels = data["pattern"].get("panels")
    if not isinstance(raw_panels, dict) or not raw_panels:
        _fail(source, "pattern.panels must be a non-empty object of named panels")
    if len(raw_panels) > MAX_PANELS:
        _fail(
            source,
            f"{len(raw_panels):,} panels, more than the {MAX_PANELS} read here (the templates and "
            "GarmentCode's examples have at most 12): is this a sewing pattern?",
        )
    panels = {name: _parse_panel(name, raw, units, absolute, source) for name, raw in raw_panels.items()}
    stitches = _parse_stitches(data["pattern"].get("stitches", []), panels, source)

    garment_type = data.get("garment_type")
    if garment_type is not None and garment_type not in GARMENT_TYPES:
        _fail(source, f"unknown garment_type {garment_type!r} (valid: {', '.join(GARMENT_TYPES)})")
    order = data["pattern"].get("panel_order")
    properties = dict(_DEFAULT_PROPERTIES)
    properties.update(props)
    properties["curvature_coords"] = "relative"  # curves are stored relative after loading
    return Pattern(
        panels=panels,
        stitches=stitches,
        garment_type=garment_type,
        panel_order=list(order) if isinstance(order, list) else None,
        properties=properties,
        extra={k: v for k, v in data.items() if k not in _KNOWN_TOP_KEYS},
        source=source,
    )


def _edge_to_dict(edge: Edge, scale: float) -> dict:
    out: dict = {"endpoints": [edge.start, edge.end]}
    if edge.kind in ("quadratic", "cubic"):
        out["curvature"] = {"type": edge.kind, "params": [[float(u), float(v)] for u, v in edge.control]}
    elif edge.kind == "circle":
        out["curvature"] = {
            "type": "circle",
            "params": [float(edge.radius) * scale, int(edge.large_arc), int(edge.right)],
        }
    if edge.label is not None:
        out["label"] = edge.label
    return out


def pattern_to_dict(pattern: Pattern) -> dict:
    """The GarmentCode JSON dict of a `Pattern` (inverse of `pattern_from_dict`)."""
    props = dict(_DEFAULT_PROPERTIES)
    props.update(pattern.properties)
    props["curvature_coords"] = "relative"
    scale = float(props["units_in_meter"])
    panels = {}
    for name, p in pattern.panels.items():
        raw = {
            "translation": [float(v) * scale for v in p.translation],
            "rotation": [float(v) for v in p.rotation],
            "vertices": [[float(x) * scale, float(y) * scale] for x, y in p.vertices],
            "edges": [_edge_to_dict(e, scale) for e in p.edges],
        }
        if p.label is not None:
            raw["label"] = p.label
        panels[name] = raw
    stitches = []
    for s in pattern.stitches:
        item: list = [{"panel": s.a.panel, "edge": s.a.edge}, {"panel": s.b.panel, "edge": s.b.edge}]
        if s.right_wrong:
            item.append("right_wrong")
        stitches.append(item)
    body: dict = {"panels": panels, "stitches": stitches}
    if pattern.panel_order is not None:
        body["panel_order"] = list(pattern.panel_order)
    out: dict = {"pattern": body}
    out.update(pattern.extra)
    out["properties"] = props
    if pattern.garment_type is not None:
        out["garment_type"] = pattern.garment_type
    return out
