// Sparse Cholesky H = L Lᵀ in 3×3 blocks for the equilibrium adjoint's SPD (projected) Hessian.
//
// The matrix is a scalar CSR (crow, col, val) with 3×3 block structure: rows 3v, 3v+1, 3v+2 share one
// pattern made of whole column triples (a vertex's three dofs couple to whole vertices). Working on the
// vertex graph makes the symbolic phase 9× smaller and each update a 3×3 block product.
//
// block_cholesky_analyze(crow, col, perm) -> (parent, l_colptr)
//   perm (nb,) int64 a fill-reducing vertex ordering (new → old). Returns the elimination tree of the
//   permuted vertex graph and the block column pointers of L (nnz per block column, diagonal included).
//   Once per sparsity pattern (the cloth's topology): the fit reuses it every iteration.
// block_cholesky_solve(crow, col, val, b, perm, parent, l_colptr) -> (x, info)
//   Numeric factorisation of P H Pᵀ (up-looking, as CSparse's cs_chol, in blocks) and the two triangular
//   solves. info (4,) float64 = [0, relative residual |b − H x| / |b|, flag (0 ok, 3 not positive
//   definite), smallest pivot of the block diagonal factors].
// The PyTorch twin is reference.block_cholesky_solve (dense Cholesky; small problems only).

#include <ATen/ATen.h>
#include <torch/library.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <tuple>
#include <vector>

#include "common.h"

namespace diffavatar {
namespace {

// Block pattern of a scalar CSR with 3×3 block structure: (bcrow (nb+1), bcol (nnzb)); checks it.
std::pair<std::vector<int64_t>, std::vector<int64_t>> block_pattern(const at::Tensor& crow, const at::Tensor& col) {
  const int64_t n = crow.size(0) - 1;
  TORCH_CHECK(n % 3 == 0, "diffavatar: block Cholesky needs 3 dofs per vertex, got n = ", n);
  const int64_t nb = n / 3;
  const int64_t* cr = crow.data_ptr<int64_t>();
  const int64_t* cl = col.data_ptr<int64_t>();
  std::vector<int64_t> bcrow(nb + 1, 0), bcol;
  bcol.reserve(col.size(0) / 9);
  bool ok = cr[0] == 0 && cr[n] == col.size(0);
  for (int64_t v = 0; ok && v < nb; ++v) {
    const int64_t len = cr[3 * v + 1] - cr[3 * v];
    ok = len % 3 == 0 && cr[3 * v + 2] - cr[3 * v + 1] == len && cr[3 * v + 3] - cr[3 * v + 2] == len;
    for (int a = 0; ok && a < 3; ++a) {
      const int64_t* c = cl + cr[3 * v + a];
      for (int64_t t = 0; ok && t < len; t += 3) {
        ok = c[t] % 3 == 0 && c[t + 1] == c[t] + 1 && c[t + 2] == c[t] + 2 && c[t] >= 0 && c[t] < n &&
             (t == 0 || c[t] > c[t - 1]) && c[t] == cl[cr[3 * v] + t];
      }
    }
    if (!ok) break;
    for (int64_t t = 0; t < len; t += 3) bcol.push_back(cl[cr[3 * v] + t] / 3);
    bcrow[v + 1] = bcrow[v] + len / 3;
  }
  TORCH_CHECK(ok, "diffavatar: block Cholesky needs a CSR with sorted columns and 3x3 block structure");
  return {bcrow, bcol};
}

// Pattern of row k of L (excluding k) in topological order, into s[top..nb); CSparse's cs_ereach on the
// permuted graph. `mark` holds k for visited nodes.
int64_t ereach(int64_t k, const std::vector<int64_t>& bcrow, const std::vector<int64_t>& bcol,
               const int64_t* perm, const std::vector<int64_t>& pinv, const int64_t* parent,
               std::vector<int64_t>& s, std::vector<int64_t>& mark) {
  const int64_t nb = static_cast<int64_t>(pinv.size());
  int64_t top = nb;
  mark[k] = k;
  const int64_t r = perm[k];
  for (int64_t p = bcrow[r]; p < bcrow[r + 1]; ++p) {
    int64_t i = pinv[bcol[p]];
    if (i > k) continue;
    int64_t len = 0;
    for (; mark[i] != k; i = parent[i]) {
      s[len++] = i;  // the path up the tree, pushed onto the stack below
      mark[i] = k;
    }
    while (len > 0) s[--top] = s[--len];
  }
  return top;
}

std::tuple<at::Tensor, at::Tensor> block_cholesky_analyze(const at::Tensor& crow, const at::Tensor& col,
                                                          const at::Tensor& perm) {
  check_cpu_contiguous(crow, "crow");
  check_cpu_contiguous(col, "col");
  check_cpu_contiguous(perm, "perm");
  check_dtype(crow, "crow", at::kLong);
  check_dtype(col, "col", at::kLong);
  check_dtype(perm, "perm", at::kLong);
  auto [bcrow, bcol] = block_pattern(crow, col);
  const int64_t nb = static_cast<int64_t>(bcrow.size()) - 1;
  check_shape(perm, "perm", {nb});
  const int64_t* pm = perm.data_ptr<int64_t>();
  std::vector<int64_t> pinv(nb, -1);
  for (int64_t i = 0; i < nb; ++i) {
    TORCH_CHECK(pm[i] >= 0 && pm[i] < nb && pinv[pm[i]] < 0, "diffavatar: perm must be a permutation of 0..nb-1");
    pinv[pm[i]] = i;
  }
  at::Tensor parent_t = at::empty({nb}, perm.options());
  at::Tensor colptr_t = at::empty({nb + 1}, perm.options());
  int64_t* parent = parent_t.data_ptr<int64_t>();
  // elimination tree (Liu's algorithm with path compression, cs_etree on the permuted symmetric graph)
  std::vector<int64_t> ancestor(nb, -1);
  for (int64_t k = 0; k < nb; ++k) {
    parent[k] = -1;
    const int64_t r = pm[k];
    for (int64_t p = bcrow[r]; p < bcrow[r + 1]; ++p) {
      for (int64_t i = pinv[bcol[p]]; i != -1 && i < k;) {
        const int64_t next = ancestor[i];
        ancestor[i] = k;
        if (next == -1) {
          parent[i] = k;
          break;
        }
        i = next;
      }
    }
  }
  // column counts by walking every row's pattern (O(nnz(L)); once per topology)
  std::vector<int64_t> count(nb, 1), s(nb), mark(nb, -1);
  for (int64_t k = 0; k < nb; ++k) {
    for (int64_t top = ereach(k, bcrow, bcol, pm, pinv, parent, s, mark); top < nb; ++top) ++count[s[top]];
  }
  int64_t* cp = colptr_t.data_ptr<int64_t>();
  cp[0] = 0;
  for (int64_t k = 0; k < nb; ++k) cp[k + 1] = cp[k] + count[k];
  return {parent_t, colptr_t};
}

using Blk = std::array<double, 9>;  // row-major 3×3

inline void blk_sub_mul_t(Blk& y, const Blk& a, const Blk& b) {  // y −= a bᵀ
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) y[3 * i + j] -= a[3 * i] * b[3 * j] + a[3 * i + 1] * b[3 * j + 1] + a[3 * i + 2] * b[3 * j + 2];
}

// Lower Cholesky factor of the 3×3 block d (in place, upper part zeroed); false when not PD.
inline bool chol3(Blk& d, double& min_pivot) {
  const double l00s = d[0];
  if (!(l00s > 0)) return false;
  const double l00 = std::sqrt(l00s);
  const double l10 = d[3] / l00, l20 = d[6] / l00;
  const double l11s = d[4] - l10 * l10;
  if (!(l11s > 0)) return false;
  const double l11 = std::sqrt(l11s);
  const double l21 = (d[7] - l20 * l10) / l11;
  const double l22s = d[8] - l20 * l20 - l21 * l21;
  if (!(l22s > 0)) return false;
  const double l22 = std::sqrt(l22s);
  min_pivot = std::min({min_pivot, l00s, l11s, l22s});
  d = {l00, 0, 0, l10, l11, 0, l20, l21, l22};
  return true;
}

// y ← y L⁻ᵀ for the lower-triangular 3×3 L (solves X Lᵀ = y row by row).
inline void blk_solve_lt(Blk& y, const Blk& L) {
  for (int i = 0; i < 3; ++i) {
    double* r = y.data() + 3 * i;
    r[0] = r[0] / L[0];
    r[1] = (r[1] - L[3] * r[0]) / L[4];
    r[2] = (r[2] - L[6] * r[0] - L[7] * r[1]) / L[8];
  }
}

template <typename T>
double true_residual_csr(const int64_t* cr, const int64_t* cl, const T* val, const T* x, const T* b, int64_t n) {
  double rr = 0, bb = 0;
  for (int64_t i = 0; i < n; ++i) {
    double s = 0;
    for (int64_t k = cr[i]; k < cr[i + 1]; ++k) s += static_cast<double>(val[k]) * static_cast<double>(x[cl[k]]);
    const double r = static_cast<double>(b[i]) - s;
    rr += r * r;
    bb += static_cast<double>(b[i]) * static_cast<double>(b[i]);
  }
  return bb > 0 ? std::sqrt(rr / bb) : std::sqrt(rr);
}

// Numeric factorisation of P H Pᵀ = L Lᵀ (up-looking, as CSparse's cs_chol, in blocks): block column j
// of L holds rows li[cp[j]..cp[j+1]) (the diagonal first, then increasing) with values lx. Returns the flag
// (0 ok, 3 not positive definite) and the smallest pivot.
template <typename T>
std::pair<int, double> factor_numeric(const at::Tensor& crow, const at::Tensor& col, const T* val,
                                      const int64_t* pm, const int64_t* parent, const int64_t* cp,
                                      int64_t* li, Blk* lx) {
  auto [bcrow, bcol] = block_pattern(crow, col);
  const int64_t nb = static_cast<int64_t>(bcrow.size()) - 1;
  const int64_t* cr = crow.data_ptr<int64_t>();
  std::vector<int64_t> pinv(nb);
  for (int64_t i = 0; i < nb; ++i) pinv[pm[i]] = i;
  std::vector<int64_t> next(cp, cp + nb), s(nb), mark(nb, -1);
  std::vector<Blk> xw(nb, Blk{});
  double min_pivot = std::numeric_limits<double>::infinity();
  for (int64_t k = 0; k < nb; ++k) {
    const int64_t top = ereach(k, bcrow, bcol, pm, pinv, parent, s, mark);
    // scatter block row perm[k] of H (columns i ≤ k of the permuted matrix) into the workspace
    const int64_t r = pm[k];
    for (int64_t p = bcrow[r]; p < bcrow[r + 1]; ++p) {
      const int64_t i = pinv[bcol[p]];
      if (i > k) continue;
      Blk& w = xw[i];
      const int64_t off = 3 * (p - bcrow[r]);
      for (int a = 0; a < 3; ++a)
        for (int c = 0; c < 3; ++c) w[3 * a + c] = static_cast<double>(val[cr[3 * r + a] + off + c]);
    }
    Blk d = xw[k];
    xw[k] = Blk{};
    for (int64_t t = top; t < nb; ++t) {
      const int64_t i = s[t];
      // L(k,i) = H̃(k,i) L(i,i)⁻ᵀ with H̃ the updated row; then push its updates down column i
      Blk lki = xw[i];
      xw[i] = Blk{};
      blk_solve_lt(lki, lx[cp[i]]);
      for (int64_t p = cp[i] + 1; p < next[i]; ++p) blk_sub_mul_t(xw[li[p]], lki, lx[p]);
      blk_sub_mul_t(d, lki, lki);
      const int64_t p = next[i]++;
      li[p] = k;
      lx[p] = lki;
    }
    // symmetrise the diagonal block against rounding before its 3×3 Cholesky
    d[1] = d[3] = 0.5 * (d[1] + d[3]);
    d[2] = d[6] = 0.5 * (d[2] + d[6]);
    d[5] = d[7] = 0.5 * (d[5] + d[7]);
    if (!chol3(d, min_pivot)) return {3, min_pivot};
    const int64_t p = next[k]++;
    li[p] = k;
    lx[p] = d;
  }
  return {0, min_pivot};
}

// x = Pᵀ L⁻ᵀ L⁻¹ P b with the factor of `factor_numeric`.
template <typename T>
void factor_apply(int64_t nb, const int64_t* li, const Blk* lx, const int64_t* pm, const int64_t* cp, const T* b,
                  T* xo) {
  // forward L y = P b (column-oriented: diagonal first in each column), then Lᵀ z = y, x = Pᵀ z
  const int64_t n = 3 * nb;
  std::vector<double> y(n);
  for (int64_t k = 0; k < nb; ++k)
    for (int a = 0; a < 3; ++a) y[3 * k + a] = static_cast<double>(b[3 * pm[k] + a]);
  for (int64_t j = 0; j < nb; ++j) {
    const Blk& L = lx[cp[j]];
    double* yj = y.data() + 3 * j;
    yj[0] = yj[0] / L[0];
    yj[1] = (yj[1] - L[3] * yj[0]) / L[4];
    yj[2] = (yj[2] - L[6] * yj[0] - L[7] * yj[1]) / L[8];
    for (int64_t p = cp[j] + 1; p < cp[j + 1]; ++p) {
      const Blk& B = lx[p];
      double* yi = y.data() + 3 * li[p];
      for (int a = 0; a < 3; ++a) yi[a] -= B[3 * a] * yj[0] + B[3 * a + 1] * yj[1] + B[3 * a + 2] * yj[2];
    }
  }
  for (int64_t j = nb - 1; j >= 0; --j) {
    double* yj = y.data() + 3 * j;
    for (int64_t p = cp[j] + 1; p < cp[j + 1]; ++p) {
      const Blk& B = lx[p];
      const double* yi = y.data() + 3 * li[p];
      for (int a = 0; a < 3; ++a) yj[a] -= B[a] * yi[0] + B[3 + a] * yi[1] + B[6 + a] * yi[2];
    }
    const Blk& L = lx[cp[j]];
    yj[2] = yj[2] / L[8];
    yj[1] = (yj[1] - L[7] * yj[2]) / L[4];
    yj[0] = (yj[0] - L[3] * yj[1] - L[6] * yj[2]) / L[0];
  }
  for (int64_t k = 0; k < nb; ++k)
    for (int a = 0; a < 3; ++a) xo[3 * pm[k] + a] = static_cast<T>(y[3 * k + a]);
}

template <typename T>
void factor_solve(const at::Tensor& crow, const at::Tensor& col, const T* val, const T* b, const int64_t* pm,
                  const int64_t* parent, const int64_t* cp, T* xo, double* info) {
  const int64_t n = crow.size(0) - 1, nb = n / 3;
  std::vector<int64_t> li(cp[nb]);
  std::vector<Blk> lx(cp[nb]);
  const auto [flag, min_pivot] = factor_numeric<T>(crow, col, val, pm, parent, cp, li.data(), lx.data());
  info[2] = flag;
  info[3] = min_pivot;
  if (flag != 0) {
    for (int64_t i = 0; i < n; ++i) xo[i] = std::numeric_limits<T>::quiet_NaN();
    info[1] = std::numeric_limits<double>::infinity();
    return;
  }
  factor_apply<T>(nb, li.data(), lx.data(), pm, cp, b, xo);
  info[1] = true_residual_csr(crow.data_ptr<int64_t>(), col.data_ptr<int64_t>(), val, xo, b, n);
}

std::tuple<at::Tensor, at::Tensor> block_cholesky_solve(const at::Tensor& crow, const at::Tensor& col,
                                                        const at::Tensor& val, const at::Tensor& b,
                                                        const at::Tensor& perm, const at::Tensor& parent,
                                                        const at::Tensor& l_colptr) {
  check_cpu_contiguous(crow, "crow");
  check_cpu_contiguous(col, "col");
  check_cpu_contiguous(val, "val");
  check_cpu_contiguous(b, "b");
  check_cpu_contiguous(perm, "perm");
  check_cpu_contiguous(parent, "parent");
  check_cpu_contiguous(l_colptr, "l_colptr");
  check_dtype(crow, "crow", at::kLong);
  check_dtype(col, "col", at::kLong);
  check_dtype(perm, "perm", at::kLong);
  check_dtype(parent, "parent", at::kLong);
  check_dtype(l_colptr, "l_colptr", at::kLong);
  const int64_t n = b.size(0);
  check_shape(b, "b", {n});
  check_shape(crow, "crow", {n + 1});
  check_shape(val, "val", {col.size(0)});
  TORCH_CHECK(n % 3 == 0, "diffavatar: block_cholesky_solve needs 3 dofs per vertex");
  const int64_t nb = n / 3;
  check_shape(perm, "perm", {nb});
  check_shape(parent, "parent", {nb});
  check_shape(l_colptr, "l_colptr", {nb + 1});
  TORCH_CHECK(val.scalar_type() == b.scalar_type(), "diffavatar: val and b must have the same dtype");
  at::Tensor x = at::empty_like(b);
  at::Tensor info = at::zeros({4}, b.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(b.scalar_type(), "block_cholesky_solve", [&] {
    factor_solve<scalar_t>(crow, col, val.data_ptr<scalar_t>(), b.data_ptr<scalar_t>(), perm.data_ptr<int64_t>(),
                           parent.data_ptr<int64_t>(), l_colptr.data_ptr<int64_t>(), x.data_ptr<scalar_t>(),
                           info.data_ptr<double>());
  });
  return {x, info};
}

void check_factor_inputs(const at::Tensor& perm, const at::Tensor& parent, const at::Tensor& l_colptr, int64_t nb) {
  check_cpu_contiguous(perm, "perm");
  check_cpu_contiguous(l_colptr, "l_colptr");
  check_dtype(perm, "perm", at::kLong);
  check_dtype(l_colptr, "l_colptr", at::kLong);
  check_shape(perm, "perm", {nb});
  check_shape(l_colptr, "l_colptr", {nb + 1});
  if (parent.defined()) {
    check_cpu_contiguous(parent, "parent");
    check_dtype(parent, "parent", at::kLong);
    check_shape(parent, "parent", {nb});
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> block_cholesky_factor(const at::Tensor& crow, const at::Tensor& col,
                                                                     const at::Tensor& val, const at::Tensor& perm,
                                                                     const at::Tensor& parent,
                                                                     const at::Tensor& l_colptr) {
  check_cpu_contiguous(crow, "crow");
  check_cpu_contiguous(col, "col");
  check_cpu_contiguous(val, "val");
  check_dtype(crow, "crow", at::kLong);
  check_dtype(col, "col", at::kLong);
  const int64_t n = crow.size(0) - 1;
  TORCH_CHECK(n % 3 == 0, "diffavatar: block_cholesky_factor needs 3 dofs per vertex");
  check_shape(val, "val", {col.size(0)});
  const int64_t nb = n / 3;
  check_factor_inputs(perm, parent, l_colptr, nb);
  const int64_t nnzl = l_colptr.data_ptr<int64_t>()[nb];
  at::Tensor l_row = at::empty({nnzl}, perm.options());
  at::Tensor l_val = at::empty({nnzl, 9}, val.options().dtype(at::kDouble));
  at::Tensor info = at::zeros({4}, val.options().dtype(at::kDouble));
  static_assert(sizeof(Blk) == 9 * sizeof(double), "a block is nine packed doubles");
  AT_DISPATCH_FLOATING_TYPES(val.scalar_type(), "block_cholesky_factor", [&] {
    const auto [flag, min_pivot] = factor_numeric<scalar_t>(
        crow, col, val.data_ptr<scalar_t>(), perm.data_ptr<int64_t>(), parent.data_ptr<int64_t>(),
        l_colptr.data_ptr<int64_t>(), l_row.data_ptr<int64_t>(), reinterpret_cast<Blk*>(l_val.data_ptr<double>()));
    info.data_ptr<double>()[2] = flag;
    info.data_ptr<double>()[3] = min_pivot;
  });
  if (info.data_ptr<double>()[2] != 0) l_val.fill_(std::numeric_limits<double>::quiet_NaN());
  return {l_row, l_val, info};
}

at::Tensor block_cholesky_apply(const at::Tensor& l_row, const at::Tensor& l_val, const at::Tensor& perm,
                                const at::Tensor& l_colptr, const at::Tensor& b) {
  check_cpu_contiguous(l_row, "l_row");
  check_cpu_contiguous(l_val, "l_val");
  check_cpu_contiguous(b, "b");
  check_dtype(l_row, "l_row", at::kLong);
  check_dtype(l_val, "l_val", at::kDouble);
  const int64_t n = b.size(0);
  check_shape(b, "b", {n});
  TORCH_CHECK(n % 3 == 0, "diffavatar: block_cholesky_apply needs 3 dofs per vertex");
  const int64_t nb = n / 3;
  check_factor_inputs(perm, at::Tensor(), l_colptr, nb);
  const int64_t* cp = l_colptr.data_ptr<int64_t>();
  check_shape(l_row, "l_row", {cp[nb]});
  check_shape(l_val, "l_val", {cp[nb], 9});
  const int64_t* li = l_row.data_ptr<int64_t>();
  for (int64_t j = 0; j < nb; ++j) {  // the layout `factor_apply` indexes: diagonal first, rows in range
    TORCH_CHECK(cp[j] < cp[j + 1] && li[cp[j]] == j, "diffavatar: l_row/l_colptr are not a block Cholesky factor");
    for (int64_t p = cp[j] + 1; p < cp[j + 1]; ++p)
      TORCH_CHECK(li[p] > j && li[p] < nb, "diffavatar: l_row/l_colptr are not a block Cholesky factor");
  }
  at::Tensor x = at::empty_like(b);
  AT_DISPATCH_FLOATING_TYPES(b.scalar_type(), "block_cholesky_apply", [&] {
    factor_apply<scalar_t>(nb, li, reinterpret_cast<const Blk*>(l_val.data_ptr<double>()), perm.data_ptr<int64_t>(),
                           cp, b.data_ptr<scalar_t>(), x.data_ptr<scalar_t>());
  });
  return x;
}

}  // namespace
}  // namespace diffavatar

TORCH_LIBRARY_FRAGMENT(diffavatar, m) {
  // Symbolic analysis of the 3x3-block sparse Cholesky: elimination tree and L's block column pointers.
  m.def("block_cholesky_analyze(Tensor crow, Tensor col, Tensor perm) -> (Tensor parent, Tensor l_colptr)");
  // Numeric block Cholesky of the SPD CSR matrix and solve; info = [0, rel. residual, flag, min pivot].
  m.def(
      "block_cholesky_solve(Tensor crow, Tensor col, Tensor val, Tensor b, Tensor perm, Tensor parent, "
      "Tensor l_colptr) -> (Tensor x, Tensor info)");
  // The numeric factor alone, to solve again later (the fit's warm-start prediction): L's block rows
  // (diagonal first per column) and its 3x3 blocks (row-major, float64); info = [0, 0, flag, min pivot].
  m.def(
      "block_cholesky_factor(Tensor crow, Tensor col, Tensor val, Tensor perm, Tensor parent, Tensor l_colptr) "
      "-> (Tensor l_row, Tensor l_val, Tensor info)");
  // x = H^-1 b with a factor of block_cholesky_factor.
  m.def("block_cholesky_apply(Tensor l_row, Tensor l_val, Tensor perm, Tensor l_colptr, Tensor b) -> Tensor");
}

TORCH_LIBRARY_IMPL(diffavatar, CPU, m) {
  m.impl("block_cholesky_analyze", &diffavatar::block_cholesky_analyze);
  m.impl("block_cholesky_solve", &diffavatar::block_cholesky_solve);
  m.impl("block_cholesky_factor", &diffavatar::block_cholesky_factor);
  m.impl("block_cholesky_apply", &diffavatar::block_cholesky_apply);
}
