"""Triangle quality and angles; the distance between sewing-pattern outlines."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_diffavatar.metrics import (
    min_angle_deg,
    outline_distance,
    pattern_outline_errors,
    quality_summary,
    triangle_angles_deg,
    triangle_quality,
)

F = torch.tensor([[0, 1, 2]])


def test_equilateral_is_one_and_degenerate_is_zero():
    eq = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.5, math.sqrt(3) / 2]])
    assert float(triangle_quality(eq, F)[0]) == pytest.approx(1.0)
    assert float(min_angle_deg(eq, F)) == pytest.approx(60.0)
    flat = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    assert float(triangle_quality(flat, F)[0]) == pytest.approx(0.0, abs=1e-12)
    collapsed = torch.zeros(3, 2)
    assert float(triangle_quality(collapsed, F)[0]) == 0.0


def test_right_isosceles_value_and_3d_matches_2d():
    tri = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    expected = 4 * math.sqrt(3) * 0.5 / (1 + 1 + 2)
    assert float(triangle_quality(tri, F)[0]) == pytest.approx(expected)
    torch.testing.assert_close(
        triangle_angles_deg(tri, F)[0], torch.tensor([90.0, 45.0, 45.0], dtype=torch.float64)
    )
    rot = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)))[
        0
    ]
    tri3 = torch.cat([tri, torch.zeros(3, 1, dtype=torch.float64)], dim=1) @ rot.T + 0.3
    torch.testing.assert_close(triangle_quality(tri3, F), triangle_quality(tri, F))
    torch.testing.assert_close(triangle_angles_deg(tri3, F), triangle_angles_deg(tri, F))
    s = quality_summary(tri3, F)
    assert float(s.quality_min) == pytest.approx(expected) and float(s.min_angle_deg) == pytest.approx(45.0)


def test_dtype_follows_input_and_scale_invariance():
    tri = torch.tensor([[0.0, 0.0], [2.0, 0.3], [0.4, 1.1]], dtype=torch.float32)
    q = triangle_quality(tri, F)
    assert q.dtype == torch.float32
    torch.testing.assert_close(triangle_quality(tri * 7.5, F), q)


def test_gradcheck():
    g = torch.Generator().manual_seed(1)
    verts = torch.rand(5, 3, dtype=torch.float64, generator=g).requires_grad_()
    faces = torch.tensor([[0, 1, 2], [1, 3, 2], [2, 3, 4]])
    assert torch.autograd.gradcheck(lambda v: triangle_quality(v, faces), (verts,))
    assert torch.autograd.gradcheck(lambda v: triangle_angles_deg(v, faces), (verts,))
    v2 = torch.rand(5, 2, dtype=torch.float64, generator=g).requires_grad_()
    assert torch.autograd.gradcheck(lambda v: triangle_quality(v, faces), (v2,))


def test_bad_shapes():
    with pytest.raises(ValueError, match=r"\(V, 2\) or \(V, 3\)"):
        triangle_quality(torch.zeros(3, 4), F)
    with pytest.raises(ValueError, match="faces"):
        triangle_quality(torch.zeros(3, 2), torch.zeros(1, 4, dtype=torch.int64))


# ------------------------------------------------------------------------------------ pattern outlines

SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
# an L shape: no rotational symmetry, so only the right rotation aligns it with itself
L_SHAPE = np.array([[0.0, 0.0], [0.5, 0.0], [0.5, 0.12], [0.15, 0.12], [0.15, 0.3], [0.0, 0.3]])
TRUTH_PATTERN = Path(__file__).resolve().parents[1] / "torch_diffavatar" / "data" / "demo_truth_pattern.json"
SKIRTS = ("skirt_front", "skirt_back")


def _rigid(poly: np.ndarray, angle_deg: float, shift) -> np.ndarray:
    t = math.radians(angle_deg)
    rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    return poly @ rot.T + np.asarray(shift)


def _to_polygon(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(N,) exact distances from ``points`` to the edges of the closed polygon ``poly`` (brute force)."""
    a, b = poly[None], np.roll(poly, -1, axis=0)[None]
    p = points[:, None]
    t = np.clip(((p - a) * (b - a)).sum(-1) / ((b - a) ** 2).sum(-1), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * (b - a)), axis=-1).min(1)


def _dense(poly: np.ndarray, step: float = 1e-3) -> np.ndarray:
    """Points every ~``step`` [m] along the closed polygon (vertices included)."""
    out = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + np.linspace(0.0, 1.0, n, endpoint=False)[:, None] * (b - a))
    return np.concatenate(out)


def _brute_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(mean, max) like `outline_distance` but without any alignment, by brute force (independent)."""
    ab, ba = _to_polygon(_dense(a), b), _to_polygon(_dense(b), a)
    return 0.5 * float(ab.mean() + ba.mean()), float(max(ab.max(), ba.max()))


@pytest.mark.parametrize("angle", [-30.0, 12.0, 27.0])
def test_outline_distance_undoes_a_rigid_motion(angle):
    moved = _rigid(L_SHAPE, angle, (0.37, -1.2))
    assert _brute_distance(moved, L_SHAPE)[0] > 0.02  # unaligned, they are far apart
    mean, worst = outline_distance(moved, L_SHAPE)
    assert mean < 1e-3 and worst < 1e-3


def test_outline_distance_of_a_scaled_square():
    # scaled by 1.02 about the centre: every side moves out by 1 cm, the corners by 1 cm·√2; the rigid
    # alignment may not scale, and by symmetry the best alignment is the identity
    big = (SQUARE - 0.5) * 1.02 + 0.5
    mean, worst = outline_distance(big, SQUARE)
    assert mean == pytest.approx(0.01, rel=0.1)
    assert worst == pytest.approx(0.01 * math.sqrt(2), rel=0.1)
    ref_mean, ref_max = _brute_distance(big, SQUARE)
    assert mean == pytest.approx(ref_mean, rel=0.02) and worst == pytest.approx(ref_max, rel=0.02)
    # symmetric in its arguments, and independent of the vertex order and the starting vertex
    for a, b in ((SQUARE, big), (big[::-1], SQUARE), (np.roll(big, 2, axis=0), SQUARE[::-1])):
        m2, w2 = outline_distance(a, b)
        assert m2 == pytest.approx(mean, rel=0.02) and w2 == pytest.approx(worst, rel=0.02)


def test_outline_distance_of_reversed_order_is_the_same():
    moved = _rigid(L_SHAPE * 1.05, 10.0, (0.1, 0.2))
    forward = outline_distance(moved, L_SHAPE)
    backward = outline_distance(moved[::-1], L_SHAPE)
    assert forward[0] > 3e-3  # a real difference (5 % larger)
    np.testing.assert_allclose(backward, forward, rtol=1e-3, atol=1e-6)


def test_pattern_outline_errors_of_a_pattern_with_itself_are_zero():
    from torch_diffavatar.pattern.library import load_template

    pattern = load_template("dress")
    errors = pattern_outline_errors(pattern, load_template("dress"))
    assert set(errors) == set(pattern.panels)
    for name, e in errors.items():
        assert set(e) == {"mean_m", "max_m"}
        assert e["mean_m"] < 1e-4 and e["max_m"] < 1e-4, name


def test_pattern_outline_errors_against_the_demo_truth():
    """The truth's skirt hems are raised 8 cm and widened 12 %; its torso panels are the template's."""
    from torch_diffavatar.pattern.garmentcode import load_pattern
    from torch_diffavatar.pattern.library import load_template

    template, truth = load_template("dress"), load_pattern(TRUTH_PATTERN)
    errors = pattern_outline_errors(template, truth)
    for name, e in errors.items():
        if name in SKIRTS:
            assert 0.01 < e["mean_m"] < 0.08, (name, e)
            assert 0.03 < e["max_m"] < 0.12, (name, e)
            assert e["max_m"] >= e["mean_m"]
            # the alignment is no worse than none (both panels are drawn in the same frame)
            unaligned_mean, _ = _brute_distance(template.panels[name].outline(), truth.panels[name].outline())
            assert e["mean_m"] <= unaligned_mean * 1.02, (name, e, unaligned_mean)
        else:
            assert e["mean_m"] < 1e-4 and e["max_m"] < 1e-4, (name, e)


def test_pattern_outline_errors_need_the_same_panels():
    from torch_diffavatar.pattern.library import load_template

    pattern = load_template("dress")
    fewer = copy.deepcopy(pattern)
    del fewer.panels["skirt_back"]
    with pytest.raises(ValueError, match="skirt_back"):
        pattern_outline_errors(fewer, pattern)
    with pytest.raises(ValueError, match="skirt_back"):
        pattern_outline_errors(pattern, fewer)
    renamed = copy.deepcopy(pattern)
    renamed.panels["skirt"] = renamed.panels.pop("skirt_front")
    with pytest.raises(ValueError, match="skirt_front"):
        pattern_outline_errors(renamed, pattern)
