// Closed-form element Hessians of the drape energy (sim/energy.py), optionally projected to PSD.
//
// stretch_hessians(x, tri_vertices, tri_rest_inv, tri_area, stiffness, project) -> (F, 9, 9)
//   Hessian of the orthotropic StVK membrane energy  A/2 Cᵀ K C  of each triangle with respect to its
//   three vertices (dof order 3·corner + axis), C = [E00, E11, E01] the Green strain of F = D D̄⁻¹.
// bend_hessians(x, edge_quads, edge_weight, edge_rest_angle, bend_stiffness, project) -> (E, 12, 12)
//   Hessian of the dihedral bending energy  k_b w/2 (θ − θ̄)²  of each interior edge with respect to its
//   four vertices, θ = atan2((n1 × n2)·ê, n1·n2) as in constraints.dihedral_angles.
// With project=true each block is replaced by its PSD part (negative eigenvalues clamped to 0). Both
// energies are translation invariant, so the block lives on the complement of the translations: we
// project the reduced (6×6 / 9×9) matrix in an orthonormal basis of that complement (same result as
// projecting the full block, a quarter of the work), skip the eigensolve when a Cholesky shows the
// reduced matrix is already positive definite, and otherwise use Householder tridiagonalisation + QL
// (tred2/tql2, the EISPACK algorithm as in JAMA). A bending block has one more exact null vector (sliding
// the vertices along the hinge, `bend_project`), so its Cholesky never succeeds: it is projected in the
// 8-dimensional complement of that one too (with plain roots for std::hypot in tql2: 0.117 → 0.081 s per
// call on the 8k-vertex dress, docs/BENCHMARKS.md).
// Arithmetic in double whatever the input dtype. PyTorch twins: reference.stretch_hessians /
// reference.bend_hessians (torch.func.hessian of the energies + eigh projection).

#include <ATen/ATen.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>

#include "common.h"

namespace diffavatar {
namespace {

// ---- small dense symmetric eigen-projection ------------------------------------------------------

// Householder reduction of the symmetric V (n×n, overwritten by the accumulated transform) to
// tridiagonal form: diagonal d, sub-diagonal e (e[0] = 0). JAMA's tred2.
template <int N>
void tred2(double (&V)[N][N], double (&d)[N], double (&e)[N]) {
  constexpr int n = N;
  for (int j = 0; j < n; ++j) d[j] = V[n - 1][j];
  for (int i = n - 1; i > 0; --i) {
    double scale = 0.0, h = 0.0;
    for (int k = 0; k < i; ++k) scale += std::abs(d[k]);
    if (scale == 0.0) {
      e[i] = d[i - 1];
      for (int j = 0; j < i; ++j) {
        d[j] = V[i - 1][j];
        V[i][j] = 0.0;
        V[j][i] = 0.0;
      }
    } else {
      for (int k = 0; k < i; ++k) {
        d[k] /= scale;
        h += d[k] * d[k];
      }
      double f = d[i - 1];
      double g = std::sqrt(h);
      if (f > 0) g = -g;
      e[i] = scale * g;
      h -= f * g;
      d[i - 1] = f - g;
      for (int j = 0; j < i; ++j) e[j] = 0.0;
      for (int j = 0; j < i; ++j) {
        f = d[j];
        V[j][i] = f;
        g = e[j] + V[j][j] * f;
        for (int k = j + 1; k <= i - 1; ++k) {
          g += V[k][j] * d[k];
          e[k] += V[k][j] * f;
        }
        e[j] = g;
      }
      f = 0.0;
      for (int j = 0; j < i; ++j) {
        e[j] /= h;
        f += e[j] * d[j];
      }
      const double hh = f / (h + h);
      for (int j = 0; j < i; ++j) e[j] -= hh * d[j];
      for (int j = 0; j < i; ++j) {
        f = d[j];
        g = e[j];
        for (int k = j; k <= i - 1; ++k) V[k][j] -= (f * e[k] + g * d[k]);
        d[j] = V[i - 1][j];
        V[i][j] = 0.0;
      }
    }
    d[i] = h;
  }
  for (int i = 0; i < n - 1; ++i) {
    V[n - 1][i] = V[i][i];
    V[i][i] = 1.0;
    const double h = d[i + 1];
    if (h != 0.0) {
      for (int k = 0; k <= i; ++k) d[k] = V[k][i + 1] / h;
      for (int j = 0; j <= i; ++j) {
        double g = 0.0;
        for (int k = 0; k <= i; ++k) g += V[k][i + 1] * V[k][j];
        for (int k = 0; k <= i; ++k) V[k][j] -= g * d[k];
      }
    }
    for (int k = 0; k <= i; ++k) V[k][i + 1] = 0.0;
  }
  for (int j = 0; j < n; ++j) {
    d[j] = V[n - 1][j];
    V[n - 1][j] = 0.0;
  }
  V[n - 1][n - 1] = 1.0;
  e[0] = 0.0;
}

// Implicit QL on the tridiagonal (d, e) with the eigenvectors accumulated into V. JAMA's tql2.
template <int N>
void tql2(double (&V)[N][N], double (&d)[N], double (&e)[N]) {
  constexpr int n = N;
  for (int i = 1; i < n; ++i) e[i - 1] = e[i];
  e[n - 1] = 0.0;
  double f = 0.0, tst1 = 0.0;
  const double eps = std::ldexp(1.0, -52);
  for (int l = 0; l < n; ++l) {
    tst1 = std::max(tst1, std::abs(d[l]) + std::abs(e[l]));
    int m = l;
    while (m < n - 1 && std::abs(e[m]) > eps * tst1) ++m;
    if (m > l) {
      for (int iter = 0; iter < 64; ++iter) {  // converges in 2-3; the cap only guards NaN input
        double g = d[l];
        double p = (d[l + 1] - g) / (2.0 * e[l]);
        double r = std::sqrt(p * p + 1.0);  // not std::hypot: this chain of roots is the op's critical path
        if (p < 0) r = -r;
        d[l] = e[l] / (p + r);
        d[l + 1] = e[l] * (p + r);
        const double dl1 = d[l + 1];
        double h = g - d[l];
        for (int i = l + 2; i < n; ++i) d[i] -= h;
        f += h;
        p = d[m];
        double c = 1.0, c2 = 1.0, c3 = 1.0, s = 0.0, s2 = 0.0;
        const double el1 = e[l + 1];
        for (int i = m - 1; i >= l; --i) {
          c3 = c2;
          c2 = c;
          s2 = s;
          g = c * e[i];
          h = c * p;
          r = std::sqrt(p * p + e[i] * e[i]);  // |p|, |e| ≪ 1e150 here: no overflow to guard
          e[i + 1] = s * r;
          s = e[i] / r;
          c = p / r;
          p = c * d[i] - s * g;
          d[i + 1] = h + s * (c * g + s * d[i]);
          for (int k = 0; k < n; ++k) {
            h = V[k][i + 1];
            V[k][i + 1] = s * V[k][i] + c * h;
            V[k][i] = c * V[k][i] - s * h;
          }
        }
        p = -s * s2 * c3 * el1 * e[l] / dl1;
        e[l] = s * p;
        d[l] = c * p;
        if (!(std::abs(e[l]) > eps * tst1)) break;
      }
    }
    d[l] += f;
    e[l] = 0.0;
  }
}

// True when the symmetric A is positive definite (a Cholesky factorisation succeeds).
template <int N>
bool positive_definite(const double (&A)[N][N]) {
  double L[N][N];
  for (int j = 0; j < N; ++j) {
    double s = A[j][j];
    for (int k = 0; k < j; ++k) s -= L[j][k] * L[j][k];
    if (!(s > 0.0)) return false;
    const double ljj = std::sqrt(s);
    L[j][j] = ljj;
    for (int i = j + 1; i < N; ++i) {
      double t = A[i][j];
      for (int k = 0; k < j; ++k) t -= L[i][k] * L[j][k];
      L[i][j] = t / ljj;
    }
  }
  return true;
}

// A ← its PSD part V max(Λ, 0) Vᵀ (A symmetric).
template <int N>
void project_psd(double (&A)[N][N]) {
  for (int i = 0; i < N; ++i)
    for (int j = 0; j < i; ++j) A[i][j] = A[j][i] = 0.5 * (A[i][j] + A[j][i]);
  if (positive_definite(A)) return;
  double V[N][N], d[N], e[N];
  for (int i = 0; i < N; ++i)
    for (int j = 0; j < N; ++j) V[i][j] = A[i][j];
  tred2(V, d, e);
  tql2(V, d, e);
  for (int k = 0; k < N; ++k) d[k] = std::max(d[k], 0.0);
  for (int i = 0; i < N; ++i) {
    for (int j = i; j < N; ++j) {
      double s = 0.0;
      for (int k = 0; k < N; ++k) s += V[i][k] * d[k] * V[j][k];
      A[i][j] = A[j][i] = s;
    }
  }
}

// Orthonormal bases of the complement of (1, …, 1) in R³ and R⁴ (Helmert), column m of Q[a][m].
constexpr double kS2 = 0.70710678118654752440;   // 1/√2
constexpr double kS6 = 0.40824829046386301637;   // 1/√6
constexpr double kS12 = 0.28867513459481288225;  // 1/√12
constexpr double kQ3[3][2] = {{kS2, kS6}, {-kS2, kS6}, {0.0, -2.0 * kS6}};
constexpr double kQ4[4][3] = {{kS2, kS6, kS12}, {-kS2, kS6, kS12}, {0.0, -2.0 * kS6, kS12}, {0.0, 0.0, -3.0 * kS12}};

// M = Qᵀ H Q for a vertex-block matrix H (3C×3C) and Q = Qc ⊗ I₃ (Qc: C×(C−1)).
template <int C>
void reduce(const double (&H)[3 * C][3 * C], const double (&Qc)[C][C - 1], double (&M)[3 * (C - 1)][3 * (C - 1)]) {
  constexpr int R = C - 1;
  double T[3 * C][3 * R];  // H Q
  for (int i = 0; i < 3 * C; ++i)
    for (int n = 0; n < R; ++n)
      for (int l = 0; l < 3; ++l) {
        double s = 0.0;
        for (int b = 0; b < C; ++b) s += H[i][3 * b + l] * Qc[b][n];
        T[i][3 * n + l] = s;
      }
  for (int m = 0; m < R; ++m)
    for (int k = 0; k < 3; ++k)
      for (int j = 0; j < 3 * R; ++j) {
        double s = 0.0;
        for (int a = 0; a < C; ++a) s += Qc[a][m] * T[3 * a + k][j];
        M[3 * m + k][j] = s;
      }
}

// H = Q M Qᵀ (inverse of `reduce` on the range of Q), written to out (3C×3C, row-major).
template <int C, typename T>
void expand(const double (&M)[3 * (C - 1)][3 * (C - 1)], const double (&Qc)[C][C - 1], T* out) {
  constexpr int R = C - 1;
  double U[3 * R][3 * C];  // M Qᵀ
  for (int i = 0; i < 3 * R; ++i)
    for (int b = 0; b < C; ++b)
      for (int l = 0; l < 3; ++l) {
        double s = 0.0;
        for (int n = 0; n < R; ++n) s += M[i][3 * n + l] * Qc[b][n];
        U[i][3 * b + l] = s;
      }
  for (int a = 0; a < C; ++a)
    for (int k = 0; k < 3; ++k)
      for (int j = 0; j < 3 * C; ++j) {
        double s = 0.0;
        for (int m = 0; m < R; ++m) s += Qc[a][m] * U[3 * m + k][j];
        out[(3 * a + k) * 3 * C + j] = static_cast<T>(s);
      }
}

// A ← P A P with P = I − β w wᵀ, β = 2 / wᵀw (a Householder reflection; A symmetric).
template <int N>
void reflect(double (&A)[N][N], const double (&w)[N], double beta) {
  double p[N], wp = 0.0;
  for (int i = 0; i < N; ++i) {
    double s = 0.0;
    for (int j = 0; j < N; ++j) s += A[i][j] * w[j];
    p[i] = beta * s;
    wp += w[i] * p[i];
  }
  const double k = 0.5 * beta * wp;
  for (int i = 0; i < N; ++i) p[i] -= k * w[i];
  for (int i = 0; i < N; ++i)
    for (int j = 0; j < N; ++j) A[i][j] -= w[i] * p[j] + p[i] * w[j];
}

// PSD part of a bending block, in the 8-dimensional complement of its null space: the translations and
// v_a = ((x_a − x_0)·ê) ê (each vertex slid along the hinge, which leaves θ unchanged; v is null for the
// whole block since every ∇_a θ ⊥ ê and Σ_a ∇_a θ (x_a·ê) = 0 by rotation invariance).
template <typename T>
void bend_project(const double (&H)[12][12], const double (&xq)[4][3], T* out) {
  double M[9][9];
  reduce<4>(H, kQ4, M);
  double eh[3], L2 = 0.0;
  for (int k = 0; k < 3; ++k) eh[k] = xq[1][k] - xq[0][k], L2 += eh[k] * eh[k];
  const double L = std::sqrt(L2);
  for (int k = 0; k < 3; ++k) eh[k] /= L;
  double c[4];
  for (int a = 0; a < 4; ++a)
    c[a] = (xq[a][0] - xq[0][0]) * eh[0] + (xq[a][1] - xq[0][1]) * eh[1] + (xq[a][2] - xq[0][2]) * eh[2];
  double w[9], yy = 0.0;  // w ← y = Qᵀ v, the null vector in the reduced basis (|y| ≥ L/√2 > 0)
  for (int m = 0; m < 3; ++m) {
    const double cm = kQ4[0][m] * c[0] + kQ4[1][m] * c[1] + kQ4[2][m] * c[2] + kQ4[3][m] * c[3];
    for (int k = 0; k < 3; ++k) w[3 * m + k] = cm * eh[k], yy += w[3 * m + k] * w[3 * m + k];
  }
  const double ny = std::sqrt(yy);
  const double y8 = std::abs(w[8]);
  w[8] += w[8] >= 0.0 ? ny : -ny;  // then P y = ∓|y| e₈ (the sign that avoids cancellation)
  const double beta = 1.0 / (ny * (ny + y8));  // 2 / wᵀw
  for (int i = 0; i < 9; ++i)
    for (int j = 0; j < i; ++j) M[i][j] = M[j][i] = 0.5 * (M[i][j] + M[j][i]);
  reflect(M, w, beta);
  double B[8][8];
  for (int i = 0; i < 8; ++i)
    for (int j = 0; j < 8; ++j) B[i][j] = M[i][j];
  project_psd(B);
  for (int i = 0; i < 9; ++i)
    for (int j = 0; j < 9; ++j) M[i][j] = i < 8 && j < 8 ? B[i][j] : 0.0;
  reflect(M, w, beta);
  expand<4>(M, kQ4, out);
}

// ---- StVK membrane --------------------------------------------------------------------------------

// Reduced Hessian (6×6, basis kQ3 ⊗ I₃) of A/2 CᵀKC for one triangle.
void stretch_reduced(const double (&xt)[3][3], const double (&R)[2][2], double area, const double (&K)[3][3],
                     double (&M)[6][6]) {
  // F = Σ_a x_a g_aᵀ with g_0 = R[0,:], g_1 = R[1,:], g_2 = −g_0 − g_1 (F = [x0−x2, x1−x2] R)
  const double g[3][2] = {{R[0][0], R[0][1]}, {R[1][0], R[1][1]}, {-R[0][0] - R[1][0], -R[0][1] - R[1][1]}};
  double f0[3], f1[3];
  for (int k = 0; k < 3; ++k) {
    f0[k] = g[0][0] * xt[0][k] + g[1][0] * xt[1][k] + g[2][0] * xt[2][k];
    f1[k] = g[0][1] * xt[0][k] + g[1][1] * xt[1][k] + g[2][1] * xt[2][k];
  }
  const double c[3] = {0.5 * (f0[0] * f0[0] + f0[1] * f0[1] + f0[2] * f0[2] - 1.0),
                       0.5 * (f1[0] * f1[0] + f1[1] * f1[1] + f1[2] * f1[2] - 1.0),
                       0.5 * (f0[0] * f1[0] + f0[1] * f1[1] + f0[2] * f1[2])};
  double s[3];
  for (int i = 0; i < 3; ++i) s[i] = K[i][0] * c[0] + K[i][1] * c[1] + K[i][2] * c[2];
  // the basis vectors' g̃_m = Σ_a Q3[a][m] g_a and the strain Jacobians J̃_m (3 components × 3 axes)
  double gt[2][2], J[2][3][3];
  for (int m = 0; m < 2; ++m) {
    for (int j = 0; j < 2; ++j) gt[m][j] = kQ3[0][m] * g[0][j] + kQ3[1][m] * g[1][j] + kQ3[2][m] * g[2][j];
    for (int k = 0; k < 3; ++k) {
      J[m][0][k] = gt[m][0] * f0[k];
      J[m][1][k] = gt[m][1] * f1[k];
      J[m][2][k] = 0.5 * (gt[m][0] * f1[k] + gt[m][1] * f0[k]);
    }
  }
  for (int m = 0; m < 2; ++m) {
    for (int n = 0; n < 2; ++n) {
      const double sig = s[0] * gt[m][0] * gt[n][0] + s[1] * gt[m][1] * gt[n][1] +
                         0.5 * s[2] * (gt[m][0] * gt[n][1] + gt[m][1] * gt[n][0]);
      double KJ[3][3];  // K J̃_n
      for (int i = 0; i < 3; ++i)
        for (int l = 0; l < 3; ++l) KJ[i][l] = K[i][0] * J[n][0][l] + K[i][1] * J[n][1][l] + K[i][2] * J[n][2][l];
      for (int k = 0; k < 3; ++k)
        for (int l = 0; l < 3; ++l) {
          const double v = J[m][0][k] * KJ[0][l] + J[m][1][k] * KJ[1][l] + J[m][2][k] * KJ[2][l];
          M[3 * m + k][3 * n + l] = area * (v + (k == l ? sig : 0.0));
        }
    }
  }
}

template <typename T>
void stretch_kernel(const T* x, const int64_t* tri, const T* rest_inv, const T* area, const double (&K)[3][3],
                    bool project, T* out, int64_t nf) {
  const int nt = num_threads();
#pragma omp parallel for schedule(static) if (nf >= kParallelGrain && nt > 1) num_threads(nt)
  for (int64_t f = 0; f < nf; ++f) {
    double xt[3][3], R[2][2], M[6][6];
    for (int a = 0; a < 3; ++a)
      for (int k = 0; k < 3; ++k) xt[a][k] = static_cast<double>(x[3 * tri[3 * f + a] + k]);
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 2; ++j) R[i][j] = static_cast<double>(rest_inv[4 * f + 2 * i + j]);
    stretch_reduced(xt, R, static_cast<double>(area[f]), K, M);
    if (project) project_psd(M);
    expand<3>(M, kQ3, out + 81 * f);
  }
}

// ---- dihedral bending -----------------------------------------------------------------------------

inline void skew(const double (&v)[3], double (&S)[3][3]) {  // S(v)_ij = ε_ijk v_k (= −[v]×)
  S[0][0] = 0.0, S[0][1] = v[2], S[0][2] = -v[1];
  S[1][0] = -v[2], S[1][1] = 0.0, S[1][2] = v[0];
  S[2][0] = v[1], S[2][1] = -v[0], S[2][2] = 0.0;
}

inline void cross3(const double (&a)[3], const double (&b)[3], double (&c)[3]) {
  c[0] = a[1] * b[2] - a[2] * b[1];
  c[1] = a[2] * b[0] - a[0] * b[2];
  c[2] = a[0] * b[1] - a[1] * b[0];
}

// Full Hessian (12×12) of k_b w/2 (θ − θ̄)² for one edge quad.
void bend_full(const double (&xq)[4][3], double weight, double rest_angle, double kb, double (&H)[12][12]) {
  double e[3], a[3], b[3], c[3], n1[3], n2[3];
  for (int k = 0; k < 3; ++k) {
    e[k] = xq[1][k] - xq[0][k];
    a[k] = xq[2][k] - xq[0][k];
    b[k] = xq[0][k] - xq[1][k];
    c[k] = xq[3][k] - xq[1][k];
  }
  cross3(e, a, n1);
  cross3(b, c, n2);
  // θ(u) with u = (n1, n2, e): p = (n1 × n2)·e / |e|, q = n1·n2, θ = atan2(p, q)
  double m[3], n2e[3], en1[3];
  cross3(n1, n2, m);
  cross3(n2, e, n2e);
  cross3(e, n1, en1);
  const double L = std::sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);
  const double eh[3] = {e[0] / L, e[1] / L, e[2] / L};
  const double P = m[0] * e[0] + m[1] * e[1] + m[2] * e[2];
  const double p = P / L;
  const double q = n1[0] * n2[0] + n1[1] * n2[1] + n1[2] * n2[2];
  const double theta = std::atan2(p, q);
  double gP[9], gL[9] = {0, 0, 0, 0, 0, 0, eh[0], eh[1], eh[2]}, gp[9], gq[9];
  for (int k = 0; k < 3; ++k) {
    gP[k] = n2e[k], gP[3 + k] = en1[k], gP[6 + k] = m[k];
    gq[k] = n2[k], gq[3 + k] = n1[k], gq[6 + k] = 0.0;
  }
  for (int i = 0; i < 9; ++i) gp[i] = gP[i] / L - P * gL[i] / (L * L);
  double hP[9][9] = {}, hp[9][9], hq[9][9] = {};
  {
    double Se[3][3], Sn1[3][3], Sn2[3][3];
    skew(e, Se);
    skew(n1, Sn1);
    skew(n2, Sn2);
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        hP[i][3 + j] = Se[i][j];       // ∂²P/∂n1∂n2
        hP[3 + j][i] = Se[i][j];
        hP[i][6 + j] = -Sn2[i][j];     // ∂²P/∂n1∂e
        hP[6 + j][i] = -Sn2[i][j];
        hP[3 + i][6 + j] = Sn1[i][j];  // ∂²P/∂n2∂e
        hP[6 + j][3 + i] = Sn1[i][j];
      }
    for (int i = 0; i < 3; ++i) hq[i][3 + i] = hq[3 + i][i] = 1.0;
  }
  for (int i = 0; i < 9; ++i)
    for (int j = 0; j < 9; ++j) {
      double v = hP[i][j] / L - (gP[i] * gL[j] + gL[i] * gP[j]) / (L * L) + 2.0 * P * gL[i] * gL[j] / (L * L * L);
      if (i >= 6 && j >= 6) v -= P * ((i == j ? 1.0 : 0.0) - eh[i - 6] * eh[j - 6]) / (L * L * L);  // P ∇²L / L²
      hp[i][j] = v;
    }
  const double r2 = p * p + q * q;
  double gt[9], ht[9][9];
  for (int i = 0; i < 9; ++i) gt[i] = (q * gp[i] - p * gq[i]) / r2;
  for (int i = 0; i < 9; ++i)
    for (int j = 0; j < 9; ++j)
      ht[i][j] = (q * hp[i][j] - p * hq[i][j]) / r2 -
                 (2.0 / (r2 * r2)) * (p * q * (gp[i] * gp[j] - gq[i] * gq[j]) +
                                      0.5 * (q * q - p * p) * (gp[i] * gq[j] + gq[i] * gp[j]));
  // chain rule to x: J (9 × 12) in 3×3 blocks J[u-block][vertex], u-blocks n1, n2, e
  double J[3][4][3][3] = {};
  {
    double Sa[3][3], Se[3][3], Sb[3][3], Sc[3][3];
    skew(a, Sa);
    skew(e, Se);
    skew(b, Sb);
    skew(c, Sc);
    // d n1 = −[a]× de + [e]× da, [v]× = −S(v); de = dx1 − dx0, da = dx2 − dx0
    // d n2 = −[c]× db + [b]× dc; db = dx0 − dx1, dc = dx3 − dx1
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        J[0][0][i][j] = Se[i][j] - Sa[i][j];
        J[0][1][i][j] = Sa[i][j];
        J[0][2][i][j] = -Se[i][j];
        J[1][0][i][j] = Sc[i][j];
        J[1][1][i][j] = Sb[i][j] - Sc[i][j];
        J[1][3][i][j] = -Sb[i][j];
      }
    for (int i = 0; i < 3; ++i) J[2][0][i][i] = -1.0, J[2][1][i][i] = 1.0;
  }
  double g12[12], H12[12][12];
  for (int v = 0; v < 4; ++v)
    for (int k = 0; k < 3; ++k) {
      double s = 0.0;
      for (int ub = 0; ub < 3; ++ub)
        for (int i = 0; i < 3; ++i) s += J[ub][v][i][k] * gt[3 * ub + i];
      g12[3 * v + k] = s;
    }
  double T[9][12];  // ∇²θ_u J
  for (int i = 0; i < 9; ++i)
    for (int v = 0; v < 4; ++v)
      for (int k = 0; k < 3; ++k) {
        double s = 0.0;
        for (int ub = 0; ub < 3; ++ub)
          for (int j = 0; j < 3; ++j) s += ht[i][3 * ub + j] * J[ub][v][j][k];
        T[i][3 * v + k] = s;
      }
  for (int v = 0; v < 4; ++v)
    for (int k = 0; k < 3; ++k)
      for (int col = 0; col < 12; ++col) {
        double s = 0.0;
        for (int ub = 0; ub < 3; ++ub)
          for (int i = 0; i < 3; ++i) s += J[ub][v][i][k] * T[3 * ub + i][col];
        H12[3 * v + k][col] = s;
      }
  // second-order terms of the bilinear normals: λ·(u × w) has ∂²/∂u∂w = S(λ)
  {
    const double l1[3] = {gt[0], gt[1], gt[2]}, l2[3] = {gt[3], gt[4], gt[5]};
    double S1[3][3], S2[3][3];
    skew(l1, S1);
    skew(l2, S2);
    const double ce[4] = {-1, 1, 0, 0}, ca[4] = {-1, 0, 1, 0}, cb[4] = {1, -1, 0, 0}, cc[4] = {0, -1, 0, 1};
    for (int al = 0; al < 4; ++al)
      for (int be = 0; be < 4; ++be) {
        const double w1 = ce[al] * ca[be], w1t = ca[al] * ce[be];
        const double w2 = cb[al] * cc[be], w2t = cc[al] * cb[be];
        if (w1 == 0 && w1t == 0 && w2 == 0 && w2t == 0) continue;
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j)
            H12[3 * al + i][3 * be + j] += w1 * S1[i][j] + w1t * S1[j][i] + w2 * S2[i][j] + w2t * S2[j][i];
      }
  }
  const double kw = kb * weight, dth = theta - rest_angle;
  for (int i = 0; i < 12; ++i)
    for (int j = 0; j < 12; ++j) H[i][j] = kw * (g12[i] * g12[j] + dth * H12[i][j]);
}

template <typename T>
void bend_kernel(const T* x, const int64_t* quads, const T* weight, const T* rest_angle, double kb, bool project,
                 T* out, int64_t ne) {
  const int nt = num_threads();
#pragma omp parallel for schedule(static) if (ne >= kParallelGrain && nt > 1) num_threads(nt)
  for (int64_t q = 0; q < ne; ++q) {
    double xq[4][3], H[12][12];
    for (int a = 0; a < 4; ++a)
      for (int k = 0; k < 3; ++k) xq[a][k] = static_cast<double>(x[3 * quads[4 * q + a] + k]);
    bend_full(xq, static_cast<double>(weight[q]), static_cast<double>(rest_angle[q]), kb, H);
    T* o = out + 144 * q;
    if (project) {
      bend_project(H, xq, o);
    } else {
      for (int i = 0; i < 12; ++i)
        for (int j = 0; j < 12; ++j) o[12 * i + j] = static_cast<T>(H[i][j]);
    }
  }
}

at::Tensor stretch_hessians(const at::Tensor& x, const at::Tensor& tri_vertices, const at::Tensor& tri_rest_inv,
                            const at::Tensor& tri_area, const at::Tensor& stiffness, bool project) {
  check_cpu_contiguous(x, "x");
  check_cpu_contiguous(tri_vertices, "tri_vertices");
  check_cpu_contiguous(tri_rest_inv, "tri_rest_inv");
  check_cpu_contiguous(tri_area, "tri_area");
  check_dtype(tri_vertices, "tri_vertices", at::kLong);
  check_shape(x, "x", {-1, 3});
  const int64_t nf = tri_vertices.size(0);
  check_shape(tri_vertices, "tri_vertices", {nf, 3});
  check_shape(tri_rest_inv, "tri_rest_inv", {nf, 2, 2});
  check_shape(tri_area, "tri_area", {nf});
  check_shape(stiffness, "stiffness", {3, 3});
  TORCH_CHECK(tri_rest_inv.scalar_type() == x.scalar_type() && tri_area.scalar_type() == x.scalar_type(),
              "diffavatar: stretch_hessians inputs must share x's dtype");
  check_index_range(tri_vertices, x.size(0), "tri_vertices");
  const at::Tensor kd = stiffness.to(at::kCPU, at::kDouble).contiguous();
  double K[3][3];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) K[i][j] = kd.data_ptr<double>()[3 * i + j];
  at::Tensor out = at::empty({nf, 9, 9}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "stretch_hessians", [&] {
    stretch_kernel<scalar_t>(x.data_ptr<scalar_t>(), tri_vertices.data_ptr<int64_t>(),
                             tri_rest_inv.data_ptr<scalar_t>(), tri_area.data_ptr<scalar_t>(), K, project,
                             out.data_ptr<scalar_t>(), nf);
  });
  return out;
}

at::Tensor bend_hessians(const at::Tensor& x, const at::Tensor& edge_quads, const at::Tensor& edge_weight,
                         const at::Tensor& edge_rest_angle, double bend_stiffness, bool project) {
  check_cpu_contiguous(x, "x");
  check_cpu_contiguous(edge_quads, "edge_quads");
  check_cpu_contiguous(edge_weight, "edge_weight");
  check_cpu_contiguous(edge_rest_angle, "edge_rest_angle");
  check_dtype(edge_quads, "edge_quads", at::kLong);
  check_shape(x, "x", {-1, 3});
  const int64_t ne = edge_quads.size(0);
  check_shape(edge_quads, "edge_quads", {ne, 4});
  check_shape(edge_weight, "edge_weight", {ne});
  check_shape(edge_rest_angle, "edge_rest_angle", {ne});
  TORCH_CHECK(edge_weight.scalar_type() == x.scalar_type() && edge_rest_angle.scalar_type() == x.scalar_type(),
              "diffavatar: bend_hessians inputs must share x's dtype");
  check_index_range(edge_quads, x.size(0), "edge_quads");
  at::Tensor out = at::empty({ne, 12, 12}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "bend_hessians", [&] {
    bend_kernel<scalar_t>(x.data_ptr<scalar_t>(), edge_quads.data_ptr<int64_t>(), edge_weight.data_ptr<scalar_t>(),
                          edge_rest_angle.data_ptr<scalar_t>(), bend_stiffness, project, out.data_ptr<scalar_t>(),
                          ne);
  });
  return out;
}

}  // namespace
}  // namespace diffavatar

TORCH_LIBRARY_FRAGMENT(diffavatar, m) {
  // Per-triangle StVK membrane Hessians (F, 9, 9), PSD-projected when project=true.
  m.def(
      "stretch_hessians(Tensor x, Tensor tri_vertices, Tensor tri_rest_inv, Tensor tri_area, Tensor stiffness, "
      "bool project) -> Tensor");
  // Per-edge dihedral bending Hessians (E, 12, 12), PSD-projected when project=true.
  m.def(
      "bend_hessians(Tensor x, Tensor edge_quads, Tensor edge_weight, Tensor edge_rest_angle, float bend_stiffness, "
      "bool project) -> Tensor");
}

TORCH_LIBRARY_IMPL(diffavatar, CPU, m) {
  m.impl("stretch_hessians", &diffavatar::stretch_hessians);
  m.impl("bend_hessians", &diffavatar::bend_hessians);
}
