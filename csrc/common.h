// Small helpers shared by the kernels: argument checks and 3-vector arithmetic.
#pragma once

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>

namespace diffavatar {

// Below this many independent work items a loop runs on the calling thread only: forking the OpenMP
// team costs a few microseconds, about as much as a few hundred constraint projections.
constexpr int64_t kParallelGrain = 512;

// Threads for an OpenMP region: PyTorch's intra-op setting (torch.set_num_threads), so one knob
// controls both.
// Largest entry of a 3x3 SPD system solved by the adjugate before it is scaled down: its determinant
// (a sum of three products ~ entry^3) must stay finite. Sub-millimetre triangles (inverse masses ~1e7)
// give stretch systems with entries ~1e13-1e14, whose determinant overflows float; systems below this
// (float: 4.4e12) are solved unscaled, as before.
template <typename T>
inline T sym3_scale_limit() {
  static const T limit = std::cbrt(std::numeric_limits<T>::max() / T(4));
  return limit;
}

inline int num_threads() { return std::max(1, at::get_num_threads()); }

inline void check_cpu_contiguous(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu(), "diffavatar: ", name, " must be a CPU tensor, got ", t.device());
  TORCH_CHECK(t.is_contiguous(), "diffavatar: ", name, " must be contiguous (call .contiguous())");
}

// Checks t has exactly `sizes` (entries < 0 match any extent) and returns nothing.
inline void check_shape(const at::Tensor& t, const char* name, at::IntArrayRef sizes) {
  bool ok = t.dim() == static_cast<int64_t>(sizes.size());
  for (size_t i = 0; ok && i < sizes.size(); ++i) {
    ok = sizes[i] < 0 || t.size(static_cast<int64_t>(i)) == sizes[i];
  }
  TORCH_CHECK(ok, "diffavatar: ", name, " must have shape ", sizes, " (-1 = any), got ", t.sizes());
}

inline void check_dtype(const at::Tensor& t, const char* name, at::ScalarType dtype) {
  TORCH_CHECK(t.scalar_type() == dtype, "diffavatar: ", name, " must be ", dtype, ", got ", t.scalar_type());
}

// Every entry of the int64 tensor `ids` lies in [0, bound).
inline void check_index_range(const at::Tensor& ids, int64_t bound, const char* name) {
  const int64_t* p = ids.data_ptr<int64_t>();
  const int64_t n = ids.numel();
  bool ok = true;
  for (int64_t i = 0; i < n; ++i) {
    ok &= (p[i] >= 0) & (p[i] < bound);
  }
  TORCH_CHECK(ok, "diffavatar: ", name, " holds indices outside [0, ", bound, ")");
}

// `color_offsets` (n_colors + 1,) is non-decreasing, starts at 0 and ends at most at `order_len`.
inline void check_color_offsets(const at::Tensor& color_offsets, int64_t order_len) {
  const int64_t* p = color_offsets.data_ptr<int64_t>();
  const int64_t n = color_offsets.numel();
  TORCH_CHECK(n >= 1, "diffavatar: color_offsets must have n_colors + 1 >= 1 entries");
  bool ok = p[0] >= 0 && p[n - 1] <= order_len;
  for (int64_t i = 1; i < n; ++i) {
    ok &= p[i] >= p[i - 1];
  }
  TORCH_CHECK(ok, "diffavatar: color_offsets must be non-decreasing within [0, len(order) = ", order_len, "]");
}

template <typename T>
struct Vec3 {
  T x, y, z;
};

template <typename T>
inline Vec3<T> load3(const T* p, int64_t i) {
  return {p[3 * i], p[3 * i + 1], p[3 * i + 2]};
}
template <typename T>
inline Vec3<T> operator+(Vec3<T> a, Vec3<T> b) {
  return {a.x + b.x, a.y + b.y, a.z + b.z};
}
template <typename T>
inline Vec3<T> operator-(Vec3<T> a, Vec3<T> b) {
  return {a.x - b.x, a.y - b.y, a.z - b.z};
}
template <typename T>
inline Vec3<T> operator*(T s, Vec3<T> a) {
  return {s * a.x, s * a.y, s * a.z};
}
template <typename T>
inline T dot(Vec3<T> a, Vec3<T> b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}
template <typename T>
inline Vec3<T> cross(Vec3<T> a, Vec3<T> b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

}  // namespace diffavatar
