// Steps that the spatial (adaptive_manifold_kernel.cpp) and the space-time
// (spacetime_kernel.cpp) CPU kernels share: both build the same tree of manifolds on the same
// low-resolution grid, so the root's masked route, the split, the children, the blur and the
// slice's normalisation are written once here. The numbered comments refer to the fixed choices
// listed at the top of torchmanifold/ops/_reference.py.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "ops/cpu/manifold_ops.h"
#include "ops/cpu/recursive_filter.h"
#include "ops/cpu/workspace.h"

namespace torchmanifold {
namespace cpu {

// The filter's parameters, as the ops take them.
struct FilterOptions {
  double sigma_s, sigma_r;
  int64_t tree_height, power_iterations;
  bool adjust_outliers;
};

// 1 / sigma_r^2, clamped to the type's largest value (a tiny sigma_r would overflow it).
template <typename T>
T inverse_square(double sigma_r) {
  const double fmax = static_cast<double>(std::numeric_limits<T>::max());
  const double r2 = sigma_r * sigma_r;
  return static_cast<T>(r2 > 0 ? std::min(1.0 / r2, fmax) : fmax);
}

// A manifold of the tree: heap id (children 2 id, 2 id + 1) and its low-res (D, Hl, Wl) map.
template <typename T>
struct ManifoldNode {
  int64_t id;
  Scratch<T> eta;
};

// A level's n nodes' slice weights w ((n, H, W)) and blurred [P, P0] ((n, C + 1, Hl, Wl)), kept
// for the last pass's slices.
template <typename T>
struct LevelSlices {
  int64_t n = 0;
  Scratch<T> w, P;
};

// A RowUpsampler per low-res plane stack in `low` (each `planes` planes of (hl, wl)), for a task's
// rows of a (h, w) image.
template <typename T>
std::vector<RowUpsampler<T>> make_upsamplers(const std::vector<const T*>& low, int64_t planes, int64_t hl,
                                             int64_t wl, int64_t w, const Taps<T>& ty, const Taps<T>& tx) {
  std::vector<RowUpsampler<T>> ups;
  ups.reserve(low.size());
  for (const T* l : low) {
    ups.emplace_back(planes, hl, wl, w, ty, tx);
    ups.back().reset(l);
  }
  return ups;
}

// Per level, a RowUpsampler per node over its blurred [P, P0] (C + 1 planes), for a task's rows.
template <typename T>
std::vector<std::vector<RowUpsampler<T>>> slice_upsamplers(const std::vector<LevelSlices<T>>& levels, int64_t C,
                                                           int64_t hl, int64_t wl, int64_t w, const Taps<T>& ty,
                                                           const Taps<T>& tx) {
  std::vector<std::vector<RowUpsampler<T>>> ups;
  for (const LevelSlices<T>& l : levels) {
    std::vector<const T*> blurred(l.n);
    for (int64_t k = 0; k < l.n; ++k) blurred[k] = l.P.data() + k * (C + 1) * hl * wl;
    ups.push_back(make_upsamplers(blurred, C + 1, hl, wl, w, ty, tx));
  }
  return ups;
}

// `planes` planes (stride nl) of block sums, the block row starting at p and covering `rows`
// full-res rows of width w -> means over the pixels that exist in each block (a partial edge
// block averages fewer, as avg_pool2d with ceil_mode).
template <typename T>
void to_block_means(T* p, int64_t planes, int64_t rows, int64_t df, int64_t w, int64_t wl, int64_t nl) {
  const int64_t full = rows * df;
  const T last = static_cast<T>(rows * (w - (wl - 1) * df));  // the last block may be partial
  // A power-of-2 count (every full block row) divides as its reciprocal multiplies, exactly, and
  // a vector multiply is several times cheaper than a divide.
  const bool pow2 = (full & (full - 1)) == 0;
  const T inv = T(1) / static_cast<T>(full);
  for (int64_t c = 0; c < planes; ++c) {
    T* q = p + c * nl;
    if (pow2)
      for (int64_t bj = 0; bj + 1 < wl; ++bj) q[bj] *= inv;
    else
      for (int64_t bj = 0; bj + 1 < wl; ++bj) q[bj] /= static_cast<T>(full);
    q[wl - 1] /= last;
  }
}

// 6. The masked route's root manifold from acc = [h(down(m g0)) planes, h(down(m))] ((D + 1, nl)):
// eta = their ratio, 0 where nothing is valid; then gs ((D, h, w)): the guide g where the mask m
// ((h, w)) is set, else the root manifold upsampled (an invalid guide pixel sits on it).
template <typename T>
void masked_root_and_guide(const T* acc, const T* g, const uint8_t* m, int64_t D, int64_t h, int64_t w,
                           int64_t hl, int64_t wl, const Taps<T>& ty, const Taps<T>& tx, T* eta, T* gs) {
  const int64_t nl = hl * wl, n = h * w;
  const T* den = acc + D * nl;
  for (int64_t d = 0; d < D; ++d)
    for (int64_t i = 0; i < nl; ++i) eta[d * nl + i] = den[i] > T(0) ? acc[d * nl + i] / den[i] : T(0);
  parallel_work(0, h, w * 3 * D, [&](int64_t b, int64_t e) {
    std::vector<T> tmp(wl), up(w);
    for (int64_t i = b; i < e; ++i)
      for (int64_t d = 0; d < D; ++d) {
        upsample_row(eta + d * nl, 1, hl, wl, i, w, ty, tx, tmp.data(), up.data());
        const uint8_t* mr = m + i * w;
        const T* src = g + d * n + i * w;
        T* dst = gs + d * n + i * w;
        for (int64_t j = 0; j < w; ++j) dst[j] = mr[j] ? src[j] : up[j];
      }
  });
}

// 3. The per-channel offset c = the point of [lo, hi] nearest 0 from `parts` partial minima / maxima
// ((parts, C) each), 0 where that is not finite (no splat sample).
template <typename T>
std::vector<T> channel_centres(const std::vector<T>& lo, const std::vector<T>& hi, int64_t parts, int64_t C) {
  std::vector<T> c(C, T(0));
  for (int64_t k = 0; k < C; ++k) {
    T l = std::numeric_limits<T>::infinity(), h = -l;
    for (int64_t p = 0; p < parts; ++p) l = std::min(l, lo[p * C + k]), h = std::max(h, hi[p * C + k]);
    const T near = std::min(std::max(T(0), l), h);
    c[k] = std::isfinite(near) ? near : T(0);
  }
  return c;
}

// 8. A node's split direction from `groups` partial sums of the upper triangle of M = sum r r^T
// ((groups, D (D + 1) / 2), added in order): power iteration u = M v, v = u / |u| from
// ones / sqrt(D); the channel of largest spread (first on ties) when |u| <= eps trace(M) or |u| is
// not finite at any step. ones / sqrt(D) without iterations (mpart is not read then).
template <typename T>
std::vector<T> split_direction(const double* mpart, int64_t groups, int64_t D, int64_t iterations) {
  const int64_t msize = D * (D + 1) / 2;
  std::vector<double> v(D, 1.0 / std::sqrt(static_cast<double>(D)));
  std::vector<T> out(D, T(0));
  if (iterations <= 0) {
    for (int64_t d = 0; d < D; ++d) out[d] = static_cast<T>(v[d]);
    return out;
  }
  std::vector<double> M(D * D, 0.0);
  {
    std::vector<double> tri(msize, 0.0);
    for (int64_t g = 0; g < groups; ++g)
      for (int64_t k = 0; k < msize; ++k) tri[k] += mpart[g * msize + k];
    int64_t k = 0;
    for (int64_t a = 0; a < D; ++a)
      for (int64_t b = a; b < D; ++b, ++k) M[a * D + b] = M[b * D + a] = tri[k];
  }
  double trace = 0;
  for (int64_t d = 0; d < D; ++d) trace += M[d * D + d];
  const double eps = static_cast<double>(std::numeric_limits<T>::epsilon());
  bool collapsed = false;
  std::vector<double> u(D);
  for (int64_t it = 0; it < iterations; ++it) {
    double norm = 0;
    for (int64_t a = 0; a < D; ++a) {
      double s = 0;
      for (int64_t b = 0; b < D; ++b) s += M[a * D + b] * v[b];
      u[a] = s;
      norm += s * s;
    }
    norm = std::sqrt(norm);
    const bool bad = !(norm > eps * trace) || !std::isfinite(norm);
    collapsed = collapsed || bad;
    if (!bad)
      for (int64_t d = 0; d < D; ++d) v[d] = u[d] / norm;
  }
  if (collapsed) {
    int64_t k = 0;
    for (int64_t d = 1; d < D; ++d)
      if (M[d * D + d] > M[k * D + k]) k = d;
    out[k] = T(1);
  } else {
    for (int64_t d = 0; d < D; ++d) out[d] = static_cast<T>(v[d]);
  }
  return out;
}

// 7. min D over the tree so far at a row: the root's distances start it.
template <typename T>
void update_min_distance(int64_t depth, const T* dist, T* mind, int64_t w) {
  if (depth == 0)
    std::copy(dist, dist + w, mind);
  else
    for (int64_t j = 0; j < w; ++j) mind[j] = std::min(mind[j], dist[j]);
}

// Whether pixel j of row `lr` (labels) / `mg` (the guide mask's row, nullptr when every guide
// sample is finite) is in the cluster `id`. The root (depth 0) holds every pixel with a finite
// guide; its labels are not stored.
inline bool in_cluster(int64_t depth, const int32_t* lr, const uint8_t* mg, int32_t id, int64_t j) {
  return depth == 0 ? !mg || mg[j] != 0 : lr[j] == id;
}

// 8. The sides of node `id`'s cluster on a row of w pixels (lr: its labels, nullptr below height 3;
// mg: as in_cluster; wr: its slice weights): on entry t0 holds the projection v . r, on exit
// t0 = theta = 1 - w on the - side (0 elsewhere) and t1 on the + side; with keep_labels the
// pixels' labels become their child's id.
template <typename T>
void split_sides(int64_t depth, int32_t id, bool keep_labels, int32_t* lr, const uint8_t* mg, const T* wr,
                 T* t0, T* t1, int64_t w) {
  if (depth == 0 && !mg && !keep_labels) {
    // every pixel is in the root's cluster and no labels are kept (height 2): the same sides
    // without branches, so that the loop vectorises
    for (int64_t j = 0; j < w; ++j) {
      const bool plus = t0[j] >= T(0);
      const T theta = T(1) - wr[j];
      t1[j] = plus ? theta : T(0);
      t0[j] = plus ? T(0) : theta;
    }
    return;
  }
  for (int64_t j = 0; j < w; ++j) {
    const bool in = in_cluster(depth, lr, mg, id, j);
    const bool plus = t0[j] >= T(0);
    const T theta = T(1) - wr[j];
    t0[j] = in && !plus ? theta : T(0);
    t1[j] = in && plus ? theta : T(0);
    if (!keep_labels) continue;
    if (in) lr[j] = 2 * id + (plus ? 1 : 0);
    else if (depth == 0) lr[j] = 0;  // label 0 is never a node
  }
}

// 7. Per node of a level: the low-res domain-transform blur of its `planes` planes of P
// ((n, planes, hl, wl)) steered by its manifold.
template <typename T>
void blur_level(const std::vector<ManifoldNode<T>>& level, T* P, int64_t planes, int64_t D, int64_t hl,
                int64_t wl, double ss_low, double sr_low) {
  const int64_t nl = hl * wl;
  for (size_t k = 0; k < level.size(); ++k) {
    std::vector<T> ah(nl), av(nl);
    domain_transform_coefficients(level[k].eta.data(), D, hl, wl, ss_low, sr_low, ah.data(), av.data());
    domain_transform_planes(P + k * planes * nl, planes, hl, wl, ah.data(), av.data());
  }
}

// 8. The children from their sums Q ([node][side][D + 1][hl wl]: down(theta gs) planes, then
// down(theta)): eta = h(down(theta gs)) / h(down(theta)), the parent's manifold where 0/0. A
// child with no mass is pruned (theta >= 0, so any positive block mean means a positive sum).
// Q is low-passed in place.
template <typename T>
std::vector<ManifoldNode<T>> children(const std::vector<ManifoldNode<T>>& level, Scratch<T>& Q, int64_t D,
                                      int64_t hl, int64_t wl, double ss_low) {
  const int64_t n = static_cast<int64_t>(level.size());
  const int64_t nl = hl * wl, qside = (D + 1) * nl;
  std::vector<uint8_t> alive(2 * n);
  for (int64_t c = 0; c < 2 * n; ++c) {
    const T* q0 = Q.data() + c * qside + D * nl;
    alive[c] = std::any_of(q0, q0 + nl, [](T x) { return x > T(0); });
  }
  lowpass_planes(Q.data(), 2 * n * (D + 1), hl, wl, ss_low);  // all children in one go
  std::vector<ManifoldNode<T>> next;
  std::vector<int64_t> made;  // the children's indices in Q
  for (int64_t c = 0; c < 2 * n; ++c)
    if (alive[c]) {
      made.push_back(c);
      next.push_back({2 * level[c / 2].id + c % 2, Scratch<T>()});
      next.back().eta.resize(D * nl);
    }
  const int64_t m = static_cast<int64_t>(made.size());
  parallel_work(0, m * D, 2 * nl, [&](int64_t b, int64_t e) {
    for (int64_t t = b; t < e; ++t) {
      const int64_t c = made[t / D], d = t % D;
      const T* __restrict q = Q.data() + c * qside + d * nl;
      const T* __restrict q0 = Q.data() + c * qside + D * nl;
      const T* __restrict parent = level[c / 2].eta.data() + d * nl;
      T* __restrict eta = next[t / D].eta.data() + d * nl;
      for (int64_t i = 0; i < nl; ++i) {
        // divided unconditionally (by 1 in the unused lane) so the loop vectorises: a division
        // under a condition may not be speculated
        const T ratio = q[i] / (q0[i] > T(0) ? q0[i] : T(1));
        eta[i] = q0[i] > T(0) ? ratio : parent[i];
      }
    }
  });
  return next;
}

// S += w up(blur [P, P0]) at full-res row i for one node: S in the C planes (stride n) from s,
// S0 in s0 (w); with `first` the node's slice starts them instead.
template <typename T>
void slice_row(RowUpsampler<T>& up, const T* wr, int64_t i, bool first, T* s, int64_t C, int64_t n, int64_t w,
               T* s0) {
  const T fy = up.seek(i);
  for (int64_t c = 0; c <= C; ++c) {
    T* sc = c < C ? s + c * n : s0;
    const T* b = up.base(c);
    const T* db = up.delta(c);
    if (first)
      for (int64_t j = 0; j < w; ++j) sc[j] = wr[j] * (b[j] + fy * db[j]);
    else
      for (int64_t j = 0; j < w; ++j) sc[j] += wr[j] * (b[j] + fy * db[j]);
  }
}

// Below tiny/eps, S and S0 are sums of subnormal terms with absolute rounding: their ratio is no
// longer a weighted mean of the samples, so such pixels take the fallback (as where S0 == 0).
template <typename T>
T s0_floor() {
  return std::numeric_limits<T>::min() / std::numeric_limits<T>::epsilon();
}

// Whether every S0 of a row (s0, w) clears s0_floor: then no fallback is needed.
template <typename T>
bool all_above_floor(const T* s0, int64_t w) {
  const T floor = s0_floor<T>();
  int64_t low = 0;
  for (int64_t j = 0; j < w; ++j) low += !(s0[j] > floor);
  return low == 0;
}

// 9., 10. A row in place: the C planes (stride n) from s hold S, out = c + S / S0 where S0 clears
// the floor, else the fallback (planes of stride fb_stride from fb; nullptr: every S0 clears it),
// then pulled towards the fallback by alpha (w; nullptr: no pull). Branch-free inner loops so they
// vectorise.
template <typename T>
void normalise_row(T* s, int64_t n, const T* s0, const T* fb, int64_t fb_stride, const T* alpha,
                   const std::vector<T>& c, int64_t C, int64_t w) {
  const T floor = s0_floor<T>();
  for (int64_t k = 0; k < C; ++k) {
    T* out = s + k * n;
    const T cc = c[k];
    if (!fb) {
      for (int64_t j = 0; j < w; ++j) out[j] = cc + out[j] / s0[j];
      continue;
    }
    const T* f = fb + k * fb_stride;
    for (int64_t j = 0; j < w; ++j) {
      // divided unconditionally (by 1 in the unused lane) so the loop vectorises
      const T mean = cc + out[j] / (s0[j] > floor ? s0[j] : T(1));
      out[j] = s0[j] > floor ? mean : f[j];
    }
    if (alpha)
      for (int64_t j = 0; j < w; ++j) out[j] = f[j] + alpha[j] * (out[j] - f[j]);
  }
}

// 10. The outlier pull's alpha = exp(-min D / (2 sigma_r^2)) at a row, 1 where `has` (w) is not set.
template <typename T>
void outlier_alpha_row(const T* mind, T half_inv_r2, const uint8_t* has, T* alpha, int64_t w) {
  exp_neg_scaled_row(mind, half_inv_r2, alpha, w);
  for (int64_t j = 0; j < w; ++j) alpha[j] = has[j] ? alpha[j] : T(1);
}

}  // namespace cpu
}  // namespace torchmanifold
