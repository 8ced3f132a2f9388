"""The equilibrium adjoint's fast path: closed-form element Hessians (C++) against their autograd twins, the
cached CSR pattern against the reference assembly, the block sparse Cholesky against dense and SuperLU
solves, and the projected-Hessian gradient of a drape with and without the extension."""

from __future__ import annotations

import math

import pytest
import torch
from test_adjoint import DT, KB, material, settle_config, sheet_on_sphere

from torch_diffavatar._ext import has_extension
from torch_diffavatar.sim import energy, ops, reference
from torch_diffavatar.sim.adjoint import EquilibriumOptions
from torch_diffavatar.sim.adjoint.linsolve import solve_symmetric, vertex_ordering
from torch_diffavatar.sim.constraints import membrane_stiffness
from torch_diffavatar.sim.differentiable import drape
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.testing import tube_garment

requires_extension = pytest.mark.skipif(not has_extension(), reason="C++ extension not built")


def _op(name):
    op = ops.extension_op(name)  # also registers the fake kernel
    assert op is not None, f"torch.ops.diffavatar.{name} is not registered"
    return op


@pytest.fixture(scope="module")
def tube():
    """An open-seam tube (stitches), its waist row pinned, crumpled so that blocks are indefinite."""
    g = tube_garment(6, 6, 0.3, 0.3, gap=0.04, y0=0.0)
    pins = torch.arange(30, 36)
    model = ClothModelBuilder(material()).add_garment(g, merge_seams=False, pinned=pins).finalize(dtype=DT)
    gen = torch.Generator().manual_seed(3)
    x = model.vert_init_pos + 0.02 * torch.randn(model.vert_init_pos.shape, generator=gen, dtype=DT)
    x[:, 0] *= 0.8  # compressed across: stretch blocks with negative eigenvalues
    rest = model.rest_data(g.vert_uv.to(DT))
    return model, rest, x


def _stretch_args(model, rest, x):
    k = membrane_stiffness(model.material, x)
    return (x, model.tri_vertices, rest.tri_rest_inv.contiguous(), rest.tri_area, k)


def _bend_args(model, rest, x):
    # rest angles off the current ones so the (θ − θ̄) ∇²θ term matters
    return (x, model.edge_quads, rest.edge_weight, rest.edge_rest_angle + 0.3, KB)


def _relative_block_error(a, b):
    return float(((a - b).abs().amax((1, 2)) / b.abs().amax((1, 2)).clamp_min(1e-300)).max())


@requires_extension
@pytest.mark.parametrize("project", [False, True])
def test_element_hessians_match_reference(tube, project):
    model, rest, x = tube
    for name, args in (("stretch_hessians", _stretch_args(*tube)), ("bend_hessians", _bend_args(*tube))):
        op = _op(name)
        got = op(*args, project)
        want = getattr(reference, name)(*args, project)
        assert got.shape == want.shape and got.dtype == DT
        assert _relative_block_error(got, want) < 1e-10, name
        # float32 inputs give float32 blocks, computed in double inside: the reference on the same
        # (rounded) inputs in float64 agrees to float32 output rounding
        args32 = tuple(a.float() if torch.is_tensor(a) and a.is_floating_point() else a for a in args)
        got32 = op(*args32, project)
        assert got32.dtype == torch.float32
        args64 = tuple(a.double() if torch.is_tensor(a) and a.is_floating_point() else a for a in args32)
        want32 = getattr(reference, name)(*args64, project)
        assert _relative_block_error(got32.double(), want32) < 1e-6, name
        torch.library.opcheck(op.default, (*args, project))


@requires_extension
def test_projection_is_psd_and_not_trivial(tube):
    for name, args in (("stretch_hessians", _stretch_args(*tube)), ("bend_hessians", _bend_args(*tube))):
        raw = (
            ops.stretch_hessians(*args, False)
            if name == "stretch_hessians"
            else ops.bend_hessians(*args, False)
        )
        proj = getattr(ops, name)(*args, True)
        scale = raw.abs().amax((1, 2))
        raw_min = torch.linalg.eigvalsh(raw).min(-1).values / scale
        assert bool((raw_min < -1e-6).any()), (
            f"{name}: no indefinite block, the test would not see projection"
        )
        assert float((torch.linalg.eigvalsh(proj).min(-1).values / scale).min()) > -1e-12
        # projection keeps the PSD blocks and the translation null space
        keep = raw_min > 1e-9
        torch.testing.assert_close(proj[keep], raw[keep], rtol=1e-10, atol=1e-10 * float(scale.max()))
        t = torch.zeros(proj.shape[1], dtype=DT)
        t[0::3] = 1.0
        assert float((proj @ t).abs().max()) < 1e-9 * float(scale.max())


def test_bending_blocks_have_the_hinge_null_vector(tube):
    """The bending kernel projects in the complement of v_a = ((x_a − x_0)·ê) ê (every vertex slid along the
    hinge ê = (x_1 − x_0)/|x_1 − x_0|, leaving θ unchanged) besides the translations: v must be a null
    vector of the exact block (the autograd twin's), and the projected block must keep it null."""
    model, rest, x = tube
    args = _bend_args(*tube)
    xq = x[model.edge_quads]  # (E, 4, 3)
    e = xq[:, 1] - xq[:, 0]
    eh = e / e.norm(dim=1, keepdim=True)
    c = ((xq - xq[:, :1]) * eh[:, None]).sum(-1)  # (E, 4)
    v = (c[:, :, None] * eh[:, None, :]).reshape(-1, 12)
    assert float((c - c.mean(1, keepdim=True)).abs().amax(1).min()) > 1e-3  # not a translation

    def worst(h):  # max over edges of |H v| / (max|H| |v|)
        return float(
            ((h @ v[:, :, None]).squeeze(-1).norm(dim=1) / (h.abs().amax((1, 2)) * v.norm(dim=1))).max()
        )

    assert worst(reference.bend_hessians(*args, False)) < 1e-12
    assert worst(reference.bend_hessians(*args, True)) < 1e-12
    if has_extension():
        assert worst(ops.bend_hessians(*args, True)) < 1e-12


def test_pattern_assembly_matches_reference(tube):
    model, rest, x = tube
    params = energy.EnergyParams()
    free_vert = rest.vert_inv_mass > 0
    assert not bool(free_vert.all()) and model.stitch_vertices.shape[0] > 0
    blocks = energy.hessian_blocks(x, model, rest, model.material, params, project=True)
    gen = torch.Generator().manual_seed(0)
    ids = torch.tensor([0, 7, 7, 33])  # a repeated vertex and a pinned one
    extra = torch.randn(4, 3, 3, generator=gen, dtype=DT)
    blocks = energy.HessianBlocks(
        blocks.tri, blocks.edge, blocks.stitch, [*blocks.vert, (ids, extra + extra.mT)]
    )
    pattern = energy.hessian_pattern(model, free_vert)
    val = pattern.assemble(blocks, 0.25)
    free_dof = free_vert[:, None].expand(-1, 3).reshape(-1)
    index = torch.full(free_dof.shape, -1, dtype=torch.int64)
    index[free_dof] = torch.arange(int(free_dof.sum()))
    elements = [(energy._dofs(model.tri_vertices), blocks.tri), (energy._dofs(model.edge_quads), blocks.edge)]
    elements += [(energy._dofs(model.stitch_vertices), blocks.stitch)]
    elements += [(energy._dofs(i[:, None]), b) for i, b in blocks.vert]
    elements += [
        (torch.arange(free_dof.shape[0])[:, None], torch.full((free_dof.shape[0], 1, 1), 0.25, dtype=DT))
    ]
    crow, col, ref = energy.assemble_csr(elements, index, int(free_dof.sum()))
    assert torch.equal(crow, pattern.crow) and torch.equal(col, pattern.col)
    torch.testing.assert_close(val, ref, rtol=1e-13, atol=0)
    # one pattern per (model, free set)
    assert energy.hessian_pattern(model, free_vert) is pattern
    other = free_vert.clone()
    other[0] = False
    assert energy.hessian_pattern(model, other) is not pattern


def _spd_system(tube, shift=1e-3):
    model, rest, x = tube
    free_vert = rest.vert_inv_mass > 0
    pattern = energy.hessian_pattern(model, free_vert)
    blocks = energy.hessian_blocks(x, model, rest, model.material, energy.EnergyParams(), project=True)
    val = pattern.assemble(blocks, shift * blocks.max_diagonal())
    b = torch.sin(torch.arange(pattern.crow.shape[0] - 1, dtype=DT))
    return pattern, val, b


def _diagonal(pattern):
    """(nnz,) bool: the diagonal entries of the pattern."""
    n = pattern.crow.shape[0] - 1
    return pattern.col == torch.repeat_interleave(torch.arange(n), pattern.crow[1:] - pattern.crow[:-1])


def _dense(crow, col, val):
    n = crow.shape[0] - 1
    row = torch.repeat_interleave(torch.arange(n), crow[1:] - crow[:-1])
    a = torch.zeros(n, n, dtype=val.dtype)
    a[row, col] = val
    return a


@requires_extension
def test_block_cholesky_matches_dense(tube):
    pattern, val, b = _spd_system(tube)
    perm = vertex_ordering(pattern.crow, pattern.col)
    assert sorted(perm.tolist()) == list(range(perm.shape[0]))
    analyze, solve = _op("block_cholesky_analyze"), _op("block_cholesky_solve")
    parent, colptr = analyze(pattern.crow, pattern.col, perm)
    parent_ref, colptr_ref = reference.block_cholesky_analyze(pattern.crow, pattern.col, perm)
    assert torch.equal(parent, parent_ref) and torch.equal(colptr, colptr_ref)
    exact = torch.linalg.solve(_dense(pattern.crow, pattern.col, val), b)
    x, info = solve(pattern.crow, pattern.col, val, b, perm, parent, colptr)
    x_ref, info_ref = reference.block_cholesky_solve(pattern.crow, pattern.col, val, b, perm, parent, colptr)
    assert int(info[2]) == 0 and float(info[1]) < 1e-12 and float(info[3]) > 0
    torch.testing.assert_close(x, exact, rtol=1e-10, atol=1e-12 * float(exact.abs().max()))
    torch.testing.assert_close(x, x_ref, rtol=1e-10, atol=1e-12 * float(exact.abs().max()))
    # any ordering gives the same answer (the identity: more fill)
    ident = torch.arange(perm.shape[0])
    p2, c2 = analyze(pattern.crow, pattern.col, ident)
    assert int(c2[-1]) >= int(colptr[-1])
    x2, _ = solve(pattern.crow, pattern.col, val, b, ident, p2, c2)
    torch.testing.assert_close(x2, exact, rtol=1e-10, atol=1e-12 * float(exact.abs().max()))
    # float32 values: same answer to float32 accuracy
    x32, _ = solve(pattern.crow, pattern.col, val.float(), b.float(), perm, parent, colptr)
    assert x32.dtype == torch.float32
    torch.testing.assert_close(x32.double(), exact, rtol=1e-3, atol=1e-3 * float(exact.abs().max()))
    torch.library.opcheck(analyze.default, (pattern.crow, pattern.col, perm))
    torch.library.opcheck(solve.default, (pattern.crow, pattern.col, val, b, perm, parent, colptr))


@requires_extension
def test_block_cholesky_factor_then_apply(tube):
    """The factor kept and applied later solves as the one-call solve does (bit for bit), matches its
    dense twin, and refuses a layout that is not a factor."""
    pattern, val, b = _spd_system(tube)
    perm = vertex_ordering(pattern.crow, pattern.col)
    parent, colptr = ops.block_cholesky_analyze(pattern.crow, pattern.col, perm)
    factor, apply = _op("block_cholesky_factor"), _op("block_cholesky_apply")
    l_row, l_val, info = factor(pattern.crow, pattern.col, val, perm, parent, colptr)
    assert int(info[2]) == 0 and l_val.shape == (int(colptr[-1]), 9)
    x_once, _ = ops.block_cholesky_solve(pattern.crow, pattern.col, val, b, perm, parent, colptr)
    assert torch.equal(apply(l_row, l_val, perm, colptr, b), x_once)
    r_row, r_val, r_info = reference.block_cholesky_factor(
        pattern.crow, pattern.col, val, perm, parent, colptr
    )
    assert torch.equal(r_row, l_row) and int(r_info[2]) == 0
    torch.testing.assert_close(r_val, l_val, rtol=1e-9, atol=1e-9 * float(l_val.abs().max()))
    x_ref = reference.block_cholesky_apply(l_row, l_val, perm, colptr, b)
    torch.testing.assert_close(x_ref, x_once, rtol=1e-10, atol=1e-12 * float(x_once.abs().max()))
    b2 = torch.cos(torch.arange(b.shape[0], dtype=DT))  # a second right-hand side, the factor reused
    exact = torch.linalg.solve(_dense(pattern.crow, pattern.col, val), b2)
    torch.testing.assert_close(apply(l_row, l_val, perm, colptr, b2), exact, rtol=1e-10, atol=1e-12)
    bad = torch.where(_diagonal(pattern), val - 2.0 * float(val.abs().max()), val)
    _, nan_val, bad_info = factor(pattern.crow, pattern.col, bad, perm, parent, colptr)
    assert int(bad_info[2]) == 3 and bool(nan_val.isnan().all())
    with pytest.raises(RuntimeError, match="not a block Cholesky factor"):
        apply(l_row.flip(0), l_val, perm, colptr, b)
    torch.library.opcheck(factor.default, (pattern.crow, pattern.col, val, perm, parent, colptr))
    torch.library.opcheck(apply.default, (l_row, l_val, perm, colptr, b))


@requires_extension
def test_block_cholesky_reports_indefinite_and_bad_structure(tube):
    pattern, val, b = _spd_system(tube)
    perm = vertex_ordering(pattern.crow, pattern.col)
    parent, colptr = ops.block_cholesky_analyze(pattern.crow, pattern.col, perm)
    diag = pattern.col == torch.repeat_interleave(
        torch.arange(b.shape[0]), pattern.crow[1:] - pattern.crow[:-1]
    )
    bad = torch.where(diag, val - 2.0 * float(val.abs().max()), val)  # negative definite
    x, info = ops.block_cholesky_solve(pattern.crow, pattern.col, bad, b, perm, parent, colptr)
    assert int(info[2]) == 3 and bool(x.isnan().all())
    _, info_ref = reference.block_cholesky_solve(pattern.crow, pattern.col, bad, b, perm, parent, colptr)
    assert int(info_ref[2]) == 3
    with pytest.raises(RuntimeError, match="block structure"):  # a scalar tridiagonal matrix
        n = 6
        crow = torch.tensor([0, 2, 5, 8, 11, 14, 16])
        col = torch.tensor([0, 1, 0, 1, 2, 1, 2, 3, 2, 3, 4, 3, 4, 5, 4, 5])
        ops.block_cholesky_analyze(crow, col, torch.arange(n // 3))


@requires_extension
def test_direct_solve_uses_the_cached_cholesky(tube):
    pattern, val, b = _spd_system(tube)
    cache: dict = {}
    x, info = solve_symmetric(pattern.crow, pattern.col, val, b, method="direct", tol=1e-12, cache=cache)
    assert info.method == "cholesky" and info.attempts == ("cholesky",) and info.residual < 1e-12
    perm = cache["perm"]
    x_lu, info_lu = solve_symmetric(pattern.crow, pattern.col, val, b, method="direct", tol=1e-12)
    assert info_lu.method == "direct"
    torch.testing.assert_close(x, x_lu, rtol=1e-10, atol=1e-12 * float(x_lu.abs().max()))
    solve_symmetric(pattern.crow, pattern.col, 2.0 * val, b, method="direct", tol=1e-12, cache=cache)
    assert cache["perm"] is perm  # the symbolic analysis is reused for new values
    # an indefinite matrix falls back to SuperLU
    diag = pattern.col == torch.repeat_interleave(
        torch.arange(b.shape[0]), pattern.crow[1:] - pattern.crow[:-1]
    )
    shifted = torch.where(diag, val - 0.5 * float(val[diag].min()) - 1e-3 * float(val.abs().max()), val)
    a = _dense(pattern.crow, pattern.col, shifted)
    assert float(torch.linalg.eigvalsh(a).min()) < 0
    x3, info3 = solve_symmetric(
        pattern.crow, pattern.col, shifted, b, method="direct", tol=1e-12, cache=cache
    )
    assert info3.attempts == ("cholesky", "direct") and info3.method == "direct"
    torch.testing.assert_close(x3, torch.linalg.solve(a, b), rtol=1e-8, atol=1e-10)


@requires_extension
def test_projected_adjoint_gradient_unchanged_by_the_fast_path():
    """The fit's adjoint (projected H, direct solve) with the C++ Hessians + block Cholesky equals the
    autograd Hessians + SuperLU path in float64."""
    g, model, body, faces = sheet_on_sphere()
    weights = torch.sin(torch.arange(model.vert_count * 3, dtype=DT)).reshape(-1, 3)
    grads = []
    for use_ext in (True, False):
        opts = EquilibriumOptions(
            hessian="projected", newton_iterations=0, active_set_rounds=1, solve_method="direct",
            use_extension=use_ext,
        )  # fmt: skip
        uv = g.vert_uv.to(DT).clone().requires_grad_(True)
        bv = body.clone().requires_grad_(True)
        log_kb = torch.tensor(math.log(KB), dtype=DT, requires_grad=True)
        stats: dict = {}
        x = drape(
            uv, model, bv, material(kb=log_kb.exp()), body_faces=faces, config=settle_config(15),
            adjoint="equilibrium", options=opts, stats=stats,
        )  # fmt: skip
        (x * weights).sum().backward()
        assert stats["adjoint_solve_method"] == ("cholesky" if use_ext else "direct")
        assert stats["adjoint_solve_residual"] < 1e-10
        grads.append((uv.grad, bv.grad, log_kb.grad))
    for fast, ref in zip(*grads):
        assert float(ref.abs().max()) > 0
        torch.testing.assert_close(fast, ref, rtol=1e-8, atol=1e-10 * float(ref.abs().max()))
