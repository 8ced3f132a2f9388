"""The C++ kernels (`torch.ops.diffavatar.*`, csrc/) against their PyTorch twins in sim/reference.py.

Skipped when the extension is not built (`python setup.py build_ext --inplace`).
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from torch_diffavatar._ext import has_extension

if not has_extension():
    pytest.skip("C++ extension torch_diffavatar._C not built", allow_module_level=True)

from torch_diffavatar.sim import ops, reference  # noqa: E402
from torch_diffavatar.sim.coloring import coloring_is_valid, greedy_coloring  # noqa: E402

F64 = torch.float64
DT = 1.0 / 240.0  # [s]


# ------------------------------------------------------------------------------------------ problems


def _op(name):
    op = ops.extension_op(name)  # also registers the fake kernel
    assert op is not None, f"torch.ops.diffavatar.{name} is not registered"
    return op


def _coloring(ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """order (K,) and color_offsets (n_colors + 1,) from the sim's greedy colouring of (K, arity) ids."""
    coloring = greedy_coloring(ids)
    assert coloring_is_valid(ids, coloring) and coloring.color_count > 1
    return coloring.order, coloring.color_offsets


def _sheet_mesh(n: int, gen: torch.Generator):
    """A perturbed n x n triangulated sheet: rest uv (V, 2) [m], 3D x (V, 3) [m], faces (F, 3) int64."""
    side = 0.5
    g = torch.linspace(0.0, side, n, dtype=F64)
    uu, vv = torch.meshgrid(g, g, indexing="ij")
    uv = torch.stack((uu.reshape(-1), vv.reshape(-1)), dim=-1)
    idx = torch.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = torch.cat(
        (torch.stack((a, c, d), -1).reshape(-1, 3), torch.stack((a, d, b), -1).reshape(-1, 3)), dim=0
    )
    h = side / (n - 1)
    x = torch.cat((uv * 1.05, 0.1 * torch.sin(6.0 * uv[:, :1]) * torch.cos(4.0 * uv[:, 1:])), dim=-1)
    x = x + 0.15 * h * torch.randn(x.shape, generator=gen, dtype=F64)
    return uv, x, faces


def _edge_quads(faces: torch.Tensor) -> torch.Tensor:
    """(E, 4) int64 (v0, v1, v2, v3) of the interior edges of a consistently oriented triangle mesh."""
    opposite = {}
    for p, q, r in faces.tolist():
        opposite[(p, q)] = r
        opposite[(q, r)] = p
        opposite[(r, p)] = q
    quads = [(a, b, c, opposite[(b, a)]) for (a, b), c in opposite.items() if a < b and (b, a) in opposite]
    return torch.tensor(quads, dtype=torch.int64)


def _stretch_problem(n: int, seed: int = 0, dtype=F64):
    """Arguments of stretch_project_ (the order/offsets pair from a greedy colouring)."""
    gen = torch.Generator().manual_seed(seed)
    uv, x, faces = _sheet_mesh(n, gen)
    vert_count, tri_count = x.shape[0], faces.shape[0]
    w = 0.5 + 1.5 * torch.rand(vert_count, generator=gen, dtype=F64)
    w[faces[0]] = 0.0  # one fully pinned triangle (skipped) and its neighbours partly pinned
    rest = uv[faces]  # (F, 3, 2)
    rest_d = torch.stack((rest[:, 0] - rest[:, 2], rest[:, 1] - rest[:, 2]), dim=-1)  # (F, 2, 2)
    rest_inv = torch.linalg.inv(rest_d).contiguous()
    m = 0.3 * torch.randn(tri_count, 3, 3, generator=gen, dtype=F64)
    compliance = 1e-7 * (torch.eye(3, dtype=F64) + m @ m.transpose(-1, -2))  # SPD
    lam = 1e-3 * torch.randn(tri_count, 3, generator=gen, dtype=F64)
    order, offsets = _coloring(faces)
    args = [x, lam, w, faces, rest_inv, compliance, order, offsets]
    return [t.to(dtype) if t.is_floating_point() else t for t in args] + [DT]


def _bend_problem(n: int, seed: int = 0, dtype=F64):
    """Arguments of bend_project_, with two degenerate quads appended (zero edge, zero normal)."""
    gen = torch.Generator().manual_seed(seed)
    _, x, faces = _sheet_mesh(n, gen)
    quads = _edge_quads(faces)
    # Two degenerate quads on 8 extra vertices that nothing else touches: a zero hinge edge (v0 = v1)
    # and a zero normal (v2 = v0).
    extra = x.shape[0]
    x = torch.cat((x, x[[5, 5, 6, 7, 8, 9, 8, 10]]), dim=0)
    quads = torch.cat((quads, extra + torch.arange(8).reshape(2, 4)), dim=0)
    vert_count = x.shape[0]
    edge_count = quads.shape[0]
    w = 0.5 + 1.5 * torch.rand(vert_count, generator=gen, dtype=F64)
    w[quads[0]] = 0.0  # a fully pinned quad: lam still moves, x does not
    rest_angle = 0.3 * (2.0 * torch.rand(edge_count, generator=gen, dtype=F64) - 1.0)
    compliance = 1e-3 * (0.5 + torch.rand(edge_count, generator=gen, dtype=F64))
    lam = 1e-4 * torch.randn(edge_count, generator=gen, dtype=F64)
    order, offsets = _coloring(quads)
    args = [x, lam, w, quads, rest_angle, compliance, order, offsets]
    return [t.to(dtype) if t.is_floating_point() else t for t in args] + [DT]


def _jacobi_args(args, omega=0.8):
    """Gauss-Seidel arguments -> Jacobi arguments (drop order/offsets, add omega)."""
    return [*args[:6], args[8], omega]


def _run(fn, args, passes: int):
    """Copies of x and lam after `passes` calls of fn (the inputs are left untouched)."""
    x, lam = args[0].clone(), args[1].clone()
    for _ in range(passes):
        fn(x, lam, *args[2:])
    return x, lam


PROJECTIONS = {
    # name: (problem builder, Jacobi?)
    "stretch_project_": (_stretch_problem, False),
    "stretch_project_jacobi_": (_stretch_problem, True),
    "bend_project_": (_bend_problem, False),
    "bend_project_jacobi_": (_bend_problem, True),
}


def _problem(name, n, dtype=F64, seed=0):
    builder, jacobi = PROJECTIONS[name]
    args = builder(n, seed=seed, dtype=dtype)
    return _jacobi_args(args) if jacobi else args


# -------------------------------------------------------------------------------------- projections


@pytest.mark.parametrize("name", sorted(PROJECTIONS))
def test_projection_matches_reference_float64(name):
    args = _problem(name, 9)
    x_cpp, lam_cpp = _run(_op(name), args, passes=6)
    x_ref, lam_ref = _run(getattr(reference, name), args, passes=6)
    assert (x_ref - args[0]).abs().max() > 1e-3, "the problem must actually move the vertices"
    torch.testing.assert_close(x_cpp, x_ref, rtol=0.0, atol=1e-10)
    torch.testing.assert_close(lam_cpp, lam_ref, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("name", sorted(PROJECTIONS))
def test_projection_matches_reference_float32(name):
    args = _problem(name, 9, dtype=torch.float32)
    x_cpp, lam_cpp = _run(_op(name), args, passes=3)
    x_ref, lam_ref = _run(getattr(reference, name), args, passes=3)
    assert x_cpp.dtype == torch.float32
    torch.testing.assert_close(x_cpp, x_ref, rtol=0.0, atol=1e-4)
    scale = lam_ref.abs().max().item()
    torch.testing.assert_close(lam_cpp, lam_ref, rtol=0.0, atol=1e-3 * scale)


def test_skipped_constraints_leave_their_state_alone():
    # stretch: the fully pinned triangle 0 keeps its lam; bend: degenerate quads keep theirs,
    # the fully pinned quad 0 updates lam but moves no vertex.
    args = _stretch_problem(6)
    x, lam = _run(_op("stretch_project_"), args, passes=1)
    assert torch.equal(lam[0], args[1][0])
    args = _bend_problem(6)
    x, lam = _run(_op("bend_project_"), args, passes=1)
    assert torch.equal(lam[-2:], args[1][-2:])
    assert lam[0] != args[1][0]
    assert torch.equal(x[args[3][0]], args[0][args[3][0]])


@pytest.mark.parametrize("name", sorted(PROJECTIONS))
def test_projection_is_identical_with_two_threads(name):
    # 24 x 24 vertices: 1,058 triangles / ~1,600 edges, above the kernels' OpenMP threshold.
    args = _problem(name, 24)
    fn = _op(name)
    previous = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        x1, lam1 = _run(fn, args, passes=2)
        torch.set_num_threads(2)
        x2, lam2 = _run(fn, args, passes=2)
    finally:
        torch.set_num_threads(previous)
    assert torch.equal(x1, x2) and torch.equal(lam1, lam2)
    x_ref, _ = _run(getattr(reference, name), args, passes=2)
    torch.testing.assert_close(x1, x_ref, rtol=0.0, atol=1e-10)


@pytest.mark.parametrize("name", sorted(PROJECTIONS))
def test_projection_opcheck(name):
    args = _problem(name, 5)
    torch.library.opcheck(_op(name).default, (args[0].clone(), args[1].clone(), *args[2:]))


def test_projection_rejects_bad_arguments():
    args = _stretch_problem(5)
    op = _op("stretch_project_")
    with pytest.raises(RuntimeError, match="tri_vertices must be"):
        op(args[0].clone(), args[1].clone(), args[2], args[3].int(), *args[4:])
    with pytest.raises(RuntimeError, match="lam must have shape"):
        op(args[0].clone(), args[1][:-1].clone(), *args[2:])
    bad_faces = args[3].clone()
    bad_faces[3, 1] = args[0].shape[0]
    with pytest.raises(RuntimeError, match="indices outside"):
        op(args[0].clone(), args[1].clone(), args[2], bad_faces, *args[4:])
    with pytest.raises(RuntimeError, match="color_offsets"):
        op(args[0].clone(), args[1].clone(), *args[2:7], args[7].flip(0), args[8])
    with pytest.raises(RuntimeError, match="contiguous"):
        op(args[0].t().contiguous().t(), args[1].clone(), *args[2:])


# ------------------------------------------------------------------------------------ closest point


def _closest_points(verts, faces, tri, bary):
    """(N, 3) points on the mesh given by (tri, bary); rows with tri = -1 are nan."""
    q = (bary[:, :, None] * verts[faces[tri.clamp_min(0)]]).sum(1)
    return torch.where((tri >= 0)[:, None], q, torch.full_like(q, math.nan))


def _assert_same_closest(points, verts, faces, got, want, atol=1e-10):
    """Same hit set, same distances and same closest points (the triangle may differ on ties)."""
    tri, bary, dist = got
    assert tri.dtype == torch.int64 and bary.shape == (points.shape[0], 3)
    assert torch.equal(tri >= 0, want[0] >= 0)
    hit = tri >= 0
    torch.testing.assert_close(dist, want[2], rtol=0.0, atol=atol)
    q = _closest_points(verts, faces, tri, bary)
    torch.testing.assert_close(q[hit], _closest_points(verts, faces, *want[:2])[hit], rtol=0.0, atol=atol)
    torch.testing.assert_close((points - q)[hit].norm(dim=-1), dist[hit], rtol=0.0, atol=atol)
    assert (bary[hit] >= -1e-12).all() and torch.allclose(bary[hit].sum(-1), torch.ones_like(dist[hit]))
    assert torch.equal(bary[~hit], torch.zeros_like(bary[~hit])) and torch.isinf(dist[~hit]).all()


def _triangle_soup(count: int, gen: torch.Generator):
    """Random triangles of widely varying size in the unit cube: verts (3 count, 3), faces (count, 3)."""
    centers = torch.rand(count, 1, 3, generator=gen, dtype=F64)
    sizes = 0.3 * torch.rand(count, 1, 1, generator=gen, dtype=F64) ** 3
    verts = (centers + sizes * torch.randn(count, 3, 3, generator=gen, dtype=F64)).reshape(-1, 3)
    return verts, torch.arange(3 * count).reshape(count, 3)


def test_closest_point_matches_reference_on_sheet():
    gen = torch.Generator().manual_seed(1)
    _, verts, faces = _sheet_mesh(16, gen)
    points = verts[torch.randint(0, verts.shape[0], (600,), generator=gen)]
    points = points + 0.03 * torch.randn(points.shape, generator=gen, dtype=F64)
    op = _op("closest_point_on_mesh")
    for max_dist in (0.02, 0.05, math.inf):
        got = op(points, verts, faces, max_dist)
        want = reference.closest_point_on_mesh(points, verts, faces, max_dist)
        _assert_same_closest(points, verts, faces, got, want)
    assert 0 < (got[0] >= 0).sum() == points.shape[0]  # max_dist = inf: every point hits


def test_closest_point_matches_reference_on_triangle_soup():
    gen = torch.Generator().manual_seed(2)
    verts, faces = _triangle_soup(400, gen)
    points = 1.4 * torch.rand(800, 3, generator=gen, dtype=F64) - 0.2  # some outside the mesh's box
    op = _op("closest_point_on_mesh")
    for max_dist in (0.01, 0.1, math.inf):
        got = op(points, verts, faces, max_dist)
        want = reference.closest_point_on_mesh(points, verts, faces, max_dist)
        _assert_same_closest(points, verts, faces, got, want)
    got = op(points.float(), verts.float(), faces, 0.1)
    want = reference.closest_point_on_mesh(points, verts, faces, 0.1)
    assert got[1].dtype == torch.float32 and got[2].dtype == torch.float32
    far = (want[2] - 0.1).abs() > 1e-5  # away from the search radius, float32 agrees on the hit set
    assert torch.equal((got[0] >= 0)[far], (want[0] >= 0)[far])
    both = (got[0] >= 0) & (want[0] >= 0)
    torch.testing.assert_close(got[2][both].double(), want[2][both], rtol=0.0, atol=1e-5)


@pytest.mark.parametrize("mesh_kind", ["sphere", "soup"])
def test_closest_point_matches_trimesh(mesh_kind):
    trimesh = pytest.importorskip("trimesh")
    gen = torch.Generator().manual_seed(3)
    if mesh_kind == "sphere":
        sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
        verts = torch.as_tensor(sphere.vertices, dtype=F64)
        faces = torch.as_tensor(sphere.faces, dtype=torch.int64)
        points = torch.randn(500, 3, generator=gen, dtype=F64)
        points = points / points.norm(dim=-1, keepdim=True) * (0.05 + 0.5 * torch.rand(500, 1, generator=gen))
    else:
        verts, faces = _triangle_soup(300, gen)
        points = torch.rand(500, 3, generator=gen, dtype=F64)
    mesh = trimesh.Trimesh(vertices=verts.numpy(), faces=faces.numpy(), process=False)
    closest, distance, _ = trimesh.proximity.closest_point(mesh, points.numpy())
    tri, bary, dist = _op("closest_point_on_mesh")(points, verts, faces, math.inf)
    assert (tri >= 0).all()
    torch.testing.assert_close(dist, torch.as_tensor(distance), rtol=0.0, atol=1e-9)
    # Random queries have a unique closest point (ties have probability zero), so the points agree too.
    q = _closest_points(verts, faces, tri, bary)
    torch.testing.assert_close(q, torch.as_tensor(closest), rtol=0.0, atol=1e-7)


def test_closest_point_edge_cases():
    op = _op("closest_point_on_mesh")
    verts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=F64)
    faces = torch.tensor([[0, 1, 2]])
    points = torch.tensor([[0.2, 0.2, 0.5], [5.0, 5.0, 5.0], [-1.0, -1.0, 0.0], [0.2, 0.3, 0.0]], dtype=F64)
    tri, bary, dist = op(points, verts, faces, 1.5)
    assert tri.tolist() == [0, -1, 0, 0]
    torch.testing.assert_close(dist[[0, 2, 3]], torch.tensor([0.5, math.sqrt(2.0), 0.0], dtype=F64))
    torch.testing.assert_close(bary[0], torch.tensor([0.6, 0.2, 0.2], dtype=F64))
    torch.testing.assert_close(bary[2], torch.tensor([1.0, 0.0, 0.0], dtype=F64))
    assert math.isinf(dist[1]) and torch.equal(bary[1], torch.zeros(3, dtype=F64))
    tri, bary, dist = op(points, verts, faces.new_zeros(0, 3), 1.0)  # no faces
    assert (tri == -1).all() and torch.isinf(dist).all()
    tri, bary, dist = op(points[:0], verts, faces, 1.0)  # no points
    assert tri.shape == (0,) and bary.shape == (0, 3) and dist.shape == (0,)
    with pytest.raises(RuntimeError, match="max_dist"):
        op(points, verts, faces, -1.0)
    with pytest.raises(RuntimeError, match="verts must be"):
        op(points, verts.float(), faces, 1.0)


def test_closest_point_opcheck():
    gen = torch.Generator().manual_seed(4)
    verts, faces = _triangle_soup(20, gen)
    points = torch.rand(30, 3, generator=gen, dtype=F64)
    torch.library.opcheck(_op("closest_point_on_mesh").default, (points, verts, faces, 0.2))


@pytest.mark.anny
def test_closest_point_on_anny_body(default_body):
    verts, faces = default_body
    gen = torch.Generator().manual_seed(5)
    points = verts[torch.randint(0, verts.shape[0], (300,), generator=gen)]
    points = points + 0.02 * torch.randn(points.shape, generator=gen, dtype=F64)
    got = _op("closest_point_on_mesh")(points, verts, faces, 0.03)
    want = reference.closest_point_on_mesh(points, verts, faces, 0.03)
    _assert_same_closest(points, verts, faces, got, want)
    assert (got[0] >= 0).float().mean() > 0.8


# ------------------------------------------------------------------------------------ fused substeps


def _sphere(dtype=F64):
    trimesh = pytest.importorskip("trimesh")
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    return torch.as_tensor(s.vertices, dtype=dtype), torch.as_tensor(s.faces, dtype=torch.int64)


def _substep_args(case: str, dtype=F64, monkeypatch=None):
    """(x, v, inputs): the exact `SubstepInputs` that `XPBDSolver.step` passes to `ops.xpbd_substeps_` in a
    state where every constraint kind is active: ``"sphere"`` a perturbed, moving sheet pressed onto a
    sphere (contacts, friction), ``"tube"`` an open stitched tube with its waist attached (stitches with
    the bounded pull, attachments), ``"jacobi"`` the sphere case with the Jacobi scheme."""
    from torch_diffavatar.sim.material import ClothMaterial
    from torch_diffavatar.sim.model import ClothModelBuilder
    from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver
    from torch_diffavatar.sim.state import ClothState
    from torch_diffavatar.sim.testing import rectangle_garment, tube_garment

    gen = torch.Generator().manual_seed(7)
    kw = {}
    if case in ("sphere", "jacobi"):
        mat = ClothMaterial(
            k_uu=800.0, k_vv=600.0, k_uv=100.0, bend_stiffness=1e-4, thickness=0.005, friction=0.4
        )
        g = rectangle_garment(10, 10, 0.6, 0.6, origin=(-0.3, 0.31, 0.3))
        model = ClothModelBuilder(mat).add_garment(g).finalize(dtype=dtype)
        kw["body_verts"], kw["body_faces"] = _sphere(dtype)
    else:
        mat = ClothMaterial(k_uu=500.0, k_vv=500.0, k_uv=100.0, bend_stiffness=1e-5)
        g = tube_garment(nx=6, ny=6, width=0.3, height=0.3, gap=0.08, y0=1.0)
        model = ClothModelBuilder(mat).add_garment(g, merge_seams=False).finalize(dtype=dtype)
        kw["stitch_compliance"] = 1e-4
        assert model.stitch_vertices.shape[0] > 0 and model.attach_vertices.shape[0] > 0
    rest = model.rest_data(g.vert_uv.to(dtype))
    x0 = model.vert_init_pos
    x = x0 + 0.004 * torch.randn(x0.shape, generator=gen, dtype=F64).to(dtype)
    v = 0.3 * torch.randn(x0.shape, generator=gen, dtype=F64).to(dtype)
    v[:, 1] -= 0.5
    cfg = XPBDConfig(substeps=6, iterations=2, scheme="jacobi" if case == "jacobi" else "gauss_seidel")
    captured = []
    monkeypatch.setattr(ops, "xpbd_substeps_", lambda *args, use_extension=True: captured.append(args))
    XPBDSolver(model, cfg).step(ClothState(x, v), rest, 1 / 60, **kw)
    monkeypatch.undo()
    (args,) = captured
    return args


def _with_params(inputs, **params):
    """``inputs`` with some `SubstepParams` fields replaced."""
    return dataclasses.replace(inputs, params=dataclasses.replace(inputs.params, **params))


def _run_substeps(fn, args, **params):
    """(x, v) after fn(x, v, *inputs.op_args()) on copies of x and v; keywords replace `SubstepParams`
    fields."""
    x, v, inputs = args
    x, v = x.clone(), v.clone()
    fn(x, v, *_with_params(inputs, **params).op_args())
    return x, v


@pytest.mark.parametrize("case", ["sphere", "tube", "jacobi"])
def test_xpbd_substeps_matches_reference_float64(case, monkeypatch):
    args = _substep_args(case, monkeypatch=monkeypatch)
    x0, _, inputs = args
    if case != "tube":
        assert inputs.body.contact_vert.numel() > 10, "the problem must have body contacts"
        assert inputs.params.friction > 0, "and friction"
    x_cpp, v_cpp = _run_substeps(_op("xpbd_substeps_"), args)
    x_ref, v_ref = _run_substeps(reference.xpbd_substeps_, args)
    assert (x_ref - x0).abs().max() > 1e-3, "the problem must actually move the vertices"
    torch.testing.assert_close(x_cpp, x_ref, rtol=0.0, atol=1e-10)
    torch.testing.assert_close(v_cpp, v_ref, rtol=0.0, atol=1e-7)
    if case == "tube":  # the bounded stitch pull was active: gaps shrink, but by at most max_move per pass
        pairs = inputs.seams.stitch_vertices
        gap0 = (x0[pairs[:, 0]] - x0[pairs[:, 1]]).norm(dim=-1)
        gap1 = (x_cpp[pairs[:, 0]] - x_cpp[pairs[:, 1]]).norm(dim=-1)
        assert float(gap1.max()) < float(gap0.max()) - 1e-3


# Each coefficient changed on its own, in a case where it acts: the C++ op must read it where the Python
# layout (`SubstepParams.op_args`) puts it, or C++ and reference part ways.
_COEFFICIENT_CASES = [
    ("sphere", {"gravity": (1.5, -9.81, 0.0)}),
    ("sphere", {"gravity": (0.0, -4.0, 0.0)}),
    ("sphere", {"gravity": (0.0, -9.81, -2.0)}),
    ("sphere", {"velocity_decay": 0.9}),
    ("sphere", {"dt": 1 / 720}),
    ("tube", {"stitch_compliance": 1.0}),
    ("tube", {"stitch_max_move": 1e-4}),
    ("tube", {"stitch_snap": 0.2}),
    ("tube", {"attach_compliance": 1e-1}),
    ("sphere", {"thickness": 0.03}),
    ("sphere", {"friction": 2.0}),
    ("jacobi", {"jacobi_omega": 0.5}),
]


@pytest.mark.parametrize("case, params", _COEFFICIENT_CASES)
def test_xpbd_substeps_coefficients_reach_the_op(case, params, monkeypatch):
    args = _substep_args(case, monkeypatch=monkeypatch)
    x_before, _ = _run_substeps(_op("xpbd_substeps_"), args)
    x_cpp, v_cpp = _run_substeps(_op("xpbd_substeps_"), args, **params)
    x_ref, v_ref = _run_substeps(reference.xpbd_substeps_, args, **params)
    assert (x_cpp - x_before).abs().max() > 1e-6, f"{params} must change the result"
    torch.testing.assert_close(x_cpp, x_ref, rtol=0.0, atol=1e-10)
    torch.testing.assert_close(v_cpp, v_ref, rtol=0.0, atol=1e-7)


def test_substep_inputs_round_trip(monkeypatch):
    from torch_diffavatar.sim.substep import SubstepInputs

    _, _, inputs = _substep_args("sphere", monkeypatch=monkeypatch)
    back = SubstepInputs.from_op_args(*inputs.op_args())
    assert back.params == inputs.params
    for group in ("stretch", "bend", "seams", "body"):
        a, b = getattr(inputs, group), getattr(back, group)
        for f in dataclasses.fields(a):
            assert getattr(a, f.name) is getattr(b, f.name)
    args = list(inputs.op_args())
    args[1] = args[1][:-1]  # a stretch list without its colour offsets
    with pytest.raises(ValueError, match="StretchInputs takes 5 tensors"):
        SubstepInputs.from_op_args(*args)


def test_xpbd_substeps_matches_reference_float32(monkeypatch):
    args = _substep_args("sphere", dtype=torch.float32, monkeypatch=monkeypatch)
    x_cpp, v_cpp = _run_substeps(_op("xpbd_substeps_"), args)
    x_ref, v_ref = _run_substeps(reference.xpbd_substeps_, args)
    assert x_cpp.dtype == torch.float32
    torch.testing.assert_close(x_cpp, x_ref, rtol=0.0, atol=2e-5)
    torch.testing.assert_close(v_cpp, v_ref, rtol=0.0, atol=5e-3)


def test_xpbd_substeps_is_identical_with_two_threads(monkeypatch):
    args = _substep_args("sphere", monkeypatch=monkeypatch)
    x1, v1 = _run_substeps(_op("xpbd_substeps_"), args, num_threads=1)
    x2, v2 = _run_substeps(_op("xpbd_substeps_"), args, num_threads=2)
    assert torch.equal(x1, x2) and torch.equal(v1, v2)


def test_xpbd_substeps_opcheck(monkeypatch):
    x, v, inputs = _substep_args("tube", monkeypatch=monkeypatch)
    torch.library.opcheck(
        _op("xpbd_substeps_").default, (x.clone(), v.clone(), *_with_params(inputs, substeps=2).op_args())
    )


@pytest.mark.parametrize("case, bounce", [("sphere", 0.0), ("sphere", 0.5), ("jacobi", 0.0)])
def test_contact_bounce_reaches_the_op(case, bounce, monkeypatch):
    """``contact_bounce`` cuts the outward normal velocity of contacts pushed out in a substep, in the op
    as in the twin. A 3 cm thickness pushes the sheet's contacts outwards (its 5 mm, the sheet falling
    onto the sphere, leaves them moving inwards: nothing to cut)."""
    args = _substep_args(case, monkeypatch=monkeypatch)
    x_one, v_one = _run_substeps(_op("xpbd_substeps_"), args, thickness=0.03)
    x_cpp, v_cpp = _run_substeps(_op("xpbd_substeps_"), args, thickness=0.03, contact_bounce=bounce)
    x_ref, v_ref = _run_substeps(reference.xpbd_substeps_, args, thickness=0.03, contact_bounce=bounce)
    assert (x_cpp - x_one).abs().max() > 1e-5, "the bounce must change the result"
    torch.testing.assert_close(x_cpp, x_ref, rtol=0.0, atol=1e-10)
    torch.testing.assert_close(v_cpp, v_ref, rtol=0.0, atol=1e-7)
    # what it cuts is outward speed: the contacts leave the sphere more slowly
    _, _, inputs = args
    vert = inputs.body.contact_vert
    normal = x_cpp[vert] / x_cpp[vert].norm(dim=-1, keepdim=True)  # the sphere's outward normal
    out_one = (v_one[vert] * normal).sum(-1).clamp_min(0).sum()
    out_cut = (v_cpp[vert] * normal).sum(-1).clamp_min(0).sum()
    assert float(out_cut) < float(out_one)


def test_xpbd_substeps_opcheck_with_contacts_that_do_not_bounce(monkeypatch):
    x, v, inputs = _substep_args("sphere", monkeypatch=monkeypatch)
    params = {"substeps": 2, "contact_bounce": 0.0, "thickness": 0.03}
    torch.library.opcheck(
        _op("xpbd_substeps_").default, (x.clone(), v.clone(), *_with_params(inputs, **params).op_args())
    )


def test_xpbd_substeps_rejects_bad_arguments(monkeypatch):
    x, v, inputs = _substep_args("sphere", monkeypatch=monkeypatch)
    op = _op("xpbd_substeps_")

    def call(v=v, **groups):
        bad = inputs
        for group, fields in groups.items():
            bad = dataclasses.replace(bad, **{group: dataclasses.replace(getattr(bad, group), **fields)})
        op(x.clone(), v.clone(), *bad.op_args())

    body, stretch = inputs.body, inputs.stretch
    with pytest.raises(RuntimeError, match="v must"):
        call(v=v.float())
    with pytest.raises(RuntimeError, match="contact_tri holds indices outside"):
        call(body={"contact_tri": torch.full_like(body.contact_tri, body.body_faces.shape[0])})
    with pytest.raises(RuntimeError, match="contact_bary must have shape"):
        call(body={"contact_bary": body.contact_bary[:-1].contiguous()})
    with pytest.raises(RuntimeError, match="tri_order"):
        call(stretch={"tri_order": stretch.tri_order + stretch.tri_vertices.shape[0]})
    args = list(inputs.op_args())
    with pytest.raises(RuntimeError, match="coefficients must hold 13"):
        op(x.clone(), v.clone(), *args[:5], args[5][:-1], *args[6:])
    with pytest.raises(RuntimeError, match="bend must hold 5 tensors"):
        op(x.clone(), v.clone(), args[0], args[1], args[2][:4], *args[3:])


def test_unfused_composition_matches_fused_op(monkeypatch):
    # the benchmark's "before" path: per-constraint C++ ops composed in Python
    args = _substep_args("sphere", monkeypatch=monkeypatch)
    x_cpp, v_cpp = _run_substeps(_op("xpbd_substeps_"), args)
    x, v, inputs = args
    x, v = reference.xpbd_substeps(x, v, inputs, reference.KernelMembrane(inputs, ops))
    torch.testing.assert_close(x, x_cpp, rtol=0.0, atol=1e-10)
    torch.testing.assert_close(v, v_cpp, rtol=0.0, atol=1e-7)


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_max_abs_green_strain_matches_reference(dtype):
    from torch_diffavatar.sim.constraints import green_strain

    args = _stretch_problem(8, dtype=dtype)
    x, faces, rest_inv = args[0], args[3], args[4]
    got = _op("max_abs_green_strain")(x, faces, rest_inv)
    want = reference.max_abs_green_strain(x, faces, rest_inv)
    assert got.shape == () and got.dtype == dtype and float(want) > 0.01
    torch.testing.assert_close(got, want, rtol=1e-6, atol=0.0)
    torch.testing.assert_close(want, green_strain(x, faces, rest_inv).abs().max(), rtol=1e-6, atol=0.0)
    assert float(_op("max_abs_green_strain")(x, faces[:0], rest_inv[:0])) == 0.0
    x_nan = x.clone()
    x_nan[faces[3, 0], 1] = float("nan")
    assert torch.isnan(_op("max_abs_green_strain")(x_nan, faces, rest_inv))
    torch.library.opcheck(_op("max_abs_green_strain").default, (x, faces, rest_inv))


@pytest.mark.parametrize("use_extension", [True, False])
def test_sub_millimetre_triangles_in_float32(use_extension):
    # GarmentCode outlines can have sub-mm edges (0.9 mm at a jumpsuit's waist): inverse masses ~1e7 make
    # the stretch systems' entries ~1e14, and the adjugate's determinant (~ entry^3) overflowed float32 —
    # the step returned NaN (C++) or skipped the constraint. The solve is scaled there: float32 now follows
    # float64 (and every larger triangle is solved exactly as before).
    from torch_diffavatar.sim.model import ClothModelBuilder
    from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver
    from torch_diffavatar.sim.state import ClothState
    from torch_diffavatar.sim.testing import rectangle_garment

    g = rectangle_garment(5, 5, 0.002, 0.002)
    out = {}
    for dtype in (F64, torch.float32):
        model = ClothModelBuilder().add_garment(g).finalize(dtype=dtype)
        rest = model.rest_data(g.vert_uv.to(dtype))
        assert float(rest.vert_inv_mass.max()) > 1e7
        x0 = model.vert_init_pos * torch.tensor([1.3, 1.0, 0.8], dtype=dtype)  # stretched and squashed
        solver = XPBDSolver(model, XPBDConfig(substeps=4, iterations=2, use_extension=use_extension))
        s = solver.step(ClothState(x0, torch.zeros_like(x0)), rest, 1 / 60, gravity_scale=0.0)
        out[dtype] = (x0, s.x.to(F64))
    x0, x64 = out[F64]
    assert (x64 - x0).abs().max() > 1e-4  # the constraints act (the sheet is 2 mm wide)
    torch.testing.assert_close(out[torch.float32][1], x64, rtol=0.0, atol=2e-6)
