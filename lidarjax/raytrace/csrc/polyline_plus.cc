// PLE+ (dissertation sec. 10.4.3) as one native CPU kernel called from JAX through the XLA
// FFI: `_plus_one` of lidarjax/features/_polyline_plus.py, round for round and candidate for
// candidate, on a batch of scans one after the other on the calling thread (no thread
// pool: XLA's thunk executor hands every loop iteration of the JAX path between pool
// threads, which a loaded machine turns into seconds per scan; issue #20).
//
// Per scan: the active vertex slots are compacted into parameter slots (ascending slot
// order, as jnp.nonzero); the end vertices of open polylines move along their own ray.
// Each round: Levenberg-Marquardt from the current vertices (and from `restarts` random
// starts drawn by JAX, the same draws as the JAX path) on the fixed-association surrogate
// (each reflected ray held on the segment it hits first at the start, of segments within
// 1024 eps of the nearest the lowest index as _first_segment; residual r_k - r^_k to that
// segment's line, the 1e-3 anchor); then the candidates, each checked exactly with
// the true first-intersection model: per polyline (step fractions, restart solutions; the
// other polylines as they are), all polylines at their own best, per vertex (step
// fractions, pattern moves along / across the ray), all vertices at their own best, the
// best single polyline, the best single vertex. The lowest exact error among those that
// keep the explained rays and do not raise the error wins; none: the round keeps its
// vertices.
//
// The solver is optimistix's LevenbergMarquardt as PLE+ configures it
// (default_plus_solver: rtol 1e-6, atol 1e-9, Cholesky of the damped normal equations),
// written out: lambda = 1 / step size, the classical trust-region update (accept when the
// loss falls by at least 1 % of the Gauss-Newton prediction, step size x3.5 above 99 %,
// x0.25 on rejection; the first step always accepted), Cauchy termination on accepted
// steps (max-norm of |dy| / (atol + rtol |y|) and |df| / (atol + rtol |f|) below 1), at most
// `max_steps` steps (rejected ones count). Analytic Jacobian; the normal equations and the
// solver state are double precision for float32 scans too. Result code per scan: 0 the
// last round's solve from the current vertices converged, 1 it ran out of steps.
//
// Exactness: the first-intersection distance is `ray_segment` of
// lidarjax/raytrace/_primitives.py (same parallel test, same end slack, same operation
// order). XLA's CPU compiler contracts `a * b - c * d` into fma(a, b, -(c * d)),
// `a * b + c` into fma(a, b, c) and a two-term dot into fma(a1, b1, a0 * b0) when the CPU
// has FMA; the kernel does the same (template flag FMA, chosen at run time), so distances
// (and with them the explained rays and every exact error) agree with the JAX path bit
// for bit, and the trial positions of the step fractions and pattern moves do too.
// Everything else is compiled with -ffp-contract=off. What cannot be bit for bit: sums
// (XLA's reduction order is its own) and the solver's linear algebra, so the two paths
// agree to round-off per solve step, and a converged solve to the resolution of its
// termination test.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int kNumFractions = 6;  // _FRACTIONS of _polyline_plus.py
constexpr double kFractions[kNumFractions] = {1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125};
constexpr double kAnchor = 1e-3;  // _ANCHOR
constexpr double kRtol = 1e-6, kAtol = 1e-9;  // default_plus_solver
// optimistix.ClassicalTrustRegion's defaults
constexpr double kLowCutoff = 0.01, kHighCutoff = 0.99, kHighConstant = 3.5, kLowConstant = 0.25;

template <typename T, bool FMA>
struct Arith {
  static inline T mul_sub(T a, T b, T c, T d) {  // a * b - c * d
    if constexpr (FMA) return std::fma(a, b, -(c * d));
    else return a * b - c * d;
  }
  static inline T mul_add(T a, T b, T c) {  // a * b + c
    if constexpr (FMA) return std::fma(a, b, c);
    else return a * b + c;
  }
  static inline T dot2(T a0, T a1, T b0, T b1) {  // a0 * b0 + a1 * b1 (XLA's dot order)
    if constexpr (FMA) return std::fma(a1, b1, a0 * b0);
    else return a0 * b0 + a1 * b1;
  }
};

template <typename T>
struct Pt {
  T x, y;
};

template <typename T>
inline bool finite(const Pt<T>& p) {
  return std::isfinite(p.x) && std::isfinite(p.y);
}

template <typename T>
inline bool same(const Pt<T>& a, const Pt<T>& b) {
  return a.x == b.x && a.y == b.y;
}

// the ray-independent parts of ray_segment for one segment start -> end
template <typename T>
struct Seg {
  T ex, ey;  // e = end - start
  T wx, wy;  // w = start - origin
  T num_t;   // cross2(w, e)
  T len_e;   // sqrt(sum(e * e))
  T n1;      // norm1(origin) + norm1(w) + norm1(e)
};

// the segment-independent parts for one ray
template <typename T>
struct Ray {
  T dx, dy;
  T len_d;  // sqrt(sum(d * d))
  T n1d;    // norm1(d)
};

template <typename T, bool FMA>
inline Seg<T> make_seg(T ox, T oy, T n1o, const Pt<T>& s, const Pt<T>& e) {
  using A = Arith<T, FMA>;
  Seg<T> g;
  g.ex = e.x - s.x;
  g.ey = e.y - s.y;
  g.wx = s.x - ox;
  g.wy = s.y - oy;
  g.num_t = A::mul_sub(g.wx, g.ey, g.wy, g.ex);
  g.len_e = std::sqrt(g.ex * g.ex + g.ey * g.ey);
  g.n1 = (n1o + (std::fabs(g.wx) + std::fabs(g.wy))) + (std::fabs(g.ex) + std::fabs(g.ey));
  return g;
}

// ray_segment: distance along the ray to the segment, inf when it misses
template <typename T, bool FMA>
inline T hit_t(const Ray<T>& r, const Seg<T>& g) {
  using A = Arith<T, FMA>;
  constexpr T inf = std::numeric_limits<T>::infinity();
  constexpr T eps64 = T(64) * std::numeric_limits<T>::epsilon();
  constexpr T tiny = std::numeric_limits<T>::min();
  const T den = A::mul_sub(r.dx, g.ey, r.dy, g.ex);  // cross2(d, e)
  const T scale = g.len_e * r.len_d;
  if (!(std::fabs(den) > eps64 * std::max(scale, tiny))) return inf;
  const T t = g.num_t / den;
  const T u = A::mul_sub(g.wx, r.dy, g.wy, r.dx) / den;  // cross2(w, d)
  const T slack = (eps64 * (g.n1 * r.n1d)) / std::fabs(den);
  return (t > T(0) && u >= -slack && u <= T(1) + slack) ? t : inf;
}

// Levenberg-Marquardt on the fixed-association surrogate of one solve (double precision)
struct Surrogate {
  int n = 0;           // parameter slots (real)
  int m = 0;           // unknowns
  int k = 0;           // rays
  std::vector<int> col;       // first unknown of each parameter
  std::vector<char> end;      // end vertex: one unknown (t along its ray)
  std::vector<double> dpx, dpy;  // each parameter's ray direction
  std::vector<double> p0x, p0y;  // anchor (the projected start)
  double ox = 0, oy = 0;
  std::vector<char> use;
  std::vector<int> pa, pb;
  std::vector<double> rng, rdx, rdy;

  // rows: k rays (up to 4 entries) then 2 anchor rows per parameter (1 entry)
  std::vector<int> jc;     // [rows 4] columns (-1: none)
  std::vector<double> jv;  // [rows 4] values

  int rows() const { return k + 2 * n; }

  void positions(const std::vector<double>& y, std::vector<double>& px,
                 std::vector<double>& py) const {
    for (int p = 0; p < n; ++p) {
      if (end[p]) {
        const double t = y[col[p]];
        px[p] = ox + t * dpx[p];
        py[p] = oy + t * dpy[p];
      } else {
        px[p] = y[col[p]];
        py[p] = y[col[p] + 1];
      }
    }
  }

  // residuals f [rows] and the Jacobian (jc, jv) at y
  void eval(const std::vector<double>& y, std::vector<double>& f, std::vector<double>& px,
            std::vector<double>& py) {
    positions(y, px, py);
    std::fill(jc.begin(), jc.end(), -1);
    std::fill(jv.begin(), jv.end(), 0.0);
    auto put = [&](int row, int slot, int p, double gx, double gy) {
      if (end[p]) {
        jc[4 * row + slot] = col[p];
        jv[4 * row + slot] = gx * dpx[p] + gy * dpy[p];
      } else {
        jc[4 * row + slot] = col[p];
        jv[4 * row + slot] = gx;
        jc[4 * row + slot + 1] = col[p] + 1;
        jv[4 * row + slot + 1] = gy;
      }
    };
    for (int i = 0; i < k; ++i) {
      f[i] = 0.0;
      if (!use[i]) continue;
      const int a = pa[i], b = pb[i];
      const double ax = px[a], ay = py[a], bx = px[b], by = py[b];
      const double ex = bx - ax, ey = by - ay, wx = ax - ox, wy = ay - oy;
      const double dx = rdx[i], dy = rdy[i];
      const double den = dx * ey - dy * ex;
      if (!(std::fabs(den) > 1e-12)) continue;
      const double rhat = (wx * ey - wy * ex) / den;
      f[i] = rng[i] - rhat;
      // d r^ / d(a, b) = (d num - r^ d den) / den; the residual is r - r^
      const double gax = -((ey + wy) - rhat * dy) / den;
      const double gay = -(-(wx + ex) + rhat * dx) / den;
      const double gbx = -(-wy + rhat * dy) / den;
      const double gby = -(wx - rhat * dx) / den;
      put(i, 0, a, gax, gay);
      put(i, 2, b, gbx, gby);
    }
    for (int p = 0; p < n; ++p) {
      const int rx = k + 2 * p, ry = rx + 1;
      f[rx] = kAnchor * (px[p] - p0x[p]);
      f[ry] = kAnchor * (py[p] - p0y[p]);
      if (end[p]) {
        jc[4 * rx] = col[p];
        jv[4 * rx] = kAnchor * dpx[p];
        jc[4 * ry] = col[p];
        jv[4 * ry] = kAnchor * dpy[p];
      } else {
        jc[4 * rx] = col[p];
        jv[4 * rx] = kAnchor;
        jc[4 * ry] = col[p] + 1;
        jv[4 * ry] = kAnchor;
      }
    }
  }

  // Solve (J^T J + lambda I) x = J^T f by Cholesky; false if not positive definite
  bool damped_step(const std::vector<double>& f, double lambda, std::vector<double>& mat,
                   std::vector<double>& x) const {
    std::fill(mat.begin(), mat.end(), 0.0);
    std::fill(x.begin(), x.end(), 0.0);
    const int nr = rows();
    for (int r = 0; r < nr; ++r) {
      for (int a = 0; a < 4; ++a) {
        const int ca = jc[4 * r + a];
        if (ca < 0) continue;
        const double va = jv[4 * r + a];
        x[ca] += va * f[r];
        for (int b = 0; b < 4; ++b) {
          const int cb = jc[4 * r + b];
          if (cb < 0 || cb > ca) continue;
          mat[static_cast<size_t>(ca) * m + cb] += va * jv[4 * r + b];
        }
      }
    }
    for (int i = 0; i < m; ++i) mat[static_cast<size_t>(i) * m + i] += lambda;
    // in-place Cholesky, lower triangle
    for (int j = 0; j < m; ++j) {
      double* rj = &mat[static_cast<size_t>(j) * m];
      double s = rj[j];
      for (int q = 0; q < j; ++q) s -= rj[q] * rj[q];
      if (!(s > 0.0)) return false;
      const double d = std::sqrt(s);
      rj[j] = d;
      for (int i = j + 1; i < m; ++i) {
        double* ri = &mat[static_cast<size_t>(i) * m];
        double v = ri[j];
        for (int q = 0; q < j; ++q) v -= ri[q] * rj[q];
        ri[j] = v / d;
      }
    }
    for (int i = 0; i < m; ++i) {  // L z = g
      const double* ri = &mat[static_cast<size_t>(i) * m];
      double v = x[i];
      for (int q = 0; q < i; ++q) v -= ri[q] * x[q];
      x[i] = v / ri[i];
    }
    for (int i = m - 1; i >= 0; --i) {  // L^T x = z
      double v = x[i];
      for (int q = i + 1; q < m; ++q) v -= mat[static_cast<size_t>(q) * m + i] * x[q];
      x[i] = v / mat[static_cast<size_t>(i) * m + i];
    }
    return true;
  }

  // optimistix.LevenbergMarquardt from y (updated in place); returns (steps, converged)
  std::pair<int, bool> solve(std::vector<double>& y, int max_steps) {
    const int nr = rows();
    jc.assign(static_cast<size_t>(nr) * 4, -1);
    jv.assign(static_cast<size_t>(nr) * 4, 0.0);
    std::vector<int> jc_acc(jc.size(), -1);
    std::vector<double> jv_acc(jv.size(), 0.0);
    std::vector<double> f_eval(nr), f_acc(nr, 0.0), px(n), py(n), x(m), y_eval = y;
    std::vector<double> mat(static_cast<size_t>(m) * m);
    double step_size = 1.0;
    bool first = true, terminate = false;
    int steps = 0;
    while (steps < max_steps && !terminate) {
      eval(y_eval, f_eval, px, py);
      // predicted reduction of 0.5 |f|^2 by the step y_eval - y, from the accepted point
      double pred = 0.0, f_min = 0.0, f_min_eval = 0.0;
      if (!first) {
        double jt = 0.0, rtr = 0.0;
        for (int r = 0; r < nr; ++r) {
          double v = f_acc[r];
          for (int a = 0; a < 4; ++a) {
            const int c = jc_acc[4 * r + a];
            if (c >= 0) v += jv_acc[4 * r + a] * (y_eval[c] - y[c]);
          }
          jt += v * v;
          rtr += f_acc[r] * f_acc[r];
        }
        pred = 0.5 * (jt - rtr);
        f_min = 0.5 * rtr;
      }
      for (int r = 0; r < nr; ++r) f_min_eval += f_eval[r] * f_eval[r];
      f_min_eval *= 0.5;
      const double diff = f_min_eval - f_min;
      const bool accept = first || diff <= kLowCutoff * pred;
      const bool good = !first && pred < 0.0 && diff < kHighCutoff * pred;
      step_size *= accept ? (good ? kHighConstant : 1.0) : kLowConstant;
      if (accept) {
        double ny = 0.0, nf = 0.0;
        for (int i = 0; i < m; ++i)
          ny = std::max(ny, std::fabs(y_eval[i] - y[i]) / (kAtol + kRtol * std::fabs(y_eval[i])));
        for (int r = 0; r < nr; ++r)
          nf = std::max(nf,
                        std::fabs(f_eval[r] - f_acc[r]) / (kAtol + kRtol * std::fabs(f_eval[r])));
        terminate = ny < 1.0 && nf < 1.0;
        y = y_eval;
        f_acc = f_eval;
        jc_acc = jc;
        jv_acc = jv;
      }
      first = false;
      ++steps;
      // the damped Gauss-Newton step from the accepted point
      const double lambda = step_size > std::numeric_limits<double>::epsilon()
                                ? 1.0 / step_size
                                : std::numeric_limits<double>::max();
      std::swap(jc, jc_acc);
      std::swap(jv, jv_acc);
      const bool ok = damped_step(f_acc, lambda, mat, x);
      std::swap(jc, jc_acc);
      std::swap(jv, jv_acc);
      for (int i = 0; i < m; ++i)
        y_eval[i] = ok ? y[i] - x[i] : std::numeric_limits<double>::quiet_NaN();
    }
    return {steps, terminate};
  }
};

template <typename T, bool FMA>
class PlusScan {
 public:
  using A = Arith<T, FMA>;
  static constexpr T kInf = std::numeric_limits<T>::infinity();

  // inputs of one scan
  int K = 0, NP = 0, max_steps = 1;
  T ox = 0, oy = 0, n1o = 0;
  std::vector<Ray<T>> rays;
  const T* ranges = nullptr;
  const bool* refl = nullptr;
  std::vector<char> hit0;

  // topology (parameter slots 0..n-1 are the active vertex slots in ascending order)
  int n = 0;
  std::vector<int> slot, succ_p, pred_p, nxt, bidx;  // bidx: index of the polyline
  std::vector<char> end_p, seg_ok;
  std::vector<int> labels;  // each polyline's label (its smallest parameter), ascending
  int nb = 0;
  std::vector<T> dpx, dpy;

  std::vector<Pt<T>> verts;  // [K] current vertices (all slots)

  // ----------------------------------------------------------------- set-up
  void setup(const T* v, const int32_t* successor, const bool* active) {
    verts.resize(K);
    for (int i = 0; i < K; ++i) verts[i] = {v[2 * i], v[2 * i + 1]};
    std::vector<int> succ(K), pred(K, -1);
    for (int i = 0; i < K; ++i) succ[i] = active[i] ? successor[i] : -1;
    for (int i = 0; i < K; ++i)
      if (succ[i] >= 0 && succ[i] < K) pred[succ[i]] = i;
    std::vector<int> param_of(K, 0);
    slot.clear();
    for (int i = 0; i < K; ++i)
      if (active[i]) {
        param_of[i] = static_cast<int>(slot.size());
        slot.push_back(i);
      }
    n = static_cast<int>(slot.size());
    end_p.assign(n, 0);
    succ_p.assign(n, -1);
    pred_p.assign(n, -1);
    seg_ok.assign(n, 0);
    nxt.assign(n, 0);
    dpx.resize(n);
    dpy.resize(n);
    for (int p = 0; p < n; ++p) {
      const int s = slot[p];
      end_p[p] = (succ[s] < 0 || pred[s] < 0) ? 1 : 0;
      dpx[p] = rays[s].dx;
      dpy[p] = rays[s].dy;
      if (succ[s] >= 0) succ_p[p] = param_of[std::min(succ[s], K - 1)];
      seg_ok[p] = succ_p[p] >= 0;
      nxt[p] = std::max(succ_p[p], 0);
    }
    for (int p = 0; p < n; ++p)
      if (succ_p[p] >= 0) pred_p[succ_p[p]] = p;
    // polylines: label = smallest parameter slot reachable along the links
    std::vector<int> lab(n, -1);
    labels.clear();
    for (int p = 0; p < n; ++p) {
      if (lab[p] >= 0) continue;
      std::vector<int> stack{p};
      lab[p] = p;
      while (!stack.empty()) {
        const int q = stack.back();
        stack.pop_back();
        for (int r : {succ_p[q], pred_p[q]})
          if (r >= 0 && lab[r] < 0) {
            lab[r] = p;
            stack.push_back(r);
          }
      }
      labels.push_back(p);
    }
    nb = static_cast<int>(labels.size());
    std::vector<int> b_of(n, 0);
    for (int b = 0; b < nb; ++b) b_of[labels[b]] = b;
    bidx.resize(n);
    for (int p = 0; p < n; ++p) bidx[p] = b_of[lab[p]];
  }

  // segments of parameter positions P (seg_ok only)
  void make_segs(const std::vector<Pt<T>>& P, std::vector<Seg<T>>& segs) const {
    segs.resize(n);
    for (int s = 0; s < n; ++s)
      if (seg_ok[s]) segs[s] = make_seg<T, FMA>(ox, oy, n1o, P[s], P[nxt[s]]);
  }

  // t [K n]: ray k to segment s (inf for no segment)
  void seg_hits(const std::vector<Seg<T>>& segs, std::vector<T>& t) const {
    t.assign(static_cast<size_t>(K) * n, kInf);
    for (int k = 0; k < K; ++k)
      for (int s = 0; s < n; ++s)
        if (seg_ok[s]) t[static_cast<size_t>(k) * n + s] = hit_t<T, FMA>(rays[k], segs[s]);
  }

  // error_of: (sse, explained set matches hit0); `stop` above which the sum may stop early
  template <typename Fn>
  bool error_of(Fn tk, double& sse, double stop = std::numeric_limits<double>::infinity()) const {
    double acc = 0.0;
    for (int k = 0; k < K; ++k) {
      const T t = tk(k);
      const bool h = refl[k] && std::isfinite(t);
      if (h != static_cast<bool>(hit0[k])) return false;
      if (h) {
        const T d = ranges[k] - t;
        acc += static_cast<double>(d * d);
        if (acc > stop) return false;  // partial sums of d^2 >= 0 only grow
      }
    }
    sse = acc;
    return true;
  }

  // ----------------------------------------------------------------- one solve
  // LM from `start` with the rays held on their first segment there; `t_start` [K n] the
  // distances at `start`. Writes the projected start p0 and the solution.
  std::pair<int, bool> solve_from(const std::vector<Pt<T>>& start, const std::vector<T>& t_start,
                                  std::vector<Pt<T>>& p0, std::vector<Pt<T>>& sol) const {
    Surrogate sg;
    sg.n = n;
    sg.k = K;
    sg.ox = ox;
    sg.oy = oy;
    sg.col.resize(n);
    sg.end.assign(end_p.begin(), end_p.end());
    sg.dpx.resize(n);
    sg.dpy.resize(n);
    sg.p0x.resize(n);
    sg.p0y.resize(n);
    p0.resize(n);
    sol.resize(n);
    std::vector<T> t0(n);
    int m = 0;
    for (int p = 0; p < n; ++p) {
      sg.col[p] = m;
      m += end_p[p] ? 1 : 2;
      sg.dpx[p] = dpx[p];
      sg.dpy[p] = dpy[p];
      t0[p] = A::dot2(start[p].x - ox, start[p].y - oy, dpx[p], dpy[p]);
      p0[p] = end_p[p] ? Pt<T>{A::mul_add(t0[p], dpx[p], ox), A::mul_add(t0[p], dpy[p], oy)}
                       : start[p];
      sg.p0x[p] = p0[p].x;
      sg.p0y[p] = p0[p].y;
    }
    sg.m = m;
    sg.use.assign(K, 0);
    sg.pa.assign(K, 0);
    sg.pb.assign(K, 0);
    sg.rng.resize(K);
    sg.rdx.resize(K);
    sg.rdy.resize(K);
    const T tie = T(1) + T(1024) * std::numeric_limits<T>::epsilon();
    for (int k = 0; k < K; ++k) {
      // _first_segment: the lowest index among the segments within 1024 eps of the nearest
      const T* tk = &t_start[static_cast<size_t>(k) * n];
      T tb = kInf;
      for (int s = 0; s < n; ++s) tb = std::min(tb, tk[s]);
      const T lim = tb * tie;
      int best = 0;
      for (int s = 0; s < n; ++s)
        if (tk[s] <= lim) {
          best = s;
          break;
        }
      sg.use[k] = refl[k] && std::isfinite(tb);
      sg.pa[k] = best;
      sg.pb[k] = std::max(succ_p[best], 0);
      sg.rng[k] = ranges[k];
      sg.rdx[k] = rays[k].dx;
      sg.rdy[k] = rays[k].dy;
    }
    std::vector<double> y(m);
    for (int p = 0; p < n; ++p) {
      if (end_p[p]) {
        y[sg.col[p]] = t0[p];
      } else {
        y[sg.col[p]] = start[p].x;
        y[sg.col[p] + 1] = start[p].y;
      }
    }
    const auto res = sg.solve(y, max_steps);
    for (int p = 0; p < n; ++p) {
      if (end_p[p]) {
        const T t = static_cast<T>(y[sg.col[p]]);
        sol[p] = {A::mul_add(t, dpx[p], ox), A::mul_add(t, dpy[p], oy)};
      } else {
        sol[p] = {static_cast<T>(y[sg.col[p]]), static_cast<T>(y[sg.col[p] + 1])};
      }
    }
    return res;
  }

  // ----------------------------------------------------------------- the search
  struct Out {
    double sse0 = 0, sse = 0, frac = 1;
    int steps = 0;
    bool converged = true;
  };

  Out run(int rounds, const T* z, int R, const T* sigma, int P, const T* pattern) {
    Out out;
    // the input's true error and explained set
    {
      std::vector<Pt<T>> pv(n);
      for (int p = 0; p < n; ++p) pv[p] = verts[slot[p]];
      std::vector<Seg<T>> segs;
      make_segs(pv, segs);
      std::vector<T> t;
      seg_hits(segs, t);
      hit0.assign(K, 0);
      double acc = 0.0;
      for (int k = 0; k < K; ++k) {
        T tm = kInf;
        for (int s = 0; s < n; ++s) tm = std::min(tm, t[static_cast<size_t>(k) * n + s]);
        const bool h = refl[k] && std::isfinite(tm);
        hit0[k] = h;
        if (h) {
          const T d = ranges[k] - tm;
          acc += static_cast<double>(d * d);
        }
      }
      out.sse0 = out.sse = acc;
    }
    const int F = kNumFractions;
    const int C = F + R;            // per-polyline trials
    const int TT = F + 4 * P;       // per-vertex trials
    const double inf = std::numeric_limits<double>::infinity();
    std::vector<Pt<T>> pc(n), p0, p_lm, p0r, psr;
    std::vector<std::vector<Pt<T>>> chain(C, std::vector<Pt<T>>(n));
    std::vector<std::vector<Pt<T>>> pall(TT, std::vector<Pt<T>>(n));
    std::vector<Seg<T>> segs, segs_s;
    std::vector<T> tseg, ts;
    std::vector<T> mb0(static_cast<size_t>(K) * nb), others(static_cast<size_t>(K) * nb);
    std::vector<T> mbf(static_cast<size_t>(C) * K * nb);
    for (int round = 0; round < rounds; ++round) {
      for (int p = 0; p < n; ++p) pc[p] = verts[slot[p]];
      // padding parameter slots of the JAX path hold vertex slot 0 and join polyline 0
      const bool pad_finite = NP <= n || finite(verts[0]);
      make_segs(pc, segs);
      seg_hits(segs, tseg);
      for (int k = 0; k < K; ++k) {
        T* mk = &mb0[static_cast<size_t>(k) * nb];
        std::fill(mk, mk + nb, kInf);
        for (int s = 0; s < n; ++s)
          mk[bidx[s]] = std::min(mk[bidx[s]], tseg[static_cast<size_t>(k) * n + s]);
        // the nearest of the other polylines
        int first = 0;
        T t1 = kInf;
        for (int b = 0; b < nb; ++b)
          if (mk[b] < t1) {
            t1 = mk[b];
            first = b;
          }
        T t2 = kInf;
        for (int b = 0; b < nb; ++b)
          if (b != first) t2 = std::min(t2, mk[b]);
        T* ok_ = &others[static_cast<size_t>(k) * nb];
        for (int b = 0; b < nb; ++b) ok_[b] = b == first ? t2 : t1;
      }
      // LM from the current vertices, the step fractions
      const auto lm = solve_from(pc, tseg, p0, p_lm);
      out.steps += lm.first;
      out.converged = lm.second;
      for (int f = 0; f < F; ++f) {
        const T fr = static_cast<T>(kFractions[f]);
        for (int p = 0; p < n; ++p)
          chain[f][p] = {A::mul_add(fr, p_lm[p].x - p0[p].x, p0[p].x),
                         A::mul_add(fr, p_lm[p].y - p0[p].y, p0[p].y)};
      }
      // restarts from random starts (Gaussian draws z of the JAX path)
      if (R > 0) {
        std::vector<T> rng_c(n), t_c0(n);
        for (int p = 0; p < n; ++p) {
          const T wx = pc[p].x - ox, wy = pc[p].y - oy;
          rng_c[p] = std::sqrt(wx * wx + wy * wy);
          t_c0[p] = A::dot2(wx, wy, dpx[p], dpy[p]);
        }
        std::vector<Pt<T>> ps(n);
        for (int r = 0; r < R; ++r) {
          const T* zr = z + (static_cast<size_t>(round) * R + r) * NP * 2;
          for (int p = 0; p < n; ++p) {
            const T sr = sigma[r] * rng_c[p];
            if (end_p[p]) {
              const T tt = A::mul_add(sr, zr[2 * p], t_c0[p]);
              ps[p] = {A::mul_add(tt, dpx[p], ox), A::mul_add(tt, dpy[p], oy)};
            } else {
              ps[p] = {A::mul_add(sr, zr[2 * p], pc[p].x), A::mul_add(sr, zr[2 * p + 1], pc[p].y)};
            }
          }
          make_segs(ps, segs_s);
          seg_hits(segs_s, ts);
          const auto rs = solve_from(ps, ts, p0r, psr);
          out.steps += rs.first;
          chain[F + r] = psr;
        }
      }
      // per polyline: trial c for polyline b, all others as they are
      std::vector<char> finite_tr(static_cast<size_t>(C) * nb);
      for (int c = 0; c < C; ++c) {
        make_segs(chain[c], segs_s);
        char* fin = &finite_tr[static_cast<size_t>(c) * nb];
        std::fill(fin, fin + nb, 1);
        for (int p = 0; p < n; ++p)
          if (!finite(chain[c][p])) fin[bidx[p]] = 0;
        if (!pad_finite && nb > 0) fin[0] = 0;
        for (int k = 0; k < K; ++k) {
          T* mk = &mbf[(static_cast<size_t>(c) * K + k) * nb];
          std::fill(mk, mk + nb, kInf);
          for (int s = 0; s < n; ++s)
            if (seg_ok[s]) mk[bidx[s]] = std::min(mk[bidx[s]], hit_t<T, FMA>(rays[k], segs_s[s]));
        }
      }
      const double sse_cur = out.sse;
      std::vector<double> sse_s(static_cast<size_t>(C) * nb, inf);  // inf: does not pass
      for (int c = 0; c < C; ++c)
        for (int b = 0; b < nb; ++b) {
          if (!finite_tr[static_cast<size_t>(c) * nb + b]) continue;
          double e;
          const bool ok = error_of(
              [&](int k) {
                return std::min(others[static_cast<size_t>(k) * nb + b],
                                mbf[(static_cast<size_t>(c) * K + k) * nb + b]);
              },
              e, sse_cur);
          if (ok && e <= sse_cur) sse_s[static_cast<size_t>(c) * nb + b] = e;
        }
      std::vector<int> f_idx(nb, 0);
      std::vector<char> has(nb, 0);
      bool any_has = false;
      for (int b = 0; b < nb; ++b) {
        double best = inf;
        for (int c = 0; c < C; ++c) {
          const double e = sse_s[static_cast<size_t>(c) * nb + b];
          if (e < best) {
            best = e;
            f_idx[b] = c;
          }
        }
        has[b] = std::isfinite(best);
        any_has = any_has || has[b];
      }
      // every polyline at its own best trial
      double sse_c = inf;
      if (any_has) {
        double e;
        const bool ok = error_of(
            [&](int k) {
              T tm = kInf;
              for (int b = 0; b < nb; ++b)
                tm = std::min(tm, has[b] ? mbf[(static_cast<size_t>(f_idx[b]) * K + k) * nb + b]
                                         : mb0[static_cast<size_t>(k) * nb + b]);
              return tm;
            },
            e);
        if (ok && e <= sse_cur) sse_c = e;
      }
      // per vertex: the step fractions, then pattern moves along / across the ray
      std::vector<T> t_c(n);
      for (int p = 0; p < n; ++p)
        t_c[p] = A::dot2(pc[p].x - ox, pc[p].y - oy, dpx[p], dpy[p]);
      for (int f = 0; f < F; ++f) pall[f] = chain[f];
      for (int l = 0; l < P; ++l)
        for (int si = 0; si < 2; ++si) {
          const T c = si == 0 ? pattern[l] : -pattern[l];
          auto& along = pall[F + 4 * l + 2 * si];
          auto& across = pall[F + 4 * l + 2 * si + 1];
          for (int p = 0; p < n; ++p) {
            if (end_p[p]) {
              const T tt = t_c[p] + c;
              along[p] = {A::mul_add(tt, dpx[p], ox), A::mul_add(tt, dpy[p], oy)};
              across[p] = pc[p];
            } else {
              along[p] = {A::mul_add(c, dpx[p], pc[p].x), A::mul_add(c, dpy[p], pc[p].y)};
              across[p] = {A::mul_add(c, -dpy[p], pc[p].x), A::mul_add(c, dpx[p], pc[p].y)};
            }
          }
        }
      // nearest unchanged segment per ray and vertex: all but the vertex's two segments
      std::vector<T> rest(static_cast<size_t>(K) * n);
      for (int k = 0; k < K; ++k) {
        const T* tk = &tseg[static_cast<size_t>(k) * n];
        T tv[3] = {kInf, kInf, kInf};
        int iv[3] = {-1, -1, -1};
        for (int s = 0; s < n; ++s) {
          const T t = tk[s];
          if (!(t < tv[2])) continue;
          int j = 2;
          while (j > 0 && t < tv[j - 1]) {
            tv[j] = tv[j - 1];
            iv[j] = iv[j - 1];
            --j;
          }
          tv[j] = t;
          iv[j] = s;
        }
        for (int v = 0; v < n; ++v) {
          T r = kInf;
          for (int j = 0; j < 3; ++j)
            if (iv[j] != v && !(iv[j] >= 0 && iv[j] == pred_p[v])) r = std::min(r, tv[j]);
          rest[static_cast<size_t>(k) * n + v] = r;
        }
      }
      std::vector<double> sse_v(static_cast<size_t>(TT) * n, inf);  // inf: does not pass
      for (int tr = 0; tr < TT; ++tr)
        for (int v = 0; v < n; ++v) {
          const Pt<T>& q = pall[tr][v];
          if (!finite(q) || same(q, pc[v])) continue;
          const bool has_in = pred_p[v] >= 0, has_out = seg_ok[v];
          Seg<T> s_in{}, s_out{};
          if (has_in) s_in = make_seg<T, FMA>(ox, oy, n1o, pc[pred_p[v]], q);
          if (has_out) s_out = make_seg<T, FMA>(ox, oy, n1o, q, pc[nxt[v]]);
          double e;
          const bool ok = error_of(
              [&](int k) {
                T t = rest[static_cast<size_t>(k) * n + v];
                if (has_in) t = std::min(t, hit_t<T, FMA>(rays[k], s_in));
                if (has_out) t = std::min(t, hit_t<T, FMA>(rays[k], s_out));
                return t;
              },
              e, sse_cur);
          if (ok && e <= sse_cur) sse_v[static_cast<size_t>(tr) * n + v] = e;
        }
      std::vector<Pt<T>> p_vc = pc;
      bool any_v = false;
      for (int v = 0; v < n; ++v) {
        double best = inf;
        int bt = 0;
        for (int tr = 0; tr < TT; ++tr)
          if (sse_v[static_cast<size_t>(tr) * n + v] < best) {
            best = sse_v[static_cast<size_t>(tr) * n + v];
            bt = tr;
          }
        if (std::isfinite(best)) {
          p_vc[v] = pall[bt][v];
          any_v = true;
        }
      }
      double sse_vc = inf;
      if (any_v) {
        make_segs(p_vc, segs_s);
        double e;
        const bool ok = error_of(
            [&](int k) {
              T tm = kInf;
              for (int s = 0; s < n; ++s)
                if (seg_ok[s]) tm = std::min(tm, hit_t<T, FMA>(rays[k], segs_s[s]));
              return tm;
            },
            e);
        if (ok && e <= sse_cur) sse_vc = e;
      }
      // the best single polyline and the best single vertex (first of equal errors)
      int fb = 0, bb = 0, tvb = 0, vb = 0;
      double e_sb = inf, e_sv = inf;
      for (int c = 0; c < C; ++c)
        for (int b = 0; b < nb; ++b)
          if (sse_s[static_cast<size_t>(c) * nb + b] < e_sb) {
            e_sb = sse_s[static_cast<size_t>(c) * nb + b];
            fb = c;
            bb = b;
          }
      for (int tr = 0; tr < TT; ++tr)
        for (int v = 0; v < n; ++v)
          if (sse_v[static_cast<size_t>(tr) * n + v] < e_sv) {
            e_sv = sse_v[static_cast<size_t>(tr) * n + v];
            tvb = tr;
            vb = v;
          }
      const double cand[4] = {sse_c, sse_vc, e_sb, e_sv};
      int best = 0;
      for (int i = 1; i < 4; ++i)
        if (cand[i] < cand[best]) best = i;
      int moved = 0;
      if (std::isfinite(cand[best])) {
        for (int p = 0; p < n; ++p) {
          Pt<T> q = pc[p];
          if (best == 0 && has[bidx[p]]) q = chain[f_idx[bidx[p]]][p];
          if (best == 1) q = p_vc[p];
          if (best == 2 && bidx[p] == bb) q = chain[fb][p];
          if (best == 3 && p == vb) q = pall[tvb][p];
          moved += same(q, pc[p]) ? 0 : 1;
          verts[slot[p]] = q;
        }
        out.sse = cand[best];
      }
      out.frac = static_cast<double>(moved) / static_cast<double>(std::max(n, 1));
    }
    return out;
  }
};

bool cpu_has_fma() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_cpu_init();
  return __builtin_cpu_supports("fma");
#elif defined(__aarch64__)
  return true;
#else
  return false;
#endif
}

template <typename T, bool FMA>
void run_scan(int K, int NP, int max_steps, int rounds, const T* v, const int32_t* succ,
              const bool* act, const T* o, const T* dirs, const T* ranges, const bool* refl,
              const T* z, int R, const T* sigma, int P, const T* pattern, T* v_out, T* sse0,
              T* sse1, T* frac, int32_t* result, int32_t* n_steps) {
  PlusScan<T, FMA> s;
  s.K = K;
  s.NP = NP;
  s.max_steps = max_steps;
  s.ox = o[0];
  s.oy = o[1];
  s.n1o = std::fabs(s.ox) + std::fabs(s.oy);
  s.rays.resize(K);
  for (int k = 0; k < K; ++k) {
    Ray<T>& r = s.rays[k];
    r.dx = dirs[2 * k];
    r.dy = dirs[2 * k + 1];
    r.len_d = std::sqrt(r.dx * r.dx + r.dy * r.dy);
    r.n1d = std::fabs(r.dx) + std::fabs(r.dy);
  }
  s.ranges = ranges;
  s.refl = refl;
  s.setup(v, succ, act);
  const auto out = s.run(rounds, z, R, sigma, P, pattern);
  for (int i = 0; i < K; ++i) {
    v_out[2 * i] = s.verts[i].x;
    v_out[2 * i + 1] = s.verts[i].y;
  }
  *sse0 = static_cast<T>(out.sse0);
  *sse1 = static_cast<T>(out.sse);
  *frac = static_cast<T>(out.frac);
  *result = out.converged ? 0 : 1;
  *n_steps = static_cast<int32_t>(out.steps);
}

ffi::Error bad(const char* what) { return ffi::Error(ffi::ErrorCode::kInvalidArgument, what); }

template <ffi::DataType DT>
ffi::Error PolylinePlus(ffi::Buffer<DT> vertices, ffi::Buffer<ffi::S32> successor,
                        ffi::Buffer<ffi::PRED> active, ffi::Buffer<DT> origin,
                        ffi::Buffer<DT> directions, ffi::Buffer<DT> ranges,
                        ffi::Buffer<ffi::PRED> reflected, ffi::Buffer<DT> z,
                        ffi::Buffer<DT> sigma, ffi::Buffer<DT> pattern, int64_t max_steps,
                        int64_t rounds, int64_t n_params, int64_t fma,
                        ffi::ResultBuffer<DT> v_out, ffi::ResultBuffer<DT> sse0_out,
                        ffi::ResultBuffer<DT> sse1_out, ffi::ResultBuffer<DT> frac_out,
                        ffi::ResultBuffer<ffi::S32> result_out,
                        ffi::ResultBuffer<ffi::S32> steps_out) {
  using T = ffi::NativeType<DT>;
  auto vd = vertices.dimensions();
  if (vd.size() != 3 || vd[2] != 2) return bad("vertices must be [scans K 2]");
  const int64_t N = vd[0], K = vd[1];
  auto cnt = [](const auto& b) { return static_cast<int64_t>(b.element_count()); };
  if (cnt(successor) != N * K || cnt(active) != N * K || cnt(ranges) != N * K ||
      cnt(reflected) != N * K)
    return bad("successor, active, ranges and reflected must be [scans K]");
  if (cnt(origin) != N * 2) return bad("origin must be [scans 2]");
  if (cnt(directions) != N * K * 2) return bad("directions must be [scans K 2]");
  if (max_steps < 1 || rounds < 1) return bad("max_steps and rounds must be >= 1");
  const int64_t R = cnt(sigma), P = cnt(pattern);
  if (n_params < 1 || cnt(z) != rounds * R * n_params * 2)
    return bad("z must be [rounds restarts n_params 2] with restarts = len(sigma)");
  const int32_t* succ = successor.typed_data();
  const bool* act = active.typed_data();
  for (int64_t i = 0; i < N * K; ++i) {
    if (act[i] && (succ[i] >= K || (succ[i] >= 0 && !act[(i / K) * K + succ[i]])))
      return bad("successor of an active slot must be -1 or an active slot of its scan");
  }
  for (int64_t s = 0; s < N; ++s) {
    int64_t na = 0;
    for (int64_t i = 0; i < K; ++i) na += act[s * K + i] ? 1 : 0;
    if (na > n_params) return bad("n_params is smaller than a scan's active vertex count");
  }
  const bool use_fma = fma < 0 ? cpu_has_fma() : fma > 0;
  for (int64_t s = 0; s < N; ++s) {
    auto f = use_fma ? run_scan<T, true> : run_scan<T, false>;
    f(static_cast<int>(K), static_cast<int>(n_params), static_cast<int>(max_steps),
      static_cast<int>(rounds), vertices.typed_data() + s * K * 2, succ + s * K, act + s * K,
      origin.typed_data() + s * 2, directions.typed_data() + s * K * 2,
      ranges.typed_data() + s * K, reflected.typed_data() + s * K, z.typed_data(),
      static_cast<int>(R), sigma.typed_data(), static_cast<int>(P), pattern.typed_data(),
      v_out->typed_data() + s * K * 2, sse0_out->typed_data() + s, sse1_out->typed_data() + s,
      frac_out->typed_data() + s, result_out->typed_data() + s, steps_out->typed_data() + s);
  }
  return ffi::Error::Success();
}

}  // namespace

#define LIDARJAX_PLUS(NAME, DT)                                      \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(NAME, (PolylinePlus<DT>),            \
                                ffi::Ffi::Bind()                     \
                                    .Arg<ffi::Buffer<DT>>()          \
                                    .Arg<ffi::Buffer<ffi::S32>>()    \
                                    .Arg<ffi::Buffer<ffi::PRED>>()   \
                                    .Arg<ffi::Buffer<DT>>()          \
                                    .Arg<ffi::Buffer<DT>>()          \
                                    .Arg<ffi::Buffer<DT>>()          \
                                    .Arg<ffi::Buffer<ffi::PRED>>()   \
                                    .Arg<ffi::Buffer<DT>>()          \
                                    .Arg<ffi::Buffer<DT>>()          \
                                    .Arg<ffi::Buffer<DT>>()          \
                                    .Attr<int64_t>("max_steps")      \
                                    .Attr<int64_t>("rounds")         \
                                    .Attr<int64_t>("n_params")       \
                                    .Attr<int64_t>("fma")            \
                                    .Ret<ffi::Buffer<DT>>()          \
                                    .Ret<ffi::Buffer<DT>>()          \
                                    .Ret<ffi::Buffer<DT>>()          \
                                    .Ret<ffi::Buffer<DT>>()          \
                                    .Ret<ffi::Buffer<ffi::S32>>()    \
                                    .Ret<ffi::Buffer<ffi::S32>>());

LIDARJAX_PLUS(LidarjaxPolylinePlusF32, ffi::F32)
LIDARJAX_PLUS(LidarjaxPolylinePlusF64, ffi::F64)
