"""The sewing-pattern model: panels (closed loops of edges), 3D placement, stitches, darts, labels.

Everything is in **metres** inside (GarmentCode files are in cm; `garmentcode.load_pattern` converts).
A panel lives in its own 2D frame (Y up); its 3D placement is ``world = R · (x, y, 0) + t`` with
``R = Rz(rz) · Ry(ry) · Rx(rx)`` of the Euler angles in degrees (scipy
``Rotation.from_euler('xyz', angles, degrees=True)``, the convention of GarmentCode's readers).

Edge kinds (GarmentCode's ``curvature`` field, see /work/shared/garmentcode/README.md):

* ``line``: straight from S to E.
* ``quadratic`` / ``cubic``: Bézier curves whose control points are stored *relative* to the edge:
  ``P = S + u·d + v·d⊥`` with ``d = E − S`` and ``d⊥ = (−d_y, d_x)``.
* ``circle``: an SVG-style arc of radius ``r`` [m] from S to E; ``large_arc`` picks the larger arc,
  ``right`` = the arc bulges to the right of S→E (SVG sweep flag in the Y-up frame).

The pattern maths here is NumPy float64 (patterns are small, discrete data); the differentiable rest
shape lives in the `GarmentMesh` built by `torch_diffavatar.pattern.mesher`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from torch_diffavatar.errors import PatternError

EDGE_KINDS = ("line", "quadratic", "cubic", "circle")
GARMENT_TYPES = ("dress", "tshirt", "longsleeve", "polo", "skirt", "pants")

_BEZIER_SAMPLES = 1025  # dense samples used to invert the arc length of Bézier curves


@dataclass
class Edge:
    """One edge of a panel outline, from vertex ``start`` to vertex ``end`` of its panel.

    Attributes:
        start, end: vertex indices in the panel's ``vertices``.
        kind: one of ``EDGE_KINDS``.
        control: relative control points ``((u, v), ...)``: one for ``quadratic``, two for ``cubic``.
        radius: circle radius [m] (``circle`` only).
        large_arc: take the larger of the two arcs (``circle`` only).
        right: the arc bulges to the right of start→end (``circle`` only).
        label: optional edge label (``"lower_interface"``, ``"left_collar"`` …).
    """

    start: int
    end: int
    kind: str = "line"
    control: tuple[tuple[float, float], ...] = ()
    radius: float = 0.0
    large_arc: bool = False
    right: bool = False
    label: str | None = None


@dataclass
class Panel:
    """A flat piece of cloth: a closed loop of edges in its own 2D frame, placed in 3D.

    Attributes:
        name: unique panel name.
        vertices: (N, 2) float64 corner positions [m] in the panel frame (Y up).
        edges: the outline; edge ``k`` ends where edge ``k + 1`` starts (checked by the loader).
        translation: (3,) float64 [m] world position of the panel origin.
        rotation: (3,) float64 Euler angles [deg] (``R = Rz·Ry·Rx``).
        label: optional panel label (``"body"``, ``"leg"``, ``"arm"``).
    """

    name: str
    vertices: np.ndarray
    edges: list[Edge]
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    label: str | None = None

    def rotation_matrix(self) -> np.ndarray:
        """(3, 3) float64 rotation ``Rz(rz) · Ry(ry) · Rx(rx)`` of the Euler angles in degrees."""
        return euler_xyz_matrix(self.rotation)

    def to_world(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) panel-frame points [m] -> (n, 3) world points [m]."""
        xy = np.asarray(xy, dtype=np.float64)
        xyz = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
        return xyz @ self.rotation_matrix().T + np.asarray(self.translation, dtype=np.float64)

    def edge_endpoints(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(2,), (2,) start and end corner of edge ``k`` [m]."""
        e = self.edges[k]
        return self.vertices[e.start], self.vertices[e.end]

    def sample_edge(self, k: int, t: np.ndarray) -> np.ndarray:
        """(n, 2) points [m] of edge ``k`` at arc-length fractions ``t`` (n,) in [0, 1]."""
        s, e = self.edge_endpoints(k)
        return sample_edge(s, e, self.edges[k], t)

    def edge_length(self, k: int) -> float:
        """Arc length [m] of edge ``k``."""
        s, e = self.edge_endpoints(k)
        return edge_length(s, e, self.edges[k])

    def outline(self, samples_per_curve: int = 32) -> np.ndarray:
        """(L, 2) closed outline polygon [m] (last point not repeated), curves sampled uniformly."""
        pts = []
        for k, edge in enumerate(self.edges):
            n = 1 if edge.kind == "line" else samples_per_curve
            pts.append(self.sample_edge(k, np.arange(n) / n))
        return np.concatenate(pts, axis=0)

    def signed_area(self) -> float:
        """Signed area [m²] of the outline: > 0 for a counter-clockwise loop (front panels)."""
        return polygon_signed_area(self.outline())


@dataclass(frozen=True)
class EdgeRef:
    """One side of a stitch: edge ``edge`` of panel ``panel``."""

    panel: str
    edge: int


@dataclass
class Stitch:
    """A seam joining two edges (of two panels, or of one panel: a dart).

    By default the END of edge ``a`` joins the START of edge ``b`` (right sides together); with
    ``right_wrong`` the two edges run the same way, start joining start.
    """

    a: EdgeRef
    b: EdgeRef
    right_wrong: bool = False

    @property
    def is_dart(self) -> bool:
        return self.a.panel == self.b.panel


@dataclass
class Pattern:
    """A sewing pattern: named panels and the stitches between their edges.

    Attributes:
        panels: panel name -> `Panel`, in file order.
        stitches: the seams (darts included).
        garment_type: one of ``GARMENT_TYPES`` or None when unknown.
        panel_order: GarmentCode's ``panel_order`` list if present (informational).
        properties: the file's ``properties`` dict (kept for writing; lengths here are metres anyway).
        extra: other top-level keys of the file, kept for writing.
        source: the file the pattern was read from, if any (used in error messages).
    """

    panels: dict[str, Panel]
    stitches: list[Stitch] = field(default_factory=list)
    garment_type: str | None = None
    panel_order: list[str] | None = None
    properties: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    source: str | None = None

    @property
    def darts(self) -> list[Stitch]:
        """Stitches that join two edges of the same panel."""
        return [s for s in self.stitches if s.is_dart]

    @property
    def panel_names(self) -> list[str]:
        return list(self.panels)

    def edges_with_label(self, label: str) -> list[EdgeRef]:
        """All edges carrying ``label``."""
        return [
            EdgeRef(name, k)
            for name, p in self.panels.items()
            for k, e in enumerate(p.edges)
            if e.label == label
        ]

    def stitch_of(self, ref: EdgeRef) -> Stitch | None:
        """The stitch that uses edge ``ref``, or None."""
        for s in self.stitches:
            if s.a == ref or s.b == ref:
                return s
        return None

    def crossed_panels(self) -> list[str]:
        """The names of the panels whose outline crosses itself (`outline_self_intersects`), in order."""
        return [name for name, p in self.panels.items() if outline_self_intersects(p.outline())]

    def validate(self) -> None:
        """Check what meshing needs beyond what loading checks: no self-intersecting panel outline.

        Raises:
            PatternError: naming the file and the first offending panel(s).
        """
        bad = self.crossed_panels()
        if bad:
            where = f"{self.source}: " if self.source else ""
            raise PatternError(
                f"{where}self-intersecting panel outline(s): {', '.join(bad)} "
                "(the edges of a panel cross each other; fix the panel's vertices or curvatures)"
            )


# ---------------------------------------------------------------------------------------------------------
# Geometry helpers (pure functions)


def euler_xyz_matrix(angles_deg) -> np.ndarray:
    """(3, 3) ``Rz(c) · Ry(b) · Rx(a)`` for Euler angles ``(a, b, c)`` [deg] (= scipy ``'xyz'``)."""
    a, b, c = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1]])
    return rz @ ry @ rx


def relative_to_absolute(start: np.ndarray, end: np.ndarray, uv) -> np.ndarray:
    """(2,) absolute control point ``S + u·d + v·d⊥`` for relative ``(u, v)``."""
    d = end - start
    return start + uv[0] * d + uv[1] * np.array([-d[1], d[0]])


def absolute_to_relative(start: np.ndarray, end: np.ndarray, p) -> tuple[float, float]:
    """Inverse of `relative_to_absolute`: relative ``(u, v)`` of an absolute point ``p``."""
    d = end - start
    dd = float(d @ d)
    w = np.asarray(p, dtype=np.float64) - start
    return float(w @ d) / dd, float(w @ np.array([-d[1], d[0]])) / dd


def circle_arc(start: np.ndarray, end: np.ndarray, radius: float, large_arc: bool, right: bool):
    """Centre and angles of an SVG-style arc in the Y-up frame.

    Returns:
        centre (2,), radius [m] (enlarged like SVG when too small for the chord), start angle [rad],
        signed sweep [rad] (> 0 counter-clockwise; ``right`` = counter-clockwise = sweep flag 1).
    """
    half = (start - end) / 2.0  # x1' in the SVG notes (no axis rotation)
    h2 = float(half @ half)
    r = max(float(radius), np.sqrt(h2))
    coef = np.sqrt(max(0.0, r * r / h2 - 1.0)) if h2 > 0 else 0.0
    if bool(large_arc) == bool(right):
        coef = -coef
    c_prime = coef * np.array([half[1], -half[0]])
    centre = c_prime + (start + end) / 2.0
    u = (half - c_prime) / r
    v = (-half - c_prime) / r
    theta0 = np.arctan2(u[1], u[0])
    sweep = np.arctan2(u[0] * v[1] - u[1] * v[0], u @ v)
    if right and sweep < 0:
        sweep += 2 * np.pi
    elif not right and sweep > 0:
        sweep -= 2 * np.pi
    return centre, r, theta0, sweep


def _bezier_points(start, end, edge: Edge) -> np.ndarray:
    ctrl = [relative_to_absolute(start, end, c) for c in edge.control]
    return np.stack([start, *ctrl, end])


def _bezier_eval(points: np.ndarray, s: np.ndarray) -> np.ndarray:
    s = s[:, None]
    if len(points) == 3:
        p0, p1, p2 = points
        return (1 - s) ** 2 * p0 + 2 * (1 - s) * s * p1 + s**2 * p2
    p0, p1, p2, p3 = points
    return (1 - s) ** 3 * p0 + 3 * (1 - s) ** 2 * s * p1 + 3 * (1 - s) * s**2 * p2 + s**3 * p3


def _bezier_arclength_table(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s = np.linspace(0.0, 1.0, _BEZIER_SAMPLES)
    p = _bezier_eval(points, s)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    return s, cum


def sample_edge(start: np.ndarray, end: np.ndarray, edge: Edge, t) -> np.ndarray:
    """Points of an edge at arc-length fractions.

    Args:
        start, end: (2,) corners [m] in the panel frame.
        edge: the edge's shape (``kind`` and its parameters).
        t: (n,) arc-length fractions in [0, 1] (0 = start, 1 = end).

    Returns:
        (n, 2) float64 points [m]; ``t = 0`` and ``t = 1`` give exactly ``start`` and ``end``.
    """
    start = np.asarray(start, dtype=np.float64)
    end = np.asarray(end, dtype=np.float64)
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    if edge.kind == "line":
        out = start + t[:, None] * (end - start)
    elif edge.kind in ("quadratic", "cubic"):
        pts = _bezier_points(start, end, edge)
        s, cum = _bezier_arclength_table(pts)
        out = _bezier_eval(pts, np.interp(t * cum[-1], cum, s))
    elif edge.kind == "circle":
        centre, r, theta0, sweep = circle_arc(start, end, edge.radius, edge.large_arc, edge.right)
        ang = theta0 + t * sweep
        out = centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    else:
        raise PatternError(f"unknown edge kind {edge.kind!r}; valid kinds: {', '.join(EDGE_KINDS)}")
    out[t <= 0.0] = start
    out[t >= 1.0] = end
    return out


def edge_length(start: np.ndarray, end: np.ndarray, edge: Edge) -> float:
    """Arc length [m] of an edge (exact for lines and arcs; 1024-segment polyline for Béziers)."""
    start = np.asarray(start, dtype=np.float64)
    end = np.asarray(end, dtype=np.float64)
    if edge.kind == "line":
        return float(np.linalg.norm(end - start))
    if edge.kind == "circle":
        _, r, _, sweep = circle_arc(start, end, edge.radius, edge.large_arc, edge.right)
        return float(r * abs(sweep))
    return float(_bezier_arclength_table(_bezier_points(start, end, edge))[1][-1])


def polygon_signed_area(poly: np.ndarray) -> float:
    """Signed area [m²] of a closed polygon (L, 2) (last point not repeated); > 0 if counter-clockwise."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def outline_self_intersects(poly: np.ndarray, tol: float = 1e-9) -> bool:
    """Whether a closed polygon (L, 2) crosses or touches itself (segments that are not neighbours).

    Args:
        poly: (L, 2) vertices in loop order, the last joining the first.
        tol: relative tolerance on orientation tests (fraction of the squared bounding-box size).
    """
    n = len(poly)
    if n < 4:
        return False
    a = poly
    b = np.roll(poly, -1, axis=0)
    scale = max(float(np.ptp(poly, axis=0).max()) ** 2, 1e-30)
    eps = tol * scale

    def orient(p, q, r):  # (…, 2) -> (…) twice the signed area of p, q, r
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (
            r[..., 0] - p[..., 0]
        )

    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))  # first and last segments are neighbours too
    i, j = i[keep], j[keep]
    a1, b1, a2, b2 = a[i], b[i], a[j], b[j]
    o1, o2 = orient(a1, b1, a2), orient(a1, b1, b2)
    o3, o4 = orient(a2, b2, a1), orient(a2, b2, b1)
    proper = (o1 * o2 < 0) & (o3 * o4 < 0) & (np.abs(o1) > eps) & (np.abs(o2) > eps)
    if proper.any():
        return True
    # touching: a vertex lying on a non-adjacent segment (collinear within tolerance and inside its span)
    for p_idx, (s0, s1) in ((a2, (a1, b1)), (a1, (a2, b2))):
        o = orient(s0, s1, p_idx)
        seg = s1 - s0
        w = p_idx - s0
        L2 = np.maximum(np.sum(seg * seg, axis=-1), 1e-30)
        along = np.sum(w * seg, axis=-1) / L2
        if np.any((np.abs(o) <= eps) & (along >= 0.0) & (along <= 1.0)):
            return True
    return False
