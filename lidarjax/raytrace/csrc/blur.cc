// Native CPU kernel of a separable 2-D Gaussian blur with the border cells extended:
// lidarjax.maps.blur (smooth_cells with edge="nearest") on a [nx ny] array, the SLAM front
// end's per-match blur of its 44 m map window (880 x 880 cells at 0.05 m) for each
// coarse-to-fine stage.
//
// Same operations as the JAX path: first along axis 0, then along axis 1, each output cell
// the sum over the kernel taps t = 0 .. T - 1 in that order of k[t] * x[clamp(i + t - h)]
// (h = (T - 1) / 2), accumulated from 0 in the input precision. The taps come from the
// caller (gaussian_kernel_1d, normalised in double and cast as the JAX path casts them).
// Compiled with -ffp-contract=off, so each product and sum is rounded as written; XLA may
// fuse them, so the two paths agree to round-off, not bit for bit. The inner loops run
// along contiguous rows, which the compiler vectorises. Every loop is bounded by the array
// and kernel sizes; a non-finite input cell is an error naming it (no silent NaN).

#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

ffi::Error bad_blur(const std::string& what) {
  return ffi::Error(ffi::ErrorCode::kInvalidArgument, what);
}

template <ffi::DataType DT>
ffi::Error Blur2D(ffi::Buffer<DT> values, ffi::Buffer<DT> taps, ffi::ResultBuffer<DT> out) {
  using T = ffi::NativeType<DT>;
  auto vd = values.dimensions();
  if (vd.size() != 2 || vd[0] < 1 || vd[1] < 1) return bad_blur("values must be [nx ny]");
  const int64_t nx = vd[0], ny = vd[1];
  const int64_t T_ = static_cast<int64_t>(taps.element_count());
  if (T_ < 1 || T_ % 2 == 0) return bad_blur("taps must have an odd length");
  const int64_t h = (T_ - 1) / 2;
  const T* x = values.typed_data();
  const T* k = taps.typed_data();
  for (int64_t t = 0; t < T_; ++t)
    if (!std::isfinite(k[t])) return bad_blur("taps must be finite");
  for (int64_t q = 0; q < nx * ny; ++q)
    if (!std::isfinite(x[q])) return bad_blur("non-finite values at cell " + std::to_string(q));
  // pass 1, along axis 0: mid[i, :] = sum_t k[t] * x[clamp(i + t - h), :]
  std::vector<T> mid(static_cast<size_t>(nx * ny), T(0));
  for (int64_t i = 0; i < nx; ++i) {
    T* m = mid.data() + i * ny;
    for (int64_t t = 0; t < T_; ++t) {
      int64_t src = i + t - h;
      src = src < 0 ? 0 : (src > nx - 1 ? nx - 1 : src);
      const T* row = x + src * ny;
      const T kt = k[t];
      for (int64_t j = 0; j < ny; ++j) m[j] = m[j] + kt * row[j];
    }
  }
  // pass 2, along axis 1: out[:, j] = sum_t k[t] * mid[:, clamp(j + t - h)], per row on a
  // padded copy so the inner loop is contiguous
  T* y = out->typed_data();
  std::vector<T> pad(static_cast<size_t>(ny + 2 * h));
  for (int64_t i = 0; i < nx; ++i) {
    const T* m = mid.data() + i * ny;
    for (int64_t j = 0; j < h; ++j) pad[j] = m[0];
    for (int64_t j = 0; j < ny; ++j) pad[h + j] = m[j];
    for (int64_t j = 0; j < h; ++j) pad[h + ny + j] = m[ny - 1];
    T* yr = y + i * ny;
    for (int64_t j = 0; j < ny; ++j) yr[j] = T(0);
    for (int64_t t = 0; t < T_; ++t) {
      const T kt = k[t];
      const T* p = pad.data() + t;
      for (int64_t j = 0; j < ny; ++j) yr[j] = yr[j] + kt * p[j];
    }
  }
  return ffi::Error::Success();
}

}  // namespace

#define LIDARJAX_BLUR(NAME, DT)                                                            \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(                                                           \
      NAME, (Blur2D<DT>),                                                                  \
      ffi::Ffi::Bind().Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>());

LIDARJAX_BLUR(LidarjaxBlur2DF32, ffi::F32)
LIDARJAX_BLUR(LidarjaxBlur2DF64, ffi::F64)
