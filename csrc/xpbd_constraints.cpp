// XPBD projection kernels: orthotropic StVK stretch (one 3-vector block per triangle) and signed
// dihedral bending (one scalar per interior edge), as colour-ordered Gauss-Seidel passes and as
// Jacobi passes. The maths follows torch_diffavatar/sim/reference.py line by line (that file is the
// contract; the tests compare the two).
//
// Gauss-Seidel: colours run in sequence; the constraints of one colour share no vertex, so one
// OpenMP team splits each colour (with a barrier between colours). A colouring that violates this
// makes the result depend on the thread schedule (a data race), so the caller must supply a valid one.

#include <vector>

#include "common.h"

namespace diffavatar {
namespace {

// --------------------------------------------------------------------------------------- stretch

// Correction of one stretch block evaluated at x. Returns false (and leaves outputs unset) when the
// triangle is skipped: all three inverse masses zero, or a singular 3x3 system.
template <typename T>
inline bool stretch_delta(const T* x, const T* w, const int64_t* tv, const T* r, const T* alpha, const T* lam,
                          T inv_dt2, T dlam[3], Vec3<T> dx[3]) {
  const int64_t i0 = tv[0], i1 = tv[1], i2 = tv[2];
  const T w0 = w[i0], w1 = w[i1], w2 = w[i2];
  if (!(w0 > 0 || w1 > 0 || w2 > 0)) return false;
  const Vec3<T> x2 = load3(x, i2);
  const Vec3<T> d0 = load3(x, i0) - x2;
  const Vec3<T> d1 = load3(x, i1) - x2;
  // F = D R (3x2), R = tri_rest_inv row-major [[r0, r1], [r2, r3]].
  const Vec3<T> f0 = r[0] * d0 + r[2] * d1;
  const Vec3<T> f1 = r[1] * d0 + r[3] * d1;
  const T c[3] = {T(0.5) * (dot(f0, f0) - T(1)), T(0.5) * (dot(f1, f1) - T(1)), T(0.5) * dot(f0, f1)};
  // g[i][k] = dC_k/dx_i: column i of P_k R^T, P_0 = [f0, 0], P_1 = [0, f1], P_2 = [f1, f0] / 2.
  Vec3<T> g[3][3];
  g[0][0] = r[0] * f0;
  g[0][1] = r[1] * f1;
  g[0][2] = T(0.5) * (r[0] * f1 + r[1] * f0);
  g[1][0] = r[2] * f0;
  g[1][1] = r[3] * f1;
  g[1][2] = T(0.5) * (r[2] * f1 + r[3] * f0);
  for (int k = 0; k < 3; ++k) g[2][k] = T(-1) * (g[0][k] + g[1][k]);
  const T wi[3] = {w0, w1, w2};
  // A = sum_i w_i G_i G_i^T + alpha / dt^2 (3x3); rhs = -C - alpha / dt^2 lam.
  T a[3][3];
  T rhs[3];
  for (int k = 0; k < 3; ++k) {
    rhs[k] = -c[k];
    for (int l = 0; l < 3; ++l) {
      const T at = alpha[3 * k + l] * inv_dt2;
      a[k][l] = at + wi[0] * dot(g[0][k], g[0][l]) + wi[1] * dot(g[1][k], g[1][l]) + wi[2] * dot(g[2][k], g[2][l]);
      rhs[k] -= at * lam[l];
    }
  }
  // Solve A dlam = rhs by the adjugate (A is 3x3 and symmetric positive definite when active), scaled
  // down when its determinant would overflow (sym3_scale_limit; m = 1 is exact).
  const T amax = std::max(a[0][0], std::max(a[1][1], a[2][2]));
  const T m = amax > sym3_scale_limit<T>() ? T(1) / amax : T(1);
  for (int k = 0; k < 3; ++k) {
    rhs[k] *= m;
    for (int l = 0; l < 3; ++l) a[k][l] *= m;
  }
  const T c00 = a[1][1] * a[2][2] - a[1][2] * a[2][1];
  const T c01 = a[1][2] * a[2][0] - a[1][0] * a[2][2];
  const T c02 = a[1][0] * a[2][1] - a[1][1] * a[2][0];
  const T det = a[0][0] * c00 + a[0][1] * c01 + a[0][2] * c02;
  if (det == T(0) || !std::isfinite(det)) return false;
  const T c10 = a[0][2] * a[2][1] - a[0][1] * a[2][2];
  const T c11 = a[0][0] * a[2][2] - a[0][2] * a[2][0];
  const T c12 = a[0][1] * a[2][0] - a[0][0] * a[2][1];
  const T c20 = a[0][1] * a[1][2] - a[0][2] * a[1][1];
  const T c21 = a[0][2] * a[1][0] - a[0][0] * a[1][2];
  const T c22 = a[0][0] * a[1][1] - a[0][1] * a[1][0];
  const T inv_det = T(1) / det;
  dlam[0] = (c00 * rhs[0] + c10 * rhs[1] + c20 * rhs[2]) * inv_det;
  dlam[1] = (c01 * rhs[0] + c11 * rhs[1] + c21 * rhs[2]) * inv_det;
  dlam[2] = (c02 * rhs[0] + c12 * rhs[1] + c22 * rhs[2]) * inv_det;
  for (int i = 0; i < 3; ++i) {
    dx[i] = wi[i] * (dlam[0] * g[i][0] + dlam[1] * g[i][1] + dlam[2] * g[i][2]);
  }
  return true;
}

template <typename T>
inline void add3(T* x, int64_t i, Vec3<T> d) {
  x[3 * i] += d.x;
  x[3 * i + 1] += d.y;
  x[3 * i + 2] += d.z;
}

void check_stretch(const at::Tensor& x, const at::Tensor& lam, const at::Tensor& vert_inv_mass,
                   const at::Tensor& tri_vertices, const at::Tensor& tri_rest_inv, const at::Tensor& tri_compliance) {
  const std::pair<const at::Tensor*, const char*> all[] = {
      {&x, "x"},
      {&lam, "lam"},
      {&vert_inv_mass, "vert_inv_mass"},
      {&tri_vertices, "tri_vertices"},
      {&tri_rest_inv, "tri_rest_inv"},
      {&tri_compliance, "tri_compliance"}};
  for (const auto& [t, name] : all) check_cpu_contiguous(*t, name);
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble,
              "diffavatar: x must be float32 or float64, got ", x.scalar_type());
  const int64_t nv = x.size(0), nf = tri_vertices.size(0);
  check_shape(x, "x", {-1, 3});
  check_shape(tri_vertices, "tri_vertices", {-1, 3});
  check_shape(lam, "lam", {nf, 3});
  check_shape(vert_inv_mass, "vert_inv_mass", {nv});
  check_shape(tri_rest_inv, "tri_rest_inv", {nf, 2, 2});
  check_shape(tri_compliance, "tri_compliance", {nf, 3, 3});
  check_dtype(lam, "lam", x.scalar_type());
  check_dtype(vert_inv_mass, "vert_inv_mass", x.scalar_type());
  check_dtype(tri_rest_inv, "tri_rest_inv", x.scalar_type());
  check_dtype(tri_compliance, "tri_compliance", x.scalar_type());
  check_dtype(tri_vertices, "tri_vertices", at::kLong);
  check_index_range(tri_vertices, nv, "tri_vertices");
}

void check_order(const at::Tensor& order, const at::Tensor& color_offsets, int64_t n_constraints) {
  check_cpu_contiguous(order, "order");
  check_cpu_contiguous(color_offsets, "color_offsets");
  check_shape(order, "order", {-1});
  check_shape(color_offsets, "color_offsets", {-1});
  check_dtype(order, "order", at::kLong);
  check_dtype(color_offsets, "color_offsets", at::kLong);
  check_index_range(order, n_constraints, "order");
  check_color_offsets(color_offsets, order.numel());
}

// One Gauss-Seidel pass over the colours (OpenMP pragmas cannot sit inside AT_DISPATCH's lambda).
template <typename T>
void stretch_gauss_seidel(T* xp, T* lp, const T* wp, const int64_t* tv, const T* rp, const T* ap,
                          const int64_t* ord, const int64_t* off, int64_t n_colors, int64_t total, T inv_dt2) {
  const int nt = num_threads();
#pragma omp parallel if (total >= kParallelGrain && nt > 1) num_threads(nt)
  for (int64_t col = 0; col < n_colors; ++col) {
#pragma omp for schedule(static)
    for (int64_t j = off[col]; j < off[col + 1]; ++j) {
      const int64_t f = ord[j];
      T dlam[3];
      Vec3<T> dx[3];
      if (!stretch_delta(xp, wp, tv + 3 * f, rp + 4 * f, ap + 9 * f, lp + 3 * f, inv_dt2, dlam, dx)) continue;
      for (int k = 0; k < 3; ++k) lp[3 * f + k] += dlam[k];
      for (int i = 0; i < 3; ++i) add3(xp, tv[3 * f + i], dx[i]);
    }
  }
}

void stretch_project_(at::Tensor x, at::Tensor lam, const at::Tensor& vert_inv_mass,
                      const at::Tensor& tri_vertices, const at::Tensor& tri_rest_inv,
                      const at::Tensor& tri_compliance, const at::Tensor& order, const at::Tensor& color_offsets,
                      double dt) {
  check_stretch(x, lam, vert_inv_mass, tri_vertices, tri_rest_inv, tri_compliance);
  check_order(order, color_offsets, tri_vertices.size(0));
  TORCH_CHECK(dt > 0, "diffavatar: dt must be > 0, got ", dt);
  const int64_t* ord = order.data_ptr<int64_t>();
  const int64_t* off = color_offsets.data_ptr<int64_t>();
  const int64_t n_colors = color_offsets.numel() - 1;
  const int64_t total = n_colors > 0 ? off[n_colors] - off[0] : 0;
  const int64_t* tv = tri_vertices.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "stretch_project_", [&] {
    stretch_gauss_seidel(x.data_ptr<scalar_t>(), lam.data_ptr<scalar_t>(), vert_inv_mass.data_ptr<scalar_t>(), tv,
                         tri_rest_inv.data_ptr<scalar_t>(), tri_compliance.data_ptr<scalar_t>(), ord, off, n_colors,
                         total, static_cast<scalar_t>(1.0 / (dt * dt)));
  });
}

// Jacobi pass shared by stretch (arity 3) and bend (arity 4): `delta(c, dx)` computes constraint c's
// corrections from the current x (and updates its lam), returning whether it is active. Then
// x += omega * (sum of dx) / (number of active constraints) per vertex.
template <int Arity, typename T, typename Delta>
void jacobi_pass(T* xp, int64_t nv, const int64_t* ids, int64_t nc, double omega, Delta delta) {
  std::vector<Vec3<T>> dx(static_cast<size_t>(nc) * Arity);
  std::vector<uint8_t> active(static_cast<size_t>(nc));
  const int nt = num_threads();
#pragma omp parallel for schedule(static) if (nc >= kParallelGrain && nt > 1) num_threads(nt)
  for (int64_t c = 0; c < nc; ++c) {
    active[c] = delta(c, &dx[static_cast<size_t>(c) * Arity]) ? 1 : 0;
  }
  std::vector<T> sum(static_cast<size_t>(nv) * 3, T(0));
  std::vector<T> count(static_cast<size_t>(nv), T(0));
  for (int64_t c = 0; c < nc; ++c) {
    if (!active[c]) continue;
    for (int i = 0; i < Arity; ++i) {
      const int64_t v = ids[Arity * c + i];
      const Vec3<T> d = dx[static_cast<size_t>(c) * Arity + i];
      sum[3 * v] += d.x;
      sum[3 * v + 1] += d.y;
      sum[3 * v + 2] += d.z;
      count[v] += T(1);
    }
  }
  const T om = static_cast<T>(omega);
#pragma omp parallel for schedule(static) if (nv >= 4 * kParallelGrain && nt > 1) num_threads(nt)
  for (int64_t v = 0; v < nv; ++v) {
    if (count[v] > T(0)) {
      const T s = om / count[v];
      xp[3 * v] += s * sum[3 * v];
      xp[3 * v + 1] += s * sum[3 * v + 1];
      xp[3 * v + 2] += s * sum[3 * v + 2];
    }
  }
}

void stretch_project_jacobi_(at::Tensor x, at::Tensor lam, const at::Tensor& vert_inv_mass,
                             const at::Tensor& tri_vertices, const at::Tensor& tri_rest_inv,
                             const at::Tensor& tri_compliance, double dt, double omega) {
  check_stretch(x, lam, vert_inv_mass, tri_vertices, tri_rest_inv, tri_compliance);
  TORCH_CHECK(dt > 0, "diffavatar: dt must be > 0, got ", dt);
  const int64_t* tv = tri_vertices.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "stretch_project_jacobi_", [&] {
    scalar_t* xp = x.data_ptr<scalar_t>();
    scalar_t* lp = lam.data_ptr<scalar_t>();
    const scalar_t* wp = vert_inv_mass.data_ptr<scalar_t>();
    const scalar_t* rp = tri_rest_inv.data_ptr<scalar_t>();
    const scalar_t* ap = tri_compliance.data_ptr<scalar_t>();
    const scalar_t inv_dt2 = static_cast<scalar_t>(1.0 / (dt * dt));
    jacobi_pass<3>(xp, x.size(0), tv, tri_vertices.size(0), omega, [&](int64_t f, Vec3<scalar_t>* dx) {
      scalar_t dlam[3];
      if (!stretch_delta(xp, wp, tv + 3 * f, rp + 4 * f, ap + 9 * f, lp + 3 * f, inv_dt2, dlam, dx)) return false;
      for (int k = 0; k < 3; ++k) lp[3 * f + k] += dlam[k];
      return true;
    });
  });
}

// ------------------------------------------------------------------------------------------ bend

constexpr double kBendEpsLen = 1e-12;  // |e| below this: degenerate quad, skipped
constexpr double kBendEpsN2 = 1e-24;   // |n1|^2 or |n2|^2 below this: degenerate quad, skipped

// Correction of one bending constraint at x (dlam and the four w_i-weighted dx). Returns false when
// the quad is degenerate (nothing changes, not even lam).
template <typename T>
inline bool bend_delta(const T* x, const T* w, const int64_t* q, T rest, T alpha, T lam, T inv_dt2, T* dlam,
                       Vec3<T> dx[4]) {
  const Vec3<T> x0 = load3(x, q[0]), x1 = load3(x, q[1]), x2 = load3(x, q[2]), x3 = load3(x, q[3]);
  const Vec3<T> e = x1 - x0;
  const T e_len = std::sqrt(dot(e, e));
  const Vec3<T> n1 = cross(e, x2 - x0);
  const Vec3<T> n2 = cross(x0 - x1, x3 - x1);
  const T n1_sq = dot(n1, n1), n2_sq = dot(n2, n2);
  if (!(e_len >= T(kBendEpsLen) && n1_sq >= T(kBendEpsN2) && n2_sq >= T(kBendEpsN2))) return false;
  const Vec3<T> e_hat = (T(1) / e_len) * e;
  const Vec3<T> m1 = (T(1) / n1_sq) * n1;
  const Vec3<T> m2 = (T(1) / n2_sq) * n2;
  const T theta = std::atan2(dot(cross(n1, n2), e_hat), dot(n1, n2));
  Vec3<T> g[4];
  g[2] = (-e_len) * m1;
  g[3] = (-e_len) * m2;
  g[0] = (-dot(x2 - x1, e_hat)) * m1 - dot(x3 - x1, e_hat) * m2;
  g[1] = dot(x2 - x0, e_hat) * m1 + dot(x3 - x0, e_hat) * m2;
  const T wq[4] = {w[q[0]], w[q[1]], w[q[2]], w[q[3]]};
  const T alpha_t = alpha * inv_dt2;
  const T denom = wq[0] * dot(g[0], g[0]) + wq[1] * dot(g[1], g[1]) + wq[2] * dot(g[2], g[2]) +
                  wq[3] * dot(g[3], g[3]) + alpha_t;
  if (!(denom > T(0))) return false;
  *dlam = (rest - theta - alpha_t * lam) / denom;
  for (int i = 0; i < 4; ++i) dx[i] = (wq[i] * *dlam) * g[i];
  return true;
}

void check_bend(const at::Tensor& x, const at::Tensor& lam, const at::Tensor& vert_inv_mass,
                const at::Tensor& edge_quads, const at::Tensor& edge_rest_angle, const at::Tensor& edge_compliance) {
  const std::pair<const at::Tensor*, const char*> all[] = {
      {&x, "x"},
      {&lam, "lam"},
      {&vert_inv_mass, "vert_inv_mass"},
      {&edge_quads, "edge_quads"},
      {&edge_rest_angle, "edge_rest_angle"},
      {&edge_compliance, "edge_compliance"}};
  for (const auto& [t, name] : all) check_cpu_contiguous(*t, name);
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble,
              "diffavatar: x must be float32 or float64, got ", x.scalar_type());
  const int64_t nv = x.size(0), ne = edge_quads.size(0);
  check_shape(x, "x", {-1, 3});
  check_shape(edge_quads, "edge_quads", {-1, 4});
  check_shape(lam, "lam", {ne});
  check_shape(vert_inv_mass, "vert_inv_mass", {nv});
  check_shape(edge_rest_angle, "edge_rest_angle", {ne});
  check_shape(edge_compliance, "edge_compliance", {ne});
  check_dtype(lam, "lam", x.scalar_type());
  check_dtype(vert_inv_mass, "vert_inv_mass", x.scalar_type());
  check_dtype(edge_rest_angle, "edge_rest_angle", x.scalar_type());
  check_dtype(edge_compliance, "edge_compliance", x.scalar_type());
  check_dtype(edge_quads, "edge_quads", at::kLong);
  check_index_range(edge_quads, nv, "edge_quads");
}

template <typename T>
void bend_gauss_seidel(T* xp, T* lp, const T* wp, const int64_t* qp, const T* rest, const T* alpha,
                       const int64_t* ord, const int64_t* off, int64_t n_colors, int64_t total, T inv_dt2) {
  const int nt = num_threads();
#pragma omp parallel if (total >= kParallelGrain && nt > 1) num_threads(nt)
  for (int64_t col = 0; col < n_colors; ++col) {
#pragma omp for schedule(static)
    for (int64_t j = off[col]; j < off[col + 1]; ++j) {
      const int64_t c = ord[j];
      T dlam;
      Vec3<T> dx[4];
      if (!bend_delta(xp, wp, qp + 4 * c, rest[c], alpha[c], lp[c], inv_dt2, &dlam, dx)) continue;
      lp[c] += dlam;
      for (int i = 0; i < 4; ++i) add3(xp, qp[4 * c + i], dx[i]);
    }
  }
}

void bend_project_(at::Tensor x, at::Tensor lam, const at::Tensor& vert_inv_mass, const at::Tensor& edge_quads,
                   const at::Tensor& edge_rest_angle, const at::Tensor& edge_compliance, const at::Tensor& order,
                   const at::Tensor& color_offsets, double dt) {
  check_bend(x, lam, vert_inv_mass, edge_quads, edge_rest_angle, edge_compliance);
  check_order(order, color_offsets, edge_quads.size(0));
  TORCH_CHECK(dt > 0, "diffavatar: dt must be > 0, got ", dt);
  const int64_t* ord = order.data_ptr<int64_t>();
  const int64_t* off = color_offsets.data_ptr<int64_t>();
  const int64_t n_colors = color_offsets.numel() - 1;
  const int64_t total = n_colors > 0 ? off[n_colors] - off[0] : 0;
  const int64_t* qp = edge_quads.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "bend_project_", [&] {
    bend_gauss_seidel(x.data_ptr<scalar_t>(), lam.data_ptr<scalar_t>(), vert_inv_mass.data_ptr<scalar_t>(), qp,
                      edge_rest_angle.data_ptr<scalar_t>(), edge_compliance.data_ptr<scalar_t>(), ord, off, n_colors,
                      total, static_cast<scalar_t>(1.0 / (dt * dt)));
  });
}

void bend_project_jacobi_(at::Tensor x, at::Tensor lam, const at::Tensor& vert_inv_mass,
                          const at::Tensor& edge_quads, const at::Tensor& edge_rest_angle,
                          const at::Tensor& edge_compliance, double dt, double omega) {
  check_bend(x, lam, vert_inv_mass, edge_quads, edge_rest_angle, edge_compliance);
  TORCH_CHECK(dt > 0, "diffavatar: dt must be > 0, got ", dt);
  const int64_t* qp = edge_quads.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "bend_project_jacobi_", [&] {
    scalar_t* xp = x.data_ptr<scalar_t>();
    scalar_t* lp = lam.data_ptr<scalar_t>();
    const scalar_t* wp = vert_inv_mass.data_ptr<scalar_t>();
    const scalar_t* rest = edge_rest_angle.data_ptr<scalar_t>();
    const scalar_t* alpha = edge_compliance.data_ptr<scalar_t>();
    const scalar_t inv_dt2 = static_cast<scalar_t>(1.0 / (dt * dt));
    jacobi_pass<4>(xp, x.size(0), qp, edge_quads.size(0), omega, [&](int64_t c, Vec3<scalar_t>* dx) {
      scalar_t dlam;
      if (!bend_delta(xp, wp, qp + 4 * c, rest[c], alpha[c], lp[c], inv_dt2, &dlam, dx)) return false;
      lp[c] += dlam;
      return true;
    });
  });
}

}  // namespace
}  // namespace diffavatar

TORCH_LIBRARY_IMPL(diffavatar, CPU, m) {
  m.impl("stretch_project_", &diffavatar::stretch_project_);
  m.impl("stretch_project_jacobi_", &diffavatar::stretch_project_jacobi_);
  m.impl("bend_project_", &diffavatar::bend_project_);
  m.impl("bend_project_jacobi_", &diffavatar::bend_project_jacobi_);
}
