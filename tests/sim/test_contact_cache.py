"""ContactCache: contact detection that queries only what can have changed, with exactly the full query's
contacts (and so bit-identical drapes)."""

from __future__ import annotations

import pytest
import torch

from torch_diffavatar.sim import collision, ops, reference
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver
from torch_diffavatar.sim.testing import rectangle_garment

F64 = torch.float64
pytestmark = pytest.mark.skipif(
    not ops.closest_point_index_available(torch.device("cpu")), reason="needs the C++ extension"
)


def _assert_same_contacts(got, want):
    for name in ("vert", "tri", "bary"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name


def _sphere(radius=0.3, subdivisions=3, dtype=F64):
    trimesh = pytest.importorskip("trimesh")
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return torch.as_tensor(s.vertices, dtype=dtype), torch.as_tensor(s.faces, dtype=torch.int64)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_random_walk_contacts_equal_the_full_query(dtype):
    """Points near a sphere wander with steps from 0.1 mm to 5 cm and a band that changes: every frame's
    contacts equal the full query's, while many frames query only part of the points."""
    verts, faces = _sphere(dtype=dtype)
    gen = torch.Generator().manual_seed(3)
    direction = torch.nn.functional.normalize(torch.randn(500, 3, generator=gen, dtype=F64), dim=-1)
    x = (direction * (0.3 + 0.08 * torch.rand(500, 1, generator=gen, dtype=F64))).to(dtype)
    index = collision.BodyIndex(verts, faces, cell_size=0.04)
    cache = collision.ContactCache(index, probe=0.02)
    partial = among = 0
    for frame in range(60):
        scale = [1e-4, 1e-3, 5e-3, 5e-2][frame % 4]
        x = x + (scale * torch.randn(500, 3, generator=gen, dtype=F64)).to(dtype)
        band = [0.02, 0.025, 0.012][frame % 3]
        want = collision.detect_contacts(x, verts, faces, band, index=index)
        got = collision.detect_contacts(x, verts, faces, band, cache=cache)
        assert want.count > 0
        _assert_same_contacts(got, want)
        partial += cache.queried < x.shape[0]
        among += cache.among
    assert partial > 20  # the cache did skip vertices (else this test would not test it)
    assert among > 1000  # and looked among candidates


def test_vertex_moving_into_the_band_is_found():
    verts, faces = _sphere()
    x = torch.tensor([[0.0, 0.0, 0.31], [0.0, 0.0, 0.5], [0.0, 0.0, 1.5]], dtype=F64)
    cache = collision.ContactCache(collision.BodyIndex(verts, faces), probe=0.02)
    assert collision.detect_contacts(x, verts, faces, 0.02, cache=cache).vert.tolist() == [0]
    for _ in range(3):  # at rest, the far ones are no longer queried
        collision.detect_contacts(x, verts, faces, 0.02, cache=cache)
    assert cache.queried == 1
    x[1, 2] = 0.305  # from 20 cm to 5 mm, within one frame
    x[2, 2] = -0.31  # through the body to the other side
    got = collision.detect_contacts(x, verts, faces, 0.02, cache=cache)
    assert got.vert.tolist() == [0, 1, 2]
    _assert_same_contacts(got, collision.detect_contacts(x, verts, faces, 0.02))


def test_vertex_sliding_within_the_margin_keeps_the_full_query_contacts():
    """Just above a fine sheet, a vertex slides almost ``margin`` along it: its closest triangle moves far
    outside the few triangles that were that close at the start, so the candidates must reach out to
    distance + 2 margin."""
    n, h = 40, 5e-4  # 2 cm sheet of 0.5 mm squares
    i, j = torch.meshgrid(torch.arange(n + 1), torch.arange(n + 1), indexing="ij")
    verts = torch.stack([h * i, h * j, torch.zeros_like(i)], -1).reshape(-1, 3).to(F64)
    v = (i[:-1, :-1] * (n + 1) + j[:-1, :-1]).reshape(-1)
    faces = torch.cat([torch.stack([v, v + n + 1, v + 1], 1), torch.stack([v + 1, v + n + 1, v + n + 2], 1)])
    cache = collision.ContactCache(collision.BodyIndex(verts, faces, cell_size=0.004), margin=0.002)
    x = torch.tensor([[0.0051, 0.0052, 1e-4]], dtype=F64)
    for step in range(20):
        y = x + torch.tensor([[0.0019 * step / 19, 0.0, 0.0]], dtype=F64)
        got = collision.detect_contacts(y, verts, faces, 0.01, cache=cache)
        _assert_same_contacts(got, collision.detect_contacts(y, verts, faces, 0.01))
        assert cache.among == (1 if step else 0)  # the candidates of step 0 served all the others


def test_no_candidates_beyond_max_radius():
    verts, faces = _sphere()
    x = torch.tensor([[0.0, 0.0, 0.305], [0.0, 0.0, -0.325]], dtype=F64)  # 5 mm and 2.5 cm away
    cache = collision.ContactCache(collision.BodyIndex(verts, faces), margin=0.002, max_radius=0.02)
    for _ in range(3):
        got = collision.detect_contacts(x, verts, faces, 0.03, cache=cache)
    assert got.vert.tolist() == [0, 1]
    assert cache.has_cand.tolist() == [True, False] and cache.among == 1
    assert int((cache.state[4][0] >= 0).sum()) < 20  # the near one's list is short


def test_hints_never_change_the_query():
    verts, faces = _sphere(subdivisions=4)
    gen = torch.Generator().manual_seed(5)
    points = (
        0.4 * torch.rand(400, 3, generator=gen, dtype=F64) - 0.2 + torch.tensor([0.0, 0.0, 0.2], dtype=F64)
    )
    grid = ops.closest_point_index(verts, faces, 0.05)
    want = ops.closest_point_query(points, verts, faces, grid, 0.1)
    nf = faces.shape[0]
    right = want[0]
    near = (right + 1).clamp(max=nf - 1)  # a neighbour by id, often close
    wild = torch.randint(-3, nf + 3, (400,), generator=gen)  # anything, out of range too
    for hint in (right, near, wild, torch.full_like(right, -1)):
        got = ops.closest_point_query(points, verts, faces, grid, 0.1, hint)
        assert all(torch.equal(g, w) for g, w in zip(got, want, strict=True))
    with pytest.raises(RuntimeError, match="hint"):
        ops.closest_point_query(points, verts, faces, grid, 0.1, right[:-1])
    torch.library.opcheck(
        ops._index_op("closest_point_query_hinted").default,
        (points[:30], verts, faces, *grid, wild[:30], 0.1),
    )


def test_candidates_and_among_match_their_twins():
    verts, faces = _sphere(subdivisions=2)
    gen = torch.Generator().manual_seed(6)
    direction = torch.nn.functional.normalize(torch.randn(200, 3, generator=gen, dtype=F64), dim=-1)
    points = direction * (0.25 + 0.1 * torch.rand(200, 1, generator=gen, dtype=F64))
    radius = 0.1 * torch.rand(200, generator=gen, dtype=F64)
    radius[:5] = -1.0  # no candidates
    grid = ops.closest_point_index(verts, faces, 0.05)
    cand = ops.closest_point_candidates(points, verts, faces, grid, radius)
    want = reference.closest_point_candidates(points, verts, faces, radius)
    got = torch.where(cand < 0, faces.shape[0], cand).sort(1).values
    assert torch.equal(torch.where(got == faces.shape[0], -1, got)[:, : want.shape[1]], want)
    assert (cand[:5] == -1).all() and (cand >= 0).any(1).sum() > 100
    # among: the twin's answer; with candidates out to the closest distance, the grid query's, bit for bit
    tri, bary, dist = ops.closest_point_among(points, verts, faces, cand, 0.08)
    ref = reference.closest_point_among(points, verts, faces, want, 0.08)
    assert torch.equal(tri, ref[0])
    torch.testing.assert_close(bary, ref[1], rtol=0, atol=1e-12)
    torch.testing.assert_close(dist, ref[2], rtol=0, atol=1e-12)
    full = ops.closest_point_query(points, verts, faces, grid, 0.5)
    enough = ops.closest_point_candidates(points, verts, faces, grid, full[2])
    got = ops.closest_point_among(points, verts, faces, enough, 0.5)
    assert all(torch.equal(g, w) for g, w in zip(got, full, strict=True))
    torch.library.opcheck(
        ops._index_op("closest_point_candidates").default, (points[:20], verts, faces, *grid, radius[:20])
    )
    torch.library.opcheck(
        ops._index_op("closest_point_among").default, (points[:20], verts, faces, cand[:20], 0.1)
    )


def _sheet_over_sphere(dtype):
    mat = ClothMaterial(k_uu=1e3, k_vv=1e3, k_uv=100.0, bend_stiffness=1e-6, thickness=0.005, damping=2.0)
    g = rectangle_garment(16, 16, 1.0, 1.0, origin=(-0.5, 0.35, 0.5))  # 5 cm above the top, corners far
    return g, ClothModelBuilder(mat).add_garment(g).finalize(dtype=dtype)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_drape_on_a_sphere_is_bit_identical_with_and_without_the_cache(dtype):
    verts, faces = _sphere(dtype=dtype)
    g, model = _sheet_over_sphere(dtype)
    rest = model.rest_data(g.vert_uv.to(dtype))
    runs = {}
    for cached in (False, True):
        solver = XPBDSolver(model, XPBDConfig(substeps=10, iterations=2, contact_cache=cached))
        state, frames, queried = model.initial_state(), [], []
        for _ in range(30):
            step = solver.advance(state, rest, 1 / 30, body_verts=verts, body_faces=faces)
            state = step.state
            frames.append((state.x, state.v, step.contacts))
            if solver._contact_cache is not None:
                queried.append((solver._contact_cache.queried, solver._contact_cache.among))
        runs[cached] = frames, queried
    assert runs[False][1] == []  # contact_cache=False: no cache
    assert min(q for q, _ in runs[True][1]) < model.vert_count  # the cache skipped vertices
    assert max(a for _, a in runs[True][1]) > 50  # and looked among candidates
    assert runs[True][0][-1][2].count > 50  # the sheet lies on the sphere
    for (x0, v0, c0), (x1, v1, c1) in zip(runs[False][0], runs[True][0], strict=True):
        assert torch.equal(x0, x1) and torch.equal(v0, v1)
        assert (c0 is None) == (c1 is None)
        if c0 is not None:
            _assert_same_contacts(c1, c0)


def test_a_changed_body_drops_the_cache_and_a_moving_body_does_not_use_it():
    verts, faces = _sphere()
    g, model = _sheet_over_sphere(F64)
    rest = model.rest_data(g.vert_uv)
    solver = XPBDSolver(model, XPBDConfig(substeps=10, iterations=2))
    state = model.initial_state()
    for _ in range(10):
        state = solver.step(state, rest, 1 / 30, body_verts=verts, body_faces=faces)
    cache = solver._contact_cache
    assert cache is not None and cache.index is solver._body_index
    # another body: a new index and a new cache, and the contacts of a full query against it
    bigger = verts * 1.02
    step = solver.advance(state, rest, 1 / 30, body_verts=bigger, body_faces=faces)
    assert solver._contact_cache is not cache and solver._contact_cache.index.matches(bigger, faces)
    fresh = XPBDSolver(model, XPBDConfig(substeps=10, iterations=2, contact_cache=False))
    want = fresh.advance(state, rest, 1 / 30, body_verts=bigger, body_faces=faces)
    assert torch.equal(step.state.x, want.state.x)
    _assert_same_contacts(step.contacts, want.contacts)
    with pytest.raises(ValueError, match="another body"):
        collision.detect_contacts(state.x, verts, faces, 0.02, cache=solver._contact_cache)
    # a moving body: neither an index nor a cache
    moving = XPBDSolver(model, XPBDConfig(substeps=10, iterations=2))
    for _ in range(3):
        moving.step(state, rest, 1 / 30, body_verts=verts, body_faces=faces, body_verts_end=bigger)
    assert moving._contact_cache is None and moving._body_index is None


def test_skirt_sewn_and_draped_on_the_body_is_bit_identical_with_and_without_the_cache(default_body):
    """A garment on the Anny body: sewing and drape give the same positions and velocities, bit for bit."""
    from dataclasses import replace

    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.sim.forward_drape import DrapeConfig, sew_and_drape
    from torch_diffavatar.sim.placement import place_garment

    verts, faces = default_body
    garment = place_garment(mesh_pattern(load_template("skirt"), spacing=0.06), verts, faces)
    base = DrapeConfig(max_steps=25, min_steps=25, sew_max_steps=40, sew_ramp_steps=20)
    results = []
    for cached in (False, True):
        config = replace(
            base,
            xpbd=replace(base.xpbd, contact_cache=cached),
            sew_xpbd=replace(base.sew_xpbd, contact_cache=cached),
        )
        results.append(sew_and_drape(garment, body_verts=verts, body_faces=faces, config=config))
    plain, cached = results
    assert plain.diagnostics["contact_count"] > 20
    assert torch.equal(plain.x, cached.x) and torch.equal(plain.v, cached.v)


def _cache_state(n, width, x):
    x64 = x.to(F64)
    return [x64.clone(), x64.new_zeros(n), torch.full((n,), -1), x64.clone(), torch.full((n, width), -1)]


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_cache_op_matches_its_twin_frame_after_frame(dtype):
    """`contact_cache_query_` (C++) and `reference.contact_cache_query_` walk the same points: the same
    contacts, counts and state every frame (candidate lists as sets: their order is the grid's); a width of
    4 makes some lists too long, which both report alike."""
    verts, faces = _sphere(subdivisions=2, dtype=dtype)
    grid = ops.closest_point_index(verts, faces, 0.05)
    gen = torch.Generator().manual_seed(8)
    direction = torch.nn.functional.normalize(torch.randn(120, 3, generator=gen, dtype=F64), dim=-1)
    x = (direction * (0.3 + 0.06 * torch.rand(120, 1, generator=gen, dtype=F64))).to(dtype)
    for width in (4, 64):
        op_state, twin_state = _cache_state(120, width, x), _cache_state(120, width, x)
        overflowed = among = 0
        for frame in range(24):
            x = x + ([1e-4, 1e-3, 2e-2][frame % 3] * torch.randn(120, 3, generator=gen, dtype=F64)).to(dtype)
            band = [0.02, 0.03][frame % 2]
            got = ops.contact_cache_query_(x, verts, faces, grid, op_state, band, 0.02, 0.002, 0.05)
            limits = (band, 0.02, 0.002, 0.05)
            want = reference.contact_cache_query_(x, verts, faces, *grid, *twin_state, *limits)
            full = ops.closest_point_query(x, verts, faces, grid, band)
            # the full query's, bit for bit
            assert torch.equal(got[0], full[0]) and torch.equal(got[1], full[1])
            assert torch.equal(got[0], want[0]) and torch.equal(got[2], want[2])
            torch.testing.assert_close(got[1], want[1], rtol=0, atol=1e-12)
            for g, w in zip(op_state[:4], twin_state[:4], strict=True):
                torch.testing.assert_close(g, w, rtol=0, atol=1e-12)
            held = op_state[4][:, 0] >= 0  # rows without candidates (first -1) keep stale entries
            assert torch.equal(held, twin_state[4][:, 0] >= 0)
            assert torch.equal(op_state[4][held].sort(1).values, twin_state[4][held].sort(1).values)
            overflowed += int(got[2][2] > 0)
            among += int(got[2][1])
        assert among > 100 and (overflowed > 0) == (width == 4)
    torch.library.opcheck(
        ops._index_op("contact_cache_query_").default,
        (x[:20].contiguous(), verts, faces, *grid, *_cache_state(20, 8, x[:20]), 0.03, 0.02, 0.002, 0.05),
    )


def test_a_cache_whose_lists_do_not_fit_widens_and_keeps_the_full_query_contacts():
    """Candidate rows of width 2 on a sphere: the first frame's lists do not fit; the cache widens its rows
    (the same frame again) and the next frames are answered among the candidates."""
    verts, faces = _sphere()
    x = torch.tensor([[0.0, 0.0, 0.305], [0.0, 0.302, 0.0], [0.3, 0.3, 0.1]], dtype=F64)
    cache = collision.ContactCache(collision.BodyIndex(verts, faces), width=2)
    for frame in range(3):
        got = collision.detect_contacts(x, verts, faces, 0.02, cache=cache)
        _assert_same_contacts(got, collision.detect_contacts(x, verts, faces, 0.02))
        assert cache.width > 2  # widened at the first frame
        assert cache.among == 2 or frame == 0  # then both contacts among their candidates
    assert cache.has_cand.tolist() == [True, True, False]
    with pytest.raises(ValueError, match="width"):
        collision.ContactCache(cache.index, width=0)


def test_cache_op_is_the_same_on_two_threads():
    """The op splits the points over OpenMP threads: each point's answer and state depend on that point
    alone, so two threads give what one gives, bit for bit."""
    verts, faces = _sphere(subdivisions=3)
    grid = ops.closest_point_index(verts, faces, 0.04)
    gen = torch.Generator().manual_seed(9)
    direction = torch.nn.functional.normalize(torch.randn(3000, 3, generator=gen, dtype=F64), dim=-1)
    x = direction * (0.3 + 0.05 * torch.rand(3000, 1, generator=gen, dtype=F64))
    threads = torch.get_num_threads()
    runs = []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            state, y, out = _cache_state(3000, 16, x), x.clone(), []
            for frame in range(6):
                y = y + [1e-3, 1e-2][frame % 2] * torch.randn(
                    3000, 3, generator=torch.Generator().manual_seed(frame)
                )
                out.append(ops.contact_cache_query_(y, verts, faces, grid, state, 0.03, 0.02, 0.002, 0.05))
            runs.append((out, state))
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(runs[0][0], runs[1][0], strict=True):
        assert all(torch.equal(p, q) for p, q in zip(a, b, strict=True))
    assert all(torch.equal(p, q) for p, q in zip(runs[0][1], runs[1][1], strict=True))
    assert sum(int(o[2][1]) for o in runs[0][0]) > 2000  # answered among candidates too
