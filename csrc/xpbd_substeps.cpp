// Fused XPBD substeps: `xpbd_substeps_` runs `substeps` × (predict → `iterations` × (stretch, bend,
// attachments, body contacts, stitches) → friction → velocity update) in one call, in place on x and v.
// Its PyTorch twin is `torch_diffavatar/sim/reference.py: xpbd_substeps_`, whose maths `xpbd_substeps`
// (the per-constraint reference kernels and `sim/contacts.py`) is also the frame the trajectory adjoint
// replays; the tests compare the two (tests/sim/test_ops_cpp.py, test_xpbd_frame.py). The arguments come
// grouped by role (tensor lists stretch, bend, seams, body and the float list coefficients), in the
// layout of `sim/substep.py` (SubstepInputs), unpacked once below (FrameTensors, unpack_options).
//
// Why one op: a substep of the 64x64 benchmark sheet is ~1 ms of arithmetic, so per-kernel dispatch,
// argument checks and the torch contact/stitch code (~2 ms) dominated. Here the inputs are checked once,
// then repacked once per call into colour-ordered structure-of-arrays with per-constraint constants
// (int32 vertex ids, w-weighted rest coefficients, alpha / dt^2), so the hot loops stream memory.
//
// The positions are padded to 4 numbers per vertex inside the op (kStride; copied in and out once per
// call). Gauss-Seidel colours are processed in blocks of kBlock constraints: gather the block's vertices,
// compute all corrections in a `#pragma omp simd` loop (branch-free; the dihedral angle uses a
// branch-free atan2 accurate to 1 ulp), scatter. A colour's constraints share no vertex, so the order
// inside a colour does not matter and the result equals the reference's (vectorised per colour) up to
// rounding. Jacobi ("jacobi" = true) treats all constraints as one colour and averages per vertex.
//
// Threads: `num_threads` > 1 runs the substeps in one OpenMP team (a barrier per colour; blocks of a
// colour split across threads); Jacobi always runs on one thread. 0 means torch's intra-op setting.

#if defined(__GNUC__) && !defined(__clang__)
// No FP exception is ever inspected, so FP operations may be speculated (no value changes): GCC can
// then if-convert the branch-free SIMD loops below. Set before the includes so that the headers'
// inline functions (std::fabs, ...) share the attribute and still inline.
#pragma GCC optimize("no-trapping-math")
// V4<double> (below) is 32 bytes: without AVX its ABI as a return value differs, which does not matter for
// helpers that are always inlined
#pragma GCC diagnostic ignored "-Wpsabi"
#endif

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <vector>

#include "common.h"

// The block kernels are inlined into per-dtype entry points that GCC compiles twice on x86-64 Linux:
// for AVX2 (8 float / 4 double lanes) and for the baseline ISA (SSE2), picked once at load time by the
// CPU's features (ifunc). Elsewhere the baseline build alone. (An x86-64-v4 clone, AVX-512, was 8 %
// faster still on the 2-core AMD EPYC but rounds differently from the AVX2 build: not taken.)
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define DIFFAVATAR_SIMD_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define DIFFAVATAR_SIMD_CLONES
#endif
#if defined(__GNUC__)
#define DIFFAVATAR_INLINE inline __attribute__((always_inline))
#else
#define DIFFAVATAR_INLINE inline
#endif

namespace diffavatar {
namespace {

constexpr int kBlock = 32;  // constraints per gather / compute / scatter block

// --------------------------------------------------------------------------------------------- atan2

// Branch-free atan2 (Cephes' atan / atanf rational and polynomial approximations after reduction of
// min(|x|,|y|)/max(|x|,|y|) to |u| <= 0.66 (double) or tan(pi/8) (float)). Max error vs std::atan2
// measured 4.4e-16 (double) and 2.6e-7 (float) over 5M random arguments. atan2(0, 0) = 0.
template <typename T>
inline T atan2_fast(T y, T x);

template <>
DIFFAVATAR_INLINE double atan2_fast<double>(double y, double x) {
  const double ax = std::fabs(x), ay = std::fabs(y);
  const double mn = ax < ay ? ax : ay, mx = ax < ay ? ay : ax;
  const bool big = mn > 0.66 * mx;
  const double u = (big ? mn - mx : mn) / (big ? mn + mx : (mx > 0 ? mx : 1.0));
  const double z = u * u;
  const double p = ((((-8.750608600031904122785E-1 * z - 1.615753718733365076637E1) * z - 7.500855792314704667340E1) * z -
                     1.228866684490136173410E2) *
                        z -
                    6.485021904942025371773E1);
  const double q = (((((z + 2.485846490142306297962E1) * z + 1.650270098316988542046E2) * z + 4.328810604912902668951E2) * z +
                     4.853903996359136964868E2) *
                        z +
                    1.945506571482613964425E2);
  constexpr double kMoreBits = 6.123233995736765886130E-17;  // pi/2 - double(pi/2)
  double r = u + u * (z * p / q);
  r = big ? r + (0.78539816339744830962 + 0.5 * kMoreBits) : r;
  r = ay > ax ? 1.57079632679489661923 - r + kMoreBits : r;
  r = x < 0 ? 3.14159265358979323846 - r + 2.0 * kMoreBits : r;
  return std::copysign(r, y);
}

template <>
DIFFAVATAR_INLINE float atan2_fast<float>(float y, float x) {
  const float ax = std::fabs(x), ay = std::fabs(y);
  const float mn = ax < ay ? ax : ay, mx = ax < ay ? ay : ax;
  const bool big = mn > 0.41421356237f * mx;
  const float u = (big ? mn - mx : mn) / (big ? mn + mx : (mx > 0 ? mx : 1.0f));
  const float z = u * u;
  float r = (((8.05374449538e-2f * z - 1.38776856032e-1f) * z + 1.99777106478e-1f) * z - 3.33329491539e-1f) * z * u + u;
  r = big ? r + 0.78539816339744830962f : r;
  r = ay > ax ? 1.57079632679489661923f - r : r;
  r = x < 0 ? 3.14159265358979323846f - r : r;
  return std::copysign(r, y);
}

// ------------------------------------------------------------------------------------ packed data

// Stretch blocks of the active triangles (at least one movable corner), colour by colour. With
// rest_inv = [[a, b], [c, d]] and per corner (p_i, q_i) = (a, b), (c, d), (-a-c, -b-d):
// wp_i = w_i p_i, wq_i = w_i q_i, wpp = sum w p^2, wqq = sum w q^2, wpq = sum w p q (see
// reference._stretch_delta), al_kl = alpha_kl / dt^2 (upper triangle; alpha is symmetric).
template <typename T>
struct StretchPack {
  std::vector<int64_t> seg;  // colour boundaries in packed order
  std::vector<int32_t> v0, v1, v2;
  std::vector<T> ra, rb, rc, rd, wpp, wqq, wpq, wp0, wp1, wp2, wq0, wq1, wq2, a00, a01, a02, a11, a12, a22;
  std::vector<T> l0, l1, l2;  // multipliers (reset every substep)
};

// Bending constraints with at least one movable vertex, colour by colour.
template <typename T>
struct BendPack {
  std::vector<int64_t> seg;
  std::vector<int32_t> q0, q1, q2, q3;
  std::vector<T> w0, w1, w2, w3, rest, at, lam;
};

// Order of the constraints to pack: colour by colour (Gauss-Seidel) or all in index order as one colour
// (Jacobi).
inline void packing_order(bool jacobi, int64_t n, const at::Tensor& order, const at::Tensor& offsets,
                          std::vector<int64_t>& ids, std::vector<int64_t>& color_end) {
  ids.clear();
  color_end.clear();
  if (jacobi) {
    for (int64_t i = 0; i < n; ++i) ids.push_back(i);
    color_end.push_back(n);
    return;
  }
  const int64_t* ord = order.data_ptr<int64_t>();
  const int64_t* off = offsets.data_ptr<int64_t>();
  for (int64_t c = 0; c + 1 < offsets.numel(); ++c) {
    for (int64_t j = off[c]; j < off[c + 1]; ++j) ids.push_back(ord[j]);
    color_end.push_back(static_cast<int64_t>(ids.size()));
  }
}

template <typename T>
StretchPack<T> pack_stretch(const at::Tensor& tri_vertices, const at::Tensor& rest_inv, const at::Tensor& compliance,
                            const at::Tensor& order, const at::Tensor& offsets, const T* w, bool jacobi, T inv_dt2) {
  StretchPack<T> p;
  std::vector<int64_t> ids, color_end;
  packing_order(jacobi, tri_vertices.size(0), order, offsets, ids, color_end);
  const int64_t* tv = tri_vertices.data_ptr<int64_t>();
  const T* r = rest_inv.data_ptr<T>();
  const T* al = compliance.data_ptr<T>();
  p.seg.push_back(0);
  size_t k = 0;
  for (const int64_t end : color_end) {
    for (; k < static_cast<size_t>(end); ++k) {
      const int64_t f = ids[k];
      const int64_t i0 = tv[3 * f], i1 = tv[3 * f + 1], i2 = tv[3 * f + 2];
      const T w0 = w[i0], w1 = w[i1], w2 = w[i2];
      if (!(w0 > 0 || w1 > 0 || w2 > 0)) continue;
      const T a = r[4 * f], b = r[4 * f + 1], c = r[4 * f + 2], d = r[4 * f + 3];
      const T pp[3] = {a, c, -a - c}, qq[3] = {b, d, -b - d}, ww[3] = {w0, w1, w2};
      T wpp = 0, wqq = 0, wpq = 0;
      for (int i = 0; i < 3; ++i) {
        wpp += ww[i] * pp[i] * pp[i];
        wqq += ww[i] * qq[i] * qq[i];
        wpq += ww[i] * pp[i] * qq[i];
      }
      p.v0.push_back(static_cast<int32_t>(i0));
      p.v1.push_back(static_cast<int32_t>(i1));
      p.v2.push_back(static_cast<int32_t>(i2));
      p.ra.push_back(a);
      p.rb.push_back(b);
      p.rc.push_back(c);
      p.rd.push_back(d);
      p.wpp.push_back(wpp);
      p.wqq.push_back(wqq);
      p.wpq.push_back(wpq);
      p.wp0.push_back(w0 * pp[0]);
      p.wp1.push_back(w1 * pp[1]);
      p.wp2.push_back(w2 * pp[2]);
      p.wq0.push_back(w0 * qq[0]);
      p.wq1.push_back(w1 * qq[1]);
      p.wq2.push_back(w2 * qq[2]);
      const T* m = al + 9 * f;
      p.a00.push_back(m[0] * inv_dt2);
      p.a01.push_back(m[1] * inv_dt2);
      p.a02.push_back(m[2] * inv_dt2);
      p.a11.push_back(m[4] * inv_dt2);
      p.a12.push_back(m[5] * inv_dt2);
      p.a22.push_back(m[8] * inv_dt2);
    }
    p.seg.push_back(static_cast<int64_t>(p.v0.size()));
  }
  p.l0.assign(p.v0.size(), T(0));
  p.l1.assign(p.v0.size(), T(0));
  p.l2.assign(p.v0.size(), T(0));
  return p;
}

template <typename T>
BendPack<T> pack_bend(const at::Tensor& quads, const at::Tensor& rest_angle, const at::Tensor& compliance,
                      const at::Tensor& order, const at::Tensor& offsets, const T* w, bool jacobi, T inv_dt2) {
  BendPack<T> p;
  std::vector<int64_t> ids, color_end;
  packing_order(jacobi, quads.size(0), order, offsets, ids, color_end);
  const int64_t* q = quads.data_ptr<int64_t>();
  const T* rest = rest_angle.data_ptr<T>();
  const T* al = compliance.data_ptr<T>();
  p.seg.push_back(0);
  size_t k = 0;
  for (const int64_t end : color_end) {
    for (; k < static_cast<size_t>(end); ++k) {
      const int64_t e = ids[k];
      const int64_t* qe = q + 4 * e;
      const T w0 = w[qe[0]], w1 = w[qe[1]], w2 = w[qe[2]], w3 = w[qe[3]];
      if (!(w0 > 0 || w1 > 0 || w2 > 0 || w3 > 0)) continue;
      p.q0.push_back(static_cast<int32_t>(qe[0]));
      p.q1.push_back(static_cast<int32_t>(qe[1]));
      p.q2.push_back(static_cast<int32_t>(qe[2]));
      p.q3.push_back(static_cast<int32_t>(qe[3]));
      p.w0.push_back(w0);
      p.w1.push_back(w1);
      p.w2.push_back(w2);
      p.w3.push_back(w3);
      p.rest.push_back(rest[e]);
      p.at.push_back(al[e] * inv_dt2);
    }
    p.seg.push_back(static_cast<int64_t>(p.q0.size()));
  }
  p.lam.assign(p.q0.size(), T(0));
  return p;
}

// ------------------------------------------------------------------------------ gather and scatter

// Inside the op the positions are padded to 4 per vertex (x, y, z, unused; `kStride`), so that a vertex
// is one 4-lane vector: a block gathers 4 vertices with 4 loads and a 4x4 transpose into its rows, and
// scatters with a 3x4 transpose and 4 load-add-stores. Per element that is about half the instructions
// of scalar loads and stores, which were 60-70 % of the block kernels' time (perf; docs/BENCHMARKS.md,
// "The substep op's gathers and scatters").
constexpr int kStride = 4;

template <typename T>
struct Lanes4 {
  typedef T type __attribute__((vector_size(4 * sizeof(T))));
};
template <typename T>
using V4 = typename Lanes4<T>::type;

template <typename T>
DIFFAVATAR_INLINE V4<T> load4(const T* p) {
  V4<T> r;
  std::memcpy(&r, p, sizeof r);
  return r;
}

template <typename T>
DIFFAVATAR_INLINE void store4(T* p, V4<T> a) {
  std::memcpy(p, &a, sizeof a);
}

// Rows rx, ry, rz [l] = the coordinates of vertex idx[l] of the padded positions xp, l < n.
template <typename T>
DIFFAVATAR_INLINE void gather_rows(const T* xp, const int32_t* idx, int n, T* rx, T* ry, T* rz) {
  int l = 0;
  for (; l + 4 <= n; l += 4) {
    const V4<T> a = load4(xp + kStride * static_cast<int64_t>(idx[l]));
    const V4<T> b = load4(xp + kStride * static_cast<int64_t>(idx[l + 1]));
    const V4<T> c = load4(xp + kStride * static_cast<int64_t>(idx[l + 2]));
    const V4<T> d = load4(xp + kStride * static_cast<int64_t>(idx[l + 3]));
    const V4<T> ab = __builtin_shufflevector(a, b, 0, 4, 1, 5);  // ax bx ay by
    const V4<T> cd = __builtin_shufflevector(c, d, 0, 4, 1, 5);  // cx dx cy dy
    const V4<T> abz = __builtin_shufflevector(a, b, 2, 6, 3, 7);
    const V4<T> cdz = __builtin_shufflevector(c, d, 2, 6, 3, 7);
    store4(rx + l, __builtin_shufflevector(ab, cd, 0, 1, 4, 5));
    store4(ry + l, __builtin_shufflevector(ab, cd, 2, 3, 6, 7));
    store4(rz + l, __builtin_shufflevector(abz, cdz, 0, 1, 4, 5));
  }
  for (; l < n; ++l) {
    const T* a = xp + kStride * static_cast<int64_t>(idx[l]);
    rx[l] = a[0], ry[l] = a[1], rz[l] = a[2];
  }
}

// Where a block's corrections go: added to the padded positions x (Gauss-Seidel: the vertices of a
// block are distinct) or summed per vertex with a count (Jacobi: they are not).
template <typename T>
struct Sink {
  T* x;
  T* acc;    // (V, kStride) or nullptr
  T* count;  // (V,) or nullptr

  // Adds (dx, dy, dz)[l] to vertex idx[l], l < n; ``active`` (may be nullptr: all) says which count for
  // Jacobi (Gauss-Seidel adds every row: an inactive row's corrections are zero).
  DIFFAVATAR_INLINE void add_rows(const int32_t* idx, int n, const T* dx, const T* dy, const T* dz,
                                  const T* active) const {
    if (acc != nullptr) {
      for (int l = 0; l < n; ++l) {
        if (active != nullptr && active[l] == T(0)) continue;
        T* a = acc + kStride * static_cast<int64_t>(idx[l]);
        a[0] += dx[l], a[1] += dy[l], a[2] += dz[l];
        count[idx[l]] += T(1);
      }
      return;
    }
    const V4<T> zero = {T(0), T(0), T(0), T(0)};
    int l = 0;
    for (; l + 4 <= n; l += 4) {
      const V4<T> vx = load4(dx + l), vy = load4(dy + l), vz = load4(dz + l);
      const V4<T> xy01 = __builtin_shufflevector(vx, vy, 0, 4, 1, 5);  // x0 y0 x1 y1
      const V4<T> xy23 = __builtin_shufflevector(vx, vy, 2, 6, 3, 7);
      const V4<T> z01 = __builtin_shufflevector(vz, zero, 0, 4, 1, 5);  // z0 0 z1 0
      const V4<T> z23 = __builtin_shufflevector(vz, zero, 2, 6, 3, 7);
      const V4<T> r[4] = {__builtin_shufflevector(xy01, z01, 0, 1, 4, 5),
                          __builtin_shufflevector(xy01, z01, 2, 3, 6, 7),
                          __builtin_shufflevector(xy23, z23, 0, 1, 4, 5),
                          __builtin_shufflevector(xy23, z23, 2, 3, 6, 7)};
      for (int k = 0; k < 4; ++k) {
        T* p = x + kStride * static_cast<int64_t>(idx[l + k]);
        store4(p, load4(p) + r[k]);
      }
    }
    for (; l < n; ++l) {
      T* p = x + kStride * static_cast<int64_t>(idx[l]);
      p[0] += dx[l], p[1] += dy[l], p[2] += dz[l];
    }
  }
};

// ------------------------------------------------------------------------------------ block kernels

// Stretch constraints [s, s + n) (n <= kBlock) of the pack, evaluated at x, corrections into `sink`.
template <typename T>
DIFFAVATAR_INLINE void stretch_block(StretchPack<T>& p, int64_t s, int n, const T* x, const Sink<T>& sink) {
  alignas(64) T X[9][kBlock];
  alignas(64) T D[9][kBlock];
  const int32_t* v0 = p.v0.data() + s;
  const int32_t* v1 = p.v1.data() + s;
  const int32_t* v2 = p.v2.data() + s;
  gather_rows(x, v0, n, X[0], X[1], X[2]);
  gather_rows(x, v1, n, X[3], X[4], X[5]);
  gather_rows(x, v2, n, X[6], X[7], X[8]);
  const T* __restrict ra = p.ra.data() + s;
  const T* __restrict rb = p.rb.data() + s;
  const T* __restrict rc = p.rc.data() + s;
  const T* __restrict rd = p.rd.data() + s;
  const T* __restrict wpp = p.wpp.data() + s;
  const T* __restrict wqq = p.wqq.data() + s;
  const T* __restrict wpq = p.wpq.data() + s;
  const T* __restrict wp0 = p.wp0.data() + s;
  const T* __restrict wp1 = p.wp1.data() + s;
  const T* __restrict wp2 = p.wp2.data() + s;
  const T* __restrict wq0 = p.wq0.data() + s;
  const T* __restrict wq1 = p.wq1.data() + s;
  const T* __restrict wq2 = p.wq2.data() + s;
  const T* __restrict a00 = p.a00.data() + s;
  const T* __restrict a01 = p.a01.data() + s;
  const T* __restrict a02 = p.a02.data() + s;
  const T* __restrict a11 = p.a11.data() + s;
  const T* __restrict a12 = p.a12.data() + s;
  const T* __restrict a22 = p.a22.data() + s;
  T* __restrict l0 = p.l0.data() + s;
  T* __restrict l1 = p.l1.data() + s;
  T* __restrict l2 = p.l2.data() + s;
  constexpr T kMax = std::numeric_limits<T>::max();
  const T kScale = sym3_scale_limit<T>();
#pragma omp simd
  for (int l = 0; l < n; ++l) {
    const T d0x = X[0][l] - X[6][l], d0y = X[1][l] - X[7][l], d0z = X[2][l] - X[8][l];
    const T d1x = X[3][l] - X[6][l], d1y = X[4][l] - X[7][l], d1z = X[5][l] - X[8][l];
    const T f0x = ra[l] * d0x + rc[l] * d1x, f0y = ra[l] * d0y + rc[l] * d1y, f0z = ra[l] * d0z + rc[l] * d1z;
    const T f1x = rb[l] * d0x + rd[l] * d1x, f1y = rb[l] * d0y + rd[l] * d1y, f1z = rb[l] * d0z + rd[l] * d1z;
    const T s00 = f0x * f0x + f0y * f0y + f0z * f0z;
    const T s11 = f1x * f1x + f1y * f1y + f1z * f1z;
    const T s01 = f0x * f1x + f0y * f1y + f0z * f1z;
    T A00 = wpp[l] * s00 + a00[l];
    T A11 = wqq[l] * s11 + a11[l];
    T A22 = T(0.25) * (wqq[l] * s00 + T(2) * wpq[l] * s01 + wpp[l] * s11) + a22[l];
    T A01 = wpq[l] * s01 + a01[l];
    T A02 = T(0.5) * (wpq[l] * s00 + wpp[l] * s01) + a02[l];
    T A12 = T(0.5) * (wqq[l] * s01 + wpq[l] * s11) + a12[l];
    T r0 = -T(0.5) * (s00 - T(1)) - (a00[l] * l0[l] + a01[l] * l1[l] + a02[l] * l2[l]);
    T r1 = -T(0.5) * (s11 - T(1)) - (a01[l] * l0[l] + a11[l] * l1[l] + a12[l] * l2[l]);
    T r2 = -T(0.5) * s01 - (a02[l] * l0[l] + a12[l] * l1[l] + a22[l] * l2[l]);
    // (A / m) dl = r / m when A is too large for the adjugate (sym3_scale_limit); m = 1 is exact
    const T amax = std::max(A00, std::max(A11, A22));
    const T m = amax > kScale ? T(1) / amax : T(1);
    A00 *= m, A11 *= m, A22 *= m, A01 *= m, A02 *= m, A12 *= m, r0 *= m, r1 *= m, r2 *= m;
    const T c00 = A11 * A22 - A12 * A12;
    const T c01 = A02 * A12 - A01 * A22;
    const T c02 = A01 * A12 - A02 * A11;
    const T c11 = A00 * A22 - A02 * A02;
    const T c12 = A01 * A02 - A00 * A12;
    const T c22 = A00 * A11 - A01 * A01;
    const T det = A00 * c00 + A01 * c01 + A02 * c02;
    const T adet = std::fabs(det);
    const bool ok = (adet > T(0)) & (adet <= kMax);  // singular or non-finite: skipped
    const T inv = ok ? T(1) / (ok ? det : T(1)) : T(0);
    const T dl0 = (c00 * r0 + c01 * r1 + c02 * r2) * inv;
    const T dl1 = (c01 * r0 + c11 * r1 + c12 * r2) * inv;
    const T dl2 = (c02 * r0 + c12 * r1 + c22 * r2) * inv;
    l0[l] += dl0;
    l1[l] += dl1;
    l2[l] += dl2;
    const T h2 = T(0.5) * dl2;
    const T g0 = wp0[l] * dl0 + wq0[l] * h2, k0 = wq0[l] * dl1 + wp0[l] * h2;
    const T g1 = wp1[l] * dl0 + wq1[l] * h2, k1 = wq1[l] * dl1 + wp1[l] * h2;
    const T g2 = wp2[l] * dl0 + wq2[l] * h2, k2 = wq2[l] * dl1 + wp2[l] * h2;
    D[0][l] = g0 * f0x + k0 * f1x, D[1][l] = g0 * f0y + k0 * f1y, D[2][l] = g0 * f0z + k0 * f1z;
    D[3][l] = g1 * f0x + k1 * f1x, D[4][l] = g1 * f0y + k1 * f1y, D[5][l] = g1 * f0z + k1 * f1z;
    D[6][l] = g2 * f0x + k2 * f1x, D[7][l] = g2 * f0y + k2 * f1y, D[8][l] = g2 * f0z + k2 * f1z;
  }
  sink.add_rows(v0, n, D[0], D[1], D[2], nullptr);
  sink.add_rows(v1, n, D[3], D[4], D[5], nullptr);
  sink.add_rows(v2, n, D[6], D[7], D[8], nullptr);
}

constexpr double kBendEpsLen = 1e-12;  // |e| below this: degenerate quad, skipped (as bend_project_)
constexpr double kBendEpsN2 = 1e-24;   // |n1|^2 or |n2|^2 below this: skipped

// Bending constraints [s, s + n) of the pack, evaluated at x, corrections into `sink`.
template <typename T>
DIFFAVATAR_INLINE void bend_block(BendPack<T>& p, int64_t s, int n, const T* x, const Sink<T>& sink) {
  alignas(64) T X[12][kBlock];
  alignas(64) T D[12][kBlock];
  alignas(64) T OK[kBlock];  // 1 where the constraint was applied
  const int32_t* q[4] = {p.q0.data() + s, p.q1.data() + s, p.q2.data() + s, p.q3.data() + s};
  for (int i = 0; i < 4; ++i) gather_rows(x, q[i], n, X[3 * i], X[3 * i + 1], X[3 * i + 2]);
  const T* __restrict w0 = p.w0.data() + s;
  const T* __restrict w1 = p.w1.data() + s;
  const T* __restrict w2 = p.w2.data() + s;
  const T* __restrict w3 = p.w3.data() + s;
  const T* __restrict rest = p.rest.data() + s;
  const T* __restrict at = p.at.data() + s;
  T* __restrict lam = p.lam.data() + s;
  const T eps_len = static_cast<T>(kBendEpsLen), eps_n2 = static_cast<T>(kBendEpsN2);
  const T tiny = static_cast<T>(sizeof(T) == 4 ? 1e-30 : 1e-300);
#pragma omp simd
  for (int l = 0; l < n; ++l) {
    const T x0 = X[0][l], y0 = X[1][l], z0 = X[2][l];
    const T ex = X[3][l] - x0, ey = X[4][l] - y0, ez = X[5][l] - z0;                  // e = x1 - x0
    const T ax = X[6][l] - x0, ay = X[7][l] - y0, az = X[8][l] - z0;                  // a = x2 - x0
    const T bx = X[9][l] - X[3][l], by = X[10][l] - X[4][l], bz = X[11][l] - X[5][l];  // b = x3 - x1
    // n1 = e x a, n2 = (x0 - x1) x b = b x e
    const T n1x = ey * az - ez * ay, n1y = ez * ax - ex * az, n1z = ex * ay - ey * ax;
    const T n2x = by * ez - bz * ey, n2y = bz * ex - bx * ez, n2z = bx * ey - by * ex;
    // vectorised only without errno (setup.py builds with -fno-math-errno; with errno on GCC calls sqrtf
    // per lane)
    const T e_len = std::sqrt(ex * ex + ey * ey + ez * ez);
    const T n1_sq = n1x * n1x + n1y * n1y + n1z * n1z;
    const T n2_sq = n2x * n2x + n2y * n2y + n2z * n2z;
    // 1 when the quad is not degenerate (masks as T: bool lanes keep GCC from vectorising)
    const T okf = (e_len >= eps_len ? T(1) : T(0)) * (n1_sq >= eps_n2 ? T(1) : T(0)) * (n2_sq >= eps_n2 ? T(1) : T(0));
    const T inv_e = T(1) / std::max(e_len, eps_len);  // = 1 / |e| where ok
    const T hx = ex * inv_e, hy = ey * inv_e, hz = ez * inv_e;
    const T i1 = T(1) / std::max(n1_sq, eps_n2), i2 = T(1) / std::max(n2_sq, eps_n2);
    const T m1x = n1x * i1, m1y = n1y * i1, m1z = n1z * i1;
    const T m2x = n2x * i2, m2y = n2y * i2, m2z = n2z * i2;
    const T cx = n1y * n2z - n1z * n2y, cy = n1z * n2x - n1x * n2z, cz = n1x * n2y - n1y * n2x;
    const T theta = atan2_fast<T>(cx * hx + cy * hy + cz * hz, n1x * n2x + n1y * n2y + n1z * n2z);
    const T pa = ax * hx + ay * hy + az * hz;  // (x2 - x0).e_hat
    const T pb = bx * hx + by * hy + bz * hz;  // (x3 - x1).e_hat
    const T u0 = e_len - pa, u1 = pa;          // dtheta/dx0 = (|e| - pa) m1 - pb m2
    const T v0 = -pb, v1 = pb + e_len;         // dtheta/dx1 = pa m1 + (pb + |e|) m2
    const T g0x = u0 * m1x + v0 * m2x, g0y = u0 * m1y + v0 * m2y, g0z = u0 * m1z + v0 * m2z;
    const T g1x = u1 * m1x + v1 * m2x, g1y = u1 * m1y + v1 * m2y, g1z = u1 * m1z + v1 * m2z;
    const T g2x = -e_len * m1x, g2y = -e_len * m1y, g2z = -e_len * m1z;
    const T g3x = -e_len * m2x, g3y = -e_len * m2y, g3z = -e_len * m2z;
    const T denom = w0[l] * (g0x * g0x + g0y * g0y + g0z * g0z) + w1[l] * (g1x * g1x + g1y * g1y + g1z * g1z) +
                    w2[l] * (g2x * g2x + g2y * g2y + g2z * g2z) + w3[l] * (g3x * g3x + g3y * g3y + g3z * g3z) + at[l];
    // masks as arithmetic: GCC does not if-convert `act ? q : 0` here (the loop would stay scalar);
    // q is finite (denominator >= tiny), so 0 * q = 0 for skipped constraints
    const T mask = denom > T(0) ? okf : T(0);
    const T dlam = mask * ((rest[l] - theta - at[l] * lam[l]) / std::max(denom, tiny));
    lam[l] += dlam;
    const T s0 = w0[l] * dlam, s1 = w1[l] * dlam, s2 = w2[l] * dlam, s3 = w3[l] * dlam;
    D[0][l] = s0 * g0x, D[1][l] = s0 * g0y, D[2][l] = s0 * g0z;
    D[3][l] = s1 * g1x, D[4][l] = s1 * g1y, D[5][l] = s1 * g1z;
    D[6][l] = s2 * g2x, D[7][l] = s2 * g2y, D[8][l] = s2 * g2z;
    D[9][l] = s3 * g3x, D[10][l] = s3 * g3y, D[11][l] = s3 * g3z;
    OK[l] = mask;
  }
  for (int i = 0; i < 4; ++i) sink.add_rows(q[i], n, D[3 * i], D[3 * i + 1], D[3 * i + 2], OK);
}

// Entry points (one per dtype, so that target_clones applies to plain functions).
DIFFAVATAR_SIMD_CLONES void stretch_blocks(StretchPack<float>& p, int64_t b, int n, const float* x,
                                           const Sink<float>& sink) {
  stretch_block<float>(p, b, n, x, sink);
}
DIFFAVATAR_SIMD_CLONES void stretch_blocks(StretchPack<double>& p, int64_t b, int n, const double* x,
                                           const Sink<double>& sink) {
  stretch_block<double>(p, b, n, x, sink);
}
DIFFAVATAR_SIMD_CLONES void bend_blocks(BendPack<float>& p, int64_t b, int n, const float* x,
                                        const Sink<float>& sink) {
  bend_block<float>(p, b, n, x, sink);
}
DIFFAVATAR_SIMD_CLONES void bend_blocks(BendPack<double>& p, int64_t b, int n, const double* x,
                                        const Sink<double>& sink) {
  bend_block<double>(p, b, n, x, sink);
}

// ------------------------------------------------------------------------------ small constraint sets

// Zero-length stitches, Jacobi-averaged per vertex with the bounded pull (reference.stitch_project_).
template <typename T>
struct StitchPack {
  std::vector<int32_t> a, b;  // pair vertices
  std::vector<int32_t> verts;          // unique stitched vertices
  std::vector<int32_t> la, lb;         // pair -> index into verts
  std::vector<T> inv_count;            // 1 / (pairs containing the vertex)
  std::vector<T> lam, acc;             // (S, 3), (U, 3)
};

template <typename T>
StitchPack<T> pack_stitches(const at::Tensor& pairs, int64_t nv) {
  StitchPack<T> p;
  const int64_t n = pairs.size(0);
  const int64_t* pp = pairs.data_ptr<int64_t>();
  std::vector<int32_t> local(static_cast<size_t>(nv), -1);
  std::vector<T> count;
  auto slot = [&](int64_t v) {
    if (local[v] < 0) {
      local[v] = static_cast<int32_t>(p.verts.size());
      p.verts.push_back(static_cast<int32_t>(v));
      count.push_back(T(0));
    }
    count[local[v]] += T(1);
    return local[v];
  };
  for (int64_t k = 0; k < n; ++k) {
    p.a.push_back(static_cast<int32_t>(pp[2 * k]));
    p.b.push_back(static_cast<int32_t>(pp[2 * k + 1]));
    p.la.push_back(slot(pp[2 * k]));
    p.lb.push_back(slot(pp[2 * k + 1]));
  }
  for (const T c : count) p.inv_count.push_back(T(1) / c);
  p.lam.assign(3 * static_cast<size_t>(n), T(0));
  p.acc.assign(3 * p.verts.size(), T(0));
  return p;
}

template <typename T>
void project_stitches(StitchPack<T>& p, T* x, const T* w, T alpha_t, T max_move, T snap) {  // x padded
  std::fill(p.acc.begin(), p.acc.end(), T(0));
  const size_t n = p.a.size();
  for (size_t k = 0; k < n; ++k) {
    const int64_t a = p.a[k], b = p.b[k];
    const T wa = w[a], wb = w[b];
    const T* xa = x + kStride * a;
    const T* xb = x + kStride * b;
    const T c[3] = {xa[0] - xb[0], xa[1] - xb[1], xa[2] - xb[2]};
    const T denom = wa + wb + alpha_t;
    T dl[3];
    for (int i = 0; i < 3; ++i) dl[i] = (-c[i] - alpha_t * p.lam[3 * k + i]) / denom;
    const T move = std::max(wa, wb) * std::sqrt(dl[0] * dl[0] + dl[1] * dl[1] + dl[2] * dl[2]);
    const T gap = std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
    const T limit = std::max(gap < snap ? move : max_move, max_move);
    const T scale = limit / std::max(move, limit);
    T* acc_a = p.acc.data() + 3 * static_cast<size_t>(p.la[k]);
    T* acc_b = p.acc.data() + 3 * static_cast<size_t>(p.lb[k]);
    for (int i = 0; i < 3; ++i) {
      const T d = dl[i] * scale;
      p.lam[3 * k + i] += d;
      acc_a[i] += wa * d;
      acc_b[i] -= wb * d;
    }
  }
  for (size_t u = 0; u < p.verts.size(); ++u) {
    const int64_t v = p.verts[u];
    for (int i = 0; i < 3; ++i) x[kStride * v + i] += p.acc[3 * u + i] * p.inv_count[u];
  }
}

// Body contacts: contact points and unit normals from the (static) body, computed once per call.
template <typename T>
struct ContactPack {
  std::vector<int32_t> vert;
  std::vector<T> point, normal;  // (C, 3) each
  std::vector<T> depth_sum;      // (C,) sum over the substep's iterations
};

template <typename T>
ContactPack<T> pack_contacts(const at::Tensor& contact_vert, const at::Tensor& contact_tri,
                             const at::Tensor& contact_bary, const at::Tensor& body_verts,
                             const at::Tensor& body_faces, const T* w) {
  ContactPack<T> p;
  const int64_t n = contact_vert.numel();
  const int64_t* cv = contact_vert.data_ptr<int64_t>();
  const int64_t* ct = contact_tri.data_ptr<int64_t>();
  const T* bary = contact_bary.data_ptr<T>();
  const T* bv = body_verts.data_ptr<T>();
  const int64_t* bf = body_faces.data_ptr<int64_t>();
  for (int64_t k = 0; k < n; ++k) {
    if (!(w[cv[k]] > 0)) continue;  // a pinned vertex gets depth 0 and no friction: nothing to do
    const int64_t* f = bf + 3 * ct[k];
    const Vec3<T> c0 = load3(bv, f[0]), c1 = load3(bv, f[1]), c2 = load3(bv, f[2]);
    const T* bb = bary + 3 * k;
    const Vec3<T> pt = (bb[0] * c0 + bb[1] * c1) + bb[2] * c2;
    const Vec3<T> nn = cross(c1 - c0, c2 - c0);
    const T len = std::max(std::sqrt(dot(nn, nn)), static_cast<T>(1e-20));
    p.vert.push_back(static_cast<int32_t>(cv[k]));
    p.point.insert(p.point.end(), {pt.x, pt.y, pt.z});
    p.normal.insert(p.normal.end(), {nn.x / len, nn.y / len, nn.z / len});
  }
  p.depth_sum.assign(p.vert.size(), T(0));
  return p;
}

// ----------------------------------------------------------------------------------------- the op

void check_long_1d(const at::Tensor& t, const char* name) {
  check_cpu_contiguous(t, name);
  check_shape(t, name, {-1});
  check_dtype(t, name, at::kLong);
}

void check_float(const at::Tensor& t, const char* name, at::ScalarType dtype, at::IntArrayRef sizes) {
  check_cpu_contiguous(t, name);
  check_shape(t, name, sizes);
  check_dtype(t, name, dtype);
}

void check_order_pair(const at::Tensor& order, const at::Tensor& offsets, int64_t n, const char* order_name) {
  check_long_1d(order, order_name);
  check_long_1d(offsets, "color_offsets");
  check_index_range(order, n, order_name);
  check_color_offsets(offsets, order.numel());
}

struct Options {
  double gravity[3];
  double velocity_decay, dt;
  int64_t substeps, iterations;
  double stitch_compliance, stitch_max_move, stitch_snap, attach_compliance, thickness, friction;
  bool jacobi;
  double omega, bounce;
  int threads;
};

// The op's tensor lists by role, unpacked once (layout: torch_diffavatar/sim/substep.py, whose
// SubstepInputs builds them; `unpack_frame` checks the list lengths).
struct FrameTensors {
  at::Tensor tri_vertices, tri_rest_inv, tri_compliance, tri_order, tri_color_offsets;    // stretch
  at::Tensor edge_quads, edge_rest_angle, edge_compliance, edge_order, edge_color_offsets;  // bend
  at::Tensor stitch_vertices, attach_vertices, attach_height;                               // seams
  at::Tensor body_verts, body_faces, contact_vert, contact_tri, contact_bary;               // body
};

void check_list_size(at::TensorList list, size_t n, const char* name, const char* layout) {
  TORCH_CHECK(list.size() == n, "diffavatar: xpbd_substeps_ ", name, " must hold ", n, " tensors ", layout,
              ", got ", list.size());
}

FrameTensors unpack_frame(at::TensorList stretch, at::TensorList bend, at::TensorList seams, at::TensorList body) {
  check_list_size(stretch, 5, "stretch", "(tri_vertices, tri_rest_inv, tri_compliance, tri_order, tri_color_offsets)");
  check_list_size(bend, 5, "bend", "(edge_quads, edge_rest_angle, edge_compliance, edge_order, edge_color_offsets)");
  check_list_size(seams, 3, "seams", "(stitch_vertices, attach_vertices, attach_height)");
  check_list_size(body, 5, "body", "(body_verts, body_faces, contact_vert, contact_tri, contact_bary)");
  return FrameTensors{stretch[0], stretch[1], stretch[2], stretch[3], stretch[4],  // stretch
                      bend[0],    bend[1],    bend[2],    bend[3],    bend[4],     // bend
                      seams[0],   seams[1],   seams[2],                            // seams
                      body[0],    body[1],    body[2],    body[3],    body[4]};    // body
}

// The op's `coefficients` (the float fields of sim/substep.py's SubstepParams, in order) and counts.
Options unpack_options(at::ArrayRef<double> c, int64_t substeps, int64_t iterations, bool jacobi,
                       int64_t num_threads) {
  TORCH_CHECK(c.size() == 13,
              "diffavatar: xpbd_substeps_ coefficients must hold 13 floats (gravity x, y, z, velocity_decay, dt, "
              "stitch_compliance, stitch_max_move, stitch_snap, attach_compliance, thickness, friction, "
              "jacobi_omega, contact_bounce), got ",
              c.size());
  TORCH_CHECK(num_threads >= 0, "diffavatar: num_threads must be >= 0 (0 = torch.get_num_threads()), got ",
              num_threads);
  Options o;
  std::copy(c.begin(), c.begin() + 3, o.gravity);
  o.velocity_decay = c[3];
  o.dt = c[4];
  o.stitch_compliance = c[5];
  o.stitch_max_move = c[6];
  o.stitch_snap = c[7];
  o.attach_compliance = c[8];
  o.thickness = c[9];
  o.friction = c[10];
  o.omega = c[11];
  o.bounce = c[12];
  o.substeps = substeps;
  o.iterations = iterations;
  o.jacobi = jacobi;
  o.threads = num_threads == 0 ? diffavatar::num_threads() : static_cast<int>(num_threads);
  return o;
}

template <typename T>
void run_substeps(at::Tensor& x_t, at::Tensor& v_t, const at::Tensor& w_t, const FrameTensors& t, const Options& o) {
  T* x_out = x_t.data_ptr<T>();
  T* v = v_t.data_ptr<T>();
  const T* w = w_t.data_ptr<T>();
  const int64_t nv = x_t.size(0);
  const T h = static_cast<T>(o.dt);
  const T inv_h = static_cast<T>(1.0 / o.dt);
  const T inv_h2 = static_cast<T>(1.0 / (o.dt * o.dt));
  const T decay = static_cast<T>(o.velocity_decay);
  const T gh[3] = {static_cast<T>(o.gravity[0]) * h, static_cast<T>(o.gravity[1]) * h,
                   static_cast<T>(o.gravity[2]) * h};

  StretchPack<T> sp = pack_stretch<T>(t.tri_vertices, t.tri_rest_inv, t.tri_compliance, t.tri_order,
                                       t.tri_color_offsets, w, o.jacobi, inv_h2);
  BendPack<T> bp = pack_bend<T>(t.edge_quads, t.edge_rest_angle, t.edge_compliance, t.edge_order,
                                t.edge_color_offsets, w, o.jacobi, inv_h2);
  StitchPack<T> st = pack_stitches<T>(t.stitch_vertices, nv);
  ContactPack<T> cp = pack_contacts<T>(t.contact_vert, t.contact_tri, t.contact_bary, t.body_verts, t.body_faces, w);
  const int64_t n_attach = t.attach_vertices.numel();
  const int64_t* attach_v = t.attach_vertices.data_ptr<int64_t>();
  const T* attach_y = t.attach_height.data_ptr<T>();
  std::vector<T> attach_lam(static_cast<size_t>(n_attach));
  const T attach_at = static_cast<T>(o.attach_compliance) * inv_h2;
  const T stitch_at = static_cast<T>(o.stitch_compliance) * inv_h2;
  const T stitch_move = static_cast<T>(o.stitch_max_move), stitch_snap = static_cast<T>(o.stitch_snap);
  const T thickness = static_cast<T>(o.thickness), mu = static_cast<T>(o.friction);
  const T bounce_cut = cp.vert.empty() ? T(0) : static_cast<T>(1.0 - o.bounce);
  const bool friction = mu > T(0) && !cp.vert.empty();
  // positions padded to kStride per vertex for the substeps (see gather_rows), copied back at the end
  std::vector<T> x_pad(static_cast<size_t>(kStride * nv), T(0));
  for (int64_t i = 0; i < nv; ++i) std::copy(x_out + 3 * i, x_out + 3 * i + 3, x_pad.data() + kStride * i);
  T* x = x_pad.data();
  std::vector<T> x_start(static_cast<size_t>(kStride * nv));
  // Jacobi accumulators
  std::vector<T> acc, count;
  if (o.jacobi) {
    acc.assign(static_cast<size_t>(kStride * nv), T(0));
    count.assign(static_cast<size_t>(nv), T(0));
  }
  const Sink<T> gs_sink{x, nullptr, nullptr};
  const Sink<T> jacobi_sink{x, acc.data(), count.data()};
  const T omega = static_cast<T>(o.omega);

  auto jacobi_apply = [&]() {
    for (int64_t i = 0; i < nv; ++i) {
      if (count[i] > T(0)) {
        const T s = omega / count[i];
        for (int k = 0; k < 3; ++k) x[kStride * i + k] += s * acc[kStride * i + k];
      }
    }
    std::fill(acc.begin(), acc.end(), T(0));
    std::fill(count.begin(), count.end(), T(0));
  };

  const int nt = o.jacobi ? 1 : o.threads;
#pragma omp parallel num_threads(nt) if (nt > 1)
  for (int64_t step = 0; step < o.substeps; ++step) {
#pragma omp for schedule(static)
    for (int64_t i = 0; i < nv; ++i) {
      const T m = w[i] > T(0) ? T(1) : T(0);
      for (int k = 0; k < 3; ++k) {
        const int64_t j = 3 * i + k, jp = kStride * i + k;
        x_start[jp] = x[jp];
        const T vel = (v[j] * decay + gh[k]) * m;
        v[j] = vel;
        x[jp] += vel * h;
      }
    }
#pragma omp single
    {
      std::fill(sp.l0.begin(), sp.l0.end(), T(0));
      std::fill(sp.l1.begin(), sp.l1.end(), T(0));
      std::fill(sp.l2.begin(), sp.l2.end(), T(0));
      std::fill(bp.lam.begin(), bp.lam.end(), T(0));
      std::fill(st.lam.begin(), st.lam.end(), T(0));
      std::fill(attach_lam.begin(), attach_lam.end(), T(0));
      std::fill(cp.depth_sum.begin(), cp.depth_sum.end(), T(0));
    }
    for (int64_t it = 0; it < o.iterations; ++it) {
      // stretch, then bending: colour by colour, blocks of a colour in parallel
      for (size_t c = 0; c + 1 < sp.seg.size(); ++c) {
        const int64_t s = sp.seg[c], e = sp.seg[c + 1];
        const Sink<T>& sink = o.jacobi ? jacobi_sink : gs_sink;
#pragma omp for schedule(static)
        for (int64_t b = s; b < e; b += kBlock) {
          stretch_blocks(sp, b, static_cast<int>(std::min<int64_t>(kBlock, e - b)), x, sink);
        }
      }
      if (o.jacobi) jacobi_apply();
      for (size_t c = 0; c + 1 < bp.seg.size(); ++c) {
        const int64_t s = bp.seg[c], e = bp.seg[c + 1];
        const Sink<T>& sink = o.jacobi ? jacobi_sink : gs_sink;
#pragma omp for schedule(static)
        for (int64_t b = s; b < e; b += kBlock) {
          bend_blocks(bp, b, static_cast<int>(std::min<int64_t>(kBlock, e - b)), x, sink);
        }
      }
#pragma omp single
      {
        if (o.jacobi) jacobi_apply();
        // waist attachments: C = y - y_target
        for (int64_t k = 0; k < n_attach; ++k) {
          const int64_t i = attach_v[k];
          const T wi = w[i];
          if (!(wi > T(0))) continue;
          const T dl = (-(x[kStride * i + 1] - attach_y[k]) - attach_at * attach_lam[k]) / (wi + attach_at);
          attach_lam[k] += dl;
          x[kStride * i + 1] += wi * dl;
        }
        // body contacts: push to `thickness` outside along the contact normal
        const size_t nc = cp.vert.size();
        for (size_t k = 0; k < nc; ++k) {
          T* xi = x + kStride * static_cast<int64_t>(cp.vert[k]);
          const T* pt = cp.point.data() + 3 * k;
          const T* nn = cp.normal.data() + 3 * k;
          const T sd = (xi[0] - pt[0]) * nn[0] + (xi[1] - pt[1]) * nn[1] + (xi[2] - pt[2]) * nn[2] - thickness;
          const T depth = std::max(-sd, T(0));
          xi[0] += nn[0] * depth;
          xi[1] += nn[1] * depth;
          xi[2] += nn[2] * depth;
          cp.depth_sum[k] += depth;
        }
        // stitches last (a seam pressed onto the body still closes)
        if (!st.a.empty()) project_stitches<T>(st, x, w, stitch_at, stitch_move, stitch_snap);
      }
    }
#pragma omp single
    if (friction) {
      // position-based Coulomb friction on the substep's tangential motion
      for (size_t k = 0; k < cp.vert.size(); ++k) {
        const T depth = cp.depth_sum[k];
        if (!(depth > T(0))) continue;
        const int64_t i = cp.vert[k];
        const T* nn = cp.normal.data() + 3 * k;
        T d[3];
        for (int j = 0; j < 3; ++j) d[j] = x[kStride * i + j] - x_start[kStride * i + j];
        const T dn = d[0] * nn[0] + d[1] * nn[1] + d[2] * nn[2];
        for (int j = 0; j < 3; ++j) d[j] -= dn * nn[j];
        const T length = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        const T limit = mu * depth;
        const T scale = length <= limit ? T(1) : limit / std::max(length, static_cast<T>(1e-20));
        for (int j = 0; j < 3; ++j) x[kStride * i + j] -= d[j] * scale;
      }
    }
#pragma omp for schedule(static)
    for (int64_t i = 0; i < nv; ++i) {
      for (int k = 0; k < 3; ++k) v[3 * i + k] = (x[kStride * i + k] - x_start[kStride * i + k]) * inv_h;
    }
#pragma omp single
    if (bounce_cut > T(0)) {
      // a contact pushed out in this substep keeps only `bounce` of its outward normal velocity (the push
      // is a position correction; as a velocity it would fling the vertex off the body)
      for (size_t k = 0; k < cp.vert.size(); ++k) {
        if (!(cp.depth_sum[k] > T(0))) continue;
        T* vi = v + 3 * static_cast<int64_t>(cp.vert[k]);
        const T* nn = cp.normal.data() + 3 * k;
        const T vn = vi[0] * nn[0] + vi[1] * nn[1] + vi[2] * nn[2];
        if (vn > T(0)) {
          for (int j = 0; j < 3; ++j) vi[j] -= bounce_cut * vn * nn[j];
        }
      }
    }
  }
  for (int64_t i = 0; i < nv; ++i) std::copy(x + kStride * i, x + kStride * i + 3, x_out + 3 * i);
}

void check_frame(const at::Tensor& x, const at::Tensor& v, const at::Tensor& vert_inv_mass, const FrameTensors& t,
                 bool jacobi) {
  const auto dtype = x.scalar_type();
  const int64_t nv = x.size(0), nf = t.tri_vertices.size(0), ne = t.edge_quads.size(0);
  check_float(v, "v", dtype, {nv, 3});
  check_float(vert_inv_mass, "vert_inv_mass", dtype, {nv});
  check_cpu_contiguous(t.tri_vertices, "tri_vertices");
  check_shape(t.tri_vertices, "tri_vertices", {-1, 3});
  check_dtype(t.tri_vertices, "tri_vertices", at::kLong);
  check_index_range(t.tri_vertices, nv, "tri_vertices");
  check_float(t.tri_rest_inv, "tri_rest_inv", dtype, {nf, 2, 2});
  check_float(t.tri_compliance, "tri_compliance", dtype, {nf, 3, 3});
  check_cpu_contiguous(t.edge_quads, "edge_quads");
  check_shape(t.edge_quads, "edge_quads", {-1, 4});
  check_dtype(t.edge_quads, "edge_quads", at::kLong);
  check_index_range(t.edge_quads, nv, "edge_quads");
  check_float(t.edge_rest_angle, "edge_rest_angle", dtype, {ne});
  check_float(t.edge_compliance, "edge_compliance", dtype, {ne});
  if (!jacobi) {
    check_order_pair(t.tri_order, t.tri_color_offsets, nf, "tri_order");
    check_order_pair(t.edge_order, t.edge_color_offsets, ne, "edge_order");
  }
  check_cpu_contiguous(t.stitch_vertices, "stitch_vertices");
  check_shape(t.stitch_vertices, "stitch_vertices", {-1, 2});
  check_dtype(t.stitch_vertices, "stitch_vertices", at::kLong);
  check_index_range(t.stitch_vertices, nv, "stitch_vertices");
  check_long_1d(t.attach_vertices, "attach_vertices");
  check_index_range(t.attach_vertices, nv, "attach_vertices");
  check_float(t.attach_height, "attach_height", dtype, {t.attach_vertices.numel()});
  check_float(t.body_verts, "body_verts", dtype, {-1, 3});
  check_cpu_contiguous(t.body_faces, "body_faces");
  check_shape(t.body_faces, "body_faces", {-1, 3});
  check_dtype(t.body_faces, "body_faces", at::kLong);
  check_index_range(t.body_faces, t.body_verts.size(0), "body_faces");
  check_long_1d(t.contact_vert, "contact_vert");
  check_index_range(t.contact_vert, nv, "contact_vert");
  const int64_t nc = t.contact_vert.numel();
  check_long_1d(t.contact_tri, "contact_tri");
  TORCH_CHECK(t.contact_tri.numel() == nc, "diffavatar: contact_tri must have shape (", nc, "), got ",
              t.contact_tri.sizes());
  check_index_range(t.contact_tri, t.body_faces.size(0), "contact_tri");
  check_float(t.contact_bary, "contact_bary", dtype, {nc, 3});
}

void xpbd_substeps_(at::Tensor x, at::Tensor v, const at::Tensor& vert_inv_mass, at::TensorList stretch,
                    at::TensorList bend, at::TensorList seams, at::TensorList body, at::ArrayRef<double> coefficients,
                    int64_t substeps, int64_t iterations, bool jacobi, int64_t num_threads) {
  check_cpu_contiguous(x, "x");
  const auto dtype = x.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "diffavatar: x must be float32 or float64, got ", dtype);
  check_shape(x, "x", {-1, 3});
  TORCH_CHECK(x.size(0) < (int64_t(1) << 31), "diffavatar: xpbd_substeps_ supports fewer than 2^31 vertices");
  const FrameTensors t = unpack_frame(stretch, bend, seams, body);
  check_frame(x, v, vert_inv_mass, t, jacobi);
  const Options o = unpack_options(coefficients, substeps, iterations, jacobi, num_threads);
  TORCH_CHECK(o.dt > 0, "diffavatar: dt must be > 0, got ", o.dt);
  TORCH_CHECK(substeps >= 0 && iterations >= 1, "diffavatar: need substeps >= 0 and iterations >= 1, got ",
              substeps, ", ", iterations);
  AT_DISPATCH_FLOATING_TYPES(dtype, "xpbd_substeps_", [&] { run_substeps<scalar_t>(x, v, vert_inv_mass, t, o); });
}

// Largest |E00|, |E11|, |E01| of the Green strain over the triangles (0-dim tensor; NaN if any is NaN).
at::Tensor max_abs_green_strain(const at::Tensor& x, const at::Tensor& tri_vertices, const at::Tensor& tri_rest_inv) {
  check_cpu_contiguous(x, "x");
  const auto dtype = x.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "diffavatar: x must be float32 or float64, got ", dtype);
  check_shape(x, "x", {-1, 3});
  check_cpu_contiguous(tri_vertices, "tri_vertices");
  check_shape(tri_vertices, "tri_vertices", {-1, 3});
  check_dtype(tri_vertices, "tri_vertices", at::kLong);
  check_index_range(tri_vertices, x.size(0), "tri_vertices");
  const int64_t nf = tri_vertices.size(0);
  check_float(tri_rest_inv, "tri_rest_inv", dtype, {nf, 2, 2});
  at::Tensor out = at::zeros({}, x.options());
  const int64_t* tv = tri_vertices.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(dtype, "max_abs_green_strain", [&] {
    using T = scalar_t;
    const T* xp = x.data_ptr<T>();
    const T* r = tri_rest_inv.data_ptr<T>();
    T best = T(0);
    bool nan = false;
    for (int64_t f = 0; f < nf; ++f) {
      const Vec3<T> x2 = load3(xp, tv[3 * f + 2]);
      const Vec3<T> d0 = load3(xp, tv[3 * f]) - x2, d1 = load3(xp, tv[3 * f + 1]) - x2;
      const T* rf = r + 4 * f;
      const Vec3<T> f0 = rf[0] * d0 + rf[2] * d1, f1 = rf[1] * d0 + rf[3] * d1;
      const T c[3] = {T(0.5) * (dot(f0, f0) - T(1)), T(0.5) * (dot(f1, f1) - T(1)), T(0.5) * dot(f0, f1)};
      for (const T ck : c) {
        nan |= std::isnan(ck);
        best = std::max(best, std::fabs(ck));
      }
    }
    out.fill_(nan ? std::numeric_limits<T>::quiet_NaN() : best);
  });
  return out;
}

}  // namespace
}  // namespace diffavatar

TORCH_LIBRARY_IMPL(diffavatar, CPU, m) {
  m.impl("xpbd_substeps_", &diffavatar::xpbd_substeps_);
  m.impl("max_abs_green_strain", &diffavatar::max_abs_green_strain);
}
