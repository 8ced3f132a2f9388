"""Pattern pictures: SVG (vector) and PNG (Pillow) with panels side by side and seams coloured by stitch.

Both edges of a stitch get the same colour (darts too); unstitched edges are grey. Panel names are
written at each panel's centre and edge labels beside their edge. Front panels (placed at z >= 0) go in
the top row, back panels in the bottom row, each row ordered by the panels' world x (as seen from the
front). 1 SVG user unit = 1 cm; the panel frame's Y axis is flipped to point down.
"""

from __future__ import annotations

import colorsys
import os
from dataclasses import dataclass
from xml.sax.saxutils import escape  # names and labels come from user files: text, never markup

import numpy as np

from torch_diffavatar.atomic_file import atomic_path, atomic_write_text
from torch_diffavatar.pattern.spec import EdgeRef, Pattern

_GAP_CM = 6.0
_MARGIN_CM = 4.0


@dataclass
class _PanelDrawing:
    name: str
    edges: list[np.ndarray]  # per edge (n, 2) points [cm], layout frame (y down)
    outline: np.ndarray  # (L, 2) closed outline [cm]
    centre: np.ndarray  # (2,)


def stitch_colours(count: int) -> list[str]:
    """``count`` distinct hex colours (evenly spaced hues, golden-ratio order)."""
    out = []
    for i in range(count):
        r, g, b = colorsys.hsv_to_rgb((i * 0.618033988749895) % 1.0, 0.85, 0.85)
        out.append(f"#{int(r * 255):02x}{int(g * 255):02x}{int(b * 255):02x}")
    return out


def _layout(pattern: Pattern, samples: int = 48) -> tuple[list[_PanelDrawing], tuple[float, float]]:
    items = []
    for name, panel in pattern.panels.items():
        edges = []
        for k, e in enumerate(panel.edges):
            n = 1 if e.kind == "line" else samples
            edges.append(panel.sample_edge(k, np.linspace(0.0, 1.0, n + 1)) * 100.0)
        outline = np.concatenate([p[:-1] for p in edges])
        world = panel.to_world(outline / 100.0)
        items.append((name, edges, outline, float(world[:, 0].mean()), float(world[:, 2].mean())))
    rows = [[it for it in items if it[4] >= 0], [it for it in items if it[4] < 0]]
    drawings, y0, width = [], _MARGIN_CM, 0.0
    for row in rows:
        if not row:
            continue
        row.sort(key=lambda it: it[3])
        x0, height = _MARGIN_CM, 0.0
        for name, edges, outline, _, _ in row:
            lo, hi = outline.min(axis=0), outline.max(axis=0)

            def place(p, lo=lo, hi=hi, x0=x0, y0=y0):
                return np.stack([p[:, 0] - lo[0] + x0, hi[1] - p[:, 1] + y0], axis=1)

            placed = [place(p) for p in edges]
            out = place(outline)
            drawings.append(_PanelDrawing(name, placed, out, out.mean(axis=0)))
            x0 += hi[0] - lo[0] + _GAP_CM
            height = max(height, hi[1] - lo[1])
        width = max(width, x0 - _GAP_CM + _MARGIN_CM)
        y0 += height + _GAP_CM
    return drawings, (width, y0 - _GAP_CM + _MARGIN_CM)


def _edge_colours(pattern: Pattern) -> dict[tuple[str, int], str]:
    colours = stitch_colours(len(pattern.stitches))
    out = {}
    for s, c in zip(pattern.stitches, colours):
        out[(s.a.panel, s.a.edge)] = out[(s.b.panel, s.b.edge)] = c
    return out


def _labelled_edges(panel) -> set[int]:
    """Edges that carry the text of their label: the middle edge of each run of equally labelled edges."""
    m, out = len(panel.edges), set()
    labels = [e.label for e in panel.edges]
    for k in range(m):
        if labels[k] is None or (labels[k - 1] == labels[k] and m > 1 and len(set(labels)) > 1):
            continue
        run = [k]
        while len(run) < m and labels[(run[-1] + 1) % m] == labels[k]:
            run.append((run[-1] + 1) % m)
        out.add(run[len(run) // 2])
    return out


def _label_anchor(points: np.ndarray, centre: np.ndarray, offset: float = 2.5) -> np.ndarray:
    mid = points[len(points) // 2] if len(points) > 2 else points.mean(axis=0)
    d = centre - mid
    n = np.linalg.norm(d)
    return mid + (d / n * offset if n > 0 else 0.0)


def pattern_svg(pattern: Pattern) -> str:
    """The pattern as an SVG document (string)."""
    drawings, (w, h) = _layout(pattern)
    colours = _edge_colours(pattern)
    out = [
        '<?xml version="1.0" encoding="utf-8" ?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{w:.1f}cm" height="{h:.1f}cm" '
        f'viewBox="0 0 {w:.3f} {h:.3f}">',
        f'<rect x="0" y="0" width="{w:.3f}" height="{h:.3f}" fill="white"/>',
    ]
    for d in drawings:
        pts = " ".join(f"{x:.3f},{y:.3f}" for x, y in d.outline)
        out.append(
            f'<polygon points="{pts}" fill="#f3e3d3" stroke="none"><title>{escape(d.name)}</title></polygon>'
        )
        panel = pattern.panels[d.name]
        labelled = _labelled_edges(panel)
        for k, p in enumerate(d.edges):
            colour = colours.get((d.name, k), "#777777")
            width = 0.6 if (d.name, k) in colours else 0.3
            pts = " ".join(f"{x:.3f},{y:.3f}" for x, y in p)
            stitch = pattern.stitch_of(EdgeRef(d.name, k))
            title = f"{d.name} edge {k}" + (
                f" stitched to {stitch.b.panel if stitch.a == EdgeRef(d.name, k) else stitch.a.panel}"
                if stitch
                else ""
            )
            out.append(
                f'<polyline points="{pts}" fill="none" stroke="{colour}" stroke-width="{width}" '
                f'stroke-linecap="round"><title>{escape(title)}</title></polyline>'
            )
            label = panel.edges[k].label
            if label and k in labelled:
                x, y = _label_anchor(p, d.centre)
                out.append(
                    f'<text x="{x:.2f}" y="{y:.2f}" font-size="2" font-family="sans-serif" fill="#333" '
                    f'text-anchor="middle">{escape(label)}</text>'
                )
        x, y = d.centre
        out.append(
            f'<text x="{x:.2f}" y="{y:.2f}" font-size="3.2" font-family="sans-serif" fill="#000" '
            f'text-anchor="middle">{escape(d.name)}</text>'
        )
    out.append("</svg>")
    return "\n".join(out) + "\n"


def save_pattern_svg(pattern: Pattern, path: str | os.PathLike) -> None:
    """Write `pattern_svg` to ``path``."""
    atomic_write_text(path, pattern_svg(pattern))


def save_pattern_png(pattern: Pattern, path: str | os.PathLike, px_per_cm: float = 5.0) -> None:
    """Render the same picture as `pattern_svg` to a PNG with Pillow (``px_per_cm`` pixels per cm)."""
    from PIL import Image, ImageDraw, ImageFont

    drawings, (w, h) = _layout(pattern)
    colours = _edge_colours(pattern)
    s = float(px_per_cm)
    img = Image.new("RGB", (int(np.ceil(w * s)), int(np.ceil(h * s))), "white")
    draw = ImageDraw.Draw(img)
    try:
        name_font = ImageFont.load_default(size=max(10, int(3.2 * s)))
        label_font = ImageFont.load_default(size=max(8, int(2.0 * s)))
    except TypeError:  # Pillow < 10.1: fixed-size bitmap font
        name_font = label_font = ImageFont.load_default()
    for d in drawings:
        draw.polygon([tuple(p) for p in d.outline * s], fill=(243, 227, 211))
    for d in drawings:
        panel = pattern.panels[d.name]
        labelled = _labelled_edges(panel)
        for k, p in enumerate(d.edges):
            colour = colours.get((d.name, k), "#777777")
            width = max(1, int(round((0.6 if (d.name, k) in colours else 0.3) * s)))
            draw.line([tuple(q) for q in p * s], fill=colour, width=width, joint="curve")
            label = panel.edges[k].label
            if label and k in labelled:
                x, y = _label_anchor(p, d.centre) * s
                draw.text((x, y), label, fill=(51, 51, 51), font=label_font, anchor="mm")
        x, y = d.centre * s
        draw.text((x, y), d.name, fill=(0, 0, 0), font=name_font, anchor="mm")
    with atomic_path(path) as tmp:
        img.save(tmp)
