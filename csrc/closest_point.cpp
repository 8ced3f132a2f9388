// closest_point_on_mesh: for each query point the closest point on a triangle mesh within max_dist.
//
// We bin the triangles' bounding boxes into a uniform grid (counting sort, two passes over the faces)
// and search each point's cells in rings of growing Chebyshev radius around its own cell, stopping once
// the best distance found is below the distance to any cell not yet visited (or once max_dist is
// exceeded). `closest_point_on_mesh` builds the grid per call; `closest_point_index` builds it once as
// tensors (for a body that does not move) and `closest_point_query` searches it. Exact ties go to the
// lowest triangle id and every pruning test has a small slack, so the result does not depend on the
// grid (cell size, visiting order): all three ops return bit-identical (tri, bary, dist). Candidates
// get the exact point-triangle distance of Ericson, "Real-Time Collision Detection", 5.1.5 (same
// region tests and order as sim/reference.py). Geometry is computed in double whatever the input
// dtype. No autograd (the collision response differentiates through the
// barycentric coordinates the caller evaluates itself).

#include <algorithm>
#include <cstring>
#include <limits>
#include <tuple>
#include <vector>

#include "common.h"

namespace diffavatar {
namespace {

using V3 = Vec3<double>;

template <typename T>
inline V3 load3d(const T* p, int64_t i) {
  return {static_cast<double>(p[3 * i]), static_cast<double>(p[3 * i + 1]), static_cast<double>(p[3 * i + 2])};
}

// One triangle in one cell: its id and its bounding box rounded outwards to float, stored inline so
// that scanning a cell reads memory sequentially.
struct Entry {
  int32_t tri;
  float lo[3], hi[3];
};

static_assert(sizeof(Entry) == 7 * sizeof(int32_t), "Entry is stored as 7 int32 per item");

// The grid as the queries see it (owned by `Grid` or by the tensors of `closest_point_index`).
struct GridView {
  double lo[3] = {0, 0, 0};  // corner of cell (0, 0, 0) [m]
  double hi[3] = {0, 0, 0};  // upper corner of the union of the triangle boxes [m]
  double h = 1;              // cell edge [m]
  int64_t n[3] = {1, 1, 1};  // cells per axis
  const int64_t* start = nullptr;  // (n0 n1 n2 + 1,) CSR offsets into items
  const Entry* items = nullptr;    // triangles (id + bounding box), cell by cell

  int64_t axis_cell(int a, double v) const {
    const double c = std::floor((v - lo[a]) / h);
    if (!(c > 0)) return 0;  // also NaN / -inf
    if (c >= static_cast<double>(n[a] - 1)) return n[a] - 1;
    return static_cast<int64_t>(c);
  }
  int64_t cell(int64_t i, int64_t j, int64_t k) const { return (i * n[1] + j) * n[2] + k; }
};

struct Grid : GridView {
  std::vector<int64_t> start_v;
  std::vector<Entry> items_v;
  std::vector<double> box;  // (Fb, 6) triangle bounding boxes: lo xyz, hi xyz
};

template <typename T>
void build_grid(const T* verts, const int64_t* faces, int64_t nf, double cell_size, Grid& g) {
  g.box.resize(static_cast<size_t>(nf) * 6);
  double glo[3] = {std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity(),
                   std::numeric_limits<double>::infinity()};
  double ghi[3] = {-glo[0], -glo[1], -glo[2]};
  double size_sum = 0;
  for (int64_t f = 0; f < nf; ++f) {
    double* b = &g.box[static_cast<size_t>(f) * 6];
    double biggest = 0;
    for (int a = 0; a < 3; ++a) {
      const double v0 = verts[3 * faces[3 * f] + a], v1 = verts[3 * faces[3 * f + 1] + a],
                   v2 = verts[3 * faces[3 * f + 2] + a];
      b[a] = std::min(v0, std::min(v1, v2));
      b[3 + a] = std::max(v0, std::max(v1, v2));
      glo[a] = std::min(glo[a], b[a]);
      ghi[a] = std::max(ghi[a], b[3 + a]);
      biggest = std::max(biggest, b[3 + a] - b[a]);
    }
    size_sum += biggest;
  }
  double ext_max = 0;
  for (int a = 0; a < 3; ++a) {
    g.lo[a] = glo[a];
    g.hi[a] = ghi[a];
    ext_max = std::max(ext_max, ghi[a] - glo[a]);
  }
  // Cell edge: the mean triangle size, grown until the grid has at most ~8 cells per triangle; or
  // cell_size if > 0 (a grid built once can afford finer cells), grown to at most ~64 cells per triangle.
  double h = cell_size > 0 ? cell_size : size_sum / static_cast<double>(nf);
  if (!(h > 1e-9 * ext_max) || !std::isfinite(h)) h = ext_max > 0 ? ext_max / 64 : 1.0;
  const double max_cells = (cell_size > 0 ? 64.0 : 8.0) * static_cast<double>(nf) + 64.0;
  auto cells_for = [&](double hh) {
    double c = 1;
    for (int a = 0; a < 3; ++a) c *= std::floor((ghi[a] - glo[a]) / hh) + 1;
    return c;
  };
  while (cells_for(h) > max_cells) h *= 1.25;
  g.h = h;
  for (int a = 0; a < 3; ++a) g.n[a] = static_cast<int64_t>(std::floor((ghi[a] - glo[a]) / h)) + 1;
  const int64_t n_cells = g.n[0] * g.n[1] * g.n[2];

  // Counting sort of (cell, triangle) pairs: count, prefix sum, fill.
  std::vector<int64_t>& start = g.start_v;
  start.assign(static_cast<size_t>(n_cells) + 1, 0);
  auto for_cells = [&](int64_t f, auto&& fn) {
    const double* b = &g.box[static_cast<size_t>(f) * 6];
    const int64_t i0 = g.axis_cell(0, b[0]), i1 = g.axis_cell(0, b[3]);
    const int64_t j0 = g.axis_cell(1, b[1]), j1 = g.axis_cell(1, b[4]);
    const int64_t k0 = g.axis_cell(2, b[2]), k1 = g.axis_cell(2, b[5]);
    for (int64_t i = i0; i <= i1; ++i)
      for (int64_t j = j0; j <= j1; ++j)
        for (int64_t k = k0; k <= k1; ++k) fn(g.cell(i, j, k));
  };
  for (int64_t f = 0; f < nf; ++f) for_cells(f, [&](int64_t c) { ++start[c + 1]; });
  for (int64_t c = 0; c < n_cells; ++c) start[c + 1] += start[c];
  g.items_v.resize(static_cast<size_t>(start[n_cells]));
  std::vector<int64_t> fill(start.begin(), start.end() - 1);
  for (int64_t f = 0; f < nf; ++f) {
    const double* b = &g.box[static_cast<size_t>(f) * 6];
    Entry e;
    e.tri = static_cast<int32_t>(f);
    for (int a = 0; a < 3; ++a) {
      e.lo[a] = std::nextafter(static_cast<float>(b[a]), -std::numeric_limits<float>::infinity());
      e.hi[a] = std::nextafter(static_cast<float>(b[3 + a]), std::numeric_limits<float>::infinity());
    }
    for_cells(f, [&](int64_t c) { g.items_v[fill[c]++] = e; });
  }
  g.start = g.start_v.data();
  g.items = g.items_v.data();
}

// Ericson 5.1.5: barycentric coordinates (u, v, w) of the point of triangle abc closest to p, with
// the reference's convention that a zero denominator yields a zero ratio (degenerate triangles).
inline void closest_on_triangle(V3 p, V3 a, V3 b, V3 c, double bary[3]) {
  auto safe_div = [](double num, double den) { return den != 0 ? num / den : 0.0; };
  const V3 ab = b - a, ac = c - a, ap = p - a;
  const double d1 = dot(ab, ap), d2 = dot(ac, ap);
  if (d1 <= 0 && d2 <= 0) {  // vertex region A
    bary[0] = 1, bary[1] = 0, bary[2] = 0;
    return;
  }
  const V3 bp = p - b;
  const double d3 = dot(ab, bp), d4 = dot(ac, bp);
  if (d3 >= 0 && d4 <= d3) {  // vertex region B
    bary[0] = 0, bary[1] = 1, bary[2] = 0;
    return;
  }
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) {  // edge region AB
    const double v = safe_div(d1, d1 - d3);
    bary[0] = 1 - v, bary[1] = v, bary[2] = 0;
    return;
  }
  const V3 cp = p - c;
  const double d5 = dot(ab, cp), d6 = dot(ac, cp);
  if (d6 >= 0 && d5 <= d6) {  // vertex region C
    bary[0] = 0, bary[1] = 0, bary[2] = 1;
    return;
  }
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) {  // edge region AC
    const double w = safe_div(d2, d2 - d6);
    bary[0] = 1 - w, bary[1] = 0, bary[2] = w;
    return;
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {  // edge region BC
    const double w = safe_div(d4 - d3, (d4 - d3) + (d5 - d6));
    bary[0] = 0, bary[1] = 1 - w, bary[2] = w;
    return;
  }
  const double denom = va + vb + vc;  // interior
  const double v = safe_div(vb, denom), w = safe_div(vc, denom);
  bary[0] = 1 - v - w, bary[1] = v, bary[2] = w;
}

// Squared distance from p to the box [lo, hi].
inline __attribute__((always_inline)) double box_dist2(const double p[3], const double* lo, const double* hi) {
  double s = 0;
  for (int a = 0; a < 3; ++a) {
    const double d = std::max(std::max(lo[a] - p[a], p[a] - hi[a]), 0.0);
    s += d * d;
  }
  return s;
}

struct Hit {
  int64_t tri = -1;
  double bary[3] = {0, 0, 0};
  double dist2 = std::numeric_limits<double>::infinity();
};

// The triangles of grid cell (i, j, k) that may lie within the bound of p and are not stamped yet: the
// cell is skipped when farther than `bound2()`, an entry when its float box is farther than `bound_f()`
// (both read anew each time: the query's bound shrinks with every closer hit); each triangle passed to
// `fn` is stamped first.
template <typename Bound2, typename BoundF, typename Fn>
inline void visit_cell(const GridView& g, int64_t i, int64_t j, int64_t k, const double p[3], const float pf[3],
                       int64_t nf, std::vector<int64_t>& stamp, int64_t stamp_id, Bound2 bound2, BoundF bound_f,
                       Fn fn) {
  const double clo[3] = {g.lo[0] + i * g.h, g.lo[1] + j * g.h, g.lo[2] + k * g.h};
  const double chi[3] = {clo[0] + g.h, clo[1] + g.h, clo[2] + g.h};
  if (box_dist2(p, clo, chi) > bound2()) return;
  const int64_t cid = g.cell(i, j, k);
  for (int64_t s = g.start[cid]; s < g.start[cid + 1]; ++s) {
    const Entry& e = g.items[s];
    float d2f = 0.0f;
    for (int a = 0; a < 3; ++a) {
      const float d = std::max(std::max(e.lo[a] - pf[a], pf[a] - e.hi[a]), 0.0f);
      d2f += d * d;
    }
    if (d2f > bound_f()) continue;
    const int32_t f = e.tri;
    if (f < 0 || f >= nf) continue;  // cannot happen with an index built for these faces; keeps reads in range
    if (stamp[f] == stamp_id) continue;
    stamp[f] = stamp_id;
    fn(f);
  }
}

template <typename T>
Hit query(const GridView& g, const T* verts, const int64_t* faces, int64_t nf, const double p[3], double max_dist,
          std::vector<int64_t>& stamp, int64_t stamp_id, int64_t hint = -1) {
  Hit hit;
  for (int a = 0; a < 3; ++a) {
    if (!std::isfinite(p[a])) return hit;
  }
  if (box_dist2(p, g.lo, g.hi) > max_dist * max_dist) return hit;
  const double max2 = max_dist * max_dist;
  const V3 pv{p[0], p[1], p[2]};
  // The per-entry box test runs in float (the boxes are stored as float, rounded outwards). Rounding p
  // and the float arithmetic err by a few float ulps of the coordinates, so the pruning radius gets a
  // slack of 1e-6 (1 + |p|_max) [m] plus 1e-6 relative: an entry is only skipped when it is certainly
  // farther than the bound.
  const float pf[3] = {static_cast<float>(p[0]), static_cast<float>(p[1]), static_cast<float>(p[2])};
  const double slack = 1e-6 * (1.0 + std::max(std::fabs(p[0]), std::max(std::fabs(p[1]), std::fabs(p[2]))));
  // The cell tests and the search limits get the same slack (in double), so that a triangle tied with
  // the best one is never pruned by rounding: the lowest-id tie-break then sees every tied triangle.
  auto slacked = [&](double bound2) {
    const double b = std::sqrt(bound2) * (1.0 + 1e-6) + slack;
    return b * b;  // inf stays inf
  };
  const double reach = std::sqrt(slacked(max2));  // >= max_dist
  // slacked bounds of the best distance so far (max_dist before the first hit), updated on each hit
  double cell_bound2 = slacked(max2);
  float bound_f = static_cast<float>(cell_bound2);
  // The exact distance test of triangle f, kept when it is closer (ties: the lowest id).
  auto test_triangle = [&](int64_t f) {
    const V3 va = load3d(verts, faces[3 * f]), vb = load3d(verts, faces[3 * f + 1]),
             vc = load3d(verts, faces[3 * f + 2]);
    double bc[3];
    closest_on_triangle(pv, va, vb, vc, bc);
    const V3 q = bc[0] * va + bc[1] * vb + bc[2] * vc;
    const V3 d = pv - q;
    const double d2 = dot(d, d);
    // ties (equal in double) go to the lowest triangle id, whatever the visiting order
    if (d2 <= max2 && (d2 < hit.dist2 || (d2 == hit.dist2 && f < hit.tri))) {
      hit.tri = f;
      hit.dist2 = d2;
      hit.bary[0] = bc[0], hit.bary[1] = bc[1], hit.bary[2] = bc[2];
      cell_bound2 = slacked(d2);
      bound_f = static_cast<float>(cell_bound2);
    }
  };
  // A hint (e.g. the point's triangle of the last frame) is tested first: when it is close, the search
  // below prunes with its distance from the start. The search still sees every triangle within that
  // bound, so the result is the same whatever the hint.
  if (hint >= 0 && hint < nf) {
    stamp[hint] = stamp_id;
    test_triangle(hint);
  }
  const double lim_r = std::sqrt(cell_bound2);  // nothing beyond the bound can be the result
  int64_t c[3], lim_lo[3], lim_hi[3];
  for (int a = 0; a < 3; ++a) {
    c[a] = g.axis_cell(a, p[a]);
    lim_lo[a] = g.axis_cell(a, p[a] - lim_r);
    lim_hi[a] = g.axis_cell(a, p[a] + lim_r);
  }
  auto visit = [&](int64_t i, int64_t j, int64_t k) {
    visit_cell(
        g, i, j, k, p, pf, nf, stamp, stamp_id, [&] { return cell_bound2; }, [&] { return bound_f; }, test_triangle);
  };
  for (int64_t r = 0;; ++r) {
    // Visit the shell of Chebyshev radius r around c, clipped to the search limits.
    const int64_t i0 = std::max(c[0] - r, lim_lo[0]), i1 = std::min(c[0] + r, lim_hi[0]);
    const int64_t j0 = std::max(c[1] - r, lim_lo[1]), j1 = std::min(c[1] + r, lim_hi[1]);
    const int64_t k0 = std::max(c[2] - r, lim_lo[2]), k1 = std::min(c[2] + r, lim_hi[2]);
    for (int64_t i = i0; i <= i1; ++i) {
      const bool i_shell = (i == c[0] - r) || (i == c[0] + r);
      for (int64_t j = j0; j <= j1; ++j) {
        if (i_shell || (j == c[1] - r) || (j == c[1] + r)) {
          for (int64_t k = k0; k <= k1; ++k) visit(i, j, k);
        } else {
          if (c[2] - r >= k0) visit(i, j, c[2] - r);
          if (r > 0 && c[2] + r <= k1) visit(i, j, c[2] + r);
        }
      }
    }
    // Distance from p to the nearest cell that is inside the limits but outside the visited box.
    double lb = std::numeric_limits<double>::infinity();
    for (int a = 0; a < 3; ++a) {
      if (c[a] - r > lim_lo[a]) lb = std::min(lb, p[a] - (g.lo[a] + (c[a] - r) * g.h));
      if (c[a] + r < lim_hi[a]) lb = std::min(lb, (g.lo[a] + (c[a] + r + 1) * g.h) - p[a]);
    }
    if (!std::isfinite(lb)) break;  // every cell within the limits visited
    lb = std::max(lb, 0.0);
    if (lb > reach || (hit.tri >= 0 && lb * lb > cell_bound2)) break;
  }
  return hit;
}

// OpenMP over the points (pragmas cannot sit inside AT_DISPATCH's lambda).
template <typename T>
void query_all(const GridView& grid, const T* pp, int64_t n, const T* vp, const int64_t* fp, int64_t nf,
               double max_dist, int64_t* tp, T* bp, T* dp, const int64_t* hints = nullptr) {
  const int nt = num_threads();
#pragma omp parallel if (n >= kParallelGrain / 8 && nt > 1) num_threads(nt)
  {
    std::vector<int64_t> stamp(static_cast<size_t>(nf), -1);  // last query that tested a triangle
#pragma omp for schedule(dynamic, 64)
    for (int64_t i = 0; i < n; ++i) {
      const double p[3] = {static_cast<double>(pp[3 * i]), static_cast<double>(pp[3 * i + 1]),
                           static_cast<double>(pp[3 * i + 2])};
      const Hit hit = query(grid, vp, fp, nf, p, max_dist, stamp, i, hints ? hints[i] : -1);
      if (hit.tri < 0) continue;
      tp[i] = hit.tri;
      for (int k = 0; k < 3; ++k) bp[3 * i + k] = static_cast<T>(hit.bary[k]);
      dp[i] = static_cast<T>(std::sqrt(hit.dist2));
    }
  }
}

// Every triangle within `radius` of p (exact distance, with query's slack so that rounding never drops
// one), appended to `out`.
template <typename T>
void collect(const GridView& g, const T* verts, const int64_t* faces, int64_t nf, const double p[3], double radius,
             std::vector<int64_t>& stamp, int64_t stamp_id, std::vector<int64_t>& out) {
  for (int a = 0; a < 3; ++a) {
    if (!std::isfinite(p[a])) return;
  }
  const double slack = 1e-6 * (1.0 + std::max(std::fabs(p[0]), std::max(std::fabs(p[1]), std::fabs(p[2]))));
  const double r = radius * (1.0 + 1e-6) + slack, r2 = r * r;
  if (box_dist2(p, g.lo, g.hi) > r2) return;
  const float pf[3] = {static_cast<float>(p[0]), static_cast<float>(p[1]), static_cast<float>(p[2])};
  const float r2f = static_cast<float>(r2);
  const V3 pv{p[0], p[1], p[2]};
  int64_t lo[3], hi[3];
  for (int a = 0; a < 3; ++a) lo[a] = g.axis_cell(a, p[a] - r), hi[a] = g.axis_cell(a, p[a] + r);
  for (int64_t i = lo[0]; i <= hi[0]; ++i)
    for (int64_t j = lo[1]; j <= hi[1]; ++j)
      for (int64_t k = lo[2]; k <= hi[2]; ++k) {
        visit_cell(
            g, i, j, k, p, pf, nf, stamp, stamp_id, [&] { return r2; }, [&] { return r2f; },
            [&](int64_t f) {
              const V3 va = load3d(verts, faces[3 * f]), vb = load3d(verts, faces[3 * f + 1]),
                       vc = load3d(verts, faces[3 * f + 2]);
              double bc[3];
              closest_on_triangle(pv, va, vb, vc, bc);
              const V3 d = pv - (bc[0] * va + bc[1] * vb + bc[2] * vc);
              if (dot(d, d) <= r2) out.push_back(f);
            });
      }
}

// The closest of the candidate triangles cand[0..k) (up to the first -1) within max_dist: the same
// distance test and tie-break (lowest id) as `query`, so when the candidates hold every triangle as close
// as the closest one, the result is `query`'s, bit for bit.
template <typename T>
Hit closest_among(const T* verts, const int64_t* faces, int64_t nf, const double p[3], double max_dist,
                  const int64_t* cand, int64_t k) {
  Hit hit;
  for (int a = 0; a < 3; ++a) {
    if (!std::isfinite(p[a])) return hit;
  }
  const double max2 = max_dist * max_dist;
  const V3 pv{p[0], p[1], p[2]};
  for (int64_t c = 0; c < k; ++c) {
    const int64_t f = cand[c];
    if (f < 0) break;  // rows are padded with -1 at their end
    if (f >= nf) continue;
    const V3 va = load3d(verts, faces[3 * f]), vb = load3d(verts, faces[3 * f + 1]),
             vc = load3d(verts, faces[3 * f + 2]);
    double bc[3];
    closest_on_triangle(pv, va, vb, vc, bc);
    const V3 d = pv - (bc[0] * va + bc[1] * vb + bc[2] * vc);
    const double d2 = dot(d, d);
    if (d2 <= max2 && (d2 < hit.dist2 || (d2 == hit.dist2 && f < hit.tri))) {
      hit.tri = f;
      hit.dist2 = d2;
      hit.bary[0] = bc[0], hit.bary[1] = bc[1], hit.bary[2] = bc[2];
    }
  }
  return hit;
}

void check_mesh(const at::Tensor& verts, const at::Tensor& faces) {
  check_cpu_contiguous(verts, "verts");
  check_cpu_contiguous(faces, "faces");
  check_shape(verts, "verts", {-1, 3});
  check_shape(faces, "faces", {-1, 3});
  TORCH_CHECK(verts.scalar_type() == at::kFloat || verts.scalar_type() == at::kDouble,
              "diffavatar: verts must be float32 or float64, got ", verts.scalar_type());
  check_dtype(faces, "faces", at::kLong);
  check_index_range(faces, verts.size(0), "faces");
  TORCH_CHECK(faces.size(0) < std::numeric_limits<int32_t>::max(), "diffavatar: too many faces");
}

void check_points(const at::Tensor& points, const at::Tensor& verts, double max_dist) {
  check_cpu_contiguous(points, "points");
  check_shape(points, "points", {-1, 3});
  TORCH_CHECK(points.scalar_type() == at::kFloat || points.scalar_type() == at::kDouble,
              "diffavatar: points must be float32 or float64, got ", points.scalar_type());
  check_dtype(verts, "verts", points.scalar_type());
  TORCH_CHECK(max_dist >= 0, "diffavatar: max_dist must be >= 0 (inf allowed), got ", max_dist);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> empty_result(const at::Tensor& points) {
  const int64_t n = points.size(0);
  return {at::full({n}, -1, points.options().dtype(at::kLong)), at::zeros({n, 3}, points.options()),
          at::full({n}, std::numeric_limits<double>::infinity(), points.options())};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> closest_point_on_mesh(const at::Tensor& points,
                                                                      const at::Tensor& verts,
                                                                      const at::Tensor& faces, double max_dist) {
  check_mesh(verts, faces);
  check_points(points, verts, max_dist);
  auto [tri, bary, dist] = empty_result(points);
  const int64_t n = points.size(0), nf = faces.size(0);
  if (n == 0 || nf == 0) return {tri, bary, dist};

  const int64_t* fp = faces.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "closest_point_on_mesh", [&] {
    Grid grid;
    build_grid(verts.data_ptr<scalar_t>(), fp, nf, 0.0, grid);
    query_all<scalar_t>(grid, points.data_ptr<scalar_t>(), n, verts.data_ptr<scalar_t>(), fp, nf, max_dist,
                        tri.data_ptr<int64_t>(), bary.data_ptr<scalar_t>(), dist.data_ptr<scalar_t>());
  });
  return {tri, bary, dist};
}

// Grid header stored in a float64 tensor: lo xyz, hi xyz, h, n xyz, face count.
constexpr int64_t kHeader = 11;

// The grid of a mesh as tensors: header (11,) float64, cell_start (cells + 1,) int64 and cell_items
// (M, 7) int32 (triangle id, then its float32 box bit-cast). cell_size <= 0 picks the mean triangle size.
std::tuple<at::Tensor, at::Tensor, at::Tensor> closest_point_index(const at::Tensor& verts, const at::Tensor& faces,
                                                                    double cell_size) {
  check_mesh(verts, faces);
  TORCH_CHECK(std::isfinite(cell_size), "diffavatar: cell_size must be finite, got ", cell_size);
  const int64_t nf = faces.size(0);
  at::Tensor header = at::zeros({kHeader}, verts.options().dtype(at::kDouble));
  double* hd = header.data_ptr<double>();
  if (nf == 0) {
    for (int a = 0; a < 3; ++a) hd[7 + a] = 1;
    hd[6] = 1;
    return {header, at::zeros({2}, verts.options().dtype(at::kLong)),
            at::zeros({0, 7}, verts.options().dtype(at::kInt))};
  }
  Grid grid;
  AT_DISPATCH_FLOATING_TYPES(verts.scalar_type(), "closest_point_index", [&] {
    build_grid(verts.data_ptr<scalar_t>(), faces.data_ptr<int64_t>(), nf, cell_size, grid);
  });
  for (int a = 0; a < 3; ++a) {
    hd[a] = grid.lo[a];
    hd[3 + a] = grid.hi[a];
    hd[7 + a] = static_cast<double>(grid.n[a]);
  }
  hd[6] = grid.h;
  hd[10] = static_cast<double>(nf);
  const auto n_start = static_cast<int64_t>(grid.start_v.size());
  const auto n_items = static_cast<int64_t>(grid.items_v.size());
  at::Tensor start = at::empty({n_start}, verts.options().dtype(at::kLong));
  at::Tensor items = at::empty({n_items, 7}, verts.options().dtype(at::kInt));
  std::copy(grid.start_v.begin(), grid.start_v.end(), start.data_ptr<int64_t>());
  if (n_items) std::memcpy(items.data_ptr<int32_t>(), grid.items_v.data(), sizeof(Entry) * n_items);
  return {header, start, items};
}

GridView grid_view(const at::Tensor& faces, const at::Tensor& header, const at::Tensor& cell_start,
                   const at::Tensor& cell_items);

// closest_point_on_mesh on a grid built by closest_point_index from the same (verts, faces); hints (N,) int64
// or undefined: a triangle per point to test first (-1: none), which changes the speed, never the result.
std::tuple<at::Tensor, at::Tensor, at::Tensor> query_index(const at::Tensor& points, const at::Tensor& verts,
                                                            const at::Tensor& faces, const at::Tensor& header,
                                                            const at::Tensor& cell_start, const at::Tensor& cell_items,
                                                            const at::Tensor& hints, double max_dist) {
  check_mesh(verts, faces);
  check_points(points, verts, max_dist);
  const int64_t nf = faces.size(0);
  const GridView g = grid_view(faces, header, cell_start, cell_items);
  const int64_t n = points.size(0);
  const int64_t* hp = nullptr;
  if (hints.defined()) {
    check_cpu_contiguous(hints, "hint");
    check_dtype(hints, "hint", at::kLong);
    TORCH_CHECK(hints.dim() == 1 && hints.size(0) == n, "diffavatar: hint must be (", n, ",), got ", hints.sizes());
    hp = hints.data_ptr<int64_t>();  // out-of-range hints are ignored by `query`
  }
  auto [tri, bary, dist] = empty_result(points);
  if (n == 0 || nf == 0) return {tri, bary, dist};
  const int64_t* fp = faces.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "closest_point_query", [&] {
    query_all<scalar_t>(g, points.data_ptr<scalar_t>(), n, verts.data_ptr<scalar_t>(), fp, nf, max_dist,
                        tri.data_ptr<int64_t>(), bary.data_ptr<scalar_t>(), dist.data_ptr<scalar_t>(), hp);
  });
  return {tri, bary, dist};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> closest_point_query(const at::Tensor& points, const at::Tensor& verts,
                                                                    const at::Tensor& faces, const at::Tensor& header,
                                                                    const at::Tensor& cell_start,
                                                                    const at::Tensor& cell_items, double max_dist) {
  return query_index(points, verts, faces, header, cell_start, cell_items, at::Tensor(), max_dist);
}

// closest_point_query that tests hint[i] first for point i (a cache of the last frame's triangles).
std::tuple<at::Tensor, at::Tensor, at::Tensor> closest_point_query_hinted(
    const at::Tensor& points, const at::Tensor& verts, const at::Tensor& faces, const at::Tensor& header,
    const at::Tensor& cell_start, const at::Tensor& cell_items, const at::Tensor& hint, double max_dist) {
  return query_index(points, verts, faces, header, cell_start, cell_items, hint, max_dist);
}

// The grid of `closest_point_index` as a view (shared by the query ops).
GridView grid_view(const at::Tensor& faces, const at::Tensor& header, const at::Tensor& cell_start,
                   const at::Tensor& cell_items) {
  check_cpu_contiguous(header, "header");
  check_cpu_contiguous(cell_start, "cell_start");
  check_cpu_contiguous(cell_items, "cell_items");
  check_dtype(header, "header", at::kDouble);
  check_dtype(cell_start, "cell_start", at::kLong);
  check_dtype(cell_items, "cell_items", at::kInt);
  check_shape(header, "header", {kHeader});
  check_shape(cell_items, "cell_items", {-1, 7});
  const double* hd = header.data_ptr<double>();
  TORCH_CHECK(hd[10] == static_cast<double>(faces.size(0)), "diffavatar: the index was built for ", hd[10],
              " faces, got ", faces.size(0));
  GridView g;
  for (int a = 0; a < 3; ++a) {
    g.lo[a] = hd[a];
    g.hi[a] = hd[3 + a];
    g.n[a] = static_cast<int64_t>(hd[7 + a]);
    TORCH_CHECK(g.n[a] >= 1, "diffavatar: bad index header");
  }
  g.h = hd[6];
  const int64_t n_cells = g.n[0] * g.n[1] * g.n[2];
  TORCH_CHECK(cell_start.dim() == 1 && cell_start.size(0) == n_cells + 1, "diffavatar: cell_start must have ",
              n_cells + 1, " entries, got ", cell_start.sizes());
  const int64_t* sp = cell_start.data_ptr<int64_t>();
  TORCH_CHECK(sp[0] == 0 && sp[n_cells] == cell_items.size(0), "diffavatar: cell_start does not match cell_items");
  g.start = sp;
  g.items = reinterpret_cast<const Entry*>(cell_items.data_ptr<int32_t>());
  return g;
}

// For each point i every triangle within radius[i] (float64, (N,)) of it: (N, K) int64 padded with -1, K the
// longest list (at least 1).
at::Tensor closest_point_candidates(const at::Tensor& points, const at::Tensor& verts, const at::Tensor& faces,
                                    const at::Tensor& header, const at::Tensor& cell_start,
                                    const at::Tensor& cell_items, const at::Tensor& radius) {
  check_mesh(verts, faces);
  check_points(points, verts, 0.0);
  check_cpu_contiguous(radius, "radius");
  check_dtype(radius, "radius", at::kDouble);
  const int64_t n = points.size(0), nf = faces.size(0);
  TORCH_CHECK(radius.dim() == 1 && radius.size(0) == n, "diffavatar: radius must be (", n, ",), got ",
              radius.sizes());
  const GridView g = grid_view(faces, header, cell_start, cell_items);
  const double* rp = radius.data_ptr<double>();
  std::vector<int64_t> offsets(static_cast<size_t>(n) + 1, 0), tris;
  std::vector<int64_t> stamp(static_cast<size_t>(nf), -1);
  int64_t width = 1;
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "closest_point_candidates", [&] {
    const scalar_t* pp = points.data_ptr<scalar_t>();
    for (int64_t i = 0; i < n; ++i) {
      const double p[3] = {static_cast<double>(pp[3 * i]), static_cast<double>(pp[3 * i + 1]),
                           static_cast<double>(pp[3 * i + 2])};
      if (rp[i] >= 0) collect(g, verts.data_ptr<scalar_t>(), faces.data_ptr<int64_t>(), nf, p, rp[i], stamp, i, tris);
      offsets[i + 1] = static_cast<int64_t>(tris.size());
      width = std::max(width, offsets[i + 1] - offsets[i]);
    }
  });
  at::Tensor out = at::full({n, width}, -1, points.options().dtype(at::kLong));
  int64_t* op = out.data_ptr<int64_t>();
  for (int64_t i = 0; i < n; ++i) std::copy(&tris[offsets[i]], &tris[offsets[i]] + (offsets[i + 1] - offsets[i]), op + i * width);
  return out;
}

// (tri, bary, dist) of the closest of each point's candidates cand[i, :] (ending at the first -1) within max_dist.
std::tuple<at::Tensor, at::Tensor, at::Tensor> closest_point_among(const at::Tensor& points, const at::Tensor& verts,
                                                                    const at::Tensor& faces, const at::Tensor& cand,
                                                                    double max_dist) {
  check_mesh(verts, faces);
  check_points(points, verts, max_dist);
  check_cpu_contiguous(cand, "cand");
  check_dtype(cand, "cand", at::kLong);
  const int64_t n = points.size(0), nf = faces.size(0);
  TORCH_CHECK(cand.dim() == 2 && cand.size(0) == n, "diffavatar: cand must be (", n, ", K), got ", cand.sizes());
  auto [tri, bary, dist] = empty_result(points);
  const int64_t k = cand.size(1);
  const int64_t* cp = cand.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "closest_point_among", [&] {
    const scalar_t* pp = points.data_ptr<scalar_t>();
    scalar_t* bp = bary.data_ptr<scalar_t>();
    for (int64_t i = 0; i < n; ++i) {
      const double p[3] = {static_cast<double>(pp[3 * i]), static_cast<double>(pp[3 * i + 1]),
                           static_cast<double>(pp[3 * i + 2])};
      const Hit hit = closest_among(verts.data_ptr<scalar_t>(), faces.data_ptr<int64_t>(), nf, p, max_dist, cp + i * k, k);
      if (hit.tri < 0) continue;
      tri.data_ptr<int64_t>()[i] = hit.tri;
      for (int c = 0; c < 3; ++c) bp[3 * i + c] = static_cast<scalar_t>(hit.bary[c]);
      dist.data_ptr<scalar_t>()[i] = static_cast<scalar_t>(std::sqrt(hit.dist2));
    }
  });
  return {tri, bary, dist};
}

// ------------------------------------------------------------------------------------ the contact cache

// One frame of `collision.ContactCache` (see its docstring) for every point, in place on the cache's state:
// last_x (N, 3) f64 where each point was last queried; lower (N,) f64 a lower bound of its distance to the
// mesh from there; last_tri (N,) i64 its triangle (or the probe's, -1: none); cand_x (N, 3) f64 where its
// candidates were collected; cand (N, K) i64 the candidates, -1 padded (cand[i, 0] < 0: none, also when
// more than K lie within the radius). Returns (tri, bary) exactly as `closest_point_query` (points, band)
// and counts (3,) i64: the points queried, of those the ones answered among their candidates, and the
// longest candidate list that did not fit in K (0: none).
template <typename T>
void cache_one(const GridView& g, const T* verts, const int64_t* faces, int64_t nf, const T* pt, int64_t i,
               double band, double probe, double margin, double max_radius, double* last_x, double* lower,
               int64_t* last_tri, double* cand_x, int64_t* cand, int64_t k, std::vector<int64_t>& stamp,
               std::vector<int64_t>& found, int64_t* tri_out, T* bary_out, int64_t& queried, int64_t& among,
               int64_t& overflow) {
  constexpr double kSlack = 1e-5;  // [m]: double distances vs float32 positions (`reference._CACHE_SLACK`)
  const double p[3] = {static_cast<double>(pt[0]), static_cast<double>(pt[1]), static_cast<double>(pt[2])};
  auto dist_from = [&](const double* q) {
    const double d0 = p[0] - q[0], d1 = p[1] - q[1], d2 = p[2] - q[2];
    return std::sqrt(d0 * d0 + d1 * d1 + d2 * d2);
  };
  // rounded as the point's dtype, as the query's output is
  auto rounded = [](const Hit& h) { return static_cast<double>(static_cast<T>(std::sqrt(h.dist2))); };
  if (lower[i] - dist_from(last_x + 3 * i) > band + kSlack) return;  // cannot be in the band (NaN: queried)
  ++queried;
  int64_t* row = cand + i * k;
  Hit hit;
  if (row[0] >= 0 && dist_from(cand_x + 3 * i) <= margin - kSlack) {
    hit = closest_among(verts, faces, nf, p, band, row, k);
    ++among;
  } else {
    hit = query(g, verts, faces, nf, p, band, stamp, 3 * i, last_tri[i]);
    row[0] = -1;
    if (hit.tri >= 0 && rounded(hit) + 2 * margin <= max_radius) {
      found.clear();
      collect(g, verts, faces, nf, p, rounded(hit) + 2 * margin, stamp, 3 * i + 1, found);
      if (static_cast<int64_t>(found.size()) <= k) {
        std::copy(found.begin(), found.end(), row);
        std::fill(row + found.size(), row + k, int64_t{-1});
        for (int a = 0; a < 3; ++a) cand_x[3 * i + a] = p[a];
      } else {
        overflow = std::max(overflow, static_cast<int64_t>(found.size()));
      }
    }
  }
  if (hit.tri >= 0) {
    tri_out[i] = hit.tri;
    for (int a = 0; a < 3; ++a) bary_out[3 * i + a] = static_cast<T>(hit.bary[a]);
    lower[i] = rounded(hit);
    last_tri[i] = hit.tri;
  } else {  // probed farther: how far it is, and a hint for when it comes closer
    const Hit far = query(g, verts, faces, nf, p, band + probe, stamp, 3 * i + 2);
    lower[i] = far.tri >= 0 ? rounded(far) : band + probe;
    last_tri[i] = far.tri;
  }
  for (int a = 0; a < 3; ++a) last_x[3 * i + a] = p[a];
}

// `cache_one` over every point, OpenMP over the points (pragmas cannot sit inside AT_DISPATCH's lambda).
template <typename T>
void cache_all(const GridView& g, const T* verts, const int64_t* faces, int64_t nf, const T* pp, int64_t n,
               double band, double probe, double margin, double max_radius, double* last_x, double* lower,
               int64_t* last_tri, double* cand_x, int64_t* cand, int64_t k, int64_t* tri_out, T* bary_out,
               int64_t& queried, int64_t& among, int64_t& overflow) {
  const int nt = num_threads();
  int64_t q = 0, a = 0, o = 0;
#pragma omp parallel if (n >= kParallelGrain / 8 && nt > 1) num_threads(nt) reduction(+ : q, a) reduction(max : o)
  {
    std::vector<int64_t> stamp(static_cast<size_t>(nf), -1), found;
#pragma omp for schedule(dynamic, 64)
    for (int64_t i = 0; i < n; ++i) {
      cache_one<T>(g, verts, faces, nf, pp + 3 * i, i, band, probe, margin, max_radius, last_x, lower, last_tri,
                   cand_x, cand, k, stamp, found, tri_out, bary_out, q, a, o);
    }
  }
  queried = q, among = a, overflow = o;
}

void check_cache_state(const at::Tensor& t, const char* name, at::ScalarType dtype, at::IntArrayRef sizes) {
  check_cpu_contiguous(t, name);
  check_dtype(t, name, dtype);
  check_shape(t, name, sizes);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> contact_cache_query_(
    const at::Tensor& points, const at::Tensor& verts, const at::Tensor& faces, const at::Tensor& header,
    const at::Tensor& cell_start, const at::Tensor& cell_items, at::Tensor last_x, at::Tensor lower,
    at::Tensor last_tri, at::Tensor cand_x, at::Tensor cand, double band, double probe, double margin,
    double max_radius) {
  check_mesh(verts, faces);
  check_points(points, verts, band);
  TORCH_CHECK(probe >= 0 && margin >= 0 && max_radius >= 0, "diffavatar: probe, margin and max_radius must be >= 0");
  const int64_t n = points.size(0), nf = faces.size(0);
  check_cache_state(last_x, "last_x", at::kDouble, {n, 3});
  check_cache_state(lower, "lower", at::kDouble, {n});
  check_cache_state(last_tri, "last_tri", at::kLong, {n});
  check_cache_state(cand_x, "cand_x", at::kDouble, {n, 3});
  check_cache_state(cand, "cand", at::kLong, {n, -1});
  TORCH_CHECK(cand.size(1) >= 1, "diffavatar: cand must have at least one column");
  const GridView g = grid_view(faces, header, cell_start, cell_items);
  auto [tri, bary, dist] = empty_result(points);
  at::Tensor counts = at::zeros({3}, points.options().dtype(at::kLong));
  if (n == 0 || nf == 0) return {tri, bary, counts};
  const int64_t k = cand.size(1);
  int64_t queried = 0, among = 0, overflow = 0;
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "contact_cache_query_", [&] {
    cache_all<scalar_t>(g, verts.data_ptr<scalar_t>(), faces.data_ptr<int64_t>(), nf, points.data_ptr<scalar_t>(),
                        n, band, probe, margin, max_radius, last_x.data_ptr<double>(), lower.data_ptr<double>(),
                        last_tri.data_ptr<int64_t>(), cand_x.data_ptr<double>(), cand.data_ptr<int64_t>(), k,
                        tri.data_ptr<int64_t>(), bary.data_ptr<scalar_t>(), queried, among, overflow);
  });
  counts[0] = queried;
  counts[1] = among;
  counts[2] = overflow;
  return {tri, bary, counts};
}

// -------------------------------------------------------------------------------- the outermost face

// `collision._FeatureFaces.outermost`: a contact whose closest point lies on an edge (one zero barycentric)
// or a vertex (two) of face tri[c] moves to the face sharing that feature (across (Fb, 3): the face across
// the edge opposite each corner; ring (Vb, R): the faces around each vertex, -1 padded) whose plane is the
// farthest from the point, when one is strictly farther than tri[c]'s (first of the farthest in candidate
// order); its barycentrics move to the new face's corners. Planes in double. Returns new (tri, bary).
std::tuple<at::Tensor, at::Tensor> contact_outermost(const at::Tensor& points, const at::Tensor& verts,
                                                     const at::Tensor& faces, const at::Tensor& across,
                                                     const at::Tensor& ring, const at::Tensor& tri,
                                                     const at::Tensor& bary) {
  check_mesh(verts, faces);
  check_cpu_contiguous(points, "points");
  check_shape(points, "points", {-1, 3});
  const int64_t n = points.size(0), nf = faces.size(0), nv = verts.size(0);
  TORCH_CHECK(points.scalar_type() == at::kFloat || points.scalar_type() == at::kDouble,
              "diffavatar: points must be float32 or float64, got ", points.scalar_type());
  check_dtype(verts, "verts", points.scalar_type());
  check_cache_state(across, "across", at::kLong, {nf, 3});
  check_cache_state(ring, "ring", at::kLong, {nv, -1});
  check_cache_state(tri, "tri", at::kLong, {n});
  check_cache_state(bary, "bary", points.scalar_type(), {n, 3});
  check_index_range(tri, nf, "tri");
  check_index_range(across, nf, "across");
  const int64_t r = ring.size(1);
  at::Tensor tri_out = tri.clone(), bary_out = bary.clone();
  const int64_t *fp = faces.data_ptr<int64_t>(), *ap = across.data_ptr<int64_t>(), *rp = ring.data_ptr<int64_t>();
  int64_t* to = tri_out.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "contact_outermost", [&] {
    const scalar_t* pp = points.data_ptr<scalar_t>();
    const scalar_t* vp = verts.data_ptr<scalar_t>();
    scalar_t* bo = bary_out.data_ptr<scalar_t>();
    auto plane_dist = [&](const V3& x, int64_t f) {
      const V3 a = load3d(vp, fp[3 * f]), b = load3d(vp, fp[3 * f + 1]), c = load3d(vp, fp[3 * f + 2]);
      const V3 nrm = cross(b - a, c - a);
      const double len = std::max(std::sqrt(dot(nrm, nrm)), 1e-20);  // as `contacts.unit_normals`
      return dot(x - a, V3{nrm.x / len, nrm.y / len, nrm.z / len});
    };
    for (int64_t c = 0; c < n; ++c) {
      const int64_t f0 = to[c];
      const scalar_t* b = bo + 3 * c;
      const int nz = (b[0] <= 0) + (b[1] <= 0) + (b[2] <= 0);
      if (nz != 1 && nz != 2) continue;  // inside the face (or degenerate): keeps it
      const V3 x = load3d(pp, c);
      double best = plane_dist(x, f0);
      int64_t pick = f0;
      auto consider = [&](int64_t f) {
        if (f < 0 || f >= nf) return;  // -1: the ring's padding
        const double s = plane_dist(x, f);
        if (s > best) best = s, pick = f;
      };
      if (nz == 1) {
        consider(ap[3 * f0 + (b[0] <= 0 ? 0 : (b[1] <= 0 ? 1 : 2))]);
      } else {
        const int64_t u = fp[3 * f0 + (b[0] > 0 ? 0 : (b[1] > 0 ? 1 : 2))];
        for (int64_t j = 0; j < r; ++j) consider(rp[u * r + j]);
      }
      if (pick == f0) continue;
      scalar_t moved[3] = {0, 0, 0};
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
          if (fp[3 * f0 + i] == fp[3 * pick + j]) moved[j] += b[i];
      to[c] = pick;
      for (int j = 0; j < 3; ++j) bo[3 * c + j] = moved[j];
    }
  });
  return {tri_out, bary_out};
}

}  // namespace
}  // namespace diffavatar

// The index ops are declared here rather than in registration.cpp: they belong with their kernels.
TORCH_LIBRARY_FRAGMENT(diffavatar, m) {
  m.def(
      "closest_point_index(Tensor verts, Tensor faces, float cell_size) "
      "-> (Tensor header, Tensor cell_start, Tensor cell_items)");
  m.def(
      "closest_point_query(Tensor points, Tensor verts, Tensor faces, Tensor header, Tensor cell_start, "
      "Tensor cell_items, float max_dist) -> (Tensor tri, Tensor bary, Tensor dist)");
  m.def(
      "closest_point_query_hinted(Tensor points, Tensor verts, Tensor faces, Tensor header, Tensor cell_start, "
      "Tensor cell_items, Tensor hint, float max_dist) -> (Tensor tri, Tensor bary, Tensor dist)");
  m.def(
      "closest_point_candidates(Tensor points, Tensor verts, Tensor faces, Tensor header, Tensor cell_start, "
      "Tensor cell_items, Tensor radius) -> Tensor");
  m.def(
      "closest_point_among(Tensor points, Tensor verts, Tensor faces, Tensor cand, float max_dist) "
      "-> (Tensor tri, Tensor bary, Tensor dist)");
  m.def(
      "contact_cache_query_(Tensor points, Tensor verts, Tensor faces, Tensor header, Tensor cell_start, "
      "Tensor cell_items, Tensor(a!) last_x, Tensor(b!) lower, Tensor(c!) last_tri, Tensor(d!) cand_x, "
      "Tensor(e!) cand, float band, float probe, float margin, float max_radius) "
      "-> (Tensor tri, Tensor bary, Tensor counts)");
  m.def(
      "contact_outermost(Tensor points, Tensor verts, Tensor faces, Tensor across, Tensor ring, Tensor tri, "
      "Tensor bary) -> (Tensor tri, Tensor bary)");
}

TORCH_LIBRARY_IMPL(diffavatar, CPU, m) {
  m.impl("closest_point_on_mesh", &diffavatar::closest_point_on_mesh);
  m.impl("closest_point_index", &diffavatar::closest_point_index);
  m.impl("closest_point_query", &diffavatar::closest_point_query);
  m.impl("closest_point_query_hinted", &diffavatar::closest_point_query_hinted);
  m.impl("closest_point_candidates", &diffavatar::closest_point_candidates);
  m.impl("closest_point_among", &diffavatar::closest_point_among);
  m.impl("contact_cache_query_", &diffavatar::contact_cache_query_);
  m.impl("contact_outermost", &diffavatar::contact_outermost);
}
