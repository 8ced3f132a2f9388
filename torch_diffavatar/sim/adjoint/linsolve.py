"""Sparse symmetric solves ``H x = b`` for the equilibrium adjoint and the Newton polish.

``H`` comes as CSR tensors (crow, col, val) over the free degrees of freedom. Methods (by name):

* ``"cg"`` / ``"minres"``: the C++ op ``torch.ops.diffavatar.sparse_sym_solve`` (csrc/adjoint_solve.cpp:
  Jacobi-preconditioned CG that stops on non-positive curvature, or |diag|-preconditioned MINRES for
  indefinite H, OpenMP mat-vecs), falling back to SciPy's ``cg``/``minres`` without the extension;
* ``"direct"``: given a ``cache`` (a matrix with 3×3 block structure, `energy.HessianPattern`) and the
  extension, the C++ block sparse Cholesky (``torch.ops.diffavatar.block_cholesky_factor``, then
  ``block_cholesky_apply``; its symbolic analysis and fill-reducing ordering are computed once and kept in
  the cache, the topology being fixed; the factor comes back in `SolveInfo.factor`, to solve again);
  otherwise, or when H is not positive definite, SciPy's sparse LU (SuperLU, ``scipy.sparse.linalg.splu``,
  symmetric mode);
* ``"auto"``: CG; when it meets non-positive curvature (H indefinite: compressed cloth, a saddle) or does
  not reach the tolerance, MINRES; when that fails too, the sparse LU.

Every answer carries a `SolveInfo`: whether the answering method met its own convergence test, the
relative residual ``|b − H x| / |b|`` and the normwise backward error ``‖b − H x‖∞ / (‖H‖∞ ‖x‖∞ + ‖b‖∞)``,
both recomputed explicitly, so that a caller can refuse a bad solve instead of returning garbage
(`check_solve`).

Why not the relative residual against the solve's own ``tol``: the methods stop on their own measure of
convergence, CG on its recursively updated residual (which drifts from ``b − H x`` by rounding), MINRES on
the residual in the norm of its diagonal preconditioner (the cloth's stiffness spread makes that norm
differ from the plain one). A solve that converged to ``tol`` therefore ends with a true relative residual
anywhere around ``tol`` or above it (1.15e-8 by CG for a 1e-8 target; 2.1e-8 by MINRES on a draped dress,
whose backward error was 5e-14), and comparing it with ``tol`` warned on about every other backward.
What decides whether the answer (the adjoint, hence the gradient) is usable is whether the method
converged, and, as a guard against accuracy lost to rounding, whether x solves a system within ``tol``
of H and b (the backward error, Rigal & Gaches 1967), which does not grow with the conditioning as the
relative residual does. Measured on stiff spring chains (condition 1e5–1e8, tests/sim/test_adjoint.py):
converged solves had forward errors 1e-10–3e-8 with relative residuals up to 4e-5, backward errors
below 1e-11; solves cut short by the iteration cap had forward errors 1e-7–1.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from torch_diffavatar._ext import has_extension
from torch_diffavatar.errors import SimulationError
from torch_diffavatar.sim import ops
from torch_diffavatar.sim.ops import extension_op

SOLVE_METHODS = ("auto", "cg", "minres", "direct")
_FAKE: list[bool] = []


def solve_op():
    """``torch.ops.diffavatar.sparse_sym_solve`` (with its fake kernel registered), or None without it."""
    if not has_extension() or not hasattr(torch.ops.diffavatar, "sparse_sym_solve"):
        return None
    if not _FAKE:
        _FAKE.append(True)

        def fake(crow, col, val, b, method, tol, max_iter):
            return torch.empty_like(b), b.new_empty((4,), dtype=torch.float64)

        try:
            torch.library.register_fake("diffavatar::sparse_sym_solve")(fake)
        except RuntimeError:
            pass  # already registered
    return torch.ops.diffavatar.sparse_sym_solve


@dataclass(frozen=True)
class SolveInfo:
    """Diagnostics of one solve.

    Attributes:
        method: the method that produced the answer; iterations: its iterations (0 for ``direct``);
        residual: ``|b − H x| / |b|``; indefinite: CG met a direction of non-positive curvature;
        attempts: the methods tried, in order; converged: the answering method met its own convergence
        test (iterative: its residual measure below ``tol`` within ``max_iter``; direct: the
        factorisation succeeded); backward_error: ``‖b − H x‖∞ / (‖H‖∞ ‖x‖∞ + ‖b‖∞)``, the relative
        change of H and b of which x is the exact solution.
    """

    method: str
    iterations: int
    residual: float
    indefinite: bool
    attempts: tuple[str, ...]
    converged: bool
    backward_error: float
    factor: CholeskyFactor | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class CholeskyFactor:
    """A block Cholesky factor of H (`cholesky_factor`), kept to solve with the same H again.

    Attributes:
        l_row: (nnzl,) int64; l_val: (nnzl, 9) float64; perm: (n/3,) int64; l_colptr: (n/3+1,) int64
        (`ops.block_cholesky_factor`).
    """

    l_row: torch.Tensor
    l_val: torch.Tensor
    perm: torch.Tensor
    l_colptr: torch.Tensor

    def solve(self, b: torch.Tensor) -> torch.Tensor:
        """(n,) ``H⁻¹ b`` in b's dtype."""
        return ops.block_cholesky_apply(self.l_row, self.l_val, self.perm, self.l_colptr, b.contiguous())


def _scipy_matrix(crow, col, val):
    import scipy.sparse as sp

    n = crow.shape[0] - 1
    return sp.csr_matrix((val.detach().cpu().numpy(), col.cpu().numpy(), crow.cpu().numpy()), shape=(n, n))


def residual(crow, col, val, x, b) -> float:
    """``|b − H x| / |b|`` (float)."""
    row = torch.repeat_interleave(torch.arange(b.shape[0], device=b.device), crow[1:] - crow[:-1])
    r = b - b.new_zeros(b.shape).index_add_(0, row, val * x[col])
    nb = float(b.norm())
    return float(r.norm()) / (nb if nb > 0 else 1.0)


def backward_error(crow, col, val, x, b) -> float:
    """Normwise backward error ``‖b − H x‖∞ / (‖H‖∞ ‖x‖∞ + ‖b‖∞)`` (float; 0 for an empty or all-zero
    system solved by x = 0)."""
    if b.numel() == 0:
        return 0.0
    row = torch.repeat_interleave(torch.arange(b.shape[0], device=b.device), crow[1:] - crow[:-1])
    r = b - b.new_zeros(b.shape).index_add_(0, row, val * x[col])
    h_norm = float(b.new_zeros(b.shape).index_add_(0, row, val.abs()).max())
    scale = h_norm * float(x.abs().max()) + float(b.abs().max())
    r_norm = float(r.abs().max())
    return r_norm / scale if scale > 0 else (0.0 if r_norm == 0 else float("inf"))


def solve_reference(crow, col, val, b, method: str, tol: float, max_iter: int):
    """SciPy twin of the C++ op: (x, iterations, flag) with flag 0 converged, 1 not, 2 non-positive
    curvature met (``cg`` only; detected by checking ``pᵀHp`` on the iterates through a callback)."""
    import scipy.sparse.linalg as spla

    h = _scipy_matrix(crow, col, val)
    rhs = b.detach().cpu().numpy()
    count = [0]
    if method == "direct":
        try:
            # symmetric ordering and mode: on the 24k-dof dress Hessian 1.1 s and half the fill, against
            # 2.2 s with SuperLU's defaults (COLAMD, partial pivoting); the residual is checked after
            lu = spla.splu(
                h.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.01, options={"SymmetricMode": True}
            )
            x = lu.solve(rhs)
        except RuntimeError:  # exactly singular
            return torch.full_like(b, float("nan")), 0, 3
        return torch.as_tensor(x, dtype=b.dtype, device=b.device), 0, 0
    d = np.abs(h.diagonal())
    d[d == 0] = 1.0
    m = spla.LinearOperator(h.shape, matvec=lambda y: y / d, dtype=rhs.dtype)

    def cb(_):
        count[0] += 1

    if method == "cg":
        x, info = spla.cg(h, rhs, rtol=tol, atol=0.0, maxiter=max_iter, M=m, callback=cb)
    else:
        x, info = spla.minres(h, rhs, rtol=tol, maxiter=max_iter, M=m, callback=cb)
    flag = 0 if info == 0 else 1
    return torch.as_tensor(x, dtype=b.dtype, device=b.device), count[0], flag


def vertex_ordering(crow: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
    """(n/3,) int64 fill-reducing vertex ordering (new → old) of a CSR pattern with 3×3 block structure.

    Multiple minimum degree on the vertex graph (SuperLU's ``MMD_AT_PLUS_A``, read off a factorisation
    of a diagonally dominant matrix with that graph): a ninth of the size of the dof graph. Measured on
    the 8k-vertex dress: 0.06 s, 517k blocks in L.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    cr, cl = crow.cpu().numpy(), col.cpu().numpy()
    nb = (cr.shape[0] - 1) // 3
    start, stop = cr[0:-1:3], cr[1::3]  # the first dof row of each vertex
    deg = (stop - start) // 3
    rows = np.repeat(np.arange(nb), deg)
    cols = np.concatenate([cl[a:b:3] for a, b in zip(start, stop)]) // 3 if nb else np.zeros(0, np.int64)
    graph = sp.csc_matrix((np.full(rows.shape[0], -0.5), (rows, cols)), shape=(nb, nb))
    graph = graph + sp.diags(deg + 1.0)
    lu = spla.splu(graph, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return torch.as_tensor(np.argsort(lu.perm_c).astype(np.int64))


def cholesky_factor(crow, col, val, cache: dict) -> tuple[CholeskyFactor | None, int]:
    """The block Cholesky factor of the SPD CSR matrix (crow, col, val), its ordering and symbolic analysis
    kept in ``cache`` (computed once per pattern); (None, 3) when H is not positive definite, (None, -1)
    without the C++ ops."""
    analyze, factor = extension_op("block_cholesky_analyze"), extension_op("block_cholesky_factor")
    if analyze is None or factor is None or val.device.type != "cpu":
        return None, -1
    if cache.get("col") is not col:  # a new pattern: order and analyse once
        perm = vertex_ordering(crow, col)
        parent, colptr = analyze(crow, col, perm)
        cache.update(col=col, perm=perm, parent=parent, l_colptr=colptr)
    l_row, l_val, info = factor(crow, col, val, cache["perm"], cache["parent"], cache["l_colptr"])
    flag = int(info[2])
    return (CholeskyFactor(l_row, l_val, cache["perm"], cache["l_colptr"]) if flag == 0 else None), flag


def _cholesky(crow, col, val, b, cache: dict):
    """Block sparse Cholesky solve (x, flag, factor) with `cholesky_factor`; None without the ops."""
    factor, flag = cholesky_factor(crow, col, val, cache)
    if flag == -1:
        return None
    if factor is None:
        return torch.full_like(b, float("nan")), flag, None
    return factor.solve(b), 0, factor


def _one(crow, col, val, b, method, tol, max_iter, use_extension, cache=None):
    if method == "cholesky":
        x, flag, factor = _cholesky(crow, col, val, b, cache)
        return x, 0, flag, factor
    op = solve_op() if (use_extension and b.device.type == "cpu") else None
    if method == "direct" or op is None:
        x, iters, flag = solve_reference(crow, col, val, b, method, tol, max_iter)
        return x, iters, flag, None
    x, info = op(
        crow.contiguous(), col.contiguous(), val.contiguous(), b.contiguous(), 0 if method == "cg" else 1,
        float(tol), int(max_iter),
    )  # fmt: skip
    return x, int(info[0]), int(info[2]), None


def solve_symmetric(
    crow: torch.Tensor,
    col: torch.Tensor,
    val: torch.Tensor,
    b: torch.Tensor,
    *,
    method: str = "auto",
    tol: float = 1e-10,
    max_iter: int = 20000,
    use_extension: bool = True,
    cache: dict | None = None,
) -> tuple[torch.Tensor, SolveInfo]:
    """Solve the symmetric sparse system ``H x = b``.

    Args:
        crow: (n+1,) int64; col: (nnz,) int64; val: (nnz,) the CSR matrix H (both triangles).
        b: (n,) right-hand side. method: one of `SOLVE_METHODS`. tol: relative residual target of the
        iterative methods. max_iter: their iteration cap. use_extension: use the C++ op when built.
        cache: for ``"direct"`` on a matrix with 3×3 block structure (`energy.HessianPattern`, whose
        ``solver_cache`` it is): where the block Cholesky keeps its ordering and symbolic analysis.

    Returns:
        x (n,), `SolveInfo` (whose ``residual`` is recomputed explicitly).
    """
    if method not in SOLVE_METHODS:
        raise ValueError(f"unknown solve method {method!r}; valid: {SOLVE_METHODS}")
    chain = {"auto": ("cg", "minres", "direct")}.get(method, (method,))
    if method == "direct" and cache is not None and use_extension and _cholesky_available(b):
        chain = ("cholesky", "direct")  # SuperLU only when H is not positive definite
    attempts, indefinite, factor = [], False, None
    x, iters, res, used, converged = b.new_zeros(b.shape), 0, float("inf"), chain[0], False
    for m in chain:
        attempts.append(m)
        xm, it, flag, fm = _one(crow, col, val, b, m, tol, max_iter, use_extension, cache)
        indefinite |= flag == 2
        rm = residual(crow, col, val, xm, b)
        if np.isfinite(rm) and (rm < res or not np.isfinite(res)):
            x, iters, res, used, converged, factor = xm, it, rm, m, flag == 0, fm
        if np.isfinite(rm) and rm <= max(10 * tol, 1e-12) and flag in (0, 1):
            break
    info = SolveInfo(
        used, iters, res, indefinite, tuple(attempts), converged, backward_error(crow, col, val, x, b), factor
    )
    return x, info


def _cholesky_available(b: torch.Tensor) -> bool:
    return b.device.type == "cpu" and extension_op("block_cholesky_factor") is not None


def check_solve(info: SolveInfo, tol: float, what: str, dtype: torch.dtype = torch.float64) -> None:
    """Refuse a bad solve (see the module docstring).

    Raises `SimulationError` when the relative residual is beyond 1e-3 or not finite. Warns when the
    answering method did not converge, or when the backward error exceeds ``tol`` or the epsilon of
    ``dtype`` (the dtype the answer is used in: a float32 gradient rounds away anything smaller). A
    converged solve whose relative residual ends somewhat above ``tol`` is no warning.
    """
    if not np.isfinite(info.residual) or info.residual > 1e-3:
        raise SimulationError(
            f"{what}: the sparse solve failed (relative residual {info.residual:.3g}, method "
            f"{info.method}, tried {info.attempts}); the Hessian is singular or strongly indefinite "
            "(drape not converged? free-floating cloth?)"
        )
    limit = max(tol, torch.finfo(dtype).eps)
    if not info.converged or not info.backward_error <= limit:
        reason = (
            "did not converge"
            if not info.converged
            else f"backward error {info.backward_error:.3g} > {limit:g}"
        )
        warnings.warn(
            f"{what}: inexact sparse solve, {reason} (relative residual {info.residual:.3g}, method "
            f"{info.method}, tried {info.attempts}, indefinite={info.indefinite}); gradients are approximate",
            RuntimeWarning,
            stacklevel=3,
        )
