"""The PyTorch reference kernels against autograd-derived versions of the contract (KERNELS.md)."""

from __future__ import annotations

import math

import pytest
import torch

from torch_diffavatar.sim import reference as R
from torch_diffavatar.sim.coloring import greedy_coloring

F64 = torch.float64


def _random_tris(gen, k=6):
    """k disjoint triangles with random rest shapes and deformed positions, random masses."""
    uv = torch.randn(k, 3, 2, generator=gen, dtype=F64) * 0.1
    dbar = torch.stack((uv[:, 0] - uv[:, 2], uv[:, 1] - uv[:, 2]), dim=-1)
    rest_inv = torch.linalg.inv(dbar)
    x = torch.randn(3 * k, 3, generator=gen, dtype=F64) * 0.1
    tri = torch.arange(3 * k).reshape(k, 3)
    w = torch.rand(3 * k, generator=gen, dtype=F64) + 0.5
    m = torch.randn(k, 3, 3, generator=gen, dtype=F64)
    compliance = (m @ m.transpose(1, 2) + torch.eye(3, dtype=F64)) * 1e-4
    return x, tri, rest_inv, w, compliance


def _strain(xt, rest_inv):
    d = torch.stack((xt[0] - xt[2], xt[1] - xt[2]), dim=-1)
    f = d @ rest_inv
    e = 0.5 * (f.T @ f - torch.eye(2, dtype=xt.dtype))
    return torch.stack((e[0, 0], e[1, 1], e[0, 1]))


def _contract_stretch(x, lam, w, tri, rest_inv, compliance, dt):
    """Textbook XPBD block step with the constraint Jacobian from autograd."""
    x = x.clone()
    lam = lam.clone()
    for t in range(tri.shape[0]):
        ids = tri[t]
        xt = x[ids]
        c = _strain(xt, rest_inv[t])
        jac = torch.autograd.functional.jacobian(lambda y, t=t: _strain(y, rest_inv[t]), xt)  # (3, 3[i], 3)
        grad = jac.reshape(3, 9)
        minv = torch.diag(w[ids].repeat_interleave(3))
        alpha_t = compliance[t] / dt**2
        a = grad @ minv @ grad.T + alpha_t
        dlam = torch.linalg.solve(a, -c - alpha_t @ lam[t])
        lam[t] += dlam
        x[ids] += (minv @ grad.T @ dlam).reshape(3, 3)
    return x, lam


def test_stretch_matches_autograd_contract():
    gen = torch.Generator().manual_seed(0)
    x, tri, rest_inv, w, compliance = _random_tris(gen)
    lam = torch.randn(tri.shape[0], 3, generator=gen, dtype=F64) * 1e-3
    coloring = greedy_coloring(tri)
    x_ref, lam_ref = _contract_stretch(x, lam, w, tri, rest_inv, compliance, 1e-2)
    x_k, lam_k = x.clone(), lam.clone()
    R.stretch_project_(x_k, lam_k, w, tri, rest_inv, compliance, coloring.order, coloring.color_offsets, 1e-2)
    torch.testing.assert_close(x_k, x_ref, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(lam_k, lam_ref, atol=1e-12, rtol=1e-10)
    # Jacobi on disjoint triangles (count = 1 everywhere) with omega = 1 is the same update
    x_j, lam_j = x.clone(), lam.clone()
    R.stretch_project_jacobi_(x_j, lam_j, w, tri, rest_inv, compliance, 1e-2, 1.0)
    torch.testing.assert_close(x_j, x_ref, atol=1e-12, rtol=1e-10)


def test_stretch_reduces_constraint_and_conserves_momentum():
    gen = torch.Generator().manual_seed(1)
    x, tri, rest_inv, w, _ = _random_tris(gen, k=1)
    compliance = torch.zeros(1, 3, 3, dtype=F64)
    lam = torch.zeros(1, 3, dtype=F64)
    order, offsets = torch.tensor([0]), torch.tensor([0, 1])
    c_before = _strain(x[tri[0]], rest_inv[0]).norm()
    momentum = (x / w[:, None]).sum(0)
    x_new = x.clone()
    for _ in range(5):
        R.stretch_project_(x_new, lam, w, tri, rest_inv, compliance, order, offsets, 1e-2)
    c_after = _strain(x_new[tri[0]], rest_inv[0]).norm()
    assert c_after < 1e-3 * c_before
    # the mass-weighted centre does not move (internal constraint: no net impulse)
    torch.testing.assert_close((x_new / w[:, None]).sum(0), momentum, atol=1e-10, rtol=1e-10)


def test_stretch_skips_fully_pinned_triangle():
    gen = torch.Generator().manual_seed(2)
    x, tri, rest_inv, _, compliance = _random_tris(gen, k=2)
    w = torch.zeros(6, dtype=F64)
    w[3:] = 1.0
    lam = torch.zeros(2, 3, dtype=F64)
    x_new = x.clone()
    R.stretch_project_(
        x_new, lam, w, tri, rest_inv, compliance, torch.tensor([0, 1]), torch.tensor([0, 2]), 1e-2
    )
    assert torch.equal(x_new[:3], x[:3]) and torch.equal(lam[0], torch.zeros(3, dtype=F64))
    assert not torch.equal(x_new[3:], x[3:])


def test_bend_gradient_is_autograd_of_signed_angle():
    gen = torch.Generator().manual_seed(3)
    for _ in range(5):
        x = torch.randn(4, 3, generator=gen, dtype=F64, requires_grad=True)
        theta = R.dihedral_angle(*x)
        (grad,) = torch.autograd.grad(theta, x)
        xd = x.detach()
        w = torch.ones(4, dtype=F64)
        zero = torch.zeros(1, dtype=F64)
        dlam, dx, active = R._bend_delta(xd, zero, w, torch.arange(4)[None], zero, zero, 1.0)
        assert bool(active[0])
        torch.testing.assert_close(dx[0] / dlam[0], grad, atol=1e-10, rtol=1e-8)
        # C = theta with zero compliance: dlam = -theta / |grad|^2
        torch.testing.assert_close(dlam[0], -theta.detach() / (grad * grad).sum(), atol=1e-12, rtol=1e-10)


def test_dihedral_angle_sign_and_value():
    # hinge along the x axis; triangle 1 in the z = 0 plane (normal +z), wing 2 rotated by phi
    x0 = torch.tensor([0.0, 0.0, 0.0], dtype=F64)
    x1 = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    x2 = torch.tensor([0.5, 1.0, 0.0], dtype=F64)
    for phi in (0.0, 0.3, -0.7, 2.0):
        x3 = torch.tensor([0.5, -math.cos(phi), math.sin(phi)], dtype=F64)
        theta = R.dihedral_angle(x0, x1, x2, x3)
        assert abs(abs(float(theta)) - abs(phi)) < 1e-12
    # lifting the wing tip along its own triangle's normal (+z for triangle 2 when flat) decreases theta
    flat = R.dihedral_angle(x0, x1, x2, torch.tensor([0.5, -1.0, 0.0], dtype=F64))
    lifted = R.dihedral_angle(x0, x1, x2, torch.tensor([0.5, -1.0, 0.01], dtype=F64))
    assert float(flat) == 0.0 and float(lifted) < 0.0


def test_bend_projection_flattens_a_folded_quad():
    x = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -0.8, 0.6]], dtype=F64)
    w = torch.ones(4, dtype=F64)
    lam = torch.zeros(1, dtype=F64)
    quads = torch.arange(4)[None]
    before = abs(float(R.dihedral_angle(*x)))
    for _ in range(10):
        R.bend_project_(x, lam, w, quads, torch.zeros(1, dtype=F64), torch.zeros(1, dtype=F64),
                        torch.tensor([0]), torch.tensor([0, 1]), 1e-2)  # fmt: skip
    assert abs(float(R.dihedral_angle(*x))) < 1e-3 * before


def test_bend_skips_degenerate_quad():
    x = torch.tensor([[0.0, 0, 0], [0, 0, 0], [0.5, 1, 0], [0.5, -1, 0.3]], dtype=F64)
    x_new, lam = x.clone(), torch.zeros(1, dtype=F64)
    R.bend_project_(x_new, lam, torch.ones(4, dtype=F64), torch.arange(4)[None], torch.zeros(1, dtype=F64),
                    torch.zeros(1, dtype=F64), torch.tensor([0]), torch.tensor([0, 1]), 1e-2)  # fmt: skip
    assert torch.equal(x_new, x) and float(lam[0]) == 0.0


def _brute_closest(pts, verts, faces):
    """(N,) distance and triangle of the closest point over ALL triangles (no pre-filter)."""
    a, b, c = (verts[faces[:, k]][None] for k in range(3))
    bc = R.closest_point_on_triangles(pts[:, None], a, b, c)  # (N, Fb, 3)
    q = bc[..., :1] * a + bc[..., 1:2] * b + bc[..., 2:] * c
    return (pts[:, None] - q).norm(dim=-1).min(dim=1)


def test_closest_point_on_triangle_matches_dense_sampling():
    gen = torch.Generator().manual_seed(4)
    a, b, c = torch.randn(3, 3, generator=gen, dtype=F64)
    # dense barycentric sampling of the triangle
    s = torch.linspace(0, 1, 201, dtype=F64)
    uu, vv = torch.meshgrid(s, s, indexing="ij")
    keep = (uu + vv) <= 1
    u, v = uu[keep], vv[keep]
    samples = (1 - u - v)[:, None] * a + u[:, None] * b + v[:, None] * c
    for _ in range(30):
        p = torch.randn(3, generator=gen, dtype=F64) * 1.5
        bc = R.closest_point_on_triangles(p, a, b, c)
        assert bool((bc >= -1e-12).all()) and abs(float(bc.sum()) - 1) < 1e-12
        q = bc[0] * a + bc[1] * b + bc[2] * c
        d = float((p - q).norm())
        d_sampled = float((samples - p).norm(dim=-1).min())
        assert d <= d_sampled + 1e-12 and d >= d_sampled - 2e-2


def test_closest_point_on_mesh_brute_force_and_max_dist():
    trimesh = pytest.importorskip("trimesh")
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    verts = torch.as_tensor(sphere.vertices, dtype=F64)
    faces = torch.as_tensor(sphere.faces, dtype=torch.int64)
    gen = torch.Generator().manual_seed(5)
    pts = torch.randn(40, 3, generator=gen, dtype=F64) * 0.3
    tri, bary, dist = R.closest_point_on_mesh(pts, verts, faces, 0.1)
    d_all, _ = _brute_closest(pts, verts, faces)
    assert bool((d_all <= 0.1).any()) and bool((d_all > 0.1).any())
    for i in range(pts.shape[0]):
        d = float(d_all[i])
        if d <= 0.1:
            assert int(tri[i]) >= 0
            assert abs(float(dist[i]) - d) < 1e-12
            q = (bary[i][:, None] * verts[faces[tri[i]]]).sum(0)
            assert abs(float((pts[i] - q).norm()) - d) < 1e-12
        else:
            assert int(tri[i]) == -1 and math.isinf(float(dist[i])) and float(bary[i].abs().sum()) == 0
