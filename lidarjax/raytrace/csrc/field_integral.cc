// Native CPU kernel of the optical depth of a bilinear decay-rate field along rays, with its
// derivatives in the rays: the inner part of SmoothDecayRateField.integral
// (lidarjax/maps/_smooth_field.py), the scan matcher's hot loop (issue #24's front end).
//
// For ray k with origin o, unit direction d, chord start t0 and chord length c, and the
// midpoint nodes s_j = (j + 1/2) / K (j = 0 .. K - 1):
//
//   p_j = o + (t0 + c s_j) d,     F = (c / K) sum_j f(p_j)
//
// where f is the bilinear interpolant of the cell rates at the cell centres, border cells
// clamped (SmoothDecayRateField._interpolate: u = (p - origin) / res - 1/2, i = floor(u),
// weights u - i, indices clipped to the grid). With g_j = grad f(p_j) (per m; the slope of
// the bilinear patch the node lies in, as JAX's autodiff of the interpolant gives it: the
// floor has derivative 0) the kernel also returns
//
//   dF/do  = (c / K) sum_j g_j
//   dF/dd  = (c / K) sum_j (t0 + c s_j) g_j
//   dF/dt0 = (c / K) sum_j g_j . d
//   dF/dc  = (1 / K) sum_j f(p_j) + (c / K) sum_j s_j g_j . d
//
// A second handler (ChordHessian) returns the [6 6] second derivatives in (o, d, t0, c)
// per ray, for second-order autodiff (see ray_hessian below).
//
// Node positions are computed in the input precision T in the JAX path's order (the cell
// coordinate multiplies by 1 / res where the JAX path divides, as XLA itself often does),
// so a node falls in the same cell as there up to round-off at a lattice line. The sums
// are accumulated in double (the float32 AVX2 path: float lanes flushed into double every
// 64 nodes), which makes the float32 result more accurate than the JAX path's float32
// reduction (they agree to its round-off). The rays are processed one after the other on
// the calling thread: one scan's 180-1000 rays are under a millisecond of work, and XLA's
// thread pool is busy with the caller's own ops. Every loop is bounded by the ray count
// times K. Non-finite inputs are an error naming the argument (never a silent NaN); the
// rates are checked on the patches the nodes read.

#include <cmath>
#include <cstdint>
#include <string>
#include <type_traits>
#include <vector>

#if defined(__AVX2__)
#include <immintrin.h>
#endif

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

ffi::Error bad(const std::string& what) {
  return ffi::Error(ffi::ErrorCode::kInvalidArgument, what);
}

struct Sums {
  double f, gx, gy, tgx, tgy, sgd;
};

// The bilinear patch of the node at p = o + t d (t = t0 + c s): the weights (wx, wy) in
// double and the four clamped corner rates, as SmoothDecayRateField._interpolate has them
// (u = (p - origin) / res - 1/2, i = floor(u), weights u - i, indices clipped).
template <typename T>
struct Patch {
  double wx, wy, a00, a10, a01, a11;
};

template <typename T>
inline Patch<T> patch_at(const T* rates, int64_t nx, int64_t ny, T ox0, T oy0, T inv_res, T ox,
                         T oy, T dx, T dy, T t) {
  const T ux = (ox + t * dx - ox0) * inv_res - T(0.5);
  const T uy = (oy + t * dy - oy0) * inv_res - T(0.5);
  // floor without a libm call (GCC emits one without SSE4.1): truncation, then one down
  // for negative non-integers; exact because |u| < 2^52 (the handlers' reach check)
  int64_t i = static_cast<int64_t>(ux);
  i -= static_cast<T>(i) > ux ? 1 : 0;
  int64_t jj = static_cast<int64_t>(uy);
  jj -= static_cast<T>(jj) > uy ? 1 : 0;
  const int64_t i0 = i < 0 ? 0 : (i > nx - 1 ? nx - 1 : i);
  const int64_t i1 = i + 1 < 0 ? 0 : (i + 1 > nx - 1 ? nx - 1 : i + 1);
  const int64_t j0 = jj < 0 ? 0 : (jj > ny - 1 ? ny - 1 : jj);
  const int64_t j1 = jj + 1 < 0 ? 0 : (jj + 1 > ny - 1 ? ny - 1 : jj + 1);
  const T* r0 = rates + i0 * ny;
  const T* r1 = rates + i1 * ny;
  return {static_cast<double>(ux - static_cast<T>(i)), static_cast<double>(uy - static_cast<T>(jj)),
          static_cast<double>(r0[j0]), static_cast<double>(r1[j0]), static_cast<double>(r0[j1]),
          static_cast<double>(r1[j1])};
}

template <typename T>
inline void ray_sums(const T* rates, int64_t nx, int64_t ny, T ox0, T oy0, T inv_res, T ox,
                     T oy, T dx, T dy, T t0, T c, const T* s_nodes, int64_t K, Sums& out) {
  double f = 0, gx = 0, gy = 0, tgx = 0, tgy = 0, sgd = 0;
  const double dinv_res = static_cast<double>(inv_res);
  for (int64_t j = 0; j < K; ++j) {
    const T s = s_nodes[j];
    const T t = t0 + c * s;
    const Patch<T> q = patch_at<T>(rates, nx, ny, ox0, oy0, inv_res, ox, oy, dx, dy, t);
    const double wx = q.wx, wy = q.wy, a00 = q.a00, a10 = q.a10, a01 = q.a01, a11 = q.a11;
    const double bx0 = a10 - a00, bx1 = a11 - a01;  // slopes along x at y-rows j0, j1
    const double v0 = a00 + wx * bx0, v1 = a01 + wx * bx1;
    const double dfx = (bx0 + wy * (bx1 - bx0)) * dinv_res;
    const double dfy = (v1 - v0) * dinv_res;
    f += v0 + wy * (v1 - v0);
    gx += dfx;
    gy += dfy;
    tgx += static_cast<double>(t) * dfx;
    tgy += static_cast<double>(t) * dfy;
    sgd += static_cast<double>(s) * (dfx * static_cast<double>(dx) + dfy * static_cast<double>(dy));
  }
  out.f = f;
  out.gx = gx;
  out.gy = gy;
  out.tgx = tgx;
  out.tgy = tgy;
  out.sgd = sgd;
}

#if defined(__AVX2__)
// float32 with AVX2 (the library variant the loader picks on such CPUs): 8 nodes of a ray
// per step, the same operations in float as the scalar path's node positions and the JAX
// path's interpolant, the cell values fetched by gathers; the per-lane float sums are
// flushed into the double sums every 64 nodes (8 steps), so the float32 rounding of a sum
// covers at most 8 terms. Needs int32 cell indices: the handler checks the reach
// (< 2^30 cells) and nx * ny < 2^31 before choosing it; the node count's remainder
// (K mod 8) goes through the scalar loop.
inline double hsum(__m256 v) {
  __m256d lo = _mm256_cvtps_pd(_mm256_castps256_ps128(v));
  __m256d hi = _mm256_cvtps_pd(_mm256_extractf128_ps(v, 1));
  __m256d s = _mm256_add_pd(lo, hi);
  __m128d a = _mm_add_pd(_mm256_castpd256_pd128(s), _mm256_extractf128_pd(s, 1));
  return _mm_cvtsd_f64(a) + _mm_cvtsd_f64(_mm_unpackhi_pd(a, a));
}

inline void ray_sums_avx2(const float* rates, int64_t nx, int64_t ny, float ox0, float oy0,
                          float inv_res, float ox, float oy, float dx, float dy, float t0,
                          float c, const float* s_nodes, int64_t K, Sums& out) {
  const int64_t K8 = K - K % 8;
  double f = 0, gx = 0, gy = 0, tgx = 0, tgy = 0, sgd = 0;
  const __m256 vt0 = _mm256_set1_ps(t0), vc = _mm256_set1_ps(c);
  const __m256 vox = _mm256_set1_ps(ox), voy = _mm256_set1_ps(oy);
  const __m256 vdx = _mm256_set1_ps(dx), vdy = _mm256_set1_ps(dy);
  const __m256 vox0 = _mm256_set1_ps(ox0), voy0 = _mm256_set1_ps(oy0);
  const __m256 vinv = _mm256_set1_ps(inv_res), half = _mm256_set1_ps(0.5f);
  const __m256i zero = _mm256_setzero_si256(), one = _mm256_set1_epi32(1);
  const __m256i xmax = _mm256_set1_epi32(static_cast<int32_t>(nx - 1));
  const __m256i ymax = _mm256_set1_epi32(static_cast<int32_t>(ny - 1));
  const __m256i vny = _mm256_set1_epi32(static_cast<int32_t>(ny));
  int64_t j = 0;
  while (j < K8) {
    __m256 F = _mm256_setzero_ps(), GX = F, GY = F, TGX = F, TGY = F, SGD = F;
    const int64_t stop = j + 64 < K8 ? j + 64 : K8;
    for (; j < stop; j += 8) {
      const __m256 vs = _mm256_loadu_ps(s_nodes + j);
      const __m256 t = _mm256_add_ps(vt0, _mm256_mul_ps(vc, vs));
      const __m256 ux = _mm256_sub_ps(
          _mm256_mul_ps(_mm256_sub_ps(_mm256_add_ps(vox, _mm256_mul_ps(t, vdx)), vox0), vinv),
          half);
      const __m256 uy = _mm256_sub_ps(
          _mm256_mul_ps(_mm256_sub_ps(_mm256_add_ps(voy, _mm256_mul_ps(t, vdy)), voy0), vinv),
          half);
      // floor: truncate, then one down where the truncation rounded up
      __m256i i = _mm256_cvttps_epi32(ux);
      i = _mm256_add_epi32(
          i, _mm256_castps_si256(_mm256_cmp_ps(_mm256_cvtepi32_ps(i), ux, _CMP_GT_OQ)));
      __m256i jj = _mm256_cvttps_epi32(uy);
      jj = _mm256_add_epi32(
          jj, _mm256_castps_si256(_mm256_cmp_ps(_mm256_cvtepi32_ps(jj), uy, _CMP_GT_OQ)));
      const __m256 wx = _mm256_sub_ps(ux, _mm256_cvtepi32_ps(i));
      const __m256 wy = _mm256_sub_ps(uy, _mm256_cvtepi32_ps(jj));
      const __m256i i0 = _mm256_max_epi32(zero, _mm256_min_epi32(xmax, i));
      const __m256i i1 = _mm256_max_epi32(zero, _mm256_min_epi32(xmax, _mm256_add_epi32(i, one)));
      const __m256i j0 = _mm256_max_epi32(zero, _mm256_min_epi32(ymax, jj));
      const __m256i j1 =
          _mm256_max_epi32(zero, _mm256_min_epi32(ymax, _mm256_add_epi32(jj, one)));
      const __m256i r0 = _mm256_mullo_epi32(i0, vny), r1 = _mm256_mullo_epi32(i1, vny);
      const __m256 a00 = _mm256_i32gather_ps(rates, _mm256_add_epi32(r0, j0), 4);
      const __m256 a10 = _mm256_i32gather_ps(rates, _mm256_add_epi32(r1, j0), 4);
      const __m256 a01 = _mm256_i32gather_ps(rates, _mm256_add_epi32(r0, j1), 4);
      const __m256 a11 = _mm256_i32gather_ps(rates, _mm256_add_epi32(r1, j1), 4);
      const __m256 bx0 = _mm256_sub_ps(a10, a00), bx1 = _mm256_sub_ps(a11, a01);
      const __m256 v0 = _mm256_add_ps(a00, _mm256_mul_ps(wx, bx0));
      const __m256 v1 = _mm256_add_ps(a01, _mm256_mul_ps(wx, bx1));
      const __m256 dv = _mm256_sub_ps(v1, v0);
      const __m256 dfx =
          _mm256_mul_ps(_mm256_add_ps(bx0, _mm256_mul_ps(wy, _mm256_sub_ps(bx1, bx0))), vinv);
      const __m256 dfy = _mm256_mul_ps(dv, vinv);
      F = _mm256_add_ps(F, _mm256_add_ps(v0, _mm256_mul_ps(wy, dv)));
      GX = _mm256_add_ps(GX, dfx);
      GY = _mm256_add_ps(GY, dfy);
      TGX = _mm256_add_ps(TGX, _mm256_mul_ps(t, dfx));
      TGY = _mm256_add_ps(TGY, _mm256_mul_ps(t, dfy));
      SGD = _mm256_add_ps(
          SGD, _mm256_mul_ps(vs, _mm256_add_ps(_mm256_mul_ps(dfx, vdx), _mm256_mul_ps(dfy, vdy))));
    }
    f += hsum(F);
    gx += hsum(GX);
    gy += hsum(GY);
    tgx += hsum(TGX);
    tgy += hsum(TGY);
    sgd += hsum(SGD);
  }
  Sums rest{0, 0, 0, 0, 0, 0};
  if (K8 < K)
    ray_sums<float>(rates, nx, ny, ox0, oy0, inv_res, ox, oy, dx, dy, t0, c, s_nodes + K8,
                    K - K8, rest);
  out.f = f + rest.f;
  out.gx = gx + rest.gx;
  out.gy = gy + rest.gy;
  out.tgx = tgx + rest.tgx;
  out.tgy = tgy + rest.tgy;
  out.sgd = sgd + rest.sgd;
}
#endif

// The inputs both handlers share, checked: shapes, a finite grid origin and a positive
// resolution, finite rays with t0, chord >= 0, and each ray's reach in cells (bounding |u|
// of every node) below 2^52, so the int64 floor cannot overflow.
template <typename T>
struct Inputs {
  const T* R;
  int64_t nx, ny, n;
  T ox0, oy0, res;
  const T *O, *D, *T0, *C;
  std::vector<double> reach;
};

template <ffi::DataType DT>
ffi::Error check_inputs(ffi::Buffer<DT>& rates, ffi::Buffer<DT>& origin, ffi::Buffer<DT>& res_buf,
                        ffi::Buffer<DT>& origins, ffi::Buffer<DT>& directions,
                        ffi::Buffer<DT>& t0s, ffi::Buffer<DT>& chords, int64_t n_nodes,
                        Inputs<ffi::NativeType<DT>>& in) {
  using T = ffi::NativeType<DT>;
  auto rd = rates.dimensions();
  if (rd.size() != 2 || rd[0] < 1 || rd[1] < 1) return bad("rates must be [nx ny], nx, ny >= 1");
  in.nx = rd[0];
  in.ny = rd[1];
  if (origin.element_count() != 2) return bad("origin must be [2]");
  if (res_buf.element_count() != 1) return bad("resolution must be a scalar");
  auto od = origins.dimensions();
  if (od.size() != 2 || od[1] != 2) return bad("origins must be [n 2]");
  const int64_t n = od[0];
  in.n = n;
  if (static_cast<int64_t>(directions.element_count()) != 2 * n)
    return bad("directions must be [n 2] like origins");
  if (static_cast<int64_t>(t0s.element_count()) != n ||
      static_cast<int64_t>(chords.element_count()) != n)
    return bad("t0 and chord must be [n]");
  if (n_nodes < 1) return bad("n_nodes must be >= 1");
  in.R = rates.typed_data();
  in.ox0 = origin.typed_data()[0];
  in.oy0 = origin.typed_data()[1];
  in.res = res_buf.typed_data()[0];
  if (!(std::isfinite(in.ox0) && std::isfinite(in.oy0))) return bad("origin must be finite");
  if (!(std::isfinite(in.res) && in.res > 0))
    return bad("resolution must be positive and finite");
  const T* O = in.O = origins.typed_data();
  const T* D = in.D = directions.typed_data();
  const T* T0 = in.T0 = t0s.typed_data();
  const T* C = in.C = chords.typed_data();
  const double limit = 4.0e15;
  in.reach.assign(static_cast<size_t>(n), 0.0);
  for (int64_t k = 0; k < n; ++k) {
    const T v[6] = {O[2 * k], O[2 * k + 1], D[2 * k], D[2 * k + 1], T0[k], C[k]};
    for (int q = 0; q < 6; ++q) {
      if (!std::isfinite(v[q])) {
        const char* what = q < 2 ? "origins" : (q < 4 ? "directions" : (q == 4 ? "t0" : "chord"));
        return bad(std::string("non-finite ") + what + " at ray " + std::to_string(k));
      }
    }
    if (C[k] < 0 || T0[k] < 0) return bad("negative t0 or chord at ray " + std::to_string(k));
    const double reach_m =
        std::fabs(static_cast<double>(O[2 * k])) + std::fabs(static_cast<double>(O[2 * k + 1])) +
        (static_cast<double>(T0[k]) + static_cast<double>(C[k])) *
            (std::fabs(static_cast<double>(D[2 * k])) +
             std::fabs(static_cast<double>(D[2 * k + 1]))) +
        std::fabs(static_cast<double>(in.ox0)) + std::fabs(static_cast<double>(in.oy0));
    in.reach[k] = reach_m / static_cast<double>(in.res);
    if (!(in.reach[k] < limit))
      return bad("ray " + std::to_string(k) + " reaches too far for the grid");
  }
  return ffi::Error::Success();
}

template <ffi::DataType DT>
ffi::Error ChordIntegral(ffi::Buffer<DT> rates, ffi::Buffer<DT> origin, ffi::Buffer<DT> res_buf,
                         ffi::Buffer<DT> origins, ffi::Buffer<DT> directions,
                         ffi::Buffer<DT> t0s, ffi::Buffer<DT> chords, int64_t n_nodes,
                         ffi::ResultBuffer<DT> value, ffi::ResultBuffer<DT> d_origins,
                         ffi::ResultBuffer<DT> d_directions, ffi::ResultBuffer<DT> d_t0,
                         ffi::ResultBuffer<DT> d_chord) {
  using T = ffi::NativeType<DT>;
  Inputs<T> in;
  ffi::Error err =
      check_inputs<DT>(rates, origin, res_buf, origins, directions, t0s, chords, n_nodes, in);
  if (err.failure()) return err;
  const T* R = in.R;
  const int64_t nx = in.nx, ny = in.ny, n = in.n;
  const T ox0 = in.ox0, oy0 = in.oy0, res = in.res;
  const T *O = in.O, *D = in.D, *T0 = in.T0, *C = in.C;
  [[maybe_unused]] const std::vector<double>& reach = in.reach;  // the AVX2 path's guard
  T* V = value->typed_data();
  T* GO = d_origins->typed_data();
  T* GD = d_directions->typed_data();
  T* GT = d_t0->typed_data();
  T* GC = d_chord->typed_data();
  Sums s;
#if defined(__AVX2__)
  // the vector path's int32 indices: cells and reach (in cells) below 2^31 and 2^30
  const bool vector_ok = nx * ny < (int64_t(1) << 31);
  constexpr double kVectorReach = double(int64_t(1) << 30);
#endif
  // the nodes' fractions as the JAX path computes them, (j + 1/2) / K in T
  std::vector<T> s_nodes(static_cast<size_t>(n_nodes));
  for (int64_t j = 0; j < n_nodes; ++j)
    s_nodes[j] = (static_cast<T>(j) + T(0.5)) / static_cast<T>(n_nodes);
  const T inv_res = T(1) / res;
  const double inv_k = 1.0 / static_cast<double>(n_nodes);
  for (int64_t k = 0; k < n; ++k) {
    const T dx = D[2 * k], dy = D[2 * k + 1], t0 = T0[k], c = C[k];
#if defined(__AVX2__)
    if constexpr (std::is_same_v<T, float>) {
      if (vector_ok && reach[k] < kVectorReach) {
        ray_sums_avx2(R, nx, ny, ox0, oy0, inv_res, O[2 * k], O[2 * k + 1], dx, dy, t0, c,
                      s_nodes.data(), n_nodes, s);
      } else {
        ray_sums<T>(R, nx, ny, ox0, oy0, inv_res, O[2 * k], O[2 * k + 1], dx, dy, t0, c,
                    s_nodes.data(), n_nodes, s);
      }
    } else
#endif
    {
      ray_sums<T>(R, nx, ny, ox0, oy0, inv_res, O[2 * k], O[2 * k + 1], dx, dy, t0, c,
                  s_nodes.data(), n_nodes, s);
    }
    // the rates are checked where they are read (a whole-grid check would cost more than
    // the integral): a NaN or infinite rate on a node's patch makes the sums non-finite
    if (!(std::isfinite(s.f) && std::isfinite(s.gx) && std::isfinite(s.gy)))
      return bad("non-finite rates on the path of ray " + std::to_string(k));
    const double w = static_cast<double>(c) * inv_k;
    const double gd = s.gx * static_cast<double>(dx) + s.gy * static_cast<double>(dy);
    V[k] = static_cast<T>(w * s.f);
    GO[2 * k] = static_cast<T>(w * s.gx);
    GO[2 * k + 1] = static_cast<T>(w * s.gy);
    GD[2 * k] = static_cast<T>(w * s.tgx);
    GD[2 * k + 1] = static_cast<T>(w * s.tgy);
    GT[k] = static_cast<T>(w * gd);
    GC[k] = static_cast<T>(inv_k * s.f + w * s.sgd);
  }
  return ffi::Error::Success();
}


// Second derivatives of F in the ray parameters x = (o_x, o_y, d_x, d_y, t0, c), per ray a
// symmetric [6 6] matrix, for second-order autodiff (the SLAM front end's match
// information, a Hessian in the pose). With p_j = o + tau_j d, tau_j = t0 + c s_j, the
// bilinear patch's Hessian is h_j [[0 1] [1 0]] (h_j = d2f/dxdy; f is linear along each
// axis within a patch, as JAX's autodiff of the interpolant sees it), P_a = dp_j/dx_a
// (e_x, e_y, tau e_x, tau e_y, d, s_j d) and A = sum_j f(p_j):
//   d2A/dx_a dx_b = sum_j h_j (P_a,x P_b,y + P_a,y P_b,x) + sum_j g_j . d2p_j/dx_a dx_b
// where d2p/dd dt0 = I and d2p/dd dc = s_j I are the only non-zero second derivatives of p,
// and F = c A / K gives d2F = c/K d2A + [a = c] dA/dx_b / K + [b = c] dA/dx_a / K.
// Scalar, in double (called once per match, not per optimiser step).
template <typename T>
void ray_hessian(const Inputs<T>& in, int64_t k, const T* s_nodes, int64_t K, double* H) {
  const double inv_res = 1.0 / static_cast<double>(in.res);
  const T tinv_res = T(1) / in.res;
  const T ox = in.O[2 * k], oy = in.O[2 * k + 1], dx = in.D[2 * k], dy = in.D[2 * k + 1];
  const T t0 = in.T0[k], c = in.C[k];
  const int64_t nx = in.nx, ny = in.ny;
  double HA[6][6] = {};
  double GA[6] = {};
  double sgx = 0, sgy = 0, ssgx = 0, ssgy = 0;
  const double ddx = dx, ddy = dy;
  for (int64_t j = 0; j < K; ++j) {
    const T s = s_nodes[j];
    const T t = t0 + c * s;
    const Patch<T> q = patch_at<T>(in.R, nx, ny, in.ox0, in.oy0, tinv_res, ox, oy, dx, dy, t);
    const double wx = q.wx, wy = q.wy, a00 = q.a00, a10 = q.a10, a01 = q.a01, a11 = q.a11;
    const double gx = ((a10 - a00) * (1 - wy) + (a11 - a01) * wy) * inv_res;
    const double gy = ((a01 - a00) * (1 - wx) + (a11 - a10) * wx) * inv_res;
    const double h = (a11 - a10 - a01 + a00) * inv_res * inv_res;
    const double ts = static_cast<double>(t), ss = static_cast<double>(s);
    const double P[6][2] = {{1, 0}, {0, 1}, {ts, 0}, {0, ts}, {ddx, ddy}, {ss * ddx, ss * ddy}};
    for (int a = 0; a < 6; ++a) {
      GA[a] += gx * P[a][0] + gy * P[a][1];
      for (int b = a; b < 6; ++b) HA[a][b] += h * (P[a][0] * P[b][1] + P[a][1] * P[b][0]);
    }
    sgx += gx;
    sgy += gy;
    ssgx += ss * gx;
    ssgy += ss * gy;
  }
  HA[2][4] += sgx;   // d2p/ddx dt0 = e_x
  HA[3][4] += sgy;   // d2p/ddy dt0 = e_y
  HA[2][5] += ssgx;  // d2p/ddx dc = s e_x
  HA[3][5] += ssgy;  // d2p/ddy dc = s e_y
  const double inv_k = 1.0 / static_cast<double>(K), w = static_cast<double>(c) * inv_k;
  for (int a = 0; a < 6; ++a) {
    for (int b = a; b < 6; ++b) {
      double v = w * HA[a][b];
      if (a == 5) v += inv_k * GA[b];
      if (b == 5) v += inv_k * GA[a];
      H[a * 6 + b] = v;
      H[b * 6 + a] = v;
    }
  }
}

template <ffi::DataType DT>
ffi::Error ChordHessian(ffi::Buffer<DT> rates, ffi::Buffer<DT> origin, ffi::Buffer<DT> res_buf,
                        ffi::Buffer<DT> origins, ffi::Buffer<DT> directions, ffi::Buffer<DT> t0s,
                        ffi::Buffer<DT> chords, int64_t n_nodes, ffi::ResultBuffer<DT> hessian) {
  using T = ffi::NativeType<DT>;
  Inputs<T> in;
  ffi::Error err =
      check_inputs<DT>(rates, origin, res_buf, origins, directions, t0s, chords, n_nodes, in);
  if (err.failure()) return err;
  std::vector<T> s_nodes(static_cast<size_t>(n_nodes));
  for (int64_t j = 0; j < n_nodes; ++j)
    s_nodes[j] = (static_cast<T>(j) + T(0.5)) / static_cast<T>(n_nodes);
  T* out = hessian->typed_data();
  double H[36];
  for (int64_t k = 0; k < in.n; ++k) {
    ray_hessian<T>(in, k, s_nodes.data(), n_nodes, H);
    for (int q = 0; q < 36; ++q) {
      if (!std::isfinite(H[q])) return bad("non-finite rates on the path of ray " + std::to_string(k));
      out[k * 36 + q] = static_cast<T>(H[q]);
    }
  }
  return ffi::Error::Success();
}

}  // namespace

#define LIDARJAX_CHORD(NAME, DT)                                  \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(NAME, (ChordIntegral<DT>),        \
                                ffi::Ffi::Bind()                  \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Attr<int64_t>("n_nodes")     \
                                    .Ret<ffi::Buffer<DT>>()       \
                                    .Ret<ffi::Buffer<DT>>()       \
                                    .Ret<ffi::Buffer<DT>>()       \
                                    .Ret<ffi::Buffer<DT>>()       \
                                    .Ret<ffi::Buffer<DT>>());

LIDARJAX_CHORD(LidarjaxChordIntegralF32, ffi::F32)
LIDARJAX_CHORD(LidarjaxChordIntegralF64, ffi::F64)

#define LIDARJAX_CHORD_HESSIAN(NAME, DT)                          \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(NAME, (ChordHessian<DT>),         \
                                ffi::Ffi::Bind()                  \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Arg<ffi::Buffer<DT>>()       \
                                    .Attr<int64_t>("n_nodes")     \
                                    .Ret<ffi::Buffer<DT>>());

LIDARJAX_CHORD_HESSIAN(LidarjaxChordHessianF32, ffi::F32)
LIDARJAX_CHORD_HESSIAN(LidarjaxChordHessianF64, ffi::F64)
