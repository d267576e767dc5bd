// First-order recursive filters on planar images, in place:
//  * lowpass_*: h(x; sigma) with one constant coefficient a = exp(-sqrt2 / sigma), the low-pass
//    that builds the manifolds (it reproduces constants exactly);
//  * domain_transform_*: the edge-aware blur whose coefficient between two neighbours depends on
//    how far apart the manifold is there (one coefficient array shared by every channel).
// Each filters rows (forward then backward), then columns (forward then backward).
// Work is split over lines (rows) or column strips; every output element is computed by the same
// sequence of operations whatever the split, so results do not depend on the thread count.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <type_traits>
#include <vector>

#include "ops/adaptive_manifold_common.h"  // downsample_factor
#include "ops/cpu/manifold_ops.h"  // exp_neg_scaled_row

#if defined(__AVX2__)
#include <immintrin.h>
#endif

namespace torchmanifold {
namespace cpu {

// Column strips are this wide: unit-stride inner loops that vectorise, a strip of a 1000-row
// plane stays in L2 for the backward sweep.
constexpr int64_t kStrip = 64;

// A task gets at least kGrainWork elementary operations (tens of microseconds), the grain
// at::parallel_for's own users aim at (grain ~ 32768 / work per item): smaller tasks cost more to
// hand out than they save. Every parallel loop states its work per item as a rough count of
// operations per element (loads, multiply-adds, compares), which only sets this grain.
constexpr int64_t kGrainWork = 32768;

inline int64_t grain_for(int64_t work_per_item) {
  return std::max<int64_t>(1, kGrainWork / std::max<int64_t>(1, work_per_item));
}

// Below this much work (~512K elementary operations, a few hundred microseconds) a loop runs on
// the calling thread: a parallel region costs tens of microseconds when the cores are free, more
// when they are not. (The progressive pipeline runs torch on one thread by default, see cli.py.)
constexpr int64_t kSerialWork = int64_t(1) << 19;

// [begin, end) over the threads with grain from the work per item, except that little total work
// runs on the calling thread: with more threads than free cores one parallel region can cost
// milliseconds, more than a 64x64 image's whole filter. The range is handed out in about
// kChunksPerThread chunks per thread, in order, to whichever thread is free: on a shared machine a
// core taken away for a while then delays one chunk, not a whole static half of the pass.
// Callers' results never depend on the split.
constexpr int64_t kChunksPerThread = 8;

template <typename F>
inline void parallel_work(int64_t begin, int64_t end, int64_t work_per_item, const F& fn) {
  if (end <= begin) return;
  const int64_t n = end - begin;
  const int64_t threads = at::get_num_threads();
  if (n * std::max<int64_t>(1, work_per_item) < kSerialWork || threads <= 1 || at::in_parallel_region()) {
    fn(begin, end);
    return;
  }
  const int64_t chunk =
      std::max(grain_for(work_per_item), (n + threads * kChunksPerThread - 1) / (threads * kChunksPerThread));
  std::atomic<int64_t> next{begin};
  at::parallel_for(0, threads, 1, [&](int64_t, int64_t) {
    for (int64_t b = next.fetch_add(chunk); b < end; b = next.fetch_add(chunk))
      fn(b, std::min(end, b + chunk));
  });
}

// fn(item) for every item in [0, items), in order: side by side, a whole item per thread, where there
// are at least as many items as threads (an item's own loops then run on its thread: parallel_work
// inside a parallel region runs serially); otherwise one after another, each over every thread. One
// image's passes scale poorly on few cores (the filter 1.35x on 2: short passes, many syncs) and
// independent images nearly 2x; an item's result never depends on the thread that ran it. Callers
// order the items costliest first, so the queue ends with short ones.
template <typename F>
inline void for_each_image(int64_t items, const F& fn) {
  const int64_t threads = at::get_num_threads();
  if (threads >= 2 && items >= threads && !at::in_parallel_region()) {
    std::atomic<int64_t> next{0};
    at::parallel_for(0, threads, 1, [&](int64_t, int64_t) {
      for (int64_t item = next.fetch_add(1); item < items; item = next.fetch_add(1)) fn(item);
    });
    return;
  }
  for (int64_t item = 0; item < items; ++item) fn(item);
}

// The tree height of image k: tree_heights holds one height for all images or one per image.
inline int64_t height_of(c10::ArrayRef<int64_t> tree_heights, size_t k) {
  return tree_heights[tree_heights.size() == 1 ? 0 : k];
}

// tree_heights holds one height or one per sigma (op names the caller in the message).
inline void check_height_count(const char* op, c10::ArrayRef<int64_t> tree_heights, size_t sigmas) {
  TORCH_CHECK_VALUE(tree_heights.size() == 1 || tree_heights.size() == sigmas, op,
                    ": tree_height must hold one height or one per sigma (", sigmas, "), got ",
                    tree_heights.size());
}

// The indices of the K images (spatial sigma sigma_s[k], tree height height_of(tree_heights, k)),
// each one already checked, the costliest first, so that for_each_image's queue ends with cheap
// images. An image costs about its nodes, 2^height - 1, times a node's full-resolution passes plus its
// blur on the low-resolution grid, which at df = 1 measured about kLowResWork times the former (the
// op at 2 and 4 px, 16-channel 256x256 images: 48 against 19 ms) and shrinks as 1 / df^2.
constexpr double kLowResWork = 4.0;

inline std::vector<int64_t> costliest_first(c10::ArrayRef<double> sigma_s,
                                            c10::ArrayRef<int64_t> tree_heights, double sigma_r) {
  std::vector<int64_t> order(sigma_s.size());
  std::vector<double> cost(sigma_s.size());
  for (size_t k = 0; k < order.size(); ++k) {
    order[k] = static_cast<int64_t>(k);
    const double df = static_cast<double>(downsample_factor(sigma_s[k], sigma_r));
    const double nodes = std::ldexp(1.0, static_cast<int>(height_of(tree_heights, k))) - 1.0;
    cost[k] = nodes * (1.0 + kLowResWork / (df * df));
  }
  std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return cost[a] > cost[b]; });
  return order;
}

// ---- constant-coefficient low-pass h ---------------------------------------------------------

// One step of the recursion, x + a (prev - x). FMA builds fuse it explicitly, so the scalar rows
// and the vector blocks of lowpass_rows give the same bits whichever rows a thread gets.
template <typename T>
inline T recursion_step(T x, T prev, T a) {
#if defined(__FMA__)
  return std::fma(a, prev - x, x);
#else
  return x + a * (prev - x);
#endif
}

template <typename T>
inline void lowpass_row(T* y, int64_t n, T a) {
  for (int64_t j = 1; j < n; ++j) y[j] = recursion_step(y[j], y[j - 1], a);
  for (int64_t j = n - 2; j >= 0; --j) y[j] = recursion_step(y[j], y[j + 1], a);
}

#if defined(__AVX2__) && defined(__FMA__)
// In-register transpose of an 8 x 8 float block.
inline void transpose8(__m256* v) {
  __m256 t[8], u[8];
  for (int k = 0; k < 8; k += 2) {
    t[k] = _mm256_unpacklo_ps(v[k], v[k + 1]);
    t[k + 1] = _mm256_unpackhi_ps(v[k], v[k + 1]);
  }
  for (int k = 0; k < 8; k += 4) {
    u[k] = _mm256_shuffle_ps(t[k], t[k + 2], _MM_SHUFFLE(1, 0, 1, 0));
    u[k + 1] = _mm256_shuffle_ps(t[k], t[k + 2], _MM_SHUFFLE(3, 2, 3, 2));
    u[k + 2] = _mm256_shuffle_ps(t[k + 1], t[k + 3], _MM_SHUFFLE(1, 0, 1, 0));
    u[k + 3] = _mm256_shuffle_ps(t[k + 1], t[k + 3], _MM_SHUFFLE(3, 2, 3, 2));
  }
  for (int k = 0; k < 4; ++k) {
    v[k] = _mm256_permute2f128_ps(u[k], u[k + 4], 0x20);
    v[k + 4] = _mm256_permute2f128_ps(u[k], u[k + 4], 0x31);
  }
}

// The coefficients of recursion_rows. A constant one (the low-pass):
struct ConstantCoefficient {
  __m256 v;
  float a;
  explicit ConstantCoefficient(float a_) : v(_mm256_set1_ps(a_)), a(a_) {}
  void load(int64_t) {}
  __m256 operator[](int) const { return v; }
  float at(int, int64_t) const { return a; }
};

// One per element, from eight coefficient rows (the domain transform): load(j0) transposes the
// 8 x 8 block at column j0 so that [q] is column j0 + q across the eight rows.
struct RowCoefficients {
  const float* const* rows;
  __m256 c[8];
  explicit RowCoefficients(const float* const* r) : rows(r) {}
  void load(int64_t j0) {
    for (int k = 0; k < 8; ++k) c[k] = _mm256_loadu_ps(rows[k] + j0);
    transpose8(c);
  }
  __m256 operator[](int q) const { return c[q]; }
  float at(int k, int64_t j) const { return rows[k][j]; }
};

// kBlocks groups of eight float rows (y[8 b + k]: row k of group b, coefficients a[b]) of length n,
// forward then backward, one vector lane per row: 8 x 8 blocks are transposed so each column is
// one vector (the scalar version keeps 8 chains of scalar operations in flight); columns left over
// at the ends run the scalar steps. Column j steps towards j - 1 by coefficient j - 1, then
// towards j + 1 by coefficient j. Each step waits on the one before (subtract, then fused
// multiply-add), so two groups side by side keep twice the work in flight; a row's operations do
// not depend on its company, so any grouping gives the same bits.
template <int kBlocks, typename Coef>
inline void recursion_rows(float* const* y, int64_t n, Coef* a) {
  __m256 v[kBlocks][8];
  alignas(32) float prev[kBlocks][8];
  auto load = [&](int64_t j0) {
    for (int b = 0; b < kBlocks; ++b) {
      for (int k = 0; k < 8; ++k) v[b][k] = _mm256_loadu_ps(y[8 * b + k] + j0);
      transpose8(v[b]);
    }
  };
  auto store = [&](int64_t j0) {
    for (int b = 0; b < kBlocks; ++b) {
      transpose8(v[b]);
      for (int k = 0; k < 8; ++k) _mm256_storeu_ps(y[8 * b + k] + j0, v[b][k]);
    }
  };
  auto coefficients = [&](int64_t j0) {
    for (int b = 0; b < kBlocks; ++b) a[b].load(j0);
  };
  __m256 p[kBlocks];
  // forward: column 0 starts the recursion
  int64_t j = 1;
  for (int b = 0; b < kBlocks; ++b)
    for (int k = 0; k < 8; ++k) prev[b][k] = y[8 * b + k][0];
  if (n >= 8) {
    load(0);
    coefficients(0);
    for (int b = 0; b < kBlocks; ++b) p[b] = v[b][0];
    for (int c = 1; c < 8; ++c)
      for (int b = 0; b < kBlocks; ++b)
        v[b][c] = p[b] = _mm256_fmadd_ps(a[b][c - 1], _mm256_sub_ps(p[b], v[b][c]), v[b][c]);
    store(0);
    for (j = 8; j + 8 <= n; j += 8) {
      load(j);
      coefficients(j - 1);
      for (int c = 0; c < 8; ++c)
        for (int b = 0; b < kBlocks; ++b)
          v[b][c] = p[b] = _mm256_fmadd_ps(a[b][c], _mm256_sub_ps(p[b], v[b][c]), v[b][c]);
      store(j);
    }
    for (int b = 0; b < kBlocks; ++b) _mm256_store_ps(prev[b], p[b]);
  }
  for (; j < n; ++j)
    for (int b = 0; b < kBlocks; ++b)
      for (int k = 0; k < 8; ++k)
        y[8 * b + k][j] = prev[b][k] = recursion_step(y[8 * b + k][j], prev[b][k], a[b].at(k, j - 1));
  // backward: column n - 1 starts it
  j = n - 2;
  for (int b = 0; b < kBlocks; ++b)
    for (int k = 0; k < 8; ++k) prev[b][k] = y[8 * b + k][n - 1];
  if (n >= 8) {
    load(n - 8);
    coefficients(n - 8);
    for (int b = 0; b < kBlocks; ++b) p[b] = v[b][7];
    for (int c = 6; c >= 0; --c)
      for (int b = 0; b < kBlocks; ++b)
        v[b][c] = p[b] = _mm256_fmadd_ps(a[b][c], _mm256_sub_ps(p[b], v[b][c]), v[b][c]);
    store(n - 8);
    for (j = n - 16; j >= 0; j -= 8) {
      load(j);
      coefficients(j);
      for (int c = 7; c >= 0; --c)
        for (int b = 0; b < kBlocks; ++b)
          v[b][c] = p[b] = _mm256_fmadd_ps(a[b][c], _mm256_sub_ps(p[b], v[b][c]), v[b][c]);
      store(j);
    }
    j += 7;  // the last column not yet done
    for (int b = 0; b < kBlocks; ++b) _mm256_store_ps(prev[b], p[b]);
  }
  for (; j >= 0; --j)
    for (int b = 0; b < kBlocks; ++b)
      for (int k = 0; k < 8; ++k)
        y[8 * b + k][j] = prev[b][k] = recursion_step(y[8 * b + k][j], prev[b][k], a[b].at(k, j));
}
#endif

// Columns j in [j0, j1) of one (h, w) plane, down then up: row i steps towards row i - 1 by the
// coefficients coef(i - 1) (a row of w, or one value for every column), then towards row i + 1 by
// coef(i).
template <typename T, typename Coef>
inline void recursion_cols(T* p, int64_t h, int64_t w, int64_t j0, int64_t j1, const Coef& coef) {
  for (int64_t i = 1; i < h; ++i) {
    T* y = p + i * w;
    const T* prev = y - w;
    const auto a = coef(i - 1);
    for (int64_t j = j0; j < j1; ++j) y[j] += a[j] * (prev[j] - y[j]);
  }
  for (int64_t i = h - 2; i >= 0; --i) {
    T* y = p + i * w;
    const T* next = y + w;
    const auto a = coef(i);
    for (int64_t j = j0; j < j1; ++j) y[j] += a[j] * (next[j] - y[j]);
  }
}

// One coefficient for every element (the low-pass), indexable like a row of coefficients.
template <typename T>
struct Same {
  T a;
  T operator[](int64_t) const { return a; }
};

template <typename T>
inline void lowpass_cols(T* p, int64_t h, int64_t w, int64_t j0, int64_t j1, T a) {
  recursion_cols(p, h, w, j0, j1, [a](int64_t) { return Same<T>{a}; });
}

// fn(plane, j0, j1) over the kStrip-wide column strips of `planes` (h, w) planes, split over threads.
template <typename F>
inline void column_strips(int64_t planes, int64_t h, int64_t w, int64_t work_per_strip, const F& fn) {
  const int64_t strips = (w + kStrip - 1) / kStrip;
  parallel_work(0, planes * strips, work_per_strip, [&](int64_t b, int64_t e) {
    for (int64_t t = b; t < e; ++t) {
      const int64_t j0 = (t % strips) * kStrip;
      fn(t / strips, j0, std::min(w, j0 + kStrip));
    }
  });
}

// Rows [r0, r1) of a plane, eight at a time with the running value kept in a register: eight
// independent recursions keep the pipeline busy (one alone is latency bound). Same operations
// per element as lowpass_row, so the same bits.
template <typename T>
inline void lowpass_rows(T* p, int64_t r0, int64_t r1, int64_t w, T a) {
  constexpr int R = 8;
  int64_t r = r0;
#if defined(__AVX2__) && defined(__FMA__)
  if constexpr (std::is_same<T, float>::value) {
    ConstantCoefficient c[2] = {ConstantCoefficient(a), ConstantCoefficient(a)};
    for (; r + 2 * R <= r1; r += 2 * R) {
      float* y[2 * R];
      for (int k = 0; k < 2 * R; ++k) y[k] = p + (r + k) * w;
      recursion_rows<2>(y, w, c);
    }
    for (; r + R <= r1; r += R) {
      float* y[R];
      for (int k = 0; k < R; ++k) y[k] = p + (r + k) * w;
      recursion_rows<1>(y, w, c);
    }
  }
#endif
  for (; r + R <= r1; r += R) {
    T* y[R];
    T prev[R];
    for (int k = 0; k < R; ++k) y[k] = p + (r + k) * w, prev[k] = y[k][0];
    for (int64_t j = 1; j < w; ++j)
      for (int k = 0; k < R; ++k) y[k][j] = prev[k] = recursion_step(y[k][j], prev[k], a);
    for (int k = 0; k < R; ++k) prev[k] = y[k][w - 1];
    for (int64_t j = w - 2; j >= 0; --j)
      for (int k = 0; k < R; ++k) y[k][j] = prev[k] = recursion_step(y[k][j], prev[k], a);
  }
  for (; r < r1; ++r) lowpass_row(p + r * w, w, a);
}

// h on `planes` contiguous (h, w) planes, in place. With enough planes every task filters whole
// planes (rows, then columns while the plane is still in cache); otherwise lines and column
// strips are spread over the threads. Both give bitwise the same result.
// rows_done: the caller already ran the row pass (fused with producing the data).
template <typename T>
inline T lowpass_coefficient(double sigma) {
  return static_cast<T>(std::exp(-std::sqrt(2.0) / sigma));
}

template <typename T>
void lowpass_planes(T* data, int64_t planes, int64_t h, int64_t w, double sigma,
                    bool rows_done = false) {
  const T a = lowpass_coefficient<T>(sigma);
  if (planes >= 2 * at::get_num_threads()) {
    parallel_work(0, planes, 4 * h * w, [&](int64_t b, int64_t e) {
      for (int64_t pl = b; pl < e; ++pl) {
        T* p = data + pl * h * w;
        if (w > 1 && !rows_done) lowpass_rows(p, 0, h, w, a);
        if (h > 1) lowpass_cols(p, h, w, 0, w, a);
      }
    });
    return;
  }
  if (w > 1 && !rows_done) {
    parallel_work(0, planes * h, 2 * w, [&](int64_t b, int64_t e) {
      // split [b, e) at plane boundaries
      for (int64_t line = b; line < e;) {
        const int64_t pl = line / h, r0 = line % h, r1 = std::min(h, r0 + (e - line));
        lowpass_rows(data + pl * h * w, r0, r1, w, a);
        line += r1 - r0;
      }
    });
  }
  if (h > 1)
    column_strips(planes, h, w, 2 * h * kStrip, [&](int64_t plane, int64_t j0, int64_t j1) {
      lowpass_cols(data + plane * h * w, h, w, j0, j1, a);
    });
}

// ---- domain transform -----------------------------------------------------------------------

// Rows handled together: two groups of eight, what recursion_rows<2> filters at once (and a block of
// coefficient sums that stays in L1).
constexpr int64_t kRowBlock = 16;

// Coefficients steered by a manifold eta (d planes of (h, w)):
//   ah[i*w + j] links (i, j) and (i, j+1); av[i*w + j] links (i, j) and (i+1, j);
//   a = exp(-sqrt2/ss * sqrt(1 + (ss/sr)^2 |d eta|^2)).
template <typename T>
void domain_transform_coefficients(const T* eta, int64_t d, int64_t h, int64_t w, double ss,
                                   double sr, T* ah, T* av) {
  const int64_t plane = h * w;
  const T k = static_cast<T>((ss / sr) * (ss / sr));
  const T c = static_cast<T>(-std::sqrt(2.0) / ss);
  parallel_work(0, h, 4 * w * (d + 1), [&](int64_t b, int64_t e) {
    // Blocks of kRowBlock rows, channel by channel: one run of memory per channel, where a row at a time
    // read d short runs (d rows a plane apart) and stalled on them; the sums stay in L1.
    for (int64_t i0 = b; i0 < e; i0 += kRowBlock) {
      const int64_t i1 = std::min(e, i0 + kRowBlock);
      const int64_t iv = std::min(i1, h - 1);  // rows with a row below
      std::fill(ah + i0 * w, ah + i1 * w, T(0));
      std::fill(av + i0 * w, av + i1 * w, T(0));
      for (int64_t ch = 0; ch < d; ++ch) {
        const T* p = eta + ch * plane;
        for (int64_t i = i0; i < i1; ++i) {
          const T* row = p + i * w;
          T* rh = ah + i * w;
          for (int64_t j = 0; j + 1 < w; ++j) {
            const T dx = row[j + 1] - row[j];
            rh[j] += dx * dx;
          }
        }
        // the vertical differences of rows [i0, iv) are one contiguous run
        const T* __restrict top = p + i0 * w;
        T* __restrict rv = av + i0 * w;
        for (int64_t q = 0; q < (iv - i0) * w; ++q) {
          const T dy = top[q + w] - top[q];
          rv[q] += dy * dy;
        }
      }
      for (int64_t i = i0; i < i1; ++i) {
        T* rh = ah + i * w;
        T* rv = av + i * w;
        // a = exp(-(sqrt2/ss) sqrt(1 + k |d eta|^2)): the square roots in place, then the vector exp
        for (int64_t j = 0; j < w; ++j) {
          rh[j] = std::sqrt(T(1) + k * rh[j]);
          rv[j] = std::sqrt(T(1) + k * rv[j]);
        }
        exp_neg_scaled_row(rh, -c, rh, w);
        exp_neg_scaled_row(rv, -c, rv, w);
      }
    }
  });
}

// One row of the domain transform, forward then backward: y[j] steps towards y[j - 1] by a[j - 1],
// then towards y[j + 1] by a[j] (recursion_step, so recursion_rows gives the same bits).
template <typename T>
inline void domain_transform_row(T* y, const T* a, int64_t n) {
  for (int64_t j = 1; j < n; ++j) y[j] = recursion_step(y[j], y[j - 1], a[j - 1]);
  for (int64_t j = n - 2; j >= 0; --j) y[j] = recursion_step(y[j], y[j + 1], a[j]);
}

// Rows [r0, r1) of one plane with row coefficients ah ((h, w), row i for row i of every plane).
template <typename T>
inline void domain_transform_rows(T* p, int64_t r0, int64_t r1, int64_t w, const T* ah) {
  int64_t r = r0;
#if defined(__AVX2__) && defined(__FMA__)
  if constexpr (std::is_same<T, float>::value) {
    for (; r + kRowBlock <= r1; r += kRowBlock) {
      float* y[kRowBlock];
      const float* a[kRowBlock];
      for (int k = 0; k < kRowBlock; ++k) y[k] = p + (r + k) * w, a[k] = ah + (r + k) * w;
      RowCoefficients c[2] = {RowCoefficients(a), RowCoefficients(a + 8)};
      recursion_rows<2>(y, w, c);
    }
    for (; r + 8 <= r1; r += 8) {
      float* y[8];
      const float* a[8];
      for (int k = 0; k < 8; ++k) y[k] = p + (r + k) * w, a[k] = ah + (r + k) * w;
      RowCoefficients c(a);
      recursion_rows<1>(y, w, &c);
    }
  }
#endif
  for (; r < r1; ++r) domain_transform_row(p + r * w, ah + r * w, w);
}

// Blur `planes` (h, w) planes in place with coefficients from domain_transform_coefficients.
template <typename T>
void domain_transform_planes(T* data, int64_t planes, int64_t h, int64_t w, const T* ah,
                             const T* av) {
  if (w > 1) {
    // tasks of up to kRowBlock rows of one plane, so the vector blocks see whole row groups wherever
    // the split falls
    const int64_t groups = (h + kRowBlock - 1) / kRowBlock;
    parallel_work(0, planes * groups, 48 * w, [&](int64_t b, int64_t e) {
      for (int64_t t = b; t < e; ++t) {
        const int64_t plane = t / groups, r0 = (t % groups) * kRowBlock, r1 = std::min(h, r0 + kRowBlock);
        domain_transform_rows(data + plane * h * w, r0, r1, w, ah);
      }
    });
  }
  if (h > 1)
    column_strips(planes, h, w, 3 * h * kStrip, [&](int64_t plane, int64_t j0, int64_t j1) {
      recursion_cols(data + plane * h * w, h, w, j0, j1, [av, w](int64_t i) { return av + i * w; });
    });
}

}  // namespace cpu
}  // namespace torchmanifold
