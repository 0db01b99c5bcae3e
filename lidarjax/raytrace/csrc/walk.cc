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
#include <type_traits>
#include <vector>

#if defined(__SSE2__)
#include <immintrin.h>
#endif

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
  bool flag;  // the kernel's own per-ray bit (set by its prep)
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

// The walks of rays [b, e), W rays at a time in the lanes of vector registers (GCC vector
// extensions: SSE2 on a baseline x86-64 build, AVX with -march, NEON on ARM). One ray's
// walk is a serial chain (crossing times -> minimum -> comparison -> step), so a lone walk
// leaves the core idle most of the time; W independent rays stepped together fill it, and
// each step is branch-free (which axes cross is data). Every lane performs exactly the
// operations of one step of the JAX path's `_step`, in the same order: the crossing time
// of axis k is t_first + n_k * |t_scale| with n_k the number of steps taken along k (held
// as a float, exactly: (cell - c0) * t_scale has the same magnitude and sign), and a
// lane is inside the grid while n_k <= the steps left to the border along k.
//
// The kernel object K provides, for lane j:
//   bool prep(i, w): set up ray i in `w`; false skips the ray (nothing else is called).
//   void start(j, i, w): ray i (set up in w) begins in lane j.
//   void body(here, seg, valid, last): one step of all lanes (vectors; `valid` and `last`
//     masks, dead lanes have valid == last == 0 and seg == 0, here a valid cell).
//   void finish(j, end): the ray in lane j is done (also for a ray that visits no cell).
template <typename T, int D>
struct End {
  int64_t flat;    // flat index of the final step's cell
  bool over;       // still active at the grid's cell bound (impossible with finite input)
  bool last;       // the final step was a valid step (its cell is the ray's last cell)
  T seg;           // length of the final step
  int32_t cell[D]; // cell of the final step
};

// Vectors of W lanes of T (V) and the matching masks and integers (M: int32 for float,
// int64 for double, the element type of a comparison of two V).
template <typename T, int W>
struct Lanes {
  using I = std::conditional_t<sizeof(T) == 4, int32_t, int64_t>;
  typedef T V __attribute__((vector_size(W * sizeof(T))));
  typedef I M __attribute__((vector_size(W * sizeof(T))));
};

// Bit j set where lane j of mask m is set (movemask where the ISA has one).
template <typename T, int W>
inline unsigned lane_bits(const typename Lanes<T, W>::M& m) {
#if defined(__AVX2__)
  if constexpr (W * sizeof(T) == 32) {
    if constexpr (sizeof(T) == 4) return unsigned(_mm256_movemask_ps(__m256(m)));
    else return unsigned(_mm256_movemask_pd(__m256d(m)));
  }
#endif
#if defined(__SSE2__)
  if constexpr (W * sizeof(T) == 16) {
    if constexpr (sizeof(T) == 4) return unsigned(_mm_movemask_ps(__m128(m)));
    else return unsigned(_mm_movemask_pd(__m128d(m)));
  }
#endif
  unsigned bits = 0;
  for (int j = 0; j < W; ++j) bits |= unsigned(m[j] != 0) << j;
  return bits;
}

template <typename T, int D, int W, typename K>
inline void walk_lanes(const Grid<T, D>& g, int64_t b, int64_t e, K& kern) {
  using I = typename Lanes<T, W>::I;
  using V = typename Lanes<T, W>::V;
  using M = typename Lanes<T, W>::M;
  const T inf = std::numeric_limits<T>::infinity();
  V ta[D], tf[D], ts[D], nk[D], room[D];
  M flat, df[D], it, live;
  V t, t_end, t_last, tol;
  int32_t c0[W][D], dir[W][D];
  for (int k = 0; k < D; ++k) {
    ta[k] = tf[k] = room[k] = V{} + inf;
    ts[k] = nk[k] = V{};
    df[k] = M{};
  }
  flat = it = live = M{};
  t = t_end = tol = V{};
  t_last = V{} - inf;
  int64_t next = b;
  // Rays are set up kStage at a time ahead of the lanes that take them: independent
  // set-ups in a tight loop overlap their division chains.
  constexpr int kStage = 16;
  Walk<T, D> stage[kStage];
  int64_t stage_ray[kStage];
  int n_stage = 0, pos = 0;
  auto refill = [&]() {
    n_stage = pos = 0;
    while (next < e && n_stage < kStage) {
      const int64_t i = next++;
      if (kern.prep(i, stage[n_stage])) stage_ray[n_stage++] = i;
    }
  };
  // Load the next ray that walks into lane j; false when none is left (lane j is dead).
  auto load = [&](int j) -> bool {
    while (true) {
      if (pos == n_stage) {
        refill();
        if (n_stage == 0) break;
      }
      const Walk<T, D>& w = stage[pos];
      const int64_t i = stage_ray[pos++];
      kern.start(j, i, w);
      if (!w.active) {
        End<T, D> end{w.flat, false, false, T(0), {}};
        for (int k = 0; k < D; ++k) end.cell[k] = w.cell[k];
        kern.finish(j, end);
        continue;
      }
      for (int k = 0; k < D; ++k) {
        tf[k][j] = w.t_first[k];
        ts[k][j] = std::abs(w.t_scale[k]);
        ta[k][j] = w.t_axis[k];
        nk[k][j] = T(0);
        room[k][j] = !w.moving[k] ? inf : T(w.up[k] ? g.n[k] - 1 - w.cell[k] : w.cell[k]);
        df[k][j] = !w.moving[k] ? I(0) : I(w.up[k] ? g.stride[k] : -g.stride[k]);
        c0[j][k] = w.cell[k];
        dir[j][k] = w.up[k] ? 1 : -1;
      }
      flat[j] = I(w.flat);
      t[j] = w.t;
      t_end[j] = w.t_end;
      t_last[j] = w.t_end - w.tol;
      tol[j] = w.tol;
      it[j] = 0;
      live[j] = -1;
      return true;
    }
    // dead lane: every step is invalid with length 0 in cell 0
    for (int k = 0; k < D; ++k) {
      ta[k][j] = tf[k][j] = room[k][j] = inf;
      ts[k][j] = nk[k][j] = T(0);
      df[k][j] = 0;
    }
    flat[j] = 0;
    t[j] = t_end[j] = tol[j] = T(0);
    t_last[j] = -inf;
    live[j] = 0;
    return false;
  };
  int n_live = 0;
  for (int j = 0; j < W; ++j) n_live += load(j);
  const V zero = V{}, one = V{} + T(1);
  const M bound = M{} + I(g.bound);
  while (n_live > 0) {
    V t_min = ta[0];
    for (int k = 1; k < D; ++k) t_min = ta[k] < t_min ? ta[k] : t_min;
    const M last = t_min >= t_last;
    const V t_stop = last ? t_end : t_min;
    const V diff = t_stop - t;
    V seg = diff < zero ? zero : diff;
    const M valid = ((seg > tol) | last) & live;
    seg = valid ? seg : zero;
    const M here = flat;
    const V lim = t_min + tol;
    M inside = live;
    V n_prev[D];
    for (int k = 0; k < D; ++k) {
      n_prev[k] = nk[k];
      const M s = ta[k] <= lim;
      nk[k] += s ? one : zero;
      flat += s & df[k];
      ta[k] = tf[k] + nk[k] * ts[k];
      inside &= nk[k] <= room[k];
    }
    t = t_stop;
    const M active = ~last & inside;
    it += 1;
    const M done = live & (~active | (it >= bound));
    kern.body(here, seg, valid, valid & ~active);
    const unsigned bits = lane_bits<T, W>(done);
    if (bits) {
      for (int j = 0; j < W; ++j) {
        if (!((bits >> j) & 1u)) continue;
        End<T, D> end{int64_t(here[j]), active[j] != 0, valid[j] != 0 && active[j] == 0, seg[j], {}};
        for (int k = 0; k < D; ++k)
          end.cell[k] = c0[j][k] + dir[j][k] * static_cast<int32_t>(n_prev[k][j]);
        kern.finish(j, end);
        if (!load(j)) --n_live;
      }
    }
  }
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
// Rays walked together per thread: one vector of lanes, 16 bytes by default (SSE2 / NEON;
// wider vectors emulated by two 16-byte halves were slower), 32 bytes in the AVX2 build
// (-mavx2 -DLIDARJAX_VECTOR_BYTES=32, chosen by the loader when the CPU has AVX2).
#ifndef LIDARJAX_VECTOR_BYTES
#define LIDARJAX_VECTOR_BYTES 16
#endif
template <typename T>
constexpr int kLanesOf = LIDARJAX_VECTOR_BYTES / sizeof(T);

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
  constexpr int kLanes = kLanesOf<T>;
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
  // Private per-thread accumulators, length and visit count of a cell side by side (one
  // cache line per visited cell instead of two); hits are rare (one per ray) and separate.
  using I = typename Lanes<T, kLanes>::I;
  struct Acc {
    T r;
    I v;
  };
  std::vector<std::vector<Acc>> acc_priv(threads);
  std::vector<std::vector<int32_t>> h_priv(threads - 1);
  // each worker allocates (and first touches) its own accumulators, in parallel
  std::fill(H, H + nc, 0);
  std::vector<char> overrun(threads, 0);
  using LV = typename Lanes<T, kLanes>::V;
  using LM = typename Lanes<T, kLanes>::M;
  struct Kernel {
    const T *o, *dir, *rng;
    const int32_t* kind;
    T r_max;
    bool sub_as_hit;
    Acc* acc;
    int32_t* h;
    char* overrun;
    bool hit[kLanes];
    bool prep(int64_t i, Walk<T, D>& w) {
      const int32_t k = kind[i];
      const bool is_hit = k == kHit || (k == kSub && sub_as_hit);
      if (!is_hit && k != kSup) return false;
      const T len = is_hit ? rng[i] : r_max;
      setup<T, D>(*grid, o + i * D, dir + i * D, len, w);
      w.flag = is_hit && w.active && (w.t_end >= len - w.tol);
      return true;
    }
    void start(int j, int64_t, const Walk<T, D>& w) { hit[j] = w.flag; }
    void body(const LM& here, const LV& seg, const LM& valid, const LM&) {
      for (int j = 0; j < kLanes; ++j) {
        Acc& a = acc[here[j]];
        a.r += seg[j];    // seg is 0 unless valid
        a.v -= valid[j];  // valid is -1 or 0
      }
    }
    void finish(int j, const End<T, D>& end) {
      if (end.over) *overrun = 1;
      if (hit[j] && end.last) h[end.flat] += 1;
    }
    const Grid<T, D>* grid;
  };
  parallel_blocks(n, threads, kBlock, [&](int64_t t, int64_t b, int64_t e) {
    Kernel kern;
    kern.o = o;
    kern.dir = dir;
    kern.rng = rng;
    kern.kind = kind;
    kern.r_max = r_max;
    kern.sub_as_hit = sub_as_hit;
    if (acc_priv[t].empty()) {
      acc_priv[t].assign(nc, Acc{T(0), I(0)});
      if (t > 0) h_priv[t - 1].assign(nc, 0);
    }
    kern.acc = acc_priv[t].data();
    kern.h = t == 0 ? H : h_priv[t - 1].data();
    kern.overrun = &overrun[t];
    kern.grid = &g;
    walk_lanes<T, D, kLanes>(g, b, e, kern);
  });
  for (char c : overrun)
    if (c)
      return ffi::Error(ffi::ErrorCode::kOutOfRange,
                        "ray walk exceeded the grid's cell bound (non-finite input)");
  parallel_blocks(nc, threads, std::max<int64_t>(4096, nc / threads + 1),
                  [&](int64_t, int64_t b, int64_t e) {
                    std::fill(R + b, R + e, T(0));
                    std::fill(V + b, V + e, 0);
                    for (int64_t t = 0; t < threads; ++t) {
                      if (acc_priv[t].empty()) continue;  // a worker that got no rays
                      const Acc* ap = acc_priv[t].data();
                      for (int64_t c = b; c < e; ++c) {
                        R[c] += ap[c].r;
                        V[c] += int32_t(ap[c].v);
                      }
                    }
                    for (int64_t t = 1; t < threads; ++t) {
                      if (h_priv[t - 1].empty()) continue;
                      const int32_t* hp = h_priv[t - 1].data();
                      for (int64_t c = b; c < e; ++c) H[c] += hp[c];
                    }
                    for (int64_t c = b; c < e; ++c) V[c] -= H[c];
                  });
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

// cell_term of all lanes at once (the same operations per lane): the table entries of
// the lanes' cells are gathered into vectors, then combined lane-wise. Lanes outside
// `use` get 0 (the Gamma term's log is evaluated only where it is used).
template <typename T, int W, int MODE>
inline typename Lanes<T, W>::V cell_terms(const T* tab, int64_t nc,
                                          const typename Lanes<T, W>::M& here,
                                          const typename Lanes<T, W>::V& seg,
                                          const typename Lanes<T, W>::M& use) {
  using V = typename Lanes<T, W>::V;
  V out{};
  if constexpr (MODE == 3) {
    for (int j = 0; j < W; ++j)
      if (use[j]) out[j] = cell_term<T, 3>(tab, nc, here[j], seg[j]);
    return out;
  } else {
    V a, b;
    for (int j = 0; j < W; ++j) {
      a[j] = tab[here[j]];
      if constexpr (MODE == 0) b[j] = tab[nc + here[j]];
    }
    if constexpr (MODE == 0) out = a + b * seg;
    if constexpr (MODE == 1) out = a * seg;
    if constexpr (MODE == 2) out = a;
    return use ? out : V{};
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
  constexpr int kLanes = kLanesOf<T>;
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
  using LV = typename Lanes<T, kLanes>::V;
  using LM = typename Lanes<T, kLanes>::M;
  struct Kernel {
    const Grid<T, D>* grid;
    const T *tab, *o, *dir, *len;
    int64_t nc;
    T *body_out, *last_len, *grid_len, *t_start, *t_end;
    int32_t* last_cell;
    bool* any_valid;
    char* overrun;
    LV acc, glen;  // per lane: body sum and length inside the grid of its current ray
    LM anyv;       // per lane: any valid step
    int32_t lc[kLanes][D];
    int64_t ray[kLanes];
    bool prep(int64_t i, Walk<T, D>& w) {
      setup<T, D>(*grid, o + i * D, dir + i * D, len[i], w);
      return true;
    }
    void start(int j, int64_t i, const Walk<T, D>& w) {
      ray[j] = i;
      acc[j] = glen[j] = T(0);
      anyv[j] = 0;
      for (int k = 0; k < D; ++k) lc[j][k] = w.cell[k];
      t_start[i] = w.t_start;
      t_end[i] = w.t_end;
    }
    void body(const LM& here, const LV& seg, const LM& valid, const LM& last) {
      const LM use = valid & ~last;
      const LV term = cell_terms<T, kLanes, MODE>(tab, nc, here, seg, use);
      acc = use ? acc + term : acc;
      anyv |= valid;
      glen = glen + seg;  // seg is 0 unless valid
    }
    void finish(int j, const End<T, D>& end) {
      if (end.over) *overrun = 1;
      const int64_t i = ray[j];
      body_out[i] = acc[j];
      for (int k = 0; k < D; ++k) last_cell[i * D + k] = end.last ? end.cell[k] : lc[j][k];
      last_len[i] = end.last ? end.seg : T(0);
      grid_len[i] = glen[j];
      any_valid[i] = anyv[j] != 0;
    }
  };
  parallel_blocks(n, threads, kBlock, [&](int64_t t, int64_t b, int64_t e) {
    Kernel kern;
    kern.acc = kern.glen = LV{};
    kern.anyv = LM{};
    kern.grid = &g;
    kern.tab = tab;
    kern.o = o;
    kern.dir = dir;
    kern.len = len;
    kern.nc = nc;
    kern.body_out = body;
    kern.last_len = last_len;
    kern.grid_len = grid_len;
    kern.t_start = t_start;
    kern.t_end = t_end;
    kern.last_cell = last_cell;
    kern.any_valid = any_valid;
    kern.overrun = &overrun[t];
    walk_lanes<T, D, kLanes>(g, b, e, kern);
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

// Bytes per vector of ray lanes this library was built with (16 or 32).
extern "C" int lidarjax_native_vector_bytes() { return LIDARJAX_VECTOR_BYTES; }

// Whether this CPU can run the AVX2 build (asked of the baseline library).
extern "C" int lidarjax_cpu_has_avx2() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2") ? 1 : 0;
#else
  return 0;
#endif
}
