"""Triangle quality and angles."""

from __future__ import annotations

import math

import pytest
import torch

from torch_diffavatar.metrics import min_angle_deg, quality_summary, triangle_angles_deg, triangle_quality

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
