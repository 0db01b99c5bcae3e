// Native CPU kernels of lidarjax's exact grid walk (dissertation Sec. 7.4), called from JAX
// through the XLA FFI (jax.ffi.ffi_call). The walk reproduces lidarjax/raytrace/_grid.py's
// `_setup` and `_step` operation for operation (same boundary rule, coincident crossings
// taken together, same tolerances), so hit/miss counts are identical to the JAX path and
// lengths agree to round-off. Compiled with -ffp-contract=off so no multiply-add is fused.
// Bit-identity with the JAX path is not attainable in general: XLA's CPU compiler rewrites
// some divisions by a broadcast scalar (x / |d|, x / resolution) into multiplications by
// the reciprocal, differently in different fusions, so the JAX path itself differs by an
// ulp between contexts; the kernels here divide exactly (correctly rounded).
//
// Kernels (T = float or double, D = 2 or 3):
//   Accumulate<T, D>: per-cell R (lengths), H (hits), M (misses) of a ray batch from the
//     rays' kinds (HIT/SUB/SUP); rays are split over `threads` worker threads with private
//     accumulators merged at the end. Memory: threads x cells, nothing per ray.
//   Fold<T, D, MODE>: per-ray fold of a per-cell term (body sum over all cells but the last,
//     last cell, its length, length inside the grid, any cell visited, t_start, t_end), the
//     input of every grid sensor model's finish. MODE selects the term from per-cell tables:
//       0: A[c] + B[c] * len   1: B[c] * len   2: A[c]
//       3: len > 0 ? a[c] * (log b[c] - log(b[c] + len)) : 0   (Gamma posterior, Sec. 8.4.5)
// Both kernels reject non-finite origins/directions and NaN or negative lengths (an error
// naming the first bad ray). Every loop over cells is bounded by sum(shape) + D steps; a
// walk still running there (impossible with finite input) is an error too.

#include <pthread.h>
#include <sched.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

template <typename T, int D>
struct Grid {
  T lo[D];
  T res;
  int32_t n[D];
  int64_t stride[D];
  int64_t ncells;
  int64_t bound;
};

template <typename T, int D>
struct Walk {
  T d[D];
  T t_first[D];
  T t_scale[D];
  T t_axis[D];
  int32_t c0[D];
  int32_t cell[D];
  int64_t flat;
  bool moving[D];
  bool up[D];
  T t_start, t_end, tol, t;
  bool active;
};

template <typename T, int D>
inline void setup(const Grid<T, D>& g, const T* o, const T* din, T length, Walk<T, D>& w) {
  const T inf = std::numeric_limits<T>::infinity();
  T ss = T(0);
  for (int k = 0; k < D; ++k) ss = ss + din[k] * din[k];
  const T norm = std::sqrt(ss);
  const bool nz = norm > T(0);
  const T nrm = nz ? norm : T(1);
  for (int k = 0; k < D; ++k) w.d[k] = din[k] / nrm;
  if (!nz) length = T(0);

  T t_near[D], t_far[D], d_safe[D];
  bool inside_axis[D];
  T t_enter = -inf, t_exit = inf;
  int entry_axis = 0;
  bool starts_inside = true;
  for (int k = 0; k < D; ++k) {
    const T hi = g.lo[k] + T(g.n[k]) * g.res;
    const bool moving = w.d[k] != T(0);
    w.moving[k] = moving;
    w.up[k] = w.d[k] > T(0);
    d_safe[k] = moving ? w.d[k] : T(1);
    const T ta = (g.lo[k] - o[k]) / d_safe[k];
    const T tb = (hi - o[k]) / d_safe[k];
    inside_axis[k] = (o[k] >= g.lo[k]) && (o[k] <= hi);
    t_near[k] = moving ? std::min(ta, tb) : (inside_axis[k] ? -inf : inf);
    t_far[k] = moving ? std::max(ta, tb) : (inside_axis[k] ? inf : -inf);
    starts_inside = starts_inside && inside_axis[k];
  }
  // argmax: first index of the maximum, as jnp.argmax
  t_enter = t_near[0];
  t_exit = t_far[0];
  for (int k = 1; k < D; ++k) {
    if (t_near[k] > t_enter) {
      t_enter = t_near[k];
      entry_axis = k;
    }
    t_exit = std::min(t_exit, t_far[k]);
  }
  T t0 = std::max(t_enter, T(0));
  T t1 = std::min(length, t_exit);
  const bool active = (t0 < t1) || ((length == T(0)) && starts_inside);
  if (!active) t1 = t0;
  if (!std::isfinite(t0)) t0 = T(0);
  if (!std::isfinite(t1)) t1 = t0;

  for (int k = 0; k < D; ++k) {
    const T p0 = o[k] + t0 * w.d[k];
    const T rel = (p0 - g.lo[k]) / g.res;
    T c = w.d[k] < T(0) ? std::ceil(rel) - T(1) : std::floor(rel);
    const T nk = T(g.n[k]);
    if (t_enter > T(0) && k == entry_axis) c = w.d[k] > T(0) ? T(0) : nk - T(1);
    if (!std::isfinite(c)) c = T(0);
    c = std::min(std::max(c, T(0)), nk - T(1));
    w.cell[k] = static_cast<int32_t>(c);
    w.c0[k] = w.cell[k];
  }
  const T eps = std::numeric_limits<T>::epsilon();
  w.tol = T(32) * eps * (t1 + g.res);
  const T big = std::numeric_limits<T>::max();
  for (int k = 0; k < D; ++k) {
    const T first =
        (g.lo[k] - o[k] + T(w.cell[k] + (w.d[k] > T(0) ? 1 : 0)) * g.res) / d_safe[k];
    w.t_first[k] = w.moving[k] ? first : inf;
    const T scale = g.res / d_safe[k];
    w.t_scale[k] = w.moving[k] ? std::min(std::max(scale, -big), big) : T(0);
  }
  w.flat = 0;
  for (int k = 0; k < D; ++k) {
    w.t_axis[k] = w.t_first[k];  // + (cell - c0) * t_scale with cell == c0
    w.flat += int64_t(w.cell[k]) * g.stride[k];
  }
  w.t_start = t0;
  w.t_end = t1;
  w.t = t0;
  w.active = active;
}

// The whole walk of one ray set up in `w`: visit(flat, cell, seg, valid, last) for each
// step (the same sequence as repeated step() calls), with the walk state in local
// variables so that the visitor's stores cannot alias it (keeps it in registers).
// Returns true if the walk was still active at the grid's cell bound (an overrun).
template <typename T, int D, typename F>
inline bool walk_ray(const Grid<T, D>& g, const Walk<T, D>& w, F&& visit) {
  T t_axis[D], t_first[D], t_scale[D];
  int32_t cell[D], c0[D], prev[D];
  int64_t dflat[D];
  bool moving[D];
  for (int k = 0; k < D; ++k) {
    t_axis[k] = w.t_axis[k];
    t_first[k] = w.t_first[k];
    t_scale[k] = w.t_scale[k];
    cell[k] = w.cell[k];
    c0[k] = w.c0[k];
    moving[k] = w.moving[k];
    dflat[k] = w.up[k] ? g.stride[k] : -g.stride[k];
  }
  int64_t flat = w.flat;
  T t = w.t;
  const T t_end = w.t_end, tol = w.tol;
  bool active = w.active;
  for (int64_t it = 0; it < g.bound && active; ++it) {
    T t_min = t_axis[0];
    for (int k = 1; k < D; ++k) t_min = std::min(t_min, t_axis[k]);
    const bool last = t_min >= t_end - tol;
    const T t_stop = last ? t_end : t_min;
    T seg = std::max(t_stop - t, T(0));
    const bool valid = (seg > tol) || last;  // active here
    if (!valid) seg = T(0);
    const int64_t here = flat;
    bool inside = true;
    const T lim = t_min + tol;
    for (int k = 0; k < D; ++k) {
      prev[k] = cell[k];
      if (moving[k] && t_axis[k] <= lim) {
        const int32_t c = cell[k] + (dflat[k] > 0 ? 1 : -1);
        cell[k] = c;
        flat += dflat[k];
        t_axis[k] = t_first[k] + T(c - c0[k]) * t_scale[k];
        inside = inside && (c >= 0) && (c < g.n[k]);
      }
    }
    t = t_stop;
    active = !last && inside;
    visit(here, prev, seg, valid, valid && (last || !inside));
  }
  return active;
}

template <typename T, int D>
ffi::Error make_grid(const T* lo, const T* res, const int64_t* dims, int rank, Grid<T, D>& g) {
  if (rank != D) return ffi::Error(ffi::ErrorCode::kInvalidArgument, "grid rank mismatch");
  g.res = res[0];
  if (!(std::isfinite(g.res) && g.res > T(0)))
    return ffi::Error(ffi::ErrorCode::kInvalidArgument,
                      "spec: resolution must be positive and finite");
  int64_t stride = 1;
  g.bound = D;
  for (int k = D - 1; k >= 0; --k) {
    g.lo[k] = lo[k];
    if (!std::isfinite(g.lo[k]))
      return ffi::Error(ffi::ErrorCode::kInvalidArgument, "spec: grid origin must be finite");
    g.n[k] = static_cast<int32_t>(dims[k]);
    g.stride[k] = stride;
    stride *= dims[k];
    g.bound += dims[k];
  }
  g.ncells = stride;
  return ffi::Error::Success();
}

inline int64_t clamp_threads(int64_t threads, int64_t n_items, int64_t min_per_thread) {
  if (threads <= 0) threads = std::max<int64_t>(1, std::thread::hardware_concurrency());
  threads = std::min<int64_t>(threads, std::max<int64_t>(1, n_items / min_per_thread));
  return std::max<int64_t>(1, std::min<int64_t>(threads, 256));
}

// The process's CPU set (the main thread's affinity). XLA runs a custom call on one of its
// worker threads, which may be pinned to a single core; threads started from it inherit
// that pin, so each worker is given the process's set instead.
inline bool process_cpus(cpu_set_t& set) {
  CPU_ZERO(&set);
  return sched_getaffinity(getpid(), sizeof(set), &set) == 0;
}

// Run fn(thread_index, begin, end) over [0, n) in interleaved blocks on `threads` threads.
template <typename Fn>
void parallel_blocks(int64_t n, int64_t threads, int64_t block, Fn fn) {
  cpu_set_t cpus;
  const bool have_cpus = threads > 1 && process_cpus(cpus);
  auto worker = [&](int64_t t) {
    if (t > 0 && have_cpus) pthread_setaffinity_np(pthread_self(), sizeof(cpus), &cpus);
    for (int64_t b = t * block; b < n; b += threads * block) fn(t, b, std::min(n, b + block));
  };
  if (threads == 1) {
    worker(0);
    return;
  }
  std::vector<std::thread> pool;
  pool.reserve(threads - 1);
  for (int64_t t = 1; t < threads; ++t) pool.emplace_back(worker, t);
  worker(0);
  for (auto& th : pool) th.join();
}

constexpr int64_t kBlock = 256;

constexpr int32_t kHit = 0, kSub = 1, kSup = 2;  // lidarjax.rays.HIT, SUB, SUP

// First ray index with a non-finite origin or direction component (or -1).
template <typename T, int D>
int64_t first_non_finite(const T* x, int64_t n) {
  for (int64_t i = 0; i < n * D; ++i)
    if (!std::isfinite(x[i])) return i / D;
  return -1;
}

ffi::Error bad_ray(const char* what, int64_t i) {
  return ffi::Error(ffi::ErrorCode::kInvalidArgument,
                    std::string("rays: ") + what + " (first bad ray: " + std::to_string(i) +
                        ")");
}

// Per-cell R, H, M of a ray batch. Ray kinds decide the trace: HIT rays to their range
// (a hit in the last cell if the end point lies inside the grid), SUP rays to r_max (all
// misses), SUB rays nothing, or like HIT rays with sub_as_hit. No per-ray temporaries.
template <ffi::DataType DT, int D>
ffi::Error Accumulate(ffi::Buffer<DT> spec_lo, ffi::Buffer<DT> spec_res, ffi::Buffer<DT> origins,
                      ffi::Buffer<DT> directions, ffi::Buffer<DT> ranges,
                      ffi::Buffer<ffi::S32> kinds, ffi::Buffer<DT> r_max_buf, bool sub_as_hit,
                      int64_t threads, ffi::ResultBuffer<DT> r_out,
                      ffi::ResultBuffer<ffi::S32> h_out, ffi::ResultBuffer<ffi::S32> m_out) {
  using T = ffi::NativeType<DT>;
  Grid<T, D> g;
  auto dims = r_out->dimensions();
  ffi::Error err = make_grid<T, D>(spec_lo.typed_data(), spec_res.typed_data(), dims.begin(),
                                   static_cast<int>(dims.size()), g);
  if (err.failure()) return err;
  const int64_t n = ranges.element_count();
  if (origins.element_count() != n * D || directions.element_count() != n * D ||
      kinds.element_count() != n)
    return ffi::Error(ffi::ErrorCode::kInvalidArgument,
                      "origins/directions must be [n d] and kind [n]");
  const T* o = origins.typed_data();
  const T* dir = directions.typed_data();
  const T* rng = ranges.typed_data();
  const int32_t* kind = kinds.typed_data();
  const T r_max = r_max_buf.typed_data()[0];
  if (std::isnan(r_max) || r_max < T(0))
    return ffi::Error(ffi::ErrorCode::kInvalidArgument, "rays: r_max must be >= 0, not NaN");
  int64_t bad = first_non_finite<T, D>(o, n);
  if (bad >= 0) return bad_ray("ray origins must be finite (NaN or inf pose?)", bad);
  bad = first_non_finite<T, D>(dir, n);
  if (bad >= 0) return bad_ray("ray directions must be finite (NaN or inf heading/azimuth?)", bad);
  for (int64_t i = 0; i < n; ++i) {
    const bool traced = kind[i] == kHit || (kind[i] == kSub && sub_as_hit);
    if (traced && (std::isnan(rng[i]) || rng[i] < T(0)))
      return bad_ray("ray lengths must be >= 0 and not NaN", i);
  }
  T* R = r_out->typed_data();
  int32_t* H = h_out->typed_data();
  int32_t* V = m_out->typed_data();  // visits first, misses at the end
  threads = clamp_threads(threads, n, 4 * kBlock);
  const int64_t nc = g.ncells;
  std::vector<std::vector<T>> r_priv(threads - 1);
  std::vector<std::vector<int32_t>> h_priv(threads - 1), v_priv(threads - 1);
  for (int64_t t = 0; t + 1 < threads; ++t) {
    r_priv[t].assign(nc, T(0));
    h_priv[t].assign(nc, 0);
    v_priv[t].assign(nc, 0);
  }
  std::fill(R, R + nc, T(0));
  std::fill(H, H + nc, 0);
  std::fill(V, V + nc, 0);
  std::vector<char> overrun(threads, 0);
  parallel_blocks(n, threads, kBlock, [&](int64_t t, int64_t b, int64_t e) {
    T* r = t == 0 ? R : r_priv[t - 1].data();
    int32_t* h = t == 0 ? H : h_priv[t - 1].data();
    int32_t* v = t == 0 ? V : v_priv[t - 1].data();
    Walk<T, D> w;
    for (int64_t i = b; i < e; ++i) {
      const int32_t k = kind[i];
      bool is_hit;
      T len;
      if (k == kHit || (k == kSub && sub_as_hit)) {
        is_hit = true;
        len = rng[i];
      } else if (k == kSup) {
        is_hit = false;
        len = r_max;
      } else {
        continue;
      }
      setup<T, D>(g, o + i * D, dir + i * D, len, w);
      const bool ends_inside = is_hit && w.active && (w.t_end >= len - w.tol);
      bool ended = false;
      int64_t last_flat = 0;
      const bool over = walk_ray<T, D>(
          g, w, [&](int64_t flat, const int32_t*, T seg, bool valid, bool last) {
            if (valid) {
              r[flat] += seg;
              v[flat] += 1;
              if (last) {
                last_flat = flat;
                ended = true;
              }
            }
          });
      if (over) overrun[t] = 1;
      if (ends_inside && ended) h[last_flat] += 1;
    }
  });
  for (char c : overrun)
    if (c)
      return ffi::Error(ffi::ErrorCode::kOutOfRange,
                        "ray walk exceeded the grid's cell bound (non-finite input)");
  if (threads > 1) {
    parallel_blocks(nc, threads, std::max<int64_t>(4096, nc / threads + 1),
                    [&](int64_t, int64_t b, int64_t e) {
                      for (int64_t t = 0; t + 1 < threads; ++t) {
                        const T* rp = r_priv[t].data();
                        const int32_t* hp = h_priv[t].data();
                        const int32_t* vp = v_priv[t].data();
                        for (int64_t c = b; c < e; ++c) {
                          R[c] += rp[c];
                          H[c] += hp[c];
                          V[c] += vp[c];
                        }
                      }
                    });
  }
  for (int64_t c = 0; c < nc; ++c) V[c] -= H[c];
  return ffi::Error::Success();
}

template <typename T, int MODE>
inline T cell_term(const T* tab, int64_t nc, int64_t c, T seg) {
  if constexpr (MODE == 0) {
    return tab[c] + tab[nc + c] * seg;
  } else if constexpr (MODE == 1) {
    return tab[c] * seg;
  } else if constexpr (MODE == 2) {
    return tab[c];
  } else {
    // a * (log b - log(b + len)) for len > 0, tables a, b, log b
    if (!(seg > T(0))) return T(0);
    return tab[c] * (tab[2 * nc + c] - std::log(tab[nc + c] + seg));
  }
}

template <ffi::DataType DT, int D, int MODE>
ffi::Error Fold(ffi::Buffer<DT> spec_lo, ffi::Buffer<DT> spec_res, ffi::Buffer<DT> tables,
                ffi::Buffer<DT> origins, ffi::Buffer<DT> directions, ffi::Buffer<DT> lengths,
                int64_t threads, ffi::ResultBuffer<DT> body_out,
                ffi::ResultBuffer<ffi::S32> last_cell_out, ffi::ResultBuffer<DT> last_len_out,
                ffi::ResultBuffer<DT> grid_len_out, ffi::ResultBuffer<ffi::PRED> any_valid_out,
                ffi::ResultBuffer<DT> t_start_out, ffi::ResultBuffer<DT> t_end_out) {
  using T = ffi::NativeType<DT>;
  Grid<T, D> g;
  auto tdims = tables.dimensions();
  if (tdims.size() != D + 1)
    return ffi::Error(ffi::ErrorCode::kInvalidArgument, "tables must be [k *shape]");
  ffi::Error err = make_grid<T, D>(spec_lo.typed_data(), spec_res.typed_data(),
                                   tdims.begin() + 1, D, g);
  if (err.failure()) return err;
  const int64_t need = MODE == 0 ? 2 : (MODE == 3 ? 3 : 1);
  if (tdims[0] != need)
    return ffi::Error(ffi::ErrorCode::kInvalidArgument, "wrong number of term tables");
  const int64_t n = lengths.element_count();
  if (origins.element_count() != n * D || directions.element_count() != n * D)
    return ffi::Error(ffi::ErrorCode::kInvalidArgument, "origins/directions must be [n d]");
  const T* tab = tables.typed_data();
  const T* o = origins.typed_data();
  const T* dir = directions.typed_data();
  const T* len = lengths.typed_data();
  int64_t bad = first_non_finite<T, D>(o, n);
  if (bad >= 0) return bad_ray("ray origins must be finite (NaN or inf pose?)", bad);
  bad = first_non_finite<T, D>(dir, n);
  if (bad >= 0) return bad_ray("ray directions must be finite (NaN or inf heading/azimuth?)", bad);
  for (int64_t i = 0; i < n; ++i)
    if (std::isnan(len[i]) || len[i] < T(0))
      return bad_ray("ray lengths must be >= 0 and not NaN", i);
  T* body = body_out->typed_data();
  int32_t* last_cell = last_cell_out->typed_data();
  T* last_len = last_len_out->typed_data();
  T* grid_len = grid_len_out->typed_data();
  bool* any_valid = any_valid_out->typed_data();
  T* t_start = t_start_out->typed_data();
  T* t_end = t_end_out->typed_data();
  threads = clamp_threads(threads, n, kBlock);
  const int64_t nc = g.ncells;
  std::vector<char> overrun(threads, 0);
  parallel_blocks(n, threads, kBlock, [&](int64_t t, int64_t b, int64_t e) {
    Walk<T, D> w;
    for (int64_t i = b; i < e; ++i) {
      setup<T, D>(g, o + i * D, dir + i * D, len[i], w);
      T acc = T(0), llen = T(0), glen = T(0);
      bool anyv = false;
      int32_t lc[D];
      for (int k = 0; k < D; ++k) lc[k] = w.cell[k];
      const bool over = walk_ray<T, D>(
          g, w, [&](int64_t flat, const int32_t* cell, T seg, bool valid, bool last) {
            if (valid) {
              if (!last) {
                acc = acc + cell_term<T, MODE>(tab, nc, flat, seg);
              } else {
                for (int k = 0; k < D; ++k) lc[k] = cell[k];
                llen = seg;
              }
              anyv = true;
            }
            glen = glen + seg;
          });
      if (over) overrun[t] = 1;
      body[i] = acc;
      for (int k = 0; k < D; ++k) last_cell[i * D + k] = lc[k];
      last_len[i] = llen;
      grid_len[i] = glen;
      any_valid[i] = anyv;
      t_start[i] = w.t_start;
      t_end[i] = w.t_end;
    }
  });
  for (char c : overrun)
    if (c)
      return ffi::Error(ffi::ErrorCode::kOutOfRange,
                        "ray walk exceeded the grid's cell bound (non-finite input)");
  return ffi::Error::Success();
}

}  // namespace

#define LIDARJAX_ACC(NAME, DT, D)                                   \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(NAME, (Accumulate<DT, D>),          \
                                ffi::Ffi::Bind()                    \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Arg<ffi::Buffer<ffi::S32>>()   \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Attr<bool>("sub_as_hit")       \
                                    .Attr<int64_t>("threads")       \
                                    .Ret<ffi::Buffer<DT>>()         \
                                    .Ret<ffi::Buffer<ffi::S32>>()   \
                                    .Ret<ffi::Buffer<ffi::S32>>());

LIDARJAX_ACC(LidarjaxAccumulateF32D2, ffi::F32, 2)
LIDARJAX_ACC(LidarjaxAccumulateF32D3, ffi::F32, 3)
LIDARJAX_ACC(LidarjaxAccumulateF64D2, ffi::F64, 2)
LIDARJAX_ACC(LidarjaxAccumulateF64D3, ffi::F64, 3)

#define LIDARJAX_FOLD(NAME, DT, D, MODE)                            \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(NAME, (Fold<DT, D, MODE>),          \
                                ffi::Ffi::Bind()                    \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Arg<ffi::Buffer<DT>>()         \
                                    .Attr<int64_t>("threads")       \
                                    .Ret<ffi::Buffer<DT>>()         \
                                    .Ret<ffi::Buffer<ffi::S32>>()   \
                                    .Ret<ffi::Buffer<DT>>()         \
                                    .Ret<ffi::Buffer<DT>>()         \
                                    .Ret<ffi::Buffer<ffi::PRED>>()  \
                                    .Ret<ffi::Buffer<DT>>()         \
                                    .Ret<ffi::Buffer<DT>>());

#define LIDARJAX_FOLD_MODES(P, DT, D)             \
  LIDARJAX_FOLD(P##M0, DT, D, 0)                  \
  LIDARJAX_FOLD(P##M1, DT, D, 1)                  \
  LIDARJAX_FOLD(P##M2, DT, D, 2)                  \
  LIDARJAX_FOLD(P##M3, DT, D, 3)

LIDARJAX_FOLD_MODES(LidarjaxFoldF32D2, ffi::F32, 2)
LIDARJAX_FOLD_MODES(LidarjaxFoldF32D3, ffi::F32, 3)
LIDARJAX_FOLD_MODES(LidarjaxFoldF64D2, ffi::F64, 2)
LIDARJAX_FOLD_MODES(LidarjaxFoldF64D3, ffi::F64, 3)

extern "C" int lidarjax_native_abi_version() { return 1; }
