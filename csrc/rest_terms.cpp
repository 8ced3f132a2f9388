// The rest pattern's regularizers with their gradients in one pass each: seam length (paper eq. 7),
// boundary curvature (eq. 8), the rest triangles' area and shape hinges, and the openings' lengths and
// their split between panels.
//
// A fit's proximal step (`fit.rest_prox`) evaluates these ~40 times per iteration on ~2k-8k panel
// vertices; as autograd graphs of ~200 small tensor ops each evaluation cost ~4 ms, almost all of it
// per-op overhead. Each op here returns (value, gradient) = (w * sum_i f_i, w * d/d(uv) sum_i f_i);
// `torch_diffavatar.rest_terms` wraps them in one autograd.Function. Their PyTorch twins are the loss
// functions of `torch_diffavatar.losses` and `torch_diffavatar.opening_lengths` (same formulas, summed in
// another order: equal to rounding). Every sum is accumulated in double; the gradient is written in the
// input's dtype.

#include <cmath>
#include <tuple>
#include <vector>

#include "common.h"

namespace diffavatar {
namespace {

struct V2 {
  double x = 0, y = 0;
};
inline V2 operator+(V2 a, V2 b) { return {a.x + b.x, a.y + b.y}; }
inline V2 operator-(V2 a, V2 b) { return {a.x - b.x, a.y - b.y}; }
inline V2 operator*(double s, V2 a) { return {s * a.x, s * a.y}; }
inline double dot(V2 a, V2 b) { return a.x * b.x + a.y * b.y; }

template <typename T>
inline V2 load2(const T* p, int64_t i) {
  return {static_cast<double>(p[2 * i]), static_cast<double>(p[2 * i + 1])};
}

// Adds `s * g` to row i of the (V, 2) double gradient.
inline void add2(std::vector<double>& grad, int64_t i, V2 g, double s = 1.0) {
  grad[2 * i] += s * g.x;
  grad[2 * i + 1] += s * g.y;
}

void check_uv(const at::Tensor& uv) {
  check_cpu_contiguous(uv, "uv");
  check_shape(uv, "uv", {-1, 2});
  TORCH_CHECK(uv.scalar_type() == at::kFloat || uv.scalar_type() == at::kDouble,
              "diffavatar: uv must be float32 or float64, got ", uv.scalar_type());
}

void check_index(const at::Tensor& ids, const char* name, int64_t columns, int64_t vertices) {
  check_cpu_contiguous(ids, name);
  check_dtype(ids, name, at::kLong);
  check_shape(ids, name, {-1, columns});
  check_index_range(ids, vertices, name);
}

void check_table(const at::Tensor& t, const char* name, at::IntArrayRef sizes, const at::Tensor& uv) {
  check_cpu_contiguous(t, name);
  check_shape(t, name, sizes);
  check_dtype(t, name, uv.scalar_type());
}

// (value, grad) as tensors of uv's dtype from the double accumulators.
std::tuple<at::Tensor, at::Tensor> finish(const at::Tensor& uv, double value, const std::vector<double>& grad) {
  at::Tensor g = at::from_blob(const_cast<double*>(grad.data()), uv.sizes(), at::kDouble)
                     .to(uv.scalar_type(), /*non_blocking=*/false, /*copy=*/true);  // owns its memory
  return {at::scalar_tensor(value, uv.options()), g};
}

// seg (K, 4): (a_i, a_{i+1}, b_i, b_{i+1}); f = (|a_{i+1} - a_i|^2 - |b_{i+1} - b_i|^2)^2.
std::tuple<at::Tensor, at::Tensor> rest_seam_length(const at::Tensor& uv, const at::Tensor& seg, double weight) {
  check_uv(uv);
  check_index(seg, "seg", 4, uv.size(0));
  const int64_t k_count = seg.size(0);
  const int64_t* s = seg.data_ptr<int64_t>();
  std::vector<double> grad(uv.numel(), 0.0);
  double value = 0.0;
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "rest_seam_length", [&] {
    const scalar_t* p = uv.data_ptr<scalar_t>();
    for (int64_t k = 0; k < k_count; ++k) {
      const int64_t* q = s + 4 * k;
      const V2 da = load2(p, q[1]) - load2(p, q[0]);
      const V2 db = load2(p, q[3]) - load2(p, q[2]);
      const double r = dot(da, da) - dot(db, db);
      value += r * r;
      const double c = 4.0 * r * weight;  // d(r^2)/d(da) = 2 r * 2 da
      add2(grad, q[1], da, c);
      add2(grad, q[0], da, -c);
      add2(grad, q[3], db, -c);
      add2(grad, q[2], db, c);
    }
  });
  return finish(uv, weight * value, grad);
}

// triplets (Nb, 3): (previous, vertex, next); edges, edges_perp (Nb, 2, 2): the template's edges to the next
// and the previous vertex and the same turned by 90 degrees; norm (Nb,): their summed squared lengths.
// f = |r|^2, r = e1 + e2 - a S - b S_perp, with e1 = p_next - p, e2 = p_prev - p, a = (e1.t1 + e2.t2) / norm,
// b = (e1.t1p + e2.t2p) / norm, S = t1 + t2, S_perp = t1p + t2p (the template's edges after the best
// similarity, `losses.curvature_loss`).
std::tuple<at::Tensor, at::Tensor> rest_curvature(const at::Tensor& uv, const at::Tensor& triplets,
                                                  const at::Tensor& edges, const at::Tensor& edges_perp,
                                                  const at::Tensor& norm, double weight) {
  check_uv(uv);
  check_index(triplets, "triplets", 3, uv.size(0));
  const int64_t n = triplets.size(0);
  check_table(edges, "edges", {n, 2, 2}, uv);
  check_table(edges_perp, "edges_perp", {n, 2, 2}, uv);
  check_table(norm, "norm", {n}, uv);
  const int64_t* tr = triplets.data_ptr<int64_t>();
  std::vector<double> grad(uv.numel(), 0.0);
  double value = 0.0;
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "rest_curvature", [&] {
    const scalar_t* p = uv.data_ptr<scalar_t>();
    const scalar_t* te = edges.data_ptr<scalar_t>();
    const scalar_t* tp = edges_perp.data_ptr<scalar_t>();
    const scalar_t* nm = norm.data_ptr<scalar_t>();
    for (int64_t i = 0; i < n; ++i) {
      const int64_t* q = tr + 3 * i;
      const V2 centre = load2(p, q[1]);
      const V2 e1 = load2(p, q[2]) - centre, e2 = load2(p, q[0]) - centre;
      const V2 t1 = load2(te, 2 * i), t2 = load2(te, 2 * i + 1);
      const V2 t1p = load2(tp, 2 * i), t2p = load2(tp, 2 * i + 1);
      const double inv = 1.0 / static_cast<double>(nm[i]);
      const double a = (dot(e1, t1) + dot(e2, t2)) * inv;
      const double b = (dot(e1, t1p) + dot(e2, t2p)) * inv;
      const V2 s = t1 + t2, sp = t1p + t2p;
      const V2 r = e1 + e2 - a * s - b * sp;
      value += dot(r, r);
      const V2 g = (2.0 * weight) * r;  // d f / d r
      const double gs = dot(g, s) * inv, gsp = dot(g, sp) * inv;
      const V2 g1 = g - gs * t1 - gsp * t1p;  // d f / d e1
      const V2 g2 = g - gs * t2 - gsp * t2p;  // d f / d e2
      add2(grad, q[2], g1);
      add2(grad, q[0], g2);
      add2(grad, q[1], g1 + g2, -1.0);
    }
  });
  return finish(uv, weight * value, grad);
}

// Per triangle (F, 3) with corners p0, p1, p2 and edges E = [p1 - p0, p2 - p0] (columns):
//   area hinge   relu(area_threshold - A / area)^2, A = det(E) / 2 (`losses.rest_area_loss`);
//   shape hinge  relu(c - shape_threshold)^2, c = |J|_F^2 / (2 max(|det J|, 1e-3)) - 1, J = E inverse
//                (`losses.rest_distortion_loss`); skipped when `inverse` has no rows.
// value = area_weight * sum(area hinges) + shape_weight * sum(shape hinges), a hinge with weight 0 not
// evaluated. A NaN hinge counts (as in the twins), so a non-finite pattern gives a non-finite value.
std::tuple<at::Tensor, at::Tensor> rest_triangle_hinges(const at::Tensor& uv, const at::Tensor& tri,
                                                        const at::Tensor& area, double area_threshold,
                                                        double area_weight, const at::Tensor& inverse,
                                                        double shape_threshold, double shape_weight) {
  check_uv(uv);
  check_index(tri, "tri", 3, uv.size(0));
  const int64_t n = tri.size(0);
  check_table(area, "area", {n}, uv);
  const bool shape = inverse.numel() > 0;
  if (shape) check_table(inverse, "inverse", {n, 2, 2}, uv);
  const int64_t* tv = tri.data_ptr<int64_t>();
  std::vector<double> grad(uv.numel(), 0.0);
  double value = 0.0;
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "rest_triangle_hinges", [&] {
    const scalar_t* p = uv.data_ptr<scalar_t>();
    const scalar_t* ar = area.data_ptr<scalar_t>();
    const scalar_t* im = shape ? inverse.data_ptr<scalar_t>() : nullptr;
    for (int64_t f = 0; f < n; ++f) {
      const int64_t* q = tv + 3 * f;
      const V2 p0 = load2(p, q[0]);
      const V2 e1 = load2(p, q[1]) - p0, e2 = load2(p, q[2]) - p0;
      V2 g1, g2;  // d value / d e1, d e2
      const double ref = static_cast<double>(ar[f]);
      const double h = area_threshold - 0.5 * (e1.x * e2.y - e1.y * e2.x) / ref;
      if (area_weight != 0.0 && !(h <= 0.0)) {
        value += area_weight * h * h;
        const double c = -area_weight * h / ref;  // 2 h * d(-A/ref)/dA * (1/2 from A = det / 2)
        g1 = g1 + c * V2{e2.y, -e2.x};
        g2 = g2 + c * V2{-e1.y, e1.x};
      }
      if (shape && shape_weight != 0.0) {
        const scalar_t* m = im + 4 * f;  // row-major inverse [[m0, m1], [m2, m3]]
        // J = E M: J00 = e1.x m0 + e2.x m2, J01 = e1.x m1 + e2.x m3, J10 = e1.y m0 + e2.y m2, J11 = ...
        const double j00 = e1.x * m[0] + e2.x * m[2], j01 = e1.x * m[1] + e2.x * m[3];
        const double j10 = e1.y * m[0] + e2.y * m[2], j11 = e1.y * m[1] + e2.y * m[3];
        const double det = j00 * j11 - j01 * j10;
        const double fro = j00 * j00 + j01 * j01 + j10 * j10 + j11 * j11;
        const double ad = std::abs(det);
        const bool clamped = !(ad >= 1e-3);
        const double den = 2.0 * (clamped ? 1e-3 : ad);
        const double hs = fro / den - 1.0 - shape_threshold;
        if (!(hs <= 0.0)) {
          value += shape_weight * hs * hs;
          const double c = 2.0 * shape_weight * hs;
          // d c / d J = 2 J / den  -  (fro / den^2) * 2 sign(det) d det / d J   (the latter 0 when clamped)
          const double k = clamped ? 0.0 : fro / (den * den) * 2.0 * ((det > 0) - (det < 0));
          const double d00 = c * (2.0 * j00 / den - k * j11), d01 = c * (2.0 * j01 / den + k * j10);
          const double d10 = c * (2.0 * j10 / den + k * j01), d11 = c * (2.0 * j11 / den - k * j00);
          // d / d E = (d / d J) M^T
          g1 = g1 + V2{d00 * m[0] + d01 * m[1], d10 * m[0] + d11 * m[1]};
          g2 = g2 + V2{d00 * m[2] + d01 * m[3], d10 * m[2] + d11 * m[3]};
        }
      }
      add2(grad, q[1], g1);
      add2(grad, q[2], g2);
      add2(grad, q[0], g1 + g2, -1.0);
    }
  });
  return finish(uv, value, grad);
}

// The openings' rest lengths (`opening_lengths.opening_length_loss` and `opening_split_loss`): edges (L, 2)
// of all openings, each edge's slot (L,) (its panel within its opening, numbered over all openings), each
// slot's opening (S,); least (K,) [m] the shortest length each opening may have, most (K,) [m] the longest (inf:
// none), shares (S,) the template's share of each slot in its opening's length. value = length_weight * sum_k
// [(max(0, least_k - L_k) / least_k)^2 + (max(0, L_k - most_k) / most_k)^2] + split_weight * sum_s (P_s / L_k(s)
// - shares_s)^2, with L_k the opening's length and P_s the slot's.
std::tuple<at::Tensor, at::Tensor> rest_openings(const at::Tensor& uv, const at::Tensor& edges,
                                                 const at::Tensor& slot, const at::Tensor& slot_opening,
                                                 const at::Tensor& least, const at::Tensor& most,
                                                 const at::Tensor& shares, double length_weight,
                                                 double split_weight) {
  check_uv(uv);
  check_index(edges, "edges", 2, uv.size(0));
  const int64_t n = edges.size(0), k_count = least.size(0), s_count = shares.size(0);
  check_table(least, "least", {-1}, uv);
  check_table(most, "most", {k_count}, uv);
  check_table(shares, "shares", {-1}, uv);
  check_shape(slot, "slot", {n});
  check_shape(slot_opening, "slot_opening", {s_count});
  check_index(slot.view({-1, 1}), "slot", 1, s_count);
  check_index(slot_opening.view({-1, 1}), "slot_opening", 1, k_count);
  const int64_t* ev = edges.data_ptr<int64_t>();
  const int64_t* sl = slot.data_ptr<int64_t>();
  const int64_t* so = slot_opening.data_ptr<int64_t>();
  std::vector<double> grad(uv.numel(), 0.0), length(n), part(s_count, 0.0), total(k_count, 0.0);
  std::vector<double> d_part(s_count, 0.0), d_total(k_count, 0.0);
  double value = 0.0;
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "rest_openings", [&] {
    const scalar_t* p = uv.data_ptr<scalar_t>();
    const scalar_t* lp = least.data_ptr<scalar_t>();
    const scalar_t* mp = most.data_ptr<scalar_t>();
    const scalar_t* sh = shares.data_ptr<scalar_t>();
    for (int64_t e = 0; e < n; ++e) {
      const V2 d = load2(p, ev[2 * e + 1]) - load2(p, ev[2 * e]);
      length[e] = std::sqrt(dot(d, d));
      part[sl[e]] += length[e];
      total[so[sl[e]]] += length[e];
    }
    if (length_weight != 0.0) {
      for (int64_t k = 0; k < k_count; ++k) {
        const double lk = static_cast<double>(lp[k]);
        const double shortfall = std::max(lk - total[k], 0.0) / lk;
        value += length_weight * shortfall * shortfall;
        d_total[k] -= 2.0 * length_weight * shortfall / lk;
        const double mk = static_cast<double>(mp[k]);
        if (std::isfinite(mk)) {
          const double excess = std::max(total[k] - mk, 0.0) / mk;
          value += length_weight * excess * excess;
          d_total[k] += 2.0 * length_weight * excess / mk;
        }
      }
    }
    if (split_weight != 0.0) {
      for (int64_t s = 0; s < s_count; ++s) {
        const double lk = total[so[s]];
        const double r = part[s] / lk - static_cast<double>(sh[s]);
        value += split_weight * r * r;
        d_part[s] += 2.0 * split_weight * r / lk;
        d_total[so[s]] -= 2.0 * split_weight * r * part[s] / (lk * lk);
      }
    }
    for (int64_t e = 0; e < n; ++e) {
      if (!(length[e] > 0.0)) continue;  // as torch's norm: no gradient through a zero length
      const double c = (d_part[sl[e]] + d_total[so[sl[e]]]) / length[e];
      const V2 d = load2(p, ev[2 * e + 1]) - load2(p, ev[2 * e]);
      add2(grad, ev[2 * e + 1], d, c);
      add2(grad, ev[2 * e], d, -c);
    }
  });
  return finish(uv, value, grad);
}

}  // namespace
}  // namespace diffavatar

TORCH_LIBRARY_FRAGMENT(diffavatar, m) {
  // (w * sum of the seam segments' squared length mismatches, its gradient (V, 2)).
  m.def("rest_seam_length(Tensor uv, Tensor seg, float weight) -> (Tensor value, Tensor grad)");
  // (w * sum of the boundary curvature residuals, its gradient (V, 2)).
  m.def(
      "rest_curvature(Tensor uv, Tensor triplets, Tensor edges, Tensor edges_perp, Tensor norm, float weight) "
      "-> (Tensor value, Tensor grad)");
  // (weighted sum of the rest triangles' area and shape hinges, its gradient (V, 2)).
  m.def(
      "rest_triangle_hinges(Tensor uv, Tensor tri, Tensor area, float area_threshold, float area_weight, "
      "Tensor inverse, float shape_threshold, float shape_weight) -> (Tensor value, Tensor grad)");
  // (weighted openings' length shortfall and excess and panel split, its gradient (V, 2)).
  m.def(
      "rest_openings(Tensor uv, Tensor edges, Tensor slot, Tensor slot_opening, Tensor least, Tensor most, "
      "Tensor shares, float length_weight, float split_weight) -> (Tensor value, Tensor grad)");
}

TORCH_LIBRARY_IMPL(diffavatar, CPU, m) {
  m.impl("rest_seam_length", &diffavatar::rest_seam_length);
  m.impl("rest_curvature", &diffavatar::rest_curvature);
  m.impl("rest_triangle_hinges", &diffavatar::rest_triangle_hinges);
  m.impl("rest_openings", &diffavatar::rest_openings);
}
