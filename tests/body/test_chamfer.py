import numpy as np
import pytest
import torch

from torch_diffavatar.chamfer import (
    chamfer_distance,
    nearest_indices,
    one_sided_chamfer,
    robust_penalty,
    sample_surface,
    surface_chamfer_m,
)


def _cloud(n, seed, dtype=torch.float64):
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def test_nearest_indices_match_brute_force():
    x, y = _cloud(50, 0), _cloud(80, 1)
    brute = torch.cdist(x, y).argmin(1).numpy()
    np.testing.assert_array_equal(nearest_indices(x, y), brute)


def test_one_and_two_sided_values_match_brute_force():
    x, y = _cloud(40, 2), _cloud(30, 3)
    d = torch.cdist(x, y) ** 2
    torch.testing.assert_close(one_sided_chamfer(x, y), d.min(1).values.mean())
    torch.testing.assert_close(one_sided_chamfer(x, y, reduction="sum"), d.min(1).values.sum())
    xy, yx = chamfer_distance(x, y, reduction="none")
    assert xy.shape == (1, 40) and yx.shape == (1, 30)
    torch.testing.assert_close(chamfer_distance(x, y), d.min(1).values.mean() + d.min(0).values.mean())


def test_batched_and_weighted():
    x = torch.stack([_cloud(20, 4), _cloud(20, 5)])
    y = _cloud(25, 6)
    per = one_sided_chamfer(x, y, reduction="none")
    assert per.shape == (2, 20)
    w = torch.zeros(2, 20, dtype=torch.float64)
    w[:, 0] = 1.0
    torch.testing.assert_close(one_sided_chamfer(x, y, x_weights=w), per[:, 0].mean())


def test_robust_kernels():
    sq = torch.tensor([0.0, 1e-6, 1e-2, 1.0], dtype=torch.float64)
    for kind in ("l2", "geman_mcclure", "huber"):
        out = robust_penalty(sq, kind, scale=0.01)
        assert out[0] == 0 and abs(out[1] - 1e-6) < 1e-8  # all behave like d² near zero
    gm = robust_penalty(sq, "geman_mcclure", scale=0.01)
    assert gm[-1] < 1e-4  # saturates at s²
    hub = robust_penalty(sq, "huber", scale=0.01)
    torch.testing.assert_close(hub[-1], torch.tensor(0.01 * (2 * 1.0 - 0.01), dtype=torch.float64))


def test_bad_arguments_are_rejected():
    x = _cloud(5, 7)
    with pytest.raises(ValueError, match="reduction"):
        chamfer_distance(x, x, reduction="avg")
    with pytest.raises(ValueError, match="robust"):
        chamfer_distance(x, x, robust="cauchy")
    with pytest.raises(ValueError, match="shape"):
        one_sided_chamfer(x[:, :2], x)
    with pytest.raises(ValueError, match="empty"):
        one_sided_chamfer(x, x[:0])


@pytest.mark.parametrize("robust", ["l2", "geman_mcclure", "huber"])
def test_gradcheck(robust):
    # Well-separated points, so small perturbations do not change the nearest-neighbour assignment.
    grid = torch.stack(torch.meshgrid(*[torch.arange(3.0, dtype=torch.float64)] * 3, indexing="ij"), -1)
    x = (grid.reshape(-1, 3)[:8] + 0.1 * _cloud(8, 8)).requires_grad_()
    y = (grid.reshape(-1, 3)[:10] + 0.1 * _cloud(10, 9)).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: chamfer_distance(a, b, robust=robust, scale=0.1), (x, y))


# ------------------------------------------------------------------------------ surface Chamfer


def _icosphere(radius=0.3, subdivisions=3, center=(0.02, 1.1, -0.03)):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    verts = torch.as_tensor(s.vertices, dtype=torch.float64) + torch.tensor(center, dtype=torch.float64)
    return verts, torch.as_tensor(s.faces, dtype=torch.int64)


def _trimesh_distance(verts, faces, points):
    """(N,) distances from points to the mesh surface by trimesh (an independent implementation)."""
    import trimesh

    mesh = trimesh.Trimesh(verts.numpy(), faces.numpy(), process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, points.numpy())
    return dist


def test_sample_surface_lies_on_the_mesh():
    verts, faces = _icosphere()
    s = sample_surface(verts, faces, 3000, generator=torch.Generator().manual_seed(0))
    assert s.shape == (3000, 3) and s.dtype == torch.float64
    assert float(np.abs(_trimesh_distance(verts, faces, s)).max()) < 1e-9
    # a float32 mesh gives float32 samples
    assert sample_surface(verts.float(), faces, 10, generator=torch.Generator().manual_seed(0)).dtype == (
        torch.float32
    )


def test_sample_surface_is_area_uniform():
    # two disjoint triangles, areas 3 : 1 (z = 0 and z = 1)
    big = [[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 2.0, 0.0]]
    small = [[5.0, 0.0, 1.0], [6.0, 0.0, 1.0], [5.0, 2.0, 1.0]]
    verts = torch.tensor(big + small, dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    n = 40000
    s = sample_surface(verts, faces, n, generator=torch.Generator().manual_seed(1))
    on_big = s[:, 2] == 0.0
    assert bool((on_big | (s[:, 2] == 1.0)).all())
    assert float(on_big.double().mean()) == pytest.approx(0.75, abs=0.01)  # binomial σ ≈ 0.002
    # inside the big triangle, uniform: barycentrics in [0, 1], mean at the centroid, and a quarter of
    # the samples in the medial triangle (the one joining the edge midpoints, a quarter of the area)
    p = s[on_big]
    u, v = p[:, 0] / 3.0, p[:, 1] / 2.0
    assert float(u.min()) >= 0 and float(v.min()) >= 0 and float((u + v).max()) <= 1 + 1e-12
    torch.testing.assert_close(p.mean(0), verts[:3].mean(0), atol=0.02, rtol=0)
    medial = (u < 0.5) & (v < 0.5) & (u + v > 0.5)
    assert float(medial.double().mean()) == pytest.approx(0.25, abs=0.01)


def test_sample_surface_is_seeded():
    verts, faces = _icosphere()
    a = sample_surface(verts, faces, 500, generator=torch.Generator().manual_seed(3))
    b = sample_surface(verts, faces, 500, generator=torch.Generator().manual_seed(3))
    c = sample_surface(verts, faces, 500, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_surface_chamfer_of_points_on_and_off_the_surface():
    verts, faces = _icosphere()
    centre = torch.tensor([0.02, 1.1, -0.03], dtype=torch.float64)
    points = sample_surface(verts, faces, 4000, generator=torch.Generator().manual_seed(5))
    on = surface_chamfer_m(verts, faces, points, samples=20000)
    assert set(on) == {"points_to_mesh", "mesh_to_points", "symmetric"}
    assert on["points_to_mesh"] < 1e-9
    # 4000 points on 1.1 m²: spacing ≈ 1.7 cm, so a surface sample's nearest point is within ~1 cm
    assert 0.0 < on["mesh_to_points"] < 0.012
    assert on["symmetric"] == pytest.approx(0.5 * (on["points_to_mesh"] + on["mesh_to_points"]))
    delta = 0.005
    radial = (points - centre) / (points - centre).norm(dim=1, keepdim=True)
    for sign in (1.0, -1.0):  # outwards, then inwards: the distance is unsigned
        moved = points + sign * delta * radial
        off = surface_chamfer_m(verts, faces, moved, samples=20000)
        assert off["points_to_mesh"] == pytest.approx(delta, rel=0.05)
        assert off["points_to_mesh"] == pytest.approx(float(_trimesh_distance(verts, faces, moved).mean()))
        assert off["mesh_to_points"] > on["mesh_to_points"]
    # seeded: the same call twice gives the same numbers, another seed other samples
    again = surface_chamfer_m(verts, faces, points, samples=20000)
    assert again == on
    other = surface_chamfer_m(verts, faces, points, samples=20000, seed=1)
    assert other["mesh_to_points"] != on["mesh_to_points"]
    assert other["mesh_to_points"] == pytest.approx(on["mesh_to_points"], rel=0.05)
