// Resampling between the full-resolution image and the low-resolution grid the manifolds live
// on: area (box) downsampling by df and bilinear upsampling at pixel centres
// (align_corners=False, edges clamped), computed a full-resolution row at a time.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

#if defined(__SSE2__)
#include <emmintrin.h>
#include <xmmintrin.h>
#endif
#if defined(__AVX2__)
#include <immintrin.h>
#endif

namespace torchmanifold {
namespace cpu {

// exp(x) for x <= 0 without a libm call, so the weight loops vectorise: x = n ln2 + r,
// |r| <= ln2/2, Taylor polynomial in r (degree 7 for float, 13 for double: the first terms below
// their epsilon), times 2^n built in the exponent bits; ln2 is split in a high part exact in the
// type and a low part (Cody-Waite) so n ln2 subtracts without rounding. Relative error ~1e-7
// (float) / ~1e-16 (double). Below -87 (float) / -708 (double) the result would be below the
// smallest normal (e^-87.3 / e^-708.4): it is exactly 0 there, and x is clamped just below the
// threshold first so that 2^n stays a normal number in the unused lane.
inline float exp_nonpositive(float x) {
  x = x < -87.0f ? -87.5f : x;
  const float shifter = 12582912.0f;  // 1.5 * 2^23: rounds to nearest integer in the low bits
  const float t = x * 1.44269504088896341f + shifter;
  const float n = t - shifter;
  const float r = (x - n * 0.693145751953125f) - n * 1.42860682030941723212e-6f;
  float p = 1.0f / 5040.0f;
  p = p * r + 1.0f / 720.0f;
  p = p * r + 1.0f / 120.0f;
  p = p * r + 1.0f / 24.0f;
  p = p * r + 1.0f / 6.0f;
  p = p * r + 0.5f;
  p = p * r + 1.0f;
  p = p * r + 1.0f;
  int32_t ti;
  std::memcpy(&ti, &t, sizeof ti);
  const int32_t bits = (ti - 0x4B400000 + 127) << 23;  // (n + 127) << 23
  float scale;
  std::memcpy(&scale, &bits, sizeof scale);
  return x < -87.0f ? 0.0f : p * scale;
}

// out[j] = exp_nonpositive(-x[j] * k) over a row, with the operations of the scalar version on
// 8-float GCC vectors: the scalar one does not auto-vectorise (its bit casts). AVX builds use one
// register, SSE ones two; about 0.5 ms per megapixel on one core.
inline void exp_neg_scaled_row(const float* x, float k, float* out, int64_t n) {
  typedef float v8f __attribute__((vector_size(32)));
  typedef int32_t v8i __attribute__((vector_size(32)));
  // unaligned views for the loads and stores: a memcpy into a v8f went through the stack in two
  // halves, and the stalled store forwarding made this loop ~100 cycles per 8 floats
  typedef float v8f_u __attribute__((vector_size(32), aligned(4), may_alias));
  int64_t j = 0;
  for (; j + 8 <= n; j += 8) {
    v8f v = *reinterpret_cast<const v8f_u*>(x + j);
    v = -v * k;
    const v8i under = v < -87.0f;
    v = under ? v8f{} - 87.5f : v;
    const v8f t = v * 1.44269504088896341f + 12582912.0f;
    const v8f nn = t - 12582912.0f;
    const v8f r = (v - nn * 0.693145751953125f) - nn * 1.42860682030941723212e-6f;
    v8f p = r * (1.0f / 5040.0f) + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    const v8i bits = (((v8i)t) - 0x4B400000 + 127) << 23;
    v8f e = p * (v8f)bits;
    e = under ? v8f{} : e;
    *reinterpret_cast<v8f_u*>(out + j) = e;
  }
  for (; j < n; ++j) out[j] = exp_nonpositive(-x[j] * k);
}

inline double exp_nonpositive(double x) {
  x = x < -708.0 ? -708.5 : x;
  const double shifter = 6755399441055744.0;  // 1.5 * 2^52
  const double t = x * 1.4426950408889634074 + shifter;
  const double n = t - shifter;
  const double r = (x - n * 0.6931471805598903) - n * 5.497923018708371e-14;
  double p = 1.0 / 6227020800.0;
  p = p * r + 1.0 / 479001600.0;
  p = p * r + 1.0 / 39916800.0;
  p = p * r + 1.0 / 3628800.0;
  p = p * r + 1.0 / 362880.0;
  p = p * r + 1.0 / 40320.0;
  p = p * r + 1.0 / 5040.0;
  p = p * r + 1.0 / 720.0;
  p = p * r + 1.0 / 120.0;
  p = p * r + 1.0 / 24.0;
  p = p * r + 1.0 / 6.0;
  p = p * r + 0.5;
  p = p * r + 1.0;
  p = p * r + 1.0;
  int64_t ti;
  std::memcpy(&ti, &t, sizeof ti);
  const int64_t bits = (ti - 0x4338000000000000LL + 1023) << 52;
  double scale;
  std::memcpy(&scale, &bits, sizeof scale);
  return x < -708.0 ? 0.0 : p * scale;
}

inline void exp_neg_scaled_row(const double* x, double k, double* out, int64_t n) {
  for (int64_t j = 0; j < n; ++j) out[j] = exp_nonpositive(-x[j] * k);
}

// Whether x[0..n) are all finite: x - x is 0 for finite x and NaN otherwise, summed in 8 lanes so
// the loop vectorises (one in-order sum would be a serial chain of adds).
template <typename T>
inline bool all_finite(const T* x, int64_t n) {
  constexpr int L = 8;
  T bad[L] = {};
  int64_t j = 0;
  for (; j + L <= n; j += L)
    for (int l = 0; l < L; ++l) bad[l] += x[j + l] - x[j + l];
  for (; j < n; ++j) bad[0] += x[j] - x[j];
  bool ok = true;
  for (int l = 0; l < L; ++l) ok = ok && bad[l] == T(0);
  return ok;
}

// lo = min(lo, x[0..n)), hi = max(hi, x[0..n)) for finite x, in 32-byte GCC vector lanes (min and
// max are exact in any order; the lane arrays of a plain loop did not vectorise).
template <typename T>
inline void min_max(const T* x, int64_t n, T& lo, T& hi) {
  typedef T vec __attribute__((vector_size(32)));
  typedef T vec_u __attribute__((vector_size(32), aligned(sizeof(T)), may_alias));  // see exp_neg_scaled_row
  constexpr int L = 32 / sizeof(T);
  vec vl = vec{} + lo, vh = vec{} + hi;
  int64_t j = 0;
  for (; j + L <= n; j += L) {
    const vec v = *reinterpret_cast<const vec_u*>(x + j);
    vl = v < vl ? v : vl;
    vh = v > vh ? v : vh;
  }
  for (int l = 0; l < L; ++l) lo = std::min(lo, vl[l]), hi = std::max(hi, vh[l]);
  for (; j < n; ++j) lo = std::min(lo, x[j]), hi = std::max(hi, x[j]);
}

// Bilinear taps for one axis: output index o reads (1-f) * in[i0] + f * in[i1].
// Source coordinate u = (o + 0.5) / df - 0.5 clamped to [0, in - 1], i.e. torch's
// interpolate(scale_factor=df, align_corners=False) cropped to the full-res size.
template <typename T>
struct Taps {
  std::vector<int64_t> i0, i1;
  std::vector<T> f;
  int64_t df;
  std::vector<T> period;  // f for the df outputs between two low-res centres

  Taps(int64_t out, int64_t in, int64_t df_) : i0(out), i1(out), f(out), df(df_), period(df_) {
    for (int64_t k = 0; k < df; ++k)
      period[k] = (static_cast<T>(k) + T(0.5)) / static_cast<T>(df);
    const T scale = T(1) / static_cast<T>(df);
    for (int64_t o = 0; o < out; ++o) {
      T src = scale * (static_cast<T>(o) + T(0.5)) - T(0.5);
      if (src < T(0)) src = T(0);
      int64_t a = static_cast<int64_t>(src);
      if (a > in - 1) a = in - 1;
      i0[o] = a;
      i1[o] = a < in - 1 ? a + 1 : a;
      f[o] = a < in - 1 ? src - static_cast<T>(a) : T(0);
    }
  }
};

// One row: out (w) from the low-res row t (wl), df > 1.
// Horizontal taps repeat with period df: between low-res centres b and b+1 the df outputs use
// weights f_k = (k + 0.5) / df (the same values Taps computes), so no per-pixel gathers.
template <typename T>
inline void upsample_cols(const T* t, int64_t wl, int64_t w, const Taps<T>& tx, T* o) {
  const int64_t df = tx.df;
  const int64_t half = df / 2;
  const T* fk = tx.period.data();
  const int64_t head = std::min(w, half);
  for (int64_t j = 0; j < head; ++j) o[j] = t[0];
  int64_t b = 0;
#if defined(__AVX2__) && defined(__FMA__)
  // float, df = 2, 4 or 8: eight outputs (8 / df intervals) per step, their end points picked out
  // of one load of t by lane permutes: lane k uses t[b + k / df] and t[b + k / df + 1].
  if constexpr (std::is_same<T, float>::value) {
    if (df == 2 || df == 4 || df == 8) {
      const int64_t per = 8 / df;
      const __m256i pa = df == 2   ? _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3)
                         : df == 4 ? _mm256_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1)
                                   : _mm256_setzero_si256();
      const __m256i pb = _mm256_add_epi32(pa, _mm256_set1_epi32(1));
      const __m256 f = df == 8 ? _mm256_loadu_ps(fk)
                               : _mm256_setr_ps(fk[0], fk[1 % df], fk[2 % df], fk[3 % df], fk[4 % df],
                                                fk[5 % df], fk[6 % df], fk[7 % df]);
      const __m256 g = _mm256_sub_ps(_mm256_set1_ps(1.0f), f);
      // steps while the 8-float load stays in t and the 8 outputs in o
      const int64_t steps =
          wl < 8 || w < half + 8 ? 0 : std::min((wl - 8) / per + 1, (w - half - 8) / 8 + 1);
      const float* src = t;
      float* dst = o + half;
      for (int64_t s = 0; s < steps; ++s, src += per, dst += 8) {
        const __m256 v = _mm256_loadu_ps(src);
        const __m256 a0 = _mm256_permutevar8x32_ps(v, pa), a1 = _mm256_permutevar8x32_ps(v, pb);
        _mm256_storeu_ps(dst, _mm256_fmadd_ps(f, a1, _mm256_mul_ps(g, a0)));
      }
      b = steps * per;
    }
  }
#endif
#if defined(__SSE2__)
  // float, df = 4: one vector per interval, the same (1 - f) a0 + f a1 per element.
  if constexpr (std::is_same<T, float>::value) {
    if (df == 4) {
      const __m128 f = _mm_loadu_ps(fk);
      const __m128 g = _mm_sub_ps(_mm_set1_ps(1.0f), f);
      for (; b + 1 < wl && half + b * df + df <= w; ++b)
        _mm_storeu_ps(o + half + b * df, _mm_add_ps(_mm_mul_ps(g, _mm_set1_ps(t[b])),
                                                    _mm_mul_ps(f, _mm_set1_ps(t[b + 1]))));
    }
  }
#endif
  for (; b + 1 < wl; ++b) {
    const int64_t j0 = half + b * df;
    if (j0 >= w) break;
    const T a0 = t[b], a1 = t[b + 1];
    if (j0 + df <= w) {
      for (int64_t k = 0; k < df; ++k) o[j0 + k] = (T(1) - fk[k]) * a0 + fk[k] * a1;
    } else {
      for (int64_t k = 0; j0 + k < w; ++k) o[j0 + k] = (T(1) - fk[k]) * a0 + fk[k] * a1;
    }
  }
  for (int64_t j = std::max(head, half + (wl - 1) * df); j < w; ++j) o[j] = t[wl - 1];
}

// Upsample `planes` low-res (hl, wl) planes at full-res row `i` into out (planes, w).
// tmp must hold planes * wl values.
template <typename T>
inline void upsample_row(const T* low, int64_t planes, int64_t hl, int64_t wl, int64_t i,
                         int64_t w, const Taps<T>& ty, const Taps<T>& tx, T* tmp, T* out) {
  const int64_t y0 = ty.i0[i], y1 = ty.i1[i];
  const T fy = ty.f[i], gy = T(1) - fy;
  const int64_t lp = hl * wl;
  for (int64_t p = 0; p < planes; ++p) {
    const T* r0 = low + p * lp + y0 * wl;
    const T* r1 = low + p * lp + y1 * wl;
    T* t = tmp + p * wl;
    for (int64_t j = 0; j < wl; ++j) t[j] = gy * r0[j] + fy * r1[j];
  }
  if (w == wl) {  // df == 1
    std::copy(tmp, tmp + planes * wl, out);
    return;
  }
  // Horizontal taps repeat with period df: between low-res centres b and b+1 the df outputs use
  // weights f_k = (k + 0.5) / df (the same values Taps computes), so no per-pixel gathers.
  for (int64_t p = 0; p < planes; ++p) upsample_cols(tmp + p * wl, wl, w, tx, out + p * w);
}

// Bilinear upsampling of `planes` low-res (hl, wl) planes one full-res row at a time. The two
// low-res rows a full-res row lies between are upsampled horizontally only when they change (every
// df rows) and kept as base = up(row y0) and delta = up(row y1) - base, so each full-res value is
// base + fy * delta: one multiply-add, where interpolating every row from scratch cost about four
// operations per value (a third of a splat pass).
template <typename T>
class RowUpsampler {
 public:
  RowUpsampler(int64_t planes, int64_t hl, int64_t wl, int64_t w, const Taps<T>& ty,
               const Taps<T>& tx)
      : planes_(planes), hl_(hl), wl_(wl), w_(w), ty_(ty), tx_(tx), base_(planes * w),
        delta_(planes * w), diff_(wl) {}

  // Serve the planes at `low` ((planes, hl, wl), contiguous) from now on.
  void reset(const T* low) {
    low_ = low;
    y0_ = y1_ = -1;
  }

  // Makes base()/delta() serve full-res row i; returns its vertical weight fy.
  T seek(int64_t i) {
    const int64_t y0 = ty_.i0[i], y1 = ty_.i1[i];
    if (y0 != y0_ || y1 != y1_) {
      y0_ = y0, y1_ = y1;
      for (int64_t p = 0; p < planes_; ++p) {
        const T* plane = low_ + p * hl_ * wl_;
        T* b = base_.data() + p * w_;
        T* d = delta_.data() + p * w_;
        horizontal(plane + y0 * wl_, b);
        if (y1 == y0) {
          std::fill(d, d + w_, T(0));
          continue;
        }
        // upsampling is linear: delta = up(row y1 - row y0), the difference taken at low res
        const T* r0 = plane + y0 * wl_;
        const T* r1 = plane + y1 * wl_;
        for (int64_t j = 0; j < wl_; ++j) diff_[j] = r1[j] - r0[j];
        horizontal(diff_.data(), d);
      }
    }
    return ty_.f[i];
  }

  const T* base(int64_t p) const { return base_.data() + p * w_; }
  const T* delta(int64_t p) const { return delta_.data() + p * w_; }

 private:
  void horizontal(const T* row, T* out) const {
    if (w_ == wl_) {  // df == 1
      std::copy(row, row + w_, out);
      return;
    }
    upsample_cols(row, wl_, w_, tx_, out);
  }

  const int64_t planes_, hl_, wl_, w_;
  const Taps<T>& ty_;
  const Taps<T>& tx_;
  std::vector<T> base_, delta_, diff_;
  const T* low_ = nullptr;
  int64_t y0_ = -1, y1_ = -1;
};

// sum a[j] b[j] with 16 interleaved partial sums combined in a fixed order: the compiler keeps
// the lanes in vector registers without reassociating anything, so it is fast and reproducible.
template <typename T>
inline T dot_lanes(const T* a, const T* b, int64_t n) {
  constexpr int L = 16;
  T acc[L] = {};
  int64_t j = 0;
  for (; j + L <= n; j += L)
    for (int l = 0; l < L; ++l) acc[l] += a[j + l] * b[j + l];
  for (int l = 0; j < n; ++j, ++l) acc[l] += a[j] * b[j];
  for (int width = L / 2; width >= 1; width /= 2)
    for (int l = 0; l < width; ++l) acc[l] += acc[l + width];
  return acc[0];
}

// acc[bj] += sum of x[j] over the block's columns j in [bj*df, min(w, (bj+1)*df)).
// Offset-major so the full blocks vectorise over bj (strided loads); the partial last block after.
template <typename T>
inline void block_sum_row(const T* x, int64_t w, int64_t df, int64_t wl, T* acc) {
  if (df == 1) {  // the same sums; the strided loop below did not vectorise at a runtime stride of 1
    for (int64_t j = 0; j < w; ++j) acc[j] += x[j];
    return;
  }
  const int64_t full = w / df;
  for (int64_t k = 0; k < df; ++k)
    for (int64_t bj = 0; bj < full; ++bj) acc[bj] += x[bj * df + k];
  if (full < wl) {
    T s = T(0);
    for (int64_t j = full * df; j < w; ++j) s += x[j];
    acc[full] += s;
  }
}

// acc[bj] += sum of a[j] * b[j] over the block's columns.
template <typename T>
inline void block_dot_row(const T* a, const T* b, int64_t w, int64_t df, int64_t wl, T* acc) {
  if (df == 1) {  // as block_sum_row
    for (int64_t j = 0; j < w; ++j) acc[j] += a[j] * b[j];
    return;
  }
  const int64_t full = w / df;
  for (int64_t k = 0; k < df; ++k)
    for (int64_t bj = 0; bj < full; ++bj) acc[bj] += a[bj * df + k] * b[bj * df + k];
  if (full < wl) {
    T s = T(0);
    for (int64_t j = full * df; j < w; ++j) s += a[j] * b[j];
    acc[full] += s;
  }
}

#if defined(__SSE2__)
// float32 with df a multiple of 4 (the common df = 4, 8, ...): each block is df/4 vectors summed
// into one, four blocks' vectors are transposed and added, so four block sums take one store.
// Every block is reduced by the same operations wherever a thread split falls, so the sums do
// not depend on the thread count (the compiler may fuse multiply-adds on FMA builds).
#if defined(__AVX2__)
// The sums of the eight 4-float blocks in v[0..3] (v[q] holds blocks 2q and 2q+1), in block order,
// each as (x0 + x1) + (x2 + x3) like the SSE transpose below.
inline __m256 sum_blocks_of_4(const __m256* v) {
  // within 128-bit lanes: [B0 B2 B4 B6 | B1 B3 B5 B7] after two horizontal adds
  const __m256 s = _mm256_hadd_ps(_mm256_hadd_ps(v[0], v[1]), _mm256_hadd_ps(v[2], v[3]));
  return _mm256_permutevar8x32_ps(s, _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7));
}
#endif

template <bool kDot>
inline void block_reduce_row_sse(const float* a, const float* b, int64_t w, int64_t df,
                                 int64_t wl, float* acc) {
  const int64_t full = w / df;
  auto block = [&](int64_t bj) {
    const float* pa = a + bj * df;
    const float* pb = kDot ? b + bj * df : nullptr;
    __m128 s = kDot ? _mm_mul_ps(_mm_loadu_ps(pa), _mm_loadu_ps(pb)) : _mm_loadu_ps(pa);
    for (int64_t k = 4; k < df; k += 4)
      s = _mm_add_ps(s, kDot ? _mm_mul_ps(_mm_loadu_ps(pa + k), _mm_loadu_ps(pb + k))
                             : _mm_loadu_ps(pa + k));
    return s;
  };
  int64_t bj = 0;
#if defined(__AVX2__)
  if (df == 4)
    for (; bj + 8 <= full; bj += 8) {
      const float* pa = a + bj * 4;
      __m256 v[4];
      for (int q = 0; q < 4; ++q) {
        v[q] = _mm256_loadu_ps(pa + 8 * q);
        if (kDot) v[q] = _mm256_mul_ps(v[q], _mm256_loadu_ps(b + bj * 4 + 8 * q));
      }
      _mm256_storeu_ps(acc + bj, _mm256_add_ps(_mm256_loadu_ps(acc + bj), sum_blocks_of_4(v)));
    }
  // df == 8: a block's halves added make the SSE path's 4-float vector; eight blocks' vectors, paired
  // into v[0..3], then sum as the df == 4 blocks do (the same operations in the same order)
  if (df == 8)
    for (; bj + 8 <= full; bj += 8) {
      __m256 v[4];
      for (int q = 0; q < 4; ++q) {
        const float* p0 = a + (bj + 2 * q) * 8;
        __m256 x0 = _mm256_loadu_ps(p0), x1 = _mm256_loadu_ps(p0 + 8);
        if (kDot) {
          const float* b0 = b + (bj + 2 * q) * 8;
          x0 = _mm256_mul_ps(x0, _mm256_loadu_ps(b0));
          x1 = _mm256_mul_ps(x1, _mm256_loadu_ps(b0 + 8));
        }
        v[q] = _mm256_add_ps(_mm256_permute2f128_ps(x0, x1, 0x20), _mm256_permute2f128_ps(x0, x1, 0x31));
      }
      _mm256_storeu_ps(acc + bj, _mm256_add_ps(_mm256_loadu_ps(acc + bj), sum_blocks_of_4(v)));
    }
#endif
  for (; bj + 4 <= full; bj += 4) {
    __m128 s0 = block(bj), s1 = block(bj + 1), s2 = block(bj + 2), s3 = block(bj + 3);
    _MM_TRANSPOSE4_PS(s0, s1, s2, s3);
    const __m128 sum = _mm_add_ps(_mm_add_ps(s0, s1), _mm_add_ps(s2, s3));
    _mm_storeu_ps(acc + bj, _mm_add_ps(_mm_loadu_ps(acc + bj), sum));
  }
  for (; bj < full; ++bj) {
    alignas(16) float l[4];
    _mm_store_ps(l, block(bj));
    acc[bj] += (l[0] + l[1]) + (l[2] + l[3]);
  }
  if (full < wl) {
    float s = 0.0f;
    for (int64_t j = full * df; j < w; ++j) s += kDot ? a[j] * b[j] : a[j];
    acc[full] += s;
  }
}

// df == 2 (the generic loop's strided columns did not vectorise): eight blocks a vector, their even and
// odd columns apart, added to acc in the generic loop's order (even, then odd) with its operations
// (vector operators, which the compiler contracts as it does the scalar loop). Returns the blocks done.
template <bool kDot>
inline int64_t block_reduce_row_df2(const float* a, const float* b, int64_t w, float* acc) {
  int64_t bj = 0;
#if defined(__AVX2__)
  // the even (odd) floats of x0, x1 in order: per 128-bit lane, then the lanes' 64-bit halves in order
  auto even = [](__m256 x0, __m256 x1) {
    return _mm256_castpd_ps(_mm256_permute4x64_pd(_mm256_castps_pd(_mm256_shuffle_ps(x0, x1, 0x88)), 0xD8));
  };
  auto odd = [](__m256 x0, __m256 x1) {
    return _mm256_castpd_ps(_mm256_permute4x64_pd(_mm256_castps_pd(_mm256_shuffle_ps(x0, x1, 0xDD)), 0xD8));
  };
  for (; bj + 8 <= w / 2; bj += 8) {
    const __m256 a0 = _mm256_loadu_ps(a + 2 * bj), a1 = _mm256_loadu_ps(a + 2 * bj + 8);
    __m256 s = _mm256_loadu_ps(acc + bj);
    if (kDot) {
      const __m256 b0 = _mm256_loadu_ps(b + 2 * bj), b1 = _mm256_loadu_ps(b + 2 * bj + 8);
      s += even(a0, a1) * even(b0, b1);
      s += odd(a0, a1) * odd(b0, b1);
    } else {
      s += even(a0, a1);
      s += odd(a0, a1);
    }
    _mm256_storeu_ps(acc + bj, s);
  }
#endif
  return bj;
}

inline void block_sum_row(const float* x, int64_t w, int64_t df, int64_t wl, float* acc) {
  if (df % 4 == 0) return block_reduce_row_sse<false>(x, nullptr, w, df, wl, acc);
  const int64_t done = df == 2 ? block_reduce_row_df2<false>(x, nullptr, w, acc) : 0;
  block_sum_row<float>(x + done * df, w - done * df, df, wl - done, acc + done);
}

inline void block_dot_row(const float* a, const float* b, int64_t w, int64_t df, int64_t wl,
                          float* acc) {
  if (df % 4 == 0) return block_reduce_row_sse<true>(a, b, w, df, wl, acc);
  const int64_t done = df == 2 ? block_reduce_row_df2<true>(a, b, w, acc) : 0;
  block_dot_row<float>(a + done * df, b + done * df, w - done * df, df, wl - done, acc + done);
}
#endif

// m += the upper triangle (row-major) of sum_j r[:, j] r[:, j]^T for d rows of length w (row
// stride w), float32 partial sums. res must hold round_up(d, 4) + 4 rows, the extra ones zero.
// Generic: one lane-interleaved dot product per entry.
template <typename T>
inline void gram_upper_row(const T* res, int64_t d, int64_t w, T* m) {
  int64_t k = 0;
  for (int64_t a = 0; a < d; ++a)
    for (int64_t b = a; b < d; ++b, ++k) m[k] += dot_lanes(res + a * w, res + b * w, w);
}

#if defined(__SSE2__)
// A 2 x 4 Gram tile (rows a, a+1 against b..b+3) after its vector part up to column wv: the scalar
// columns left, then its entries on or above the diagonal into the upper triangle m.
inline void gram_tile_finish(float* tile, const float* ra0, const float* ra1, const float* rb,
                             int64_t wv, int64_t w, int64_t a, int64_t b, int64_t d, float* m) {
  for (int64_t j = wv; j < w; ++j)
    for (int q = 0; q < 4; ++q) {
      tile[q] += ra0[j] * rb[q * w + j];
      tile[4 + q] += ra1[j] * rb[q * w + j];
    }
  for (int p = 0; p < 2; ++p)
    for (int q = 0; q < 4; ++q) {
      const int64_t aa = a + p, bb = b + q;
      if (aa < d && bb < d && bb >= aa) m[aa * d - aa * (aa - 1) / 2 + (bb - aa)] += tile[4 * p + q];
    }
}
#endif

#if defined(__AVX2__) && defined(__FMA__)
// float32 on AVX2 + FMA builds: 2 x 4 tiles of 8-float vectors and fused multiply-adds (the root's
// 17-channel Gram matrix was a third of its splat pass with SSE). A tile row pair (a, a+1) starts
// at column a, so a tile wastes at most the one entry below the diagonal (25 tiles for d = 17
// instead of 29 starting at a multiple of 4); res needs round_up(d, 4) + 4 rows.
inline void gram_upper_row(const float* res, int64_t d, int64_t w, float* m) {
  const int64_t dp = (d + 3) / 4 * 4;
  const int64_t wv = w / 8 * 8;
  float tile[8];
  auto hsum = [](__m256 v) {
    alignas(32) float l[8];
    _mm256_store_ps(l, v);
    return ((l[0] + l[1]) + (l[2] + l[3])) + ((l[4] + l[5]) + (l[6] + l[7]));
  };
  for (int64_t a = 0; a < d; a += 2) {
    const float* ra0 = res + a * w;
    const float* ra1 = a + 1 < dp ? ra0 + w : ra0;
    for (int64_t b = a; b < d; b += 4) {
      const float* rb = res + b * w;
      __m256 c00 = _mm256_setzero_ps(), c01 = c00, c02 = c00, c03 = c00;
      __m256 c10 = c00, c11 = c00, c12 = c00, c13 = c00;
      for (int64_t j = 0; j < wv; j += 8) {
        const __m256 x0 = _mm256_loadu_ps(ra0 + j), x1 = _mm256_loadu_ps(ra1 + j);
        const __m256 y0 = _mm256_loadu_ps(rb + j), y1 = _mm256_loadu_ps(rb + w + j);
        const __m256 y2 = _mm256_loadu_ps(rb + 2 * w + j), y3 = _mm256_loadu_ps(rb + 3 * w + j);
        c00 = _mm256_fmadd_ps(x0, y0, c00);
        c01 = _mm256_fmadd_ps(x0, y1, c01);
        c02 = _mm256_fmadd_ps(x0, y2, c02);
        c03 = _mm256_fmadd_ps(x0, y3, c03);
        c10 = _mm256_fmadd_ps(x1, y0, c10);
        c11 = _mm256_fmadd_ps(x1, y1, c11);
        c12 = _mm256_fmadd_ps(x1, y2, c12);
        c13 = _mm256_fmadd_ps(x1, y3, c13);
      }
      tile[0] = hsum(c00), tile[1] = hsum(c01), tile[2] = hsum(c02), tile[3] = hsum(c03);
      tile[4] = hsum(c10), tile[5] = hsum(c11), tile[6] = hsum(c12), tile[7] = hsum(c13);
      gram_tile_finish(tile, ra0, ra1, rb, wv, w, a, b, d, m);
    }
  }
}
#elif defined(__SSE2__)
// float32: 2 x 4 tiles of entries share their loads (6 vector loads per 8 multiply-adds instead of
// 16), each entry a 4-lane accumulator reduced in a fixed order; entries below the diagonal that a
// tile also covers are dropped.
inline void gram_upper_row(const float* res, int64_t d, int64_t w, float* m) {
  const int64_t dp = (d + 3) / 4 * 4;
  const int64_t wv = w / 4 * 4;
  float tile[8];
  auto hsum = [](__m128 v) {
    alignas(16) float l[4];
    _mm_store_ps(l, v);
    return (l[0] + l[1]) + (l[2] + l[3]);
  };
  for (int64_t a = 0; a < d; a += 2) {
    const float* ra0 = res + a * w;
    const float* ra1 = a + 1 < dp ? ra0 + w : ra0;
    for (int64_t b = a / 4 * 4; b < d; b += 4) {
      const float* rb = res + b * w;
      __m128 c00 = _mm_setzero_ps(), c01 = c00, c02 = c00, c03 = c00;
      __m128 c10 = c00, c11 = c00, c12 = c00, c13 = c00;
      for (int64_t j = 0; j < wv; j += 4) {
        const __m128 x0 = _mm_loadu_ps(ra0 + j), x1 = _mm_loadu_ps(ra1 + j);
        const __m128 y0 = _mm_loadu_ps(rb + j), y1 = _mm_loadu_ps(rb + w + j);
        const __m128 y2 = _mm_loadu_ps(rb + 2 * w + j), y3 = _mm_loadu_ps(rb + 3 * w + j);
        c00 = _mm_add_ps(c00, _mm_mul_ps(x0, y0));
        c01 = _mm_add_ps(c01, _mm_mul_ps(x0, y1));
        c02 = _mm_add_ps(c02, _mm_mul_ps(x0, y2));
        c03 = _mm_add_ps(c03, _mm_mul_ps(x0, y3));
        c10 = _mm_add_ps(c10, _mm_mul_ps(x1, y0));
        c11 = _mm_add_ps(c11, _mm_mul_ps(x1, y1));
        c12 = _mm_add_ps(c12, _mm_mul_ps(x1, y2));
        c13 = _mm_add_ps(c13, _mm_mul_ps(x1, y3));
      }
      tile[0] = hsum(c00), tile[1] = hsum(c01), tile[2] = hsum(c02), tile[3] = hsum(c03);
      tile[4] = hsum(c10), tile[5] = hsum(c11), tile[6] = hsum(c12), tile[7] = hsum(c13);
      gram_tile_finish(tile, ra0, ra1, rb, wv, w, a, b, d, m);
    }
  }
}
#endif

// acc0 += block sums of a0 * b and acc1 += those of a1 * b: b read once.
template <typename T>
inline void block_dot2_row(const T* a0, const T* a1, const T* b, int64_t w, int64_t df,
                           int64_t wl, T* acc0, T* acc1) {
  block_dot_row(a0, b, w, df, wl, acc0);
  block_dot_row(a1, b, w, df, wl, acc1);
}

#if defined(__SSE2__)
inline void block_dot2_row(const float* a0, const float* a1, const float* b, int64_t w,
                           int64_t df, int64_t wl, float* acc0, float* acc1) {
  if (df != 4) {
    block_dot_row(a0, b, w, df, wl, acc0);
    block_dot_row(a1, b, w, df, wl, acc1);
    return;
  }
  // Same operations as block_reduce_row_sse<true> for each output.
  const int64_t full = w / 4;
  int64_t bj = 0;
#if defined(__AVX2__)
  for (; bj + 8 <= full; bj += 8) {
    __m256 y[4], v0[4], v1[4];
    for (int q = 0; q < 4; ++q) {
      y[q] = _mm256_loadu_ps(b + bj * 4 + 8 * q);
      v0[q] = _mm256_mul_ps(_mm256_loadu_ps(a0 + bj * 4 + 8 * q), y[q]);
      v1[q] = _mm256_mul_ps(_mm256_loadu_ps(a1 + bj * 4 + 8 * q), y[q]);
    }
    _mm256_storeu_ps(acc0 + bj, _mm256_add_ps(_mm256_loadu_ps(acc0 + bj), sum_blocks_of_4(v0)));
    _mm256_storeu_ps(acc1 + bj, _mm256_add_ps(_mm256_loadu_ps(acc1 + bj), sum_blocks_of_4(v1)));
  }
#endif
  for (; bj + 4 <= full; bj += 4) {
    const float* pb = b + bj * 4;
    const __m128 y0 = _mm_loadu_ps(pb), y1 = _mm_loadu_ps(pb + 4);
    const __m128 y2 = _mm_loadu_ps(pb + 8), y3 = _mm_loadu_ps(pb + 12);
    // the four block sums of a * b into acc, b's loads shared by both outputs
    auto four_blocks = [&](const float* a, float* acc) {
      const float* pa = a + bj * 4;
      __m128 s0 = _mm_mul_ps(_mm_loadu_ps(pa), y0), s1 = _mm_mul_ps(_mm_loadu_ps(pa + 4), y1);
      __m128 s2 = _mm_mul_ps(_mm_loadu_ps(pa + 8), y2), s3 = _mm_mul_ps(_mm_loadu_ps(pa + 12), y3);
      _MM_TRANSPOSE4_PS(s0, s1, s2, s3);
      const __m128 sum = _mm_add_ps(_mm_add_ps(s0, s1), _mm_add_ps(s2, s3));
      _mm_storeu_ps(acc + bj, _mm_add_ps(_mm_loadu_ps(acc + bj), sum));
    };
    four_blocks(a0, acc0);
    four_blocks(a1, acc1);
  }
  if (bj < wl) {  // the last few blocks, partial one included
    const int64_t j0 = bj * 4;
    block_dot_row(a0 + j0, b + j0, w - j0, int64_t(4), wl - bj, acc0 + bj);
    block_dot_row(a1 + j0, b + j0, w - j0, int64_t(4), wl - bj, acc1 + bj);
  }
}
#endif

}  // namespace cpu
}  // namespace torchmanifold
