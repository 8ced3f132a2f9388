"""BodyIndex / closest_point_index + closest_point_query: the prebuilt-grid path of contact detection."""

from __future__ import annotations

import math

import pytest
import torch

from torch_diffavatar.sim import collision, ops, reference

F64 = torch.float64
pytestmark = pytest.mark.skipif(
    not ops.closest_point_index_available(torch.device("cpu")), reason="needs the C++ extension"
)


def _soup(count: int, gen: torch.Generator):
    """Random triangles of widely varying size in the unit cube: verts (3 count, 3), faces (count, 3)."""
    centers = torch.rand(count, 1, 3, generator=gen, dtype=F64)
    sizes = 0.3 * torch.rand(count, 1, 1, generator=gen, dtype=F64) ** 3
    verts = (centers + sizes * torch.randn(count, 3, 3, generator=gen, dtype=F64)).reshape(-1, 3)
    return verts, torch.arange(3 * count).reshape(count, 3)


def _sheet(n: int):
    """Flat (n+1)^2-vertex grid in z = 0 with 0.25 m spacing (exact binary coordinates), 2 n^2 faces."""
    i, j = torch.meshgrid(torch.arange(n + 1), torch.arange(n + 1), indexing="ij")
    verts = torch.stack([0.25 * i, 0.25 * j, torch.zeros_like(i)], -1).reshape(-1, 3).to(F64)
    v = (i[:-1, :-1] * (n + 1) + j[:-1, :-1]).reshape(-1)
    faces = torch.cat([torch.stack([v, v + n + 1, v + 1], 1), torch.stack([v + 1, v + n + 1, v + n + 2], 1)])
    return verts, faces


def _assert_bit_identical(got, want):
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and torch.equal(g, w)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_query_equals_per_call_op_and_reference(dtype):
    gen = torch.Generator().manual_seed(11)
    verts, faces = _soup(300, gen)
    points = 1.4 * torch.rand(700, 3, generator=gen, dtype=F64) - 0.2  # some outside the mesh's box
    points = torch.cat([points, verts[:50]])  # on the mesh: distance 0, and max_dist = 0 hits
    verts, points = verts.to(dtype), points.to(dtype)
    grids = [ops.closest_point_index(verts, faces, h) for h in (0.0, 0.003, 0.02, 0.1, 0.7, 5.0)]
    for max_dist in (0.0, 1e-3, 0.02, 0.1, math.inf):
        want = ops.closest_point_on_mesh(points, verts, faces, max_dist)
        for grid in grids:
            _assert_bit_identical(ops.closest_point_query(points, verts, faces, grid, max_dist), want)
        if dtype == F64:  # the brute-force reference: same hit set, distances and closest points
            ref = reference.closest_point_on_mesh(points, verts, faces, max_dist)
            assert torch.equal(want[0] >= 0, ref[0] >= 0)
            torch.testing.assert_close(want[2], ref[2], rtol=0.0, atol=1e-12)
            hit = want[0] >= 0
            q = (want[1][:, :, None] * verts[faces[want[0].clamp_min(0)]]).sum(1)[hit]
            q_ref = (ref[1][:, :, None] * verts[faces[ref[0].clamp_min(0)]]).sum(1)[hit]
            torch.testing.assert_close(q, q_ref, rtol=0.0, atol=1e-12)
    assert (want[0] >= 0).all()  # max_dist = inf


def test_ties_go_to_the_lowest_triangle_whatever_the_grid():
    verts, faces = _sheet(6)
    # above vertices (up to 6 triangles tie), above edges (2 tie), above faces and off the sheet's corner
    xy = torch.tensor([[0.5, 0.5], [0.75, 1.0], [0.25, 0.125], [1.125, 0.375], [-0.25, -0.25], [0.0, 0.75]])
    points = torch.cat([xy, torch.full((xy.shape[0], 1), 0.5)], 1).to(F64)
    # brute force with exact binary geometry: every triangle's distance, lowest id among the minima
    n, f = points.shape[0], faces.shape[0]
    a, b, c = (verts[faces[:, k]].expand(n, f, 3).reshape(-1, 3) for k in range(3))
    bc = reference.closest_point_on_triangles(points.repeat_interleave(f, 0), a, b, c)
    q = bc[:, :1] * a + bc[:, 1:2] * b + bc[:, 2:] * c
    d2 = ((points.repeat_interleave(f, 0) - q) ** 2).sum(-1).reshape(n, f)
    lowest = (d2 == d2.min(1, keepdim=True).values).int().argmax(1)
    assert ((d2 == d2.min(1, keepdim=True).values).sum(1) > 1).sum() >= 4  # the test does exercise ties
    want = ops.closest_point_on_mesh(points, verts, faces, 1.0)
    assert torch.equal(want[0], lowest)
    for h in (0.0, 0.1, 0.25, 0.3, 1.0):
        _assert_bit_identical(
            ops.closest_point_query(points, verts, faces, ops.closest_point_index(verts, faces, h), 1.0), want
        )


def test_query_edge_cases():
    verts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=F64)
    faces = torch.tensor([[0, 1, 2]])
    points = torch.tensor(
        [[0.2, 0.2, 0.5], [5.0, 5.0, 5.0], [math.nan, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=F64
    )
    grid = ops.closest_point_index(verts, faces)
    tri, bary, dist = ops.closest_point_query(points, verts, faces, grid, 0.5)
    assert tri.tolist() == [0, -1, -1, 0]  # 0.5 exactly: inside the band
    torch.testing.assert_close(bary[0], torch.tensor([0.6, 0.2, 0.2], dtype=F64))
    tri, _, dist = ops.closest_point_query(points, verts, faces, grid, 0.0)
    assert tri.tolist() == [-1, -1, -1, 0] and dist[3] == 0  # a vertex: exactly on the mesh
    _assert_bit_identical((tri, _, dist), ops.closest_point_on_mesh(points, verts, faces, 0.0))
    tri, bary, dist = ops.closest_point_query(points[:0], verts, faces, grid, 1.0)
    assert tri.shape == (0,) and bary.shape == (0, 3)
    empty = ops.closest_point_index(verts, faces[:0])
    tri, _, dist = ops.closest_point_query(points, verts, faces[:0], empty, 1.0)
    assert (tri == -1).all() and torch.isinf(dist).all()
    with pytest.raises(RuntimeError, match="faces"):
        ops.closest_point_query(points, verts, faces[:0], grid, 1.0)  # the index is for another mesh
    with pytest.raises(RuntimeError, match="max_dist"):
        ops.closest_point_query(points, verts, faces, grid, -1.0)
    with pytest.raises(RuntimeError, match="verts must be"):
        ops.closest_point_query(points, verts.float(), faces, grid, 1.0)


def test_detect_contacts_with_index():
    gen = torch.Generator().manual_seed(12)
    verts, faces = _soup(200, gen)
    x = torch.rand(400, 3, generator=gen, dtype=F64)
    index = collision.BodyIndex(verts, faces, cell_size=0.05)
    want = collision.detect_contacts(x, verts, faces, 0.05)
    got = collision.detect_contacts(x, verts, faces, 0.05, index=index)
    assert want.count > 0
    for name in ("vert", "tri", "bary"):
        assert torch.equal(getattr(got, name), getattr(want, name))
    slow = collision.BodyIndex(verts, faces, use_extension=False)  # no grid: the PyTorch reference
    assert slow.grid is None
    ref = collision.detect_contacts(x, verts, faces, 0.05, index=slow)
    assert torch.equal(ref.vert, want.vert)
    moved = verts.clone()
    moved[0, 0] += 1e-3
    assert index.matches(verts, faces) and not index.matches(moved, faces)
    with pytest.raises(ValueError, match="another body"):
        collision.detect_contacts(x, moved, faces, 0.05, index=index)
    original = verts.clone()
    verts[0, 0] += 1e-3  # in place: the index kept its own copy, so it no longer matches
    assert not index.matches(verts, faces)
    verts.copy_(original)  # back: equal again, found by comparing (the tensors' versions moved on)
    assert index.matches(verts, faces) and index.matches(verts, faces)
    faces[0, :2] = faces[0, [1, 0]].clone()  # faces edited in place after a match are seen too
    assert not index.matches(verts, faces)
    with torch.inference_mode():  # tensors without a version counter: compared every time
        inference = original.clone()
    assert index.matches(inference, index.faces) and index.matches(inference, index.faces)


def test_index_ops_opcheck():
    gen = torch.Generator().manual_seed(13)
    verts, faces = _soup(20, gen)
    points = torch.rand(30, 3, generator=gen, dtype=F64)
    torch.library.opcheck(ops._index_op("closest_point_index").default, (verts, faces, 0.1))
    grid = ops.closest_point_index(verts, faces, 0.1)
    torch.library.opcheck(ops._index_op("closest_point_query").default, (points, verts, faces, *grid, 0.2))
