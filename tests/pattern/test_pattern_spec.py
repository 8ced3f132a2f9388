"""Edge geometry (every edge kind against analytic values), placement, self-intersection checks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.spatial.transform import Rotation

from torch_diffavatar.pattern.spec import (
    Edge,
    Panel,
    circle_arc,
    edge_length,
    euler_xyz_matrix,
    outline_self_intersects,
    relative_to_absolute,
    sample_edge,
)

S, E = np.array([0.1, 0.2]), np.array([0.5, 0.3])


def test_line_samples_are_evenly_spaced():
    t = np.linspace(0, 1, 5)
    pts = sample_edge(S, E, Edge(0, 1), t)
    np.testing.assert_allclose(pts, S + t[:, None] * (E - S))
    assert edge_length(S, E, Edge(0, 1)) == pytest.approx(np.linalg.norm(E - S))


def test_relative_control_point_convention():
    d = E - S
    p = relative_to_absolute(S, E, (0.25, 0.5))
    np.testing.assert_allclose(p, S + 0.25 * d + 0.5 * np.array([-d[1], d[0]]))
    # positive v bulges to the left of start -> end
    mid = sample_edge(S, E, Edge(0, 1, "quadratic", control=((0.5, 0.3),)), np.array([0.5]))[0]
    assert d[0] * (mid - S)[1] - d[1] * (mid - S)[0] > 0


def _bezier(points, s):
    n = len(points) - 1
    from math import comb

    return sum(comb(n, i) * (1 - s) ** (n - i) * s**i * points[i] for i in range(n + 1))


def _bezier_speed(points, s):
    n = len(points) - 1
    from math import comb

    der = sum(
        comb(n - 1, i) * (1 - s) ** (n - 1 - i) * s**i * n * (points[i + 1] - points[i]) for i in range(n)
    )
    return float(np.linalg.norm(der))


@pytest.mark.parametrize(
    "kind,control",
    [
        ("quadratic", ((0.3, 0.4),)),
        ("cubic", ((0.2, 0.5), (0.8, -0.3))),
        ("cubic", ((0.4, -0.2), (0.5, 0.6))),
    ],
)
def test_bezier_length_and_arclength_sampling(kind, control):
    edge = Edge(0, 1, kind, control=control)
    pts = [S, *[relative_to_absolute(S, E, c) for c in control], E]
    exact, _ = quad(lambda s: _bezier_speed(pts, s), 0, 1, limit=200)
    assert edge_length(S, E, edge) == pytest.approx(exact, rel=1e-5)
    t = np.array([0.0, 0.2, 0.5, 0.9, 1.0])
    samples = sample_edge(S, E, edge, t)
    for ti, p in zip(t, samples):
        # the sample is on the curve at the parameter whose arc length is ti * L
        from scipy.optimize import brentq

        target = ti * exact

        def remaining(s, target=target):
            return quad(lambda u: _bezier_speed(pts, u), 0, s)[0] - target

        s = brentq(remaining, 0, 1) if 0 < ti < 1 else ti
        np.testing.assert_allclose(p, _bezier(pts, s), atol=2e-6)


@pytest.mark.parametrize("large_arc", [False, True])
@pytest.mark.parametrize("right", [False, True])
def test_circle_arc_radius_sagitta_and_side(large_arc, right):
    r = 0.3
    edge = Edge(0, 1, "circle", radius=r, large_arc=large_arc, right=right)
    t = np.linspace(0, 1, 41)
    pts = sample_edge(S, E, edge, t)
    centre, radius, _, sweep = circle_arc(S, E, r, large_arc, right)
    assert radius == pytest.approx(r)
    np.testing.assert_allclose(np.linalg.norm(pts - centre, axis=1), r, atol=1e-12)
    np.testing.assert_allclose(pts[[0, -1]], [S, E], atol=1e-12)
    chord = np.linalg.norm(E - S)
    small_sag = r - np.sqrt(r**2 - (chord / 2) ** 2)
    sagitta = small_sag if not large_arc else 2 * r - small_sag
    d = (E - S) / chord
    offsets = (pts - S) @ np.array([-d[1], d[0]])  # signed distance to the left of the chord
    bulge = offsets[np.argmax(np.abs(offsets))]
    assert abs(bulge) == pytest.approx(sagitta, rel=1e-3)
    assert (bulge < 0) == right  # right = bulges to the right of start -> end
    theta = 2 * np.arcsin(chord / (2 * r))
    expected_len = r * (2 * np.pi - theta if large_arc else theta)
    assert edge_length(S, E, edge) == pytest.approx(expected_len)
    assert abs(sweep) * r == pytest.approx(expected_len)
    # equal arc-length steps
    steps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    np.testing.assert_allclose(steps, steps[0], rtol=1e-9)


def test_circle_radius_too_small_is_enlarged_like_svg():
    chord = np.linalg.norm(E - S)
    edge = Edge(0, 1, "circle", radius=chord / 4, right=True)
    pts = sample_edge(S, E, edge, np.linspace(0, 1, 11))
    centre, r, _, _ = circle_arc(S, E, chord / 4, False, True)
    assert r == pytest.approx(chord / 2)
    np.testing.assert_allclose(centre, (S + E) / 2)
    np.testing.assert_allclose(np.linalg.norm(pts - centre, axis=1), chord / 2)


def test_rotation_matches_scipy_xyz():
    angles = np.array([90.0, 45.0, -30.0])
    np.testing.assert_allclose(
        euler_xyz_matrix(angles), Rotation.from_euler("xyz", angles, degrees=True).as_matrix(), atol=1e-12
    )
    panel = Panel("p", np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), [], np.array([1.0, 2.0, 3.0]), angles)
    world = panel.to_world(np.array([[0.2, 0.3]]))
    expected = Rotation.from_euler("xyz", angles, degrees=True).apply([0.2, 0.3, 0.0]) + [1, 2, 3]
    np.testing.assert_allclose(world[0], expected, atol=1e-12)


def test_self_intersection_detection():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
    bow_tie = np.array([[0, 0], [1, 1], [1, 0], [0, 1]], dtype=float)
    touching = np.array([[0, 0], [2, 0], [2, 2], [1, 0], [0, 2]], dtype=float)  # vertex 3 on edge 0
    assert not outline_self_intersects(square)
    assert outline_self_intersects(bow_tie)
    assert outline_self_intersects(touching)
