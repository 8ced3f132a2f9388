"""Garment measurements of a sewing pattern: what a tailor checks with a tape measure, in metres.

Every measurement is intrinsic to the 2D pattern (lengths and distances inside each panel's own plane):
it does not change when a panel is moved rigidly, in its 2D frame or in its 3D placement, and ignores
ease and stretch. The openings come from the meshed pattern (`mesh_pattern`'s named boundary loops); a
fitted pattern keeps its template's panels and edges, so it can be measured with the openings of its
truth (`pattern_openings` of the truth passed to `measure_pattern`), and both get the same names.

Measurements (`GarmentMeasurements.lengths`, [m]):

* ``<opening>_circumference`` for each named opening (``neck``, ``waist``, ``hem``, ``cuff_left``,
  ``cuff_right``, ``hem_left``, ``hem_right``; ``opening_<k>`` when the mesher could not name it): the
  total 2D length of the pattern edges that form the opening, summed over panels. On a sleeveless
  dress the mesher names the armholes ``cuff_left`` / ``cuff_right``.
* ``length_<panel>`` for each panel on a hem opening (``hem``, ``hem_left``, ``hem_right``): the
  panel's extent perpendicular to its hem, i.e. the panel outline's extent along the normal of the
  principal direction of its hem edges (for a straight hem, the normal of the hem): waist to hem on a
  skirt or trouser panel, high shoulder point to hem on a bodice.
* ``hem_width_<panel>``: the length of that panel's hem edges.
* ``garment_length``: the longest of the hem panels' lengths, each continued upwards through the seams
  of its ``lower_interface`` edges (GarmentCode's label for where a skirt joins a bodice): a dress is
  its skirt panel's length plus the length of the bodice panel sewn to the skirt's top, measured
  perpendicular to that seam. For tops, skirts and trousers it is the longest hem panel's length.
* ``sleeve_length_left`` / ``sleeve_length_right``: the longest extent perpendicular to the cuff of
  the panels whose only opening is that cuff (the sleeve halves): cuff to the top of the sleeve cap.

`GarmentMeasurements.area` is the total area of the panels [m²] (darts cut out).

Limitations: curves are sampled (64 points per curve; sub-millimetre on the shipped templates); a
length is a straight extent inside one panel (plus the panels above a ``lower_interface`` seam), not a
geodesic over the sewn garment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torch_diffavatar.errors import PatternError
from torch_diffavatar.pattern.mesher import mesh_pattern
from torch_diffavatar.pattern.spec import EdgeRef, Panel, Pattern, polygon_signed_area

HEM_OPENINGS = ("hem", "hem_left", "hem_right")
CUFF_OPENINGS = {"cuff_left": "left", "cuff_right": "right"}
TOP_INTERFACE = "lower_interface"  # GarmentCode's label of the edges where a skirt joins a bodice
# the order in which circumferences are listed (others, ``opening_<k>``, follow in name order)
OPENING_ORDER = ("neck", "waist", "hem", "hem_left", "hem_right", "cuff_left", "cuff_right")
_CURVE_SAMPLES = 64  # points per curved edge for outlines, extents and hem directions


@dataclass
class GarmentMeasurements:
    """Measurements of one pattern (see the module docstring for each name's definition).

    Attributes:
        lengths: measurement name -> length [m] (circumferences, lengths, widths).
        area: total area of the panels [m²].
    """

    lengths: dict[str, float]
    area: float


def pattern_openings(pattern: Pattern, spacing: float = 0.03) -> dict[str, list[EdgeRef]]:
    """The pattern edges that form each opening of the sewn garment.

    The pattern is meshed at ``spacing`` [m] (`mesh_pattern`, which names the openings); an edge
    belongs to an opening when it is sewn to nothing and all its mesh vertices lie on that opening.

    Returns:
        opening name (``"hem"``, ``"neck"`` …) -> its edges, in panel and edge order.

    Raises:
        PatternError: the pattern cannot be meshed (see `mesh_pattern`).
    """
    garment = mesh_pattern(pattern, spacing=spacing)
    loop_of = {v: loop.name for loop in garment.boundary_loops for v in loop.vertices.tolist()}
    sewn = {s.a for s in pattern.stitches} | {s.b for s in pattern.stitches}
    out: dict[str, list[EdgeRef]] = {loop.name: [] for loop in garment.boundary_loops}
    for name, panel in pattern.panels.items():
        for k in range(len(panel.edges)):
            if EdgeRef(name, k) in sewn:
                continue
            sim = garment.vert_to_sim[garment.edge_vertices[(name, k)]].tolist()
            loops = {loop_of.get(v) for v in sim}
            if len(loops) == 1 and None not in loops:
                out[loops.pop()].append(EdgeRef(name, k))
    return out


def measure_pattern(
    pattern: Pattern, openings: dict[str, list[EdgeRef]] | None = None, *, spacing: float = 0.03
) -> GarmentMeasurements:
    """Garment measurements of ``pattern`` (definitions in the module docstring).

    Args:
        pattern: the sewing pattern [m].
        openings: the edges of each opening (`pattern_openings`); None finds them by meshing
            ``pattern`` at ``spacing`` [m]. Pass the truth's to measure a fit with the same edges.

    Raises:
        PatternError: ``openings`` names a panel or edge the pattern lacks, or the pattern cannot be
            meshed.
    """
    openings = pattern_openings(pattern, spacing) if openings is None else openings
    _check_openings(pattern, openings)
    lengths = {
        f"{name}_circumference": sum(pattern.panels[r.panel].edge_length(r.edge) for r in refs)
        for name, refs in sorted(openings.items(), key=lambda item: _opening_rank(item[0]))
        if refs
    }
    hem_edges = dict(sorted(_edges_by_panel(openings, HEM_OPENINGS).items()))
    if hem_edges:
        lengths["garment_length"] = max(_length_to_top(pattern, p, ks, {p}) for p, ks in hem_edges.items())
    lengths.update(_sleeve_lengths(pattern, openings))
    for name, ks in hem_edges.items():
        lengths[f"length_{name}"] = _extent_across(pattern.panels[name], ks)
    for name, ks in hem_edges.items():
        lengths[f"hem_width_{name}"] = sum(pattern.panels[name].edge_length(k) for k in ks)
    area = sum(abs(polygon_signed_area(p.outline(_CURVE_SAMPLES))) for p in pattern.panels.values())
    return GarmentMeasurements(lengths=lengths, area=float(area))


def _opening_rank(name: str) -> tuple[int, str]:
    return (OPENING_ORDER.index(name) if name in OPENING_ORDER else len(OPENING_ORDER), name)


def _check_openings(pattern: Pattern, openings: dict[str, list[EdgeRef]]) -> None:
    for name, refs in openings.items():
        for r in refs:
            panel = pattern.panels.get(r.panel)
            if panel is None or not 0 <= r.edge < len(panel.edges):
                size = "no such panel" if panel is None else f"the panel has {len(panel.edges)} edges"
                raise PatternError(
                    f"opening {name!r} names edge {r.edge} of panel {r.panel!r} ({size}): measure a pattern "
                    "with the openings of a pattern with the same panels and edges"
                )


def _edges_by_panel(openings: dict[str, list[EdgeRef]], names) -> dict[str, list[int]]:
    """Panel -> its edge indices on the openings ``names``, in panel order of appearance."""
    out: dict[str, list[int]] = {}
    for name in names:
        for r in openings.get(name, []):
            out.setdefault(r.panel, []).append(r.edge)
    return out


def _edge_samples(panel: Panel, ks: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) points [m] spread evenly along the edges ``ks`` and (n,) their arc-length weights [m]."""
    t = np.linspace(0.0, 1.0, _CURVE_SAMPLES + 1)
    pts = np.concatenate([panel.sample_edge(k, t) for k in ks])
    weights = np.concatenate([np.full(len(t), panel.edge_length(k) / len(t)) for k in ks])
    return pts, weights


def _extent_across(panel: Panel, ks: list[int]) -> float:
    """Extent [m] of the panel outline perpendicular to the principal direction of its edges ``ks``.

    The direction is the weighted principal axis of points along those edges, so it follows the panel
    when it is rotated; for one straight edge it is the edge itself.
    """
    pts, weights = _edge_samples(panel, ks)
    centred = pts - (weights[:, None] * pts).sum(0) / max(weights.sum(), 1e-300)
    _, vecs = np.linalg.eigh((weights[:, None] * centred).T @ centred)
    along = vecs[:, -1]  # eigh sorts eigenvalues ascending: the last is the principal direction
    across = panel.outline(_CURVE_SAMPLES) @ np.array([-along[1], along[0]])
    return float(across.max() - across.min())


def _length_to_top(pattern: Pattern, name: str, ks: list[int], seen: set[str]) -> float:
    """Length [m] of panel ``name`` across its edges ``ks``, plus the longest chain of panels sewn to its
    ``lower_interface`` edges (each measured across its edges sewn to the panel below); ``seen`` panels
    are not revisited."""
    panel = pattern.panels[name]
    above: dict[str, list[int]] = {}
    for s in pattern.stitches:
        for mine, other in ((s.a, s.b), (s.b, s.a)):
            if mine.panel != name or other.panel in seen:
                continue
            if panel.edges[mine.edge].label == TOP_INTERFACE:
                above.setdefault(other.panel, []).append(other.edge)
    length = _extent_across(panel, ks)
    if not above:
        return length
    return length + max(_length_to_top(pattern, q, edges, seen | {q}) for q, edges in above.items())


def _sleeve_lengths(pattern: Pattern, openings: dict[str, list[EdgeRef]]) -> dict[str, float]:
    """``sleeve_length_<side>`` [m]: the longest extent across the cuff of the panels on that cuff and on
    no other opening (a sleeveless dress's armhole panels touch the neck too: no sleeve length)."""
    on_other: dict[str, set[str]] = {}
    for opening, refs in openings.items():
        for r in refs:
            on_other.setdefault(r.panel, set()).add(opening)
    out = {}
    for cuff, side in CUFF_OPENINGS.items():
        sleeves = {p: ks for p, ks in _edges_by_panel(openings, (cuff,)).items() if on_other[p] == {cuff}}
        if sleeves:
            extents = [_extent_across(pattern.panels[p], ks) for p, ks in sleeves.items()]
            out[f"sleeve_length_{side}"] = max(extents)
    return out
