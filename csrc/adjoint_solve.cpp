// Sparse symmetric solves for the equilibrium adjoint (and the Newton polish of the drape).
//
// sparse_sym_solve(crow, col, val, b, method, tol, max_iter) -> (x, info)
//   crow (n+1,) int64, col (nnz,) int64, val (nnz,) float32/float64: a symmetric matrix H in CSR (both
//   triangles stored); b (n,) right-hand side. method 0: conjugate gradients with a Jacobi (diagonal)
//   preconditioner, stops at the first direction of non-positive curvature (H not positive definite);
//   method 1: MINRES (Paige & Saunders 1975, the recurrences of scipy.sparse.linalg.minres) with the
//   preconditioner |diag H|, valid for symmetric indefinite H. Both stop when the (preconditioned)
//   residual estimate falls below tol relative to its start, or after max_iter iterations.
//   info (4,) float64 = [iterations, relative residual |b - H x| / |b| (recomputed explicitly),
//   flag (0 converged, 1 max_iter reached, 2 non-positive curvature met (CG), 3 breakdown),
//   smallest curvature p'Hp / p'p seen (CG) or 0 (MINRES)].
// The PyTorch/SciPy twin is torch_diffavatar/sim/adjoint/linsolve.py (`solve_reference`).

#include <ATen/ATen.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <tuple>
#include <vector>

#include "common.h"

namespace diffavatar {
namespace {

constexpr int64_t kSolveGrain = 4096;  // rows below which loops stay on one thread

template <typename T>
void spmv(const int64_t* crow, const int64_t* col, const T* val, const T* x, T* y, int64_t n) {
#pragma omp parallel for num_threads(num_threads()) if (n > kSolveGrain) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    T s = 0;
    for (int64_t k = crow[i]; k < crow[i + 1]; ++k) s += val[k] * x[col[k]];
    y[i] = s;
  }
}

template <typename T>
double dotp(const T* a, const T* b, int64_t n) {
  double s = 0;
#pragma omp parallel for num_threads(num_threads()) if (n > kSolveGrain) reduction(+ : s) schedule(static)
  for (int64_t i = 0; i < n; ++i) s += static_cast<double>(a[i]) * static_cast<double>(b[i]);
  return s;
}

template <typename T>
std::vector<T> inv_abs_diag(const int64_t* crow, const int64_t* col, const T* val, int64_t n) {
  std::vector<T> d(n, T(1));
  for (int64_t i = 0; i < n; ++i) {
    for (int64_t k = crow[i]; k < crow[i + 1]; ++k) {
      if (col[k] == i && val[k] != T(0)) d[i] = T(1) / std::abs(val[k]);
    }
  }
  return d;
}

template <typename T>
double true_residual(const int64_t* crow, const int64_t* col, const T* val, const T* x, const T* b, int64_t n) {
  std::vector<T> hx(n);
  spmv(crow, col, val, x, hx.data(), n);
  double rr = 0, bb = 0;
  for (int64_t i = 0; i < n; ++i) {
    const double r = static_cast<double>(b[i]) - static_cast<double>(hx[i]);
    rr += r * r;
    bb += static_cast<double>(b[i]) * static_cast<double>(b[i]);
  }
  return bb > 0 ? std::sqrt(rr / bb) : std::sqrt(rr);
}

// Jacobi-preconditioned conjugate gradients. Returns (iterations, flag, min curvature).
template <typename T>
std::tuple<int64_t, int, double> pcg(const int64_t* crow, const int64_t* col, const T* val, const T* b, T* x,
                                     int64_t n, double tol, int64_t max_iter) {
  const std::vector<T> dinv = inv_abs_diag(crow, col, val, n);
  std::vector<T> r(b, b + n), z(n), p(n), hp(n);
  std::fill(x, x + n, T(0));
  for (int64_t i = 0; i < n; ++i) z[i] = dinv[i] * r[i];
  p = z;
  double rz = dotp(r.data(), z.data(), n);
  const double bnorm = std::sqrt(dotp(b, b, n));
  double min_curv = std::numeric_limits<double>::infinity();
  if (bnorm == 0) return {0, 0, 0.0};
  for (int64_t it = 1; it <= max_iter; ++it) {
    spmv(crow, col, val, p.data(), hp.data(), n);
    const double php = dotp(p.data(), hp.data(), n);
    const double pp = dotp(p.data(), p.data(), n);
    min_curv = std::min(min_curv, php / std::max(pp, 1e-300));
    if (!(php > 0)) return {it, 2, min_curv};
    const T a = static_cast<T>(rz / php);
    double rr = 0;
#pragma omp parallel for num_threads(num_threads()) if (n > kSolveGrain) reduction(+ : rr) schedule(static)
    for (int64_t i = 0; i < n; ++i) {
      x[i] += a * p[i];
      r[i] -= a * hp[i];
      rr += static_cast<double>(r[i]) * static_cast<double>(r[i]);
    }
    if (std::sqrt(rr) <= tol * bnorm) return {it, 0, min_curv};
    for (int64_t i = 0; i < n; ++i) z[i] = dinv[i] * r[i];
    const double rz_new = dotp(r.data(), z.data(), n);
    const T beta = static_cast<T>(rz_new / rz);
    rz = rz_new;
    for (int64_t i = 0; i < n; ++i) p[i] = z[i] + beta * p[i];
  }
  return {max_iter, 1, min_curv};
}

// MINRES with the SPD preconditioner M = |diag H| (scipy.sparse.linalg.minres recurrences).
template <typename T>
std::tuple<int64_t, int> minres(const int64_t* crow, const int64_t* col, const T* val, const T* b, T* xo,
                                int64_t n, double tol, int64_t max_iter) {
  const std::vector<T> dinv = inv_abs_diag(crow, col, val, n);
  std::vector<double> x(n, 0.0), r1(b, b + n), r2(b, b + n), y(n), v(n), w(n, 0.0), w1(n), w2(n, 0.0);
  std::vector<T> vt(n), hv(n);
  for (int64_t i = 0; i < n; ++i) y[i] = dinv[i] * r1[i];
  double beta1 = 0;
  for (int64_t i = 0; i < n; ++i) beta1 += r1[i] * y[i];
  std::fill(xo, xo + n, T(0));
  if (beta1 <= 0) return {0, beta1 == 0 ? 0 : 3};
  beta1 = std::sqrt(beta1);
  double oldb = 0, beta = beta1, dbar = 0, epsln = 0, phibar = beta1, cs = -1, sn = 0;
  const double eps = std::numeric_limits<T>::epsilon();
  int64_t it = 0;
  int flag = 1;
  for (it = 1; it <= max_iter; ++it) {
    const double s = 1.0 / beta;
    for (int64_t i = 0; i < n; ++i) {
      v[i] = s * y[i];
      vt[i] = static_cast<T>(v[i]);
    }
    spmv(crow, col, val, vt.data(), hv.data(), n);
    for (int64_t i = 0; i < n; ++i) y[i] = hv[i];
    if (it >= 2) {
      const double c = beta / oldb;
      for (int64_t i = 0; i < n; ++i) y[i] -= c * r1[i];
    }
    double alfa = 0;
    for (int64_t i = 0; i < n; ++i) alfa += v[i] * y[i];
    const double c2 = alfa / beta;
    for (int64_t i = 0; i < n; ++i) {
      y[i] -= c2 * r2[i];
      r1[i] = r2[i];
      r2[i] = y[i];
      y[i] = dinv[i] * r2[i];
    }
    oldb = beta;
    beta = 0;
    for (int64_t i = 0; i < n; ++i) beta += r2[i] * y[i];
    if (beta < 0) {
      flag = 3;
      break;
    }
    beta = std::sqrt(beta);
    const double oldeps = epsln;
    const double delta = cs * dbar + sn * alfa;
    const double gbar = sn * dbar - cs * alfa;
    epsln = sn * beta;
    dbar = -cs * beta;
    const double gamma = std::max(std::hypot(gbar, beta), eps);
    cs = gbar / gamma;
    sn = beta / gamma;
    const double phi = cs * phibar;
    phibar = sn * phibar;
    const double denom = 1.0 / gamma;
    for (int64_t i = 0; i < n; ++i) {
      w1[i] = w2[i];
      w2[i] = w[i];
      w[i] = (v[i] - oldeps * w1[i] - delta * w2[i]) * denom;
      x[i] += phi * w[i];
    }
    if (phibar <= tol * beta1) {
      flag = 0;
      break;
    }
    if (beta == 0) {
      flag = 0;
      break;
    }
  }
  for (int64_t i = 0; i < n; ++i) xo[i] = static_cast<T>(x[i]);
  return {std::min(it, max_iter), flag};
}

std::tuple<at::Tensor, at::Tensor> sparse_sym_solve(const at::Tensor& crow, const at::Tensor& col,
                                                    const at::Tensor& val, const at::Tensor& b, int64_t method,
                                                    double tol, int64_t max_iter) {
  check_cpu_contiguous(crow, "crow");
  check_cpu_contiguous(col, "col");
  check_cpu_contiguous(val, "val");
  check_cpu_contiguous(b, "b");
  check_dtype(crow, "crow", at::kLong);
  check_dtype(col, "col", at::kLong);
  const int64_t n = b.size(0);
  check_shape(b, "b", {n});
  check_shape(crow, "crow", {n + 1});
  check_shape(col, "col", {-1});
  check_shape(val, "val", {col.size(0)});
  TORCH_CHECK(val.scalar_type() == b.scalar_type(), "diffavatar: val and b must have the same dtype");
  TORCH_CHECK(method == 0 || method == 1, "diffavatar: sparse_sym_solve method must be 0 (CG) or 1 (MINRES)");
  TORCH_CHECK(crow.data_ptr<int64_t>()[0] == 0 && crow.data_ptr<int64_t>()[n] == col.size(0),
              "diffavatar: crow must start at 0 and end at nnz");
  check_index_range(col, n, "col");
  at::Tensor x = at::zeros_like(b);
  at::Tensor info = at::zeros({4}, b.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(b.scalar_type(), "sparse_sym_solve", [&] {
    const int64_t* cr = crow.data_ptr<int64_t>();
    const int64_t* cl = col.data_ptr<int64_t>();
    const scalar_t* vl = val.data_ptr<scalar_t>();
    const scalar_t* bp = b.data_ptr<scalar_t>();
    scalar_t* xp = x.data_ptr<scalar_t>();
    double* ip = info.data_ptr<double>();
    if (method == 0) {
      auto [iters, flag, curv] = pcg(cr, cl, vl, bp, xp, n, tol, max_iter);
      ip[0] = static_cast<double>(iters);
      ip[2] = flag;
      ip[3] = curv;
    } else {
      auto [iters, flag] = minres(cr, cl, vl, bp, xp, n, tol, max_iter);
      ip[0] = static_cast<double>(iters);
      ip[2] = flag;
    }
    ip[1] = true_residual(cr, cl, vl, xp, bp, n);
  });
  return {x, info};
}

}  // namespace
}  // namespace diffavatar

TORCH_LIBRARY_FRAGMENT(diffavatar, m) {
  // Symmetric sparse solve H x = b (CSR): method 0 Jacobi-PCG, 1 MINRES; info = [iters, rel. residual,
  // flag, min curvature].
  m.def(
      "sparse_sym_solve(Tensor crow, Tensor col, Tensor val, Tensor b, int method, float tol, int max_iter) "
      "-> (Tensor x, Tensor info)");
}

TORCH_LIBRARY_IMPL(diffavatar, CPU, m) { m.impl("sparse_sym_solve", &diffavatar::sparse_sym_solve); }
