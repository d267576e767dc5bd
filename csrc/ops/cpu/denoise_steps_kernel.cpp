// CPU kernels of the denoiser's fused frame-step ops (schemas: ops/denoise_steps.cpp). Each mirrors a
// PyTorch stage of torchmanifold/pipeline/denoise.py step by step, in the same float operations and
// order where the PyTorch op's order is known (so results agree to float rounding; exp/log and
// reductions may differ in the last bits).
//
// Every task writes its own rows and every reduction sums per-row partials in row order, so the
// output is the same bytes for any thread count.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <tuple>
#include <type_traits>
#include <vector>

#include "ops/cpu/workspace.h"

#if defined(__AVX2__)
#include <immintrin.h>
#endif

// No fused multiply-adds: the PyTorch stages round every product before the sum, and a 3x3 variance
// that rounds differently can pick another Kuwahara window.
#pragma GCC optimize("fp-contract=off")

namespace torchmanifold {
namespace cpu {
namespace {

// Rec. 709 luminance in denoise.luminance's order: (0.2126 r + 0.7152 g) + 0.0722 b.
template <typename T>
inline T lum(T r, T g, T b) {
  return T(0.2126) * r + T(0.7152) * g + T(0.0722) * b;
}

// denoise._light_share: 4 y - 2 clamped to [0, 1] (NaN kept, as torch.clamp)
template <typename T>
inline T light_share(T y) {
  const T v = T(4) * y - T(2);
  return v < T(0) ? T(0) : (v > T(1) ? T(1) : v);
}

// max that propagates NaN from either side, as torch.maximum does
template <typename T>
inline T nan_max(T a, T b) {
  return ((a > b) | (a != a)) ? a : b;
}

inline int64_t clampi(int64_t i, int64_t n) { return i < 0 ? 0 : (i >= n ? n - 1 : i); }

// denoise._min_support: the least den whose num / den is taken, 100 eps (den rounds to about eps), not
// below 1e-8 (in double, rounded once to T as PyTorch rounds the Python float)
template <typename T>
inline T min_support() {
  return static_cast<T>(std::max(1e-8, 1e2 * static_cast<double>(std::numeric_limits<T>::epsilon())));
}

// Rows of about this many pixels per parallel task.
inline int64_t row_grain(int64_t W) { return std::max<int64_t>(1, 16384 / std::max<int64_t>(W, 1)); }

void check_float(const at::Tensor& x, const char* name, const char* op) {
  TORCH_CHECK_VALUE(x.device().is_cpu(), op, ": ", name, " must be a CPU tensor, got ", x.device());
  TORCH_CHECK_VALUE(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble, op, ": ", name,
                    " must be float32 or float64, got ", x.scalar_type());
}

void check_shape(const at::Tensor& x, const char* name, const char* op, int64_t dims) {
  TORCH_CHECK_VALUE(x.dim() == dims, op, ": ", name, " must have ", dims, " dimensions, got ", x.sizes());
}

// ------------------------------------------------------------------------------ box max (the guard)
// Max over a window of 2r + 1 rows (-inf beyond the ends) at every row of an (n, width) array, by van
// Herk / Gil-Werman: running maxima from each block start (g) and to each block end (h) of the padded
// rows; a window is the suffix of one block and the prefix of the next. Whole rows at a time, so the
// lanes vectorise. Exact, so it equals the sparse table of denoise._window_max bit for bit.
template <typename T>
void window_max_rows(const T* __restrict src, int64_t n, int64_t r, int64_t width, T* __restrict dst,
                     T* __restrict g, T* __restrict h, const T* __restrict ninf) {
  const int64_t len = n + 2 * r, w = 2 * r + 1;
  auto row = [&](int64_t i) { return (i < r || i >= r + n) ? ninf : src + (i - r) * width; };
  for (int64_t i = 0, pos = 0; i < len; ++i, pos = (pos + 1 == w) ? 0 : pos + 1) {
    T* gi = g + i * width;
    const T* p = row(i);
    if (pos == 0) {
      std::copy(p, p + width, gi);
    } else {
      const T* gp = gi - width;
      for (int64_t x = 0; x < width; ++x) gi[x] = nan_max(gp[x], p[x]);
    }
  }
  for (int64_t i = len - 1; i >= 0; --i) {
    T* hi = h + i * width;
    const T* p = row(i);
    if (i % w == w - 1 || i == len - 1) {
      std::copy(p, p + width, hi);
    } else {
      const T* hn = hi + width;
      for (int64_t x = 0; x < width; ++x) hi[x] = nan_max(hn[x], p[x]);
    }
  }
  for (int64_t j = 0; j < n; ++j) {
    const T* a = h + j * width;
    const T* b = g + (j + 2 * r) * width;
    T* d = dst + j * width;
    for (int64_t x = 0; x < width; ++x) d[x] = nan_max(a[x], b[x]);
  }
}

// One step of a sparse table along a row: out[i] = max(in[i], in[i + span]) for i < n.
template <typename T>
void span_max(const T* __restrict in, int64_t n, int64_t span, T* __restrict out) {
  for (int64_t i = 0; i < n; ++i) out[i] = nan_max(in[i], in[i + span]);
}

// The window max along one row of n values (the scans of window_max_rows are serial along a row): maxima
// over doubling spans of the -inf-padded row, the window read as two overlapping spans, as
// denoise._window_max does it. a, b: n + 2r values each.
template <typename T>
void window_max_1d(const T* __restrict src, int64_t n, int64_t r, T* __restrict dst, T* a, T* b) {
  const int64_t w = 2 * r + 1;
  int64_t len = n + 2 * r, span = 1;
  const T ninf = -std::numeric_limits<T>::infinity();
  std::fill(a, a + r, ninf);
  std::copy(src, src + n, a + r);
  std::fill(a + r + n, a + len, ninf);
  while (2 * span <= w) {
    span_max(a, len - span, span, b);
    len -= span;
    span *= 2;
    std::swap(a, b);
  }
  span_max(a, n, w - span, dst);
}

// (2r+1)^2 box max of an (H, W) plane: rows (dim 3) first, then columns, as denoise._box_max (max is exact:
// the same bits in any order). Scratch: HW + 2 (H + 2r) W + 2 (W + 2r) + W values, pooled (fresh pages
// cost more than the work).
template <typename T>
void box_max_plane(const T* src, int64_t H, int64_t W, int64_t r, T* dst, Scratch<T>& scratch) {
  const int64_t HW = H * W, G = (H + 2 * r) * W, L = W + 2 * r;
  scratch.resize(HW + 2 * G + 2 * L + W);
  T *a = scratch.data(), *g = a + HW, *h = g + G, *p1 = h + G, *p2 = p1 + L, *ninf = p2 + L;
  for (int64_t y = 0; y < H; ++y) window_max_1d(src + y * W, W, r, a + y * W, p1, p2);  // along x
  std::fill(ninf, ninf + W, -std::numeric_limits<T>::infinity());
  window_max_rows(a, H, r, W, dst, g, h, ninf);  // along y, whole rows at a time
}

// Row helpers with restrict parameters (GCC vectorises only when told the rows are apart).
template <typename T>
void masked_row(const T* __restrict v, const T* __restrict m, T sign, T fill, int64_t n, T* __restrict out) {
  for (int64_t i = 0; i < n; ++i) out[i] = m[i] > T(0) ? sign * v[i] : fill;
}

template <typename T>
void normalise_row(const T* __restrict a, const T* __restrict d, const T* __restrict v, const T* __restrict m,
                   int64_t W, T* __restrict o) {
  const T support = min_support<T>();
  for (int64_t x = 0; x < W; ++x) o[x] = d[x] > support ? a[x] / d[x] : v[x] * m[x];
}

// out = min(max(out, lo), hi) where the box held a valid sample (hi > -max/2), as torch.maximum /
// minimum do it: a NaN out stays NaN (the comparisons fail); NaN bounds come only from a NaN value in the
// box, which makes hi NaN too, and then the pixel is not guarded (PyTorch's `ok` is false as well)
template <typename T>
void clamp_row(const T* __restrict hi, const T* __restrict nlo, int64_t W, T* __restrict o) {
  const T half_big = -std::numeric_limits<T>::max() / T(2);
  for (int64_t x = 0; x < W; ++x) {
    const T z = o[x], lo = -nlo[x], h = hi[x];
    const T z1 = z < lo ? lo : z;
    const T z2 = z1 > h ? h : z1;
    o[x] = h > half_big ? z2 : z;
  }
}

template <typename T>
void normalise_fallback_row(const T* __restrict a, const T* __restrict d, const T* __restrict fb, int64_t W,
                            T* __restrict o) {
  const T support = min_support<T>();
  for (int64_t x = 0; x < W; ++x) o[x] = d[x] > support ? a[x] / d[x] : fb[x];
}

// The guarded normalisation over (N, C, H, W) into po: bound_plane(b, dst) writes plane b = (n, c, side)
// of the bound sources (side 0: valid values, side 1: minus valid values, -max where none), which are
// box-maxed (radius > 0); normalise(n, c, y, o) writes row y of (n, c) unguarded.
template <typename T, typename BoundPlane, typename Normalise>
void guarded_normalise(int64_t N, int64_t C, int64_t H, int64_t W, int64_t radius, const BoundPlane& bound_plane,
                       const Normalise& normalise, T* po) {
  const int64_t HW = H * W;
  Scratch<T> bounds;  // (N, C, 2, H, W): box max of valid values, box max of minus valid values (pooled)
  T* pb = nullptr;
  if (radius > 0) {
    bounds.resize(N * C * 2 * HW);
    pb = bounds.data();
    at::parallel_for(0, N * C * 2, 1, [&](int64_t b0, int64_t b1) {
      Scratch<T> src, scratch;
      src.resize(HW);
      for (int64_t b = b0; b < b1; ++b) {
        bound_plane(b, src.data());
        box_max_plane(src.data(), H, W, radius, pb + b * HW, scratch);
      }
    });
  }
  at::parallel_for(0, N * H, row_grain(W), [&](int64_t r0, int64_t r1) {
    for (int64_t row = r0; row < r1; ++row) {
      const int64_t n = row / H, y = row % H;
      for (int64_t c = 0; c < C; ++c) {
        T* o = po + (n * C + c) * HW + y * W;
        normalise(n, c, y, o);
        if (pb) {
          const T* hi = pb + ((n * C + c) * 2) * HW + y * W;
          clamp_row(hi, hi + HW, W, o);
        }
      }
    }
  });
}

at::Tensor normalise_guard_cpu(const at::Tensor& num_, const at::Tensor& den_, const at::Tensor& values_,
                               const at::Tensor& mask_, int64_t radius) {
  const char* op = "_normalise_guard";
  for (auto* p : {&num_, &den_, &values_, &mask_}) check_shape(*p, "every input", op, 4);
  check_float(num_, "num", op);
  TORCH_CHECK_VALUE(den_.scalar_type() == num_.scalar_type() && values_.scalar_type() == num_.scalar_type() &&
                    mask_.scalar_type() == num_.scalar_type(), op, ": inputs must share num's dtype");
  TORCH_CHECK_VALUE(values_.sizes() == num_.sizes(), op, ": values ", values_.sizes(), " must match num ",
                    num_.sizes());
  const int64_t N = num_.size(0), C = num_.size(1), H = num_.size(2), W = num_.size(3), HW = H * W;
  TORCH_CHECK_VALUE(den_.sizes() == at::IntArrayRef({N, 1, H, W}) && mask_.sizes() == den_.sizes(), op,
                    ": den and mask must be (N, 1, H, W) = ", at::IntArrayRef({N, 1, H, W}), ", got ",
                    den_.sizes(), " and ", mask_.sizes());
  const at::Tensor num = num_.contiguous(), den = den_.contiguous(), values = values_.contiguous(),
                   mask = mask_.contiguous();
  at::Tensor out = at::empty_like(num, at::MemoryFormat::Contiguous);
  if (out.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(num.scalar_type(), "normalise_guard_cpu", [&] {
    using T = scalar_t;
    const T *pn = num.data_ptr<T>(), *pd = den.data_ptr<T>(), *pv = values.data_ptr<T>(), *pm = mask.data_ptr<T>();
    const T big = std::numeric_limits<T>::max();
    guarded_normalise<T>(
        N, C, H, W, radius,
        [&](int64_t b, T* dst) {
          const int64_t n = b / (2 * C), c = (b / 2) % C;
          masked_row(pv + (n * C + c) * HW, pm + n * HW, (b % 2) ? T(-1) : T(1), -big, HW, dst);
        },
        [&](int64_t n, int64_t c, int64_t y, T* o) {
          const int64_t off = (n * C + c) * HW + y * W;
          normalise_row(pn + off, pd + n * HW + y * W, pv + off, pm + n * HW + y * W, W, o);
        },
        out.data_ptr<T>());
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> window_bounds_cpu(const at::Tensor& values_, const at::Tensor& mask_,
                                                     at::IntArrayRef starts, at::IntArrayRef lengths) {
  const char* op = "_window_bounds";
  check_shape(values_, "values", op, 4);
  check_float(values_, "values", op);
  const int64_t T = values_.size(0), C = values_.size(1), H = values_.size(2), W = values_.size(3), HW = H * W;
  TORCH_CHECK_VALUE(mask_.sizes() == at::IntArrayRef({T, 1, H, W}) && mask_.scalar_type() == values_.scalar_type(),
                    op, ": mask must be (T, 1, H, W) = ", at::IntArrayRef({T, 1, H, W}), " of values' dtype, got ",
                    mask_.sizes(), " ", mask_.scalar_type());
  TORCH_CHECK_VALUE(starts.size() == lengths.size(), op, ": starts and lengths must have one entry per query, got ",
                    starts.size(), " and ", lengths.size());
  const int64_t Q = static_cast<int64_t>(starts.size());
  for (int64_t w = 0; w < Q; ++w)
    TORCH_CHECK_VALUE(lengths[w] >= 1 && starts[w] >= 0 && starts[w] + lengths[w] <= T, op, ": query ", w,
                      "'s frames ", starts[w], " .. ", starts[w] + lengths[w] - 1, " must lie in 0 .. ", T - 1);
  const at::Tensor values = values_.contiguous(), mask = mask_.contiguous();
  at::Tensor hi = at::empty({Q, C, H, W}, values.options()), nlo = at::empty({Q, C, H, W}, values.options());
  if (hi.numel() == 0) return {hi, nlo};
  AT_DISPATCH_FLOATING_TYPES(values.scalar_type(), "window_bounds_cpu", [&] {
    using T_ = scalar_t;
    const T_ *pv = values.data_ptr<T_>(), *pm = mask.data_ptr<T_>();
    T_ *ph = hi.data_ptr<T_>(), *pl = nlo.data_ptr<T_>();
    const T_ big = std::numeric_limits<T_>::max();
    at::parallel_for(0, Q * C * H, row_grain(W * 4), [&](int64_t r0, int64_t r1) {
      for (int64_t r = r0; r < r1; ++r) {
        const int64_t w = r / (C * H), c = (r / H) % C, y = r % H;
        T_* h = ph + r * W;
        T_* l = pl + r * W;
        for (int64_t f = starts[w]; f < starts[w] + lengths[w]; ++f) {
          const T_* v = pv + (f * C + c) * HW + y * W;
          const T_* m = pm + f * HW + y * W;
          for (int64_t x = 0; x < W; ++x) {
            const T_ a = m[x] > T_(0) ? v[x] : -big, b = m[x] > T_(0) ? -v[x] : -big;
            // the first frame's value, then the larger (a NaN stays)
            h[x] = f == starts[w] || a > h[x] || std::isnan(a) ? a : h[x];
            l[x] = f == starts[w] || b > l[x] || std::isnan(b) ? b : l[x];
          }
        }
      }
    });
  });
  return {hi, nlo};
}

at::Tensor normalise_guard_bounds_cpu(const at::Tensor& num_, const at::Tensor& den_, const at::Tensor& fallback_,
                                      const at::Tensor& hi_, const at::Tensor& nlo_, int64_t radius) {
  const char* op = "_normalise_guard_bounds";
  for (auto* p : {&num_, &den_, &fallback_, &hi_, &nlo_}) check_shape(*p, "every input", op, 4);
  check_float(num_, "num", op);
  for (auto* p : {&den_, &fallback_, &hi_, &nlo_})
    TORCH_CHECK_VALUE(p->scalar_type() == num_.scalar_type(), op, ": inputs must share num's dtype");
  for (auto* p : {&fallback_, &hi_, &nlo_})
    TORCH_CHECK_VALUE(p->sizes() == num_.sizes(), op, ": fallback, hi and nlo must match num ", num_.sizes(),
                      ", got ", p->sizes());
  const int64_t N = num_.size(0), C = num_.size(1), H = num_.size(2), W = num_.size(3), HW = H * W;
  TORCH_CHECK_VALUE(den_.sizes() == at::IntArrayRef({N, 1, H, W}), op, ": den must be (N, 1, H, W) = ",
                    at::IntArrayRef({N, 1, H, W}), ", got ", den_.sizes());
  const at::Tensor num = num_.contiguous(), den = den_.contiguous(), fallback = fallback_.contiguous(),
                   hi = hi_.contiguous(), nlo = nlo_.contiguous();
  at::Tensor out = at::empty_like(num, at::MemoryFormat::Contiguous);
  if (out.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(num.scalar_type(), "normalise_guard_bounds_cpu", [&] {
    using T = scalar_t;
    const T *pn = num.data_ptr<T>(), *pd = den.data_ptr<T>(), *pf = fallback.data_ptr<T>();
    const T *ph = hi.data_ptr<T>(), *pl = nlo.data_ptr<T>();
    guarded_normalise<T>(
        N, C, H, W, radius,
        [&](int64_t b, T* dst) {
          const T* src = ((b % 2) ? pl : ph) + (b / 2) * HW;
          std::copy(src, src + HW, dst);
        },
        [&](int64_t n, int64_t c, int64_t y, T* o) {
          const int64_t off = (n * C + c) * HW + y * W;
          normalise_fallback_row(pn + off, pd + n * HW + y * W, pf + off, W, o);
        },
        out.data_ptr<T>());
  });
  return out;
}

// --------------------------------------------------------------------------------- Gaussian taps
// Radius of denoise.footprint_blur's Gaussian (three sigmas, at least one pixel).
inline int64_t gaussian_radius(double sigma) {
  return std::max<int64_t>(1, static_cast<int64_t>(std::ceil(3 * sigma)));
}

// Taps of denoise.footprint_blur's Gaussian, computed as it computes them, in T.
template <typename T>
std::vector<T> gaussian_taps(double sigma, int64_t r) {
  std::vector<T> taps(2 * r + 1);
  const T two_s2 = static_cast<T>(2 * sigma * sigma);
  T sum = 0;
  for (int64_t i = -r; i <= r; ++i) {
    const T f = static_cast<T>(i);
    taps[i + r] = std::exp(-(f * f) / two_s2);
  }
  for (T v : taps) sum += v;
  for (T& v : taps) v = v / sum;
  return taps;
}

// ------------------------------------------------------------------------- footprint average
// exp in plain arithmetic, so loops over it vectorise (std::exp does not): Cephes' expf (range reduction
// by ln 2 in two parts, degree-6 polynomial, 2^n from the exponent bits): within 1 ulp of the exact exp
// on [-87, 88] (measured on a dense sample), like the SLEEF exp PyTorch uses. NaN gives NaN; below -87.3
// it gives 0 (PyTorch: a denormal or 0). float64 uses std::exp.
inline float exp_lanes(float x) {
  const float xc = x < -87.3f ? -87.3f : (x > 88.0f ? 88.0f : x);
  const float n = std::floor(xc * 1.44269504088896341f + 0.5f);
  const float r = (xc - n * 0.693359375f) - n * -2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const float e = p * (r * r) + r + 1.0f;
  const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof(scale));
  const float out = x < -87.3f ? 0.0f : e * scale;
  return x != x ? x : out;
}
inline double exp_lanes(double x) { return std::exp(x); }

// a_c += w * n_c, den += w over a row (restrict parameters: GCC vectorises only when told the rows are apart)
template <typename T>
void accumulate_weighted(T* __restrict a0, T* __restrict a1, T* __restrict a2, T* __restrict den,
                         const T* __restrict w, const T* __restrict n0, const T* __restrict n1,
                         const T* __restrict n2, int64_t W) {
  for (int64_t x = 0; x < W; ++x) {
    a0[x] += w[x] * n0[x];
    a1[x] += w[x] * n1[x];
    a2[x] += w[x] * n2[x];
    den[x] += w[x];
  }
}

// x (T, 3, H, W) float radiance and k (T,) its tone-mapping knees, of x's dtype.
void check_frames_and_knees(const at::Tensor& x, const at::Tensor& k, const char* op) {
  check_float(x, "x", op);
  check_shape(x, "x", op, 4);
  TORCH_CHECK_VALUE(x.size(1) == 3, op, ": x must be (T, 3, H, W), got ", x.sizes());
  TORCH_CHECK_VALUE(k.dim() == 1 && k.size(0) == x.size(0) && k.scalar_type() == x.scalar_type(), op,
                    ": k must be (T,) = (", x.size(0), ",) of x's dtype, got ", k.sizes(), " ", k.scalar_type());
}

// footprint._tone_mapped: y = x / (k + x) of an (H, W) frame's three planes px clamped at 0 (NaN kept), and
// their luminance: four planes into y.
template <typename T>
void tone_mapped(const T* px, T k, int64_t H, int64_t W, T* y) {
  const int64_t HW = H * W;
  auto cl = [](T v) { return v < T(0) ? T(0) : v; };  // clamp_min(0), NaN kept
  at::parallel_for(0, H, row_grain(W), [&](int64_t y0, int64_t y1) {
    for (int64_t i = y0 * W; i < y1 * W; ++i) {
      const T a = cl(px[i]), b = cl(px[HW + i]), c = cl(px[2 * HW + i]);
      y[i] = a / (k + a);
      y[HW + i] = b / (k + b);
      y[2 * HW + i] = c / (k + c);
      y[3 * HW + i] = lum(y[i], y[HW + i], y[2 * HW + i]);
    }
  });
}

at::Tensor footprint_average_cpu(const at::Tensor& x_, const at::Tensor& k_, double sigma, double range_sigma,
                                 double unseen_border) {
  const char* op = "_footprint_average";
  check_frames_and_knees(x_, k_, op);
  const at::Tensor kt = k_.contiguous();
  TORCH_CHECK_VALUE(sigma > 0 && range_sigma > 0, op, ": sigma and range_sigma must be > 0");
  TORCH_CHECK_VALUE(unseen_border >= 0 && unseen_border <= 1, op, ": unseen_border must be in [0, 1], got ",
                    unseen_border);
  const at::Tensor x = x_.contiguous();
  const int64_t Tn = x.size(0), H = x.size(2), W = x.size(3), HW = H * W;
  at::Tensor out = at::empty_like(x, at::MemoryFormat::Contiguous);
  if (out.numel() == 0) return out;
  const int64_t r = gaussian_radius(sigma);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "footprint_average_cpu", [&] {
    using T = scalar_t;
    std::vector<T> ws((2 * r + 1) * (2 * r + 1));
    for (int64_t dy = -r; dy <= r; ++dy)
      for (int64_t dx = -r; dx <= r; ++dx)
        ws[(dy + r) * (2 * r + 1) + dx + r] =
            static_cast<T>(std::exp(-static_cast<double>(dx * dx + dy * dy) / (2 * sigma * sigma)));
    const T inv_den = static_cast<T>(2 * (range_sigma * range_sigma));
    const T lone = static_cast<T>(unseen_border);
    const int64_t Hp = H + 2 * r, Wp = W + 2 * r;
    // y (3 planes), its luminance and how many adjacent pixels are above the knee; the same padded by r
    Scratch<T> yb, ypb;
    yb.resize(5 * HW);
    ypb.resize(5 * Hp * Wp);
    T* yp = ypb.data();
    for (int64_t t = 0; t < Tn; ++t) {
      const T* px = x.data_ptr<T>() + t * 3 * HW;
      T* po = out.data_ptr<T>() + t * 3 * HW;
      const T k = kt.data_ptr<T>()[t];
      T* y = yb.data();
      tone_mapped(px, k, H, W, y);
      const T* yl = y + 3 * HW;
      T* cnt = y + 4 * HW;
      auto lit = [&](int64_t i, int64_t j) {  // the light share; none beyond the border
        return (i >= 0 && i < H && j >= 0 && j < W) ? light_share(yl[i * W + j]) : T(0);
      };
      for (int64_t i = 0; i < H; ++i)
        for (int64_t j = 0; j < W; ++j)
          cnt[i * W + j] = lit(i - 1, j) + lit(i + 1, j) + lit(i, j - 1) + lit(i, j + 1);
      // replicate-padded copy of y, its luminance and the light shares: the window loops run without clamping
      for (int64_t c = 0; c < 5; ++c)
        for (int64_t i = 0; i < Hp; ++i) {
          const T* srow = y + c * HW + clampi(i - r, H) * W;
          T* prow = yp + (c * Hp + i) * Wp;
          for (int64_t j = 0; j < Wp; ++j) prow[j] = srow[clampi(j - r, W)];
        }
      at::parallel_for(0, H, row_grain(W * (2 * r + 1) * (2 * r + 1) / 4), [&](int64_t y0, int64_t y1) {
        Scratch<T> acc;
        acc.resize(5 * W);
        T* num = acc.data();
        T* __restrict a0 = num;
        T* __restrict a1 = num + W;
        T* __restrict a2 = num + 2 * W;
        T* __restrict den = num + 3 * W;
        T* __restrict wt = num + 4 * W;
        for (int64_t row = y0; row < y1; ++row) {
          std::fill(num, num + 4 * W, T(0));
          const T* ly = yp + (3 * Hp + row + r) * Wp + r;
          for (int64_t dy = -r; dy <= r; ++dy) {
            for (int64_t dx = -r; dx <= r; ++dx) {
              const T wsp = ws[(dy + r) * (2 * r + 1) + dx + r];
              const int64_t o = (row + r + dy) * Wp + r + dx;
              const T* __restrict n0 = yp + o;
              const T* __restrict n1 = n0 + Hp * Wp;
              const T* __restrict n2 = n1 + Hp * Wp;
              const T* __restrict nl = n2 + Hp * Wp;
              if (std::abs(dx) + std::abs(dy) == 1) {
                // a light's border through the dimmer of two adjacent pixels: the range weight gives way
                const T* __restrict nc = nl + Hp * Wp;
                const T* __restrict oc = ly + Hp * Wp;
                for (int64_t xx = 0; xx < W; ++xx) {
                  const T d = nl[xx] - ly[xx];
                  const T w = exp_lanes(-(d * d) / inv_den);
                  const T dimmer = nl[xx] < ly[xx] ? nc[xx] : oc[xx];
                  const T over = (dimmer - T(1)) + lone;
                  const T border = light_share(nan_max(nl[xx], ly[xx])) *
                                   (over < T(0) ? T(0) : (over > T(1) ? T(1) : over));
                  wt[xx] = wsp * (w + (T(1) - w) * border);
                }
              } else {
                for (int64_t xx = 0; xx < W; ++xx) {
                  const T d = nl[xx] - ly[xx];
                  wt[xx] = wsp * exp_lanes(-(d * d) / inv_den);
                }
              }
              accumulate_weighted(a0, a1, a2, den, wt, n0, n1, n2, W);
            }
          }
          for (int64_t c = 0; c < 3; ++c) {
            T* o = po + c * HW + row * W;
            for (int64_t xx = 0; xx < W; ++xx) {
              const T v = num[c * W + xx] / den[xx];
              T q = T(1) - v;
              q = (q != q || q > T(1e-6)) ? q : T(1e-6);
              o[xx] = k * v / q;
            }
          }
        }
      });
    }
  });
  return out;
}

// ------------------------------------------------------------------------------ 3x3 Kuwahara
at::Tensor kuwahara3_cpu(const at::Tensor& x_) {
  const char* op = "_kuwahara3";
  check_float(x_, "x", op);
  check_shape(x_, "x", op, 4);
  const at::Tensor x = x_.contiguous();
  const int64_t P = x.size(0) * x.size(1), H = x.size(2), W = x.size(3), HW = H * W;
  at::Tensor out = at::empty_like(x, at::MemoryFormat::Contiguous);
  if (out.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "kuwahara3_cpu", [&] {
    using T = scalar_t;
    const int64_t H2 = H + 2, W2 = W + 2;
    std::vector<T> mom(2 * H2 * W2);  // 3x3 means of x and x^2 over the replicate-padded grid
    for (int64_t p = 0; p < P; ++p) {
      const T* px = x.data_ptr<T>() + p * HW;
      T* po = out.data_ptr<T>() + p * HW;
      // avg_pool2d(3, 1) of the 2-padded plane: window (i, j) covers rows i-2..i, cols j-2..j, clamped;
      // summed row by row in T as ATen's avg_pool2d does, then divided by 9
      at::parallel_for(0, H2, row_grain(W2 * 9), [&](int64_t i0, int64_t i1) {
        for (int64_t i = i0; i < i1; ++i)
          for (int64_t j = 0; j < W2; ++j) {
            T s1 = 0, s2 = 0;
            for (int64_t a = i - 2; a <= i; ++a)
              for (int64_t b = j - 2; b <= j; ++b) {
                const T v = px[clampi(a, H) * W + clampi(b, W)];
                s1 += v;
                s2 += v * v;
              }
            mom[i * W2 + j] = s1 / T(9);
            mom[H2 * W2 + i * W2 + j] = s2 / T(9);
          }
      });
      // each pixel: the mean of the least varying of the four windows that hold it in a corner (the
      // first of equals, in denoise._log_radiance's order)
      at::parallel_for(0, H, row_grain(W * 4), [&](int64_t y0, int64_t y1) {
        for (int64_t y = y0; y < y1; ++y)
          for (int64_t xx = 0; xx < W; ++xx) {
            T best_v = 0, best_m = 0;
            bool first = true;
            for (int64_t dy = 0; dy <= 2; dy += 2)
              for (int64_t dx = 0; dx <= 2; dx += 2) {
                const int64_t j = (y + dy) * W2 + xx + dx;
                const T mu = mom[j];
                const T v = mom[H2 * W2 + j] - mu * mu;
                if (first || v < best_v) {
                  best_v = v;
                  best_m = mu;
                  first = false;
                }
              }
            po[y * W + xx] = best_m;
          }
      });
    }
  });
  return out;
}

// -------------------------------------------------------------------------- cross-validated blend
// Row helpers with restrict parameters, so the loops vectorise.
template <typename T>
void sq_error_row(const T* __restrict q0, const T* __restrict q1, const T* __restrict q2, const T* __restrict e0,
                  const T* __restrict e1, const T* __restrict e2, const T* __restrict w, int64_t W, T* __restrict out) {
  for (int64_t x = 0; x < W; ++x) {
    const T d0 = q0[x] - e0[x], d1 = q1[x] - e1[x], d2 = q2[x] - e2[x];
    out[x] = (d0 * d0 + d1 * d1 + d2 * d2) * w[x];
  }
}
template <typename T>
void axpy(T a, const T* __restrict x, int64_t n, T* __restrict y) {
  for (int64_t i = 0; i < n; ++i) y[i] += a * x[i];
}
// A row of W values blurred along x by the taps (radius r), replicate borders, into out; pad holds
// W + 2 r values.
template <typename T>
void blur_row(const T* row, const std::vector<T>& taps, int64_t r, int64_t W, T* pad, T* out) {
  std::copy(row, row + W, pad + r);
  std::fill(pad, pad + r, pad[r]);
  std::fill(pad + r + W, pad + 2 * r + W, pad[r + W - 1]);
  std::fill(out, out + W, T(0));
  for (int64_t i = -r; i <= r; ++i) axpy(taps[i + r], pad + r + i, W, out);
}
// Row y of an (H, W) plane blurred along y by the taps (radius r), replicate borders, into out.
template <typename T>
void blur_column(const T* plane, int64_t H, int64_t W, int64_t y, const std::vector<T>& taps, int64_t r, T* out) {
  std::fill(out, out + W, T(0));
  for (int64_t i = -r; i <= r; ++i) axpy(taps[i + r], plane + clampi(y + i, H) * W, W, out);
}
template <typename T>
void divide_row(const T* __restrict d, int64_t n, T* __restrict y) {
  for (int64_t i = 0; i < n; ++i) y[i] = y[i] / d[i];
}
template <typename T>
void fma_row(const T* __restrict a, const T* __restrict b, int64_t n, T* __restrict y) {
  for (int64_t i = 0; i < n; ++i) y[i] += a[i] * b[i];
}

// Row y of frame t's K weighted squared residuals (preds (K, T, 3, H, W) against e (T, 3, H, W), times weight)
// into out (K rows of W), then the mask's row: a prediction without support (NaN) takes the worst held
// residual there (0 if none is held).
template <typename T>
void residual_rows(const T* pp, const T* pe, const T* pw, const T* pm, int64_t K, int64_t Tn, int64_t t, int64_t y,
                   int64_t H, int64_t W, T* out) {
  const int64_t HW = H * W;
  for (int64_t kk = 0; kk < K; ++kk) {
    const T* q = pp + (kk * Tn + t) * 3 * HW + y * W;
    sq_error_row(q, q + HW, q + 2 * HW, pe + t * 3 * HW + y * W, pe + t * 3 * HW + HW + y * W,
                 pe + t * 3 * HW + 2 * HW + y * W, pw + t * HW + y * W, W, out + kk * W);
  }
  for (int64_t x = 0; x < W; ++x) {
    T worst = -std::numeric_limits<T>::infinity();
    for (int64_t kk = 0; kk < K; ++kk)
      if (out[kk * W + x] == out[kk * W + x] && out[kk * W + x] > worst) worst = out[kk * W + x];
    if (!(worst > -std::numeric_limits<T>::infinity())) worst = T(0);
    for (int64_t kk = 0; kk < K; ++kk)
      if (out[kk * W + x] != out[kk * W + x]) out[kk * W + x] = worst;
  }
  std::copy(pm + t * HW + y * W, pm + t * HW + (y + 1) * W, out + K * W);
}

void check_cv_inputs(const at::Tensor& preds_, const at::Tensor& e_, const at::Tensor& weight_,
                     const at::Tensor& mask_, const char* op) {
  check_float(e_, "e", op);
  check_shape(preds_, "preds", op, 5);
  check_shape(e_, "e", op, 4);
  const int64_t K = preds_.size(0), Tn = e_.size(0), H = e_.size(2), W = e_.size(3);
  TORCH_CHECK_VALUE(e_.size(1) == 3, op, ": e must be (T, 3, H, W), got ", e_.sizes());
  TORCH_CHECK_VALUE(K >= 1 && preds_.sizes() == at::IntArrayRef({K, Tn, 3, H, W}), op,
                    ": preds must be (K, T, 3, H, W) = (K, ", e_.sizes(), "), got ", preds_.sizes());
  TORCH_CHECK_VALUE(weight_.sizes() == at::IntArrayRef({Tn, 1, H, W}) && mask_.sizes() == weight_.sizes(), op,
                    ": weight and mask must be (T, 1, H, W), got ", weight_.sizes(), " and ", mask_.sizes());
  for (auto* p : {&preds_, &weight_, &mask_})
    TORCH_CHECK_VALUE(p->scalar_type() == e_.scalar_type(), op, ": inputs must share e's dtype");
}

// The residual planes a neighbouring query's blend borrows: (K + 1, T, H, W), each candidate's weighted
// squared residuals (NaN resolved as in _cv_blend), then the mask.
at::Tensor cv_residuals_cpu(const at::Tensor& preds_, const at::Tensor& e_, const at::Tensor& weight_,
                            const at::Tensor& mask_) {
  const char* op = "_cv_residuals";
  check_cv_inputs(preds_, e_, weight_, mask_, op);
  const int64_t K = preds_.size(0), Tn = e_.size(0), H = e_.size(2), W = e_.size(3), HW = H * W;
  const at::Tensor preds = preds_.contiguous(), e = e_.contiguous(), weight = weight_.contiguous(),
                   mask = mask_.contiguous();
  at::Tensor out = at::empty({K + 1, Tn, H, W}, e.options());
  if (out.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(e.scalar_type(), "cv_residuals_cpu", [&] {
    using T = scalar_t;
    T* po = out.data_ptr<T>();
    at::parallel_for(0, Tn * H, row_grain(W * K * 4), [&](int64_t r0, int64_t r1) {
      std::vector<T> rows((K + 1) * W);
      for (int64_t tr = r0; tr < r1; ++tr) {
        const int64_t t = tr / H, y = tr % H;
        residual_rows(preds.data_ptr<T>(), e.data_ptr<T>(), weight.data_ptr<T>(), mask.data_ptr<T>(), K, Tn, t, y,
                      H, W, rows.data());
        for (int64_t kk = 0; kk <= K; ++kk)
          std::copy(rows.data() + kk * W, rows.data() + (kk + 1) * W, po + (kk * Tn + t) * HW + y * W);
      }
    });
  });
  return out;
}

at::Tensor cv_blend_cpu(const at::Tensor& preds_, const at::Tensor& fulls_, const at::Tensor& e_,
                        const at::Tensor& weight_, const at::Tensor& mask_, double blur_sigma, double softness,
                        double error_cut, const c10::optional<at::Tensor>& others_,
                        const c10::optional<at::Tensor>& other_weights_) {
  const char* op = "_cv_blend";
  check_cv_inputs(preds_, e_, weight_, mask_, op);
  const int64_t K = preds_.size(0), Tn = e_.size(0), H = e_.size(2), W = e_.size(3), HW = H * W;
  TORCH_CHECK_VALUE(fulls_.sizes() == preds_.sizes() && fulls_.scalar_type() == e_.scalar_type(), op,
                    ": preds and fulls must be (K, T, 3, H, W) of e's dtype, got ", preds_.sizes(), " and ",
                    fulls_.sizes());
  TORCH_CHECK_VALUE(blur_sigma > 0 && softness > 0, op, ": blur_sigma and softness must be > 0");
  TORCH_CHECK_VALUE(others_.has_value() == other_weights_.has_value(), op,
                    ": others and other_weights come together");
  // the neighbouring queries' residual planes (J, K + 1, T, H, W) and their weights (J, T, H, W), relative to
  // the query's own 1
  at::Tensor others, ow;
  int64_t J = 0;
  if (others_.has_value()) {
    J = others_->size(0);
    TORCH_CHECK_VALUE(others_->dim() == 5 && others_->sizes() == at::IntArrayRef({J, K + 1, Tn, H, W}) &&
                          other_weights_->sizes() == at::IntArrayRef({J, Tn, H, W}),
                      op, ": others must be (J, K + 1, T, H, W) and other_weights (J, T, H, W), got ",
                      others_->sizes(), " and ", other_weights_->sizes());
    TORCH_CHECK_VALUE(others_->scalar_type() == e_.scalar_type() && other_weights_->scalar_type() == e_.scalar_type(),
                      op, ": inputs must share e's dtype");
    others = others_->contiguous();
    ow = other_weights_->contiguous();
  }
  const at::Tensor preds = preds_.contiguous(), fulls = fulls_.contiguous(), e = e_.contiguous(),
                   weight = weight_.contiguous(), mask = mask_.contiguous();
  at::Tensor out = at::empty_like(e, at::MemoryFormat::Contiguous);
  if (out.numel() == 0) return out;
  const int64_t r = gaussian_radius(blur_sigma);
  AT_DISPATCH_FLOATING_TYPES(e.scalar_type(), "cv_blend_cpu", [&] {
    using T = scalar_t;
    const std::vector<T> taps = gaussian_taps<T>(blur_sigma, r);
    const T* pp = preds.data_ptr<T>();
    const T* pf = fulls.data_ptr<T>();
    const T* pe = e.data_ptr<T>();
    const T* pw = weight.data_ptr<T>();
    const T* pm = mask.data_ptr<T>();
    T* po = out.data_ptr<T>();
    // Planes per frame (z^2 of denoise._excess_error_z2): at blur_sigma the K residual planes sq and the
    // mask; at blur_sigma / sqrt(2) (sum k^2 f = c blur2(f)) sq again, the squared differences of every
    // pair and the mask.
    const int64_t npairs = K * (K - 1) / 2;
    const int64_t r2 = gaussian_radius(blur_sigma / std::sqrt(2.0));
    const std::vector<T> taps2 = gaussian_taps<T>(blur_sigma / std::sqrt(2.0), r2);
    double c = 0;  // (sum of the 1-D taps' squares)^2, from float64 taps as denoise._excess_error_z2
    for (double v : gaussian_taps<double>(blur_sigma, r)) c += v * v;
    c *= c;
    std::vector<std::pair<int64_t, int64_t>> pairs;
    for (int64_t a = 0; a < K; ++a)
      for (int64_t b = a + 1; b < K; ++b) pairs.emplace_back(a, b);
    const int64_t n1 = K + 1, n2 = K + npairs + 1, NP = n1 + n2;  // planes per frame
    // pass 1: every plane of every frame, blurred along x
    Scratch<T> hbuf;
    hbuf.resize(Tn * NP * HW);
    T* hb = hbuf.data();  // (T, NP, H, W)
    at::parallel_for(0, Tn * H, row_grain(W * NP * (2 * r + 1)), [&](int64_t r0, int64_t r1) {
      Scratch<T> srcb, sqb;
      srcb.resize(W + 2 * r);
      sqb.resize((K + 1) * W * (J > 0 ? 3 : 1) + (J > 0 ? npairs * W + W : 0));
      T* src = srcb.data();  // a row, replicate-padded by the taps' radius
      T* sqr = sqb.data();   // the K residual rows, then the mask row
      // with neighbours: the rows pooled over them (A: weights w / sum w, B: their squares), the pairs' B rows
      T* rowa = J > 0 ? sqr + (K + 1) * W : sqr;
      T* rowb = J > 0 ? rowa + (K + 1) * W : sqr;
      T* rowp = J > 0 ? rowb + (K + 1) * W : nullptr;
      T* tot = J > 0 ? rowp + npairs * W : nullptr;
      auto hblur = [&](const T* row, const std::vector<T>& tp, int64_t rr, T* o) {
        blur_row(row, tp, rr, W, src, o);
      };
      std::vector<T> d(W);
      for (int64_t tr = r0; tr < r1; ++tr) {
        const int64_t t = tr / H, y = tr % H;
        residual_rows(pp, pe, pw, pm, K, Tn, t, y, H, W, sqr);
        if (J > 0) {
          const T* po_ = others.data_ptr<T>();
          const T* pow_ = ow.data_ptr<T>();
          auto other = [&](int64_t j, int64_t kk, int64_t x) {
            return po_[((j * (K + 1) + kk) * Tn + t) * HW + y * W + x];
          };
          auto wt = [&](int64_t j, int64_t x) { return pow_[(j * Tn + t) * HW + y * W + x]; };
          for (int64_t x = 0; x < W; ++x) {
            T s = T(1);
            for (int64_t j = 0; j < J; ++j) s += wt(j, x);
            tot[x] = s;
          }
          for (int64_t kk = 0; kk <= K; ++kk)
            for (int64_t x = 0; x < W; ++x) {
              T a = sqr[kk * W + x], b = sqr[kk * W + x];
              for (int64_t j = 0; j < J; ++j) {
                const T w = wt(j, x), o = other(j, kk, x);
                a += w * o;
                b += w * w * o;
              }
              rowa[kk * W + x] = a / tot[x];
              rowb[kk * W + x] = b / (tot[x] * tot[x]);
            }
          for (int64_t k = 0; k < npairs; ++k)
            for (int64_t x = 0; x < W; ++x) {
              const T dd = sqr[pairs[k].second * W + x] - sqr[pairs[k].first * W + x];
              T p = dd * dd;
              for (int64_t j = 0; j < J; ++j) {
                const T w = wt(j, x), od = other(j, pairs[k].second, x) - other(j, pairs[k].first, x);
                p += w * w * od * od;
              }
              rowp[k * W + x] = p / (tot[x] * tot[x]);
            }
        }
        T* base = hb + t * NP * HW + y * W;
        for (int64_t kk = 0; kk <= K; ++kk) hblur(rowa + kk * W, taps, r, base + kk * HW);
        for (int64_t kk = 0; kk < K; ++kk) hblur(rowb + kk * W, taps2, r2, base + (n1 + kk) * HW);
        for (int64_t k = 0; k < npairs; ++k) {
          if (J > 0) {
            hblur(rowp + k * W, taps2, r2, base + (n1 + K + k) * HW);
            continue;
          }
          const T *sa = sqr + pairs[k].first * W, *sb = sqr + pairs[k].second * W;
          for (int64_t x = 0; x < W; ++x) d[x] = (sb[x] - sa[x]) * (sb[x] - sa[x]);
          hblur(d.data(), taps2, r2, base + (n1 + K + k) * HW);
        }
        hblur(rowb + K * W, taps2, r2, base + (n1 + K + npairs) * HW);
      }
    });
    // pass 2: blur along y; per pixel the least-error candidate a, every other's excess D and its
    // variance, weights exp(-z^2 / 2 softness^2) normalised (the least error has z = 0), blend
    const T inv_two_s2 = static_cast<T>(1.0 / (2 * softness * softness));
    at::parallel_for(0, Tn * H, row_grain(W * (2 * r + 1) * NP), [&](int64_t r0, int64_t r1) {
      Scratch<T> buf;
      buf.resize((NP + K + 1) * W);
      T* pl = buf.data();  // the NP planes' rows
      T* wts = pl + NP * W;
      T* wsum = wts + K * W;
      auto vblur = [&](int64_t t, int64_t p, int64_t y, const std::vector<T>& tp, int64_t rr, T* dst) {
        blur_column(hb + (t * NP + p) * HW, H, W, y, tp, rr, dst);
      };
      std::vector<int64_t> pair_index(K * K, -1);
      for (int64_t k = 0; k < npairs; ++k)
        pair_index[pairs[k].first * K + pairs[k].second] = pair_index[pairs[k].second * K + pairs[k].first] = k;
      for (int64_t row = r0; row < r1; ++row) {
        const int64_t t = row / H, y = row % H;
        for (int64_t p = 0; p < NP; ++p)
          vblur(t, p, y, p < n1 ? taps : taps2, p < n1 ? r : r2, pl + p * W);
        const T* pool_raw = pl + K * W;
        const T* s1 = pl + n1 * W;
        const T* m2 = pl + (n1 + K + npairs) * W;
        std::fill(wsum, wsum + W, T(0));
        for (int64_t x = 0; x < W; ++x) {
          const T pool = pool_raw[x] < T(1e-6) ? T(1e-6) : pool_raw[x];
          const T inv = static_cast<T>(c) / (pool * pool);
          // allowed: the candidates whose prediction had support (not NaN), or all if none had
          bool any_held = false;
          for (int64_t kk = 0; kk < K; ++kk) {
            const T pv = pp[(kk * Tn + t) * 3 * HW + y * W + x];
            any_held |= pv == pv;
          }
          auto allowed = [&](int64_t kk) {
            const T pv = pp[(kk * Tn + t) * 3 * HW + y * W + x];
            return !any_held || pv == pv;
          };
          int64_t a = -1;
          T least = 0;
          for (int64_t kk = 0; kk < K; ++kk) {
            const T v = pl[kk * W + x] / pool;
            if (allowed(kk) && (a < 0 || v < least)) least = v, a = kk;
          }
          const T cut = static_cast<T>(error_cut) * least;
          for (int64_t kk = 0; kk < K; ++kk) {
            T z2 = 0;
            if (kk != a) {
              if (!allowed(kk) || pl[kk * W + x] / pool > cut) {
                wts[kk * W + x] = -std::numeric_limits<T>::infinity();
                continue;
              }
              const T D = pl[kk * W + x] / pool - least;
              const T var = pl[(n1 + K + pair_index[a * K + kk]) * W + x] * inv -
                            T(2) * D * (s1[kk * W + x] * inv - s1[a * W + x] * inv) + D * D * (m2[x] * inv);
              const T Dp = D > T(0) ? D : T(0);
              z2 = Dp * Dp / (var < T(1e-30) ? T(1e-30) : var);
            }
            wts[kk * W + x] = -z2 * inv_two_s2;
          }
        }
        for (int64_t kk = 0; kk < K; ++kk) {
          T* wk = wts + kk * W;
          for (int64_t x = 0; x < W; ++x) wk[x] = exp_lanes(wk[x]);
          for (int64_t x = 0; x < W; ++x) wsum[x] += wk[x];
        }
        for (int64_t kk = 0; kk < K; ++kk) divide_row(wsum, W, wts + kk * W);
        for (int64_t c3 = 0; c3 < 3; ++c3) {
          T* o = po + (t * 3 + c3) * HW + y * W;
          std::fill(o, o + W, T(0));
          for (int64_t kk = 0; kk < K; ++kk) fma_row(pf + ((kk * Tn + t) * 3 + c3) * HW + y * W, wts + kk * W, W, o);
        }
      }
    });
  });
  return out;
}

// ------------------------------------------------------------------------------ quantiles
// torch.quantile(v.double(), q, dim=1) (linear interpolation) by selection instead of a sort: the same
// order statistics, ranks and lerp, so the same float64 bits. A row with a NaN gives NaN (as torch).
at::Tensor quantiles_cpu(const at::Tensor& v_, at::ArrayRef<double> q) {
  const char* op = "_quantiles";
  check_float(v_, "v", op);
  check_shape(v_, "v", op, 2);
  TORCH_CHECK_VALUE(v_.size(1) >= 1, op, ": v must have at least one column, got ", v_.sizes());
  for (double x : q) TORCH_CHECK_VALUE(x >= 0 && x <= 1, op, ": q must lie in [0, 1], got ", x);
  const at::Tensor v = v_.contiguous();
  const int64_t R = v.size(0), N = v.size(1), Q = static_cast<int64_t>(q.size());
  at::Tensor out = at::empty({R, Q}, v.options().dtype(at::kDouble));
  double* po = out.data_ptr<double>();
  AT_DISPATCH_FLOATING_TYPES(v.scalar_type(), "quantiles_cpu", [&] {
    const scalar_t* pv = v.data_ptr<scalar_t>();
    at::parallel_for(0, R, 1, [&](int64_t r0, int64_t r1) {
      std::vector<double> buf(N);
      for (int64_t r = r0; r < r1; ++r) {
        bool nan = false;
        for (int64_t i = 0; i < N; ++i) {
          buf[i] = static_cast<double>(pv[r * N + i]);
          nan |= buf[i] != buf[i];
        }
        for (int64_t k = 0; k < Q; ++k) {
          if (nan) {
            po[r * Q + k] = std::numeric_limits<double>::quiet_NaN();
            continue;
          }
          const double rank = q[k] * static_cast<double>(N - 1);
          const int64_t below = static_cast<int64_t>(rank), above = static_cast<int64_t>(std::ceil(rank));
          std::nth_element(buf.begin(), buf.begin() + below, buf.end());
          const double lo = buf[below];
          const double hi = above == below ? lo : *std::min_element(buf.begin() + below + 1, buf.end());
          const double w = rank - static_cast<double>(below);
          po[r * Q + k] = std::abs(w) < 0.5 ? lo + w * (hi - lo) : hi - (hi - lo) * (1 - w);  // at::lerp
        }
      }
    });
  });
  return out;
}

// ------------------------------------------------------------------ cross-validation halves and split
// m * h, h the half or 1 - half (rounded as PyTorch rounds them: exactly)
template <typename T>
void half_mask_row(const T* __restrict m, const T* __restrict half, bool other, int64_t n, T* __restrict out) {
  if (other) {
    for (int64_t i = 0; i < n; ++i) out[i] = m[i] * (T(1) - half[i]);
  } else {
    for (int64_t i = 0; i < n; ++i) out[i] = m[i] * half[i];
  }
}
template <typename T>
void times_row(const T* __restrict a, const T* __restrict b, int64_t n, T* __restrict out) {
  for (int64_t i = 0; i < n; ++i) out[i] = a[i] * b[i];
}

// denoise._select_bandwidth's channel stack for one op call: per checkerboard half h ((y + x) even, then
// odd), [e * m, m] with m = mask * h, the same float products as the PyTorch stack.
void cv_halves_into(const at::Tensor& e_, const at::Tensor& mask_, at::Tensor& out) {
  const char* op = "_cv_halves";
  check_float(e_, "e", op);
  check_shape(e_, "e", op, 4);
  const int64_t Tn = e_.size(0), H = e_.size(2), W = e_.size(3), HW = H * W;
  TORCH_CHECK_VALUE(e_.size(1) == 3, op, ": e must be (T, 3, H, W), got ", e_.sizes());
  TORCH_CHECK_VALUE(mask_.sizes() == at::IntArrayRef({Tn, 1, H, W}) && mask_.scalar_type() == e_.scalar_type(), op,
                    ": mask must be (T, 1, H, W) of e's dtype, got ", mask_.sizes());
  const at::Tensor e = e_.contiguous(), mask = mask_.contiguous();
  if (!out.defined()) out = at::empty({Tn, 8, H, W}, e.options());
  TORCH_CHECK_VALUE(out.sizes() == at::IntArrayRef({Tn, 8, H, W}) && out.scalar_type() == e.scalar_type() &&
                    out.is_contiguous() && out.device().is_cpu(), op, ": out must be a contiguous (T, 8, H, W) = (",
                    Tn, ", 8, ", H, ", ", W, ") CPU tensor of e's dtype, got ", out.sizes());
  if (out.numel() == 0) return;
  AT_DISPATCH_FLOATING_TYPES(e.scalar_type(), "cv_halves_cpu", [&] {
    using T = scalar_t;
    const T* pe = e.data_ptr<T>();
    const T* pm = mask.data_ptr<T>();
    T* po = out.data_ptr<T>();
    at::parallel_for(0, Tn * H, row_grain(W * 8), [&](int64_t r0, int64_t r1) {
      Scratch<T> hb;
      hb.resize(2 * W);
      T* half = hb.data();  // the row's checkerboard: 1 where (y + x) is even
      T* mh = half + W;     // mask * half
      for (int64_t row = r0; row < r1; ++row) {
        const int64_t t = row / H, y = row % H, i0 = y * W;
        const T* er = pe + t * 3 * HW + i0;
        for (int64_t x = 0; x < W; ++x) half[x] = ((y + x) & 1) ? T(0) : T(1);
        for (int64_t j = 0; j < 2; ++j) {
          half_mask_row(pm + t * HW + i0, half, j == 1, W, mh);
          T* o = po + (t * 8 + j * 4) * HW + i0;
          times_row(er, mh, W, o);
          times_row(er + HW, mh, W, o + HW);
          times_row(er + 2 * HW, mh, W, o + 2 * HW);
          std::copy(mh, mh + W, o + 3 * HW);
        }
      }
    });
  });
}

at::Tensor cv_halves_cpu(const at::Tensor& e, const at::Tensor& mask) {
  at::Tensor out;
  cv_halves_into(e, mask, out);
  return out;
}

void cv_halves_out_cpu(const at::Tensor& e, const at::Tensor& mask, at::Tensor out) { cv_halves_into(e, mask, out); }

// The op's output y (T, 8, H, W) on that stack -> the prediction of every pixel from the other half
// (T, 3, H, W) (NaN where the other half has no weight), and the sums of both halves: num (T, 3, H, W),
// den (T, 1, H, W).
std::tuple<at::Tensor, at::Tensor, at::Tensor> cv_split_cpu(const at::Tensor& y_) {
  const char* op = "_cv_split";
  check_float(y_, "y", op);
  check_shape(y_, "y", op, 4);
  TORCH_CHECK_VALUE(y_.size(1) == 8, op, ": y must be (T, 8, H, W), got ", y_.sizes());
  const at::Tensor y = y_.contiguous();
  const int64_t Tn = y.size(0), H = y.size(2), W = y.size(3), HW = H * W;
  at::Tensor pred = at::empty({Tn, 3, H, W}, y.options());
  at::Tensor num = at::empty({Tn, 3, H, W}, y.options());
  at::Tensor den = at::empty({Tn, 1, H, W}, y.options());
  if (y.numel() == 0) return {pred, num, den};
  AT_DISPATCH_FLOATING_TYPES(y.scalar_type(), "cv_split_cpu", [&] {
    using T = scalar_t;
    const T* py = y.data_ptr<T>();
    T *pp = pred.data_ptr<T>(), *pn = num.data_ptr<T>(), *pd = den.data_ptr<T>();
    const T support = min_support<T>();
    at::parallel_for(0, Tn * H, row_grain(W * 8), [&](int64_t r0, int64_t r1) {
      for (int64_t row = r0; row < r1; ++row) {
        const int64_t t = row / H, yy = row % H, i0 = yy * W;
        const T* a = py + t * 8 * HW + i0;  // half 0: num 0..2, den 3; half 1: num 4..6, den 7
        const T* da = a + 3 * HW;
        const T* db = a + 7 * HW;
        T* d = pd + t * HW + i0;
        for (int64_t x = 0; x < W; ++x) d[x] = da[x] + db[x];
        for (int64_t c = 0; c < 3; ++c) {
          const T* na = a + c * HW;
          const T* nb = a + (4 + c) * HW;
          T* n = pn + (t * 3 + c) * HW + i0;
          T* p = pp + (t * 3 + c) * HW + i0;
          for (int64_t x = 0; x < W; ++x) {
            n[x] = na[x] + nb[x];
            const bool first_half = (yy + x) % 2 == 0;  // predicted from the second half, and the other way round
            const T on = first_half ? nb[x] : na[x];
            const T od = first_half ? db[x] : da[x];
            p[x] = od > support ? on / od : std::numeric_limits<T>::quiet_NaN();  // no support
          }
        }
      }
    });
  });
  return {pred, num, den};
}

// ------------------------------------------------------------------------------ sanitise
// denoise._sanitize without emission: non-finite samples of c (T, C, H, W) and f (T, D, H, W) set to 0,
// the mask (T, 1, H, W) = 1 where every channel of both is finite, and the counts (non-finite colour
// values, non-finite feature values, masked pixels) as int64 (3,). Selections and counts only: exact.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> sanitize_cpu(const at::Tensor& c_, const at::Tensor& f_) {
  const char* op = "_sanitize";
  check_float(c_, "c", op);
  check_shape(c_, "c", op, 4);
  check_shape(f_, "f", op, 4);
  TORCH_CHECK_VALUE(f_.scalar_type() == c_.scalar_type() && f_.size(0) == c_.size(0) && f_.size(2) == c_.size(2) &&
                    f_.size(3) == c_.size(3), op, ": f must be (T, D, H, W) of c's dtype and sizes ", c_.sizes(),
                    ", got ", f_.sizes());
  const at::Tensor c = c_.contiguous(), f = f_.contiguous();
  const int64_t Tn = c.size(0), C = c.size(1), D = f.size(1), H = c.size(2), W = c.size(3), HW = H * W;
  at::Tensor co = at::empty_like(c, at::MemoryFormat::Contiguous), fo = at::empty_like(f, at::MemoryFormat::Contiguous);
  at::Tensor mask = at::empty({Tn, 1, H, W}, c.options());
  at::Tensor counts = at::zeros({3}, c.options().dtype(at::kLong));
  if (Tn * HW == 0) return {co, fo, mask, counts};
  AT_DISPATCH_FLOATING_TYPES(c.scalar_type(), "sanitize_cpu", [&] {
    using T = scalar_t;
    std::vector<int64_t> rows(3 * Tn * H, 0);
    at::parallel_for(0, Tn * H, row_grain(W * (C + D)), [&](int64_t r0, int64_t r1) {
      std::vector<uint8_t> ok(W);
      for (int64_t row = r0; row < r1; ++row) {
        const int64_t t = row / H, i0 = (row % H) * W;
        std::fill(ok.begin(), ok.end(), uint8_t(1));
        auto clean = [&](const T* src, T* dst, int64_t n_ch, int64_t& bad) {
          for (int64_t ch = 0; ch < n_ch; ++ch) {
            const T* s = src + ch * HW + i0;
            T* d = dst + ch * HW + i0;
            for (int64_t x = 0; x < W; ++x) {
              const bool fin = std::isfinite(s[x]);
              d[x] = fin ? s[x] : T(0);
              ok[x] &= fin;
              bad += !fin;
            }
          }
        };
        clean(c.data_ptr<T>() + t * C * HW, co.data_ptr<T>() + t * C * HW, C, rows[3 * row]);
        clean(f.data_ptr<T>() + t * D * HW, fo.data_ptr<T>() + t * D * HW, D, rows[3 * row + 1]);
        T* m = mask.data_ptr<T>() + t * HW + i0;
        for (int64_t x = 0; x < W; ++x) {
          m[x] = ok[x] ? T(1) : T(0);
          rows[3 * row + 2] += !ok[x];
        }
      }
    });
    int64_t* pc = counts.data_ptr<int64_t>();
    for (int64_t row = 0; row < Tn * H; ++row)
      for (int64_t k = 0; k < 3; ++k) pc[k] += rows[3 * row + k];
  });
  return {co, fo, mask, counts};
}

// ------------------------------------------------------------------------- normalised blur
// denoise._normalised_blur: blur(x w) / blur(w) (footprint_blur's taps and replicate borders) for x
// (T, C, H, W) and weights w (T, 1, H, W), x itself where blur(w) <= 1e-8. A weight of 0 takes nothing
// of its value, so NaN or inf there stays out.
at::Tensor normalised_blur_cpu(const at::Tensor& x_, const at::Tensor& w_, double sigma) {
  const char* op = "_normalised_blur";
  check_float(x_, "x", op);
  check_shape(x_, "x", op, 4);
  const int64_t Tn = x_.size(0), C = x_.size(1), H = x_.size(2), W = x_.size(3), HW = H * W;
  TORCH_CHECK_VALUE(w_.sizes() == at::IntArrayRef({Tn, 1, H, W}) && w_.scalar_type() == x_.scalar_type(), op,
                    ": weight must be (T, 1, H, W) = (", Tn, ", 1, ", H, ", ", W, ") of x's dtype, got ",
                    w_.sizes(), " ", w_.scalar_type());
  TORCH_CHECK_VALUE(sigma > 0, op, ": sigma must be > 0, got ", sigma);
  const at::Tensor x = x_.contiguous(), wt = w_.contiguous();
  at::Tensor out = at::empty_like(x, at::MemoryFormat::Contiguous);
  if (out.numel() == 0) return out;
  const int64_t r = gaussian_radius(sigma), P = C + 1;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "normalised_blur_cpu", [&] {
    using T = scalar_t;
    const std::vector<T> taps = gaussian_taps<T>(sigma, r);
    const T* px = x.data_ptr<T>();
    const T* pw = wt.data_ptr<T>();
    T* po = out.data_ptr<T>();
    Scratch<T> hbuf;  // (T, C + 1, H, W): x w (C planes) and w, blurred along x
    hbuf.resize(Tn * P * HW);
    T* hb = hbuf.data();
    at::parallel_for(0, Tn * P * H, row_grain(W * (2 * r + 1)), [&](int64_t r0, int64_t r1) {
      Scratch<T> padb, xwb;
      padb.resize(W + 2 * r);
      xwb.resize(W);
      T* xw = xwb.data();  // x w, 0 where w is
      for (int64_t pr = r0; pr < r1; ++pr) {
        const int64_t t = pr / (P * H), c = (pr / H) % P, y = pr % H;
        const T* w = pw + t * HW + y * W;
        if (c < C) {
          const T* a = px + (t * C + c) * HW + y * W;
          for (int64_t j = 0; j < W; ++j) xw[j] = w[j] != T(0) ? a[j] * w[j] : T(0);
        }
        blur_row(c < C ? xw : w, taps, r, W, padb.data(), hb + (t * P + c) * HW + y * W);
      }
    });
    at::parallel_for(0, Tn * H, row_grain(W * (2 * r + 1) * P), [&](int64_t r0, int64_t r1) {
      Scratch<T> buf;
      buf.resize(P * W);
      T* acc = buf.data();
      for (int64_t row = r0; row < r1; ++row) {
        const int64_t t = row / H, y = row % H;
        for (int64_t c = 0; c < P; ++c) blur_column(hb + (t * P + c) * HW, H, W, y, taps, r, acc + c * W);
        const T* den = acc + C * W;
        for (int64_t c = 0; c < C; ++c) {
          const T* a = px + (t * C + c) * HW + y * W;
          T* o = po + (t * C + c) * HW + y * W;
          for (int64_t j = 0; j < W; ++j) o[j] = den[j] > T(1e-8) ? acc[c * W + j] / den[j] : a[j];
        }
      }
    });
  });
  return out;
}

// ------------------------------------------------------------------------------ edges
// footprint._edge_directions: x (T, 3, H, W), k (T,) -> (T, 3, H, W): each pixel's coherence^power and
// edge direction (tx, ty), from the structure tensor of the tone-mapped luminance's central differences
// (0 on the border rows and columns), blurred by footprint_blur's Gaussian of tensor_sigma.
at::Tensor edge_directions_cpu(const at::Tensor& x_, const at::Tensor& k_, double tensor_sigma, double power) {
  const char* op = "_edge_directions";
  check_frames_and_knees(x_, k_, op);
  TORCH_CHECK_VALUE(tensor_sigma > 0, op, ": tensor_sigma must be > 0, got ", tensor_sigma);
  const at::Tensor x = x_.contiguous(), kt = k_.contiguous();
  const int64_t Tn = x.size(0), H = x.size(2), W = x.size(3), HW = H * W;
  at::Tensor out = at::empty_like(x, at::MemoryFormat::Contiguous);
  if (out.numel() == 0) return out;
  const int64_t r = gaussian_radius(tensor_sigma);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "edge_directions_cpu", [&] {
    using T = scalar_t;
    const std::vector<T> taps = gaussian_taps<T>(tensor_sigma, r);
    const T pw = static_cast<T>(power);
    Scratch<T> yb, jb;
    yb.resize(4 * HW);
    jb.resize(3 * HW);  // gx gx, gx gy, gy gy blurred along x
    for (int64_t t = 0; t < Tn; ++t) {
      T* y = yb.data();
      T* j3 = jb.data();
      tone_mapped(x.data_ptr<T>() + t * 3 * HW, kt.data_ptr<T>()[t], H, W, y);
      const T* ly = y + 3 * HW;
      at::parallel_for(0, H, row_grain(W * (2 * r + 1)), [&](int64_t y0, int64_t y1) {
        Scratch<T> rowb, padb;
        rowb.resize(3 * W);
        padb.resize(W + 2 * r);
        for (int64_t i = y0; i < y1; ++i) {
          T* g = rowb.data();
          for (int64_t j = 0; j < W; ++j) {
            const T gx = (j > 0 && j < W - 1) ? (ly[i * W + j + 1] - ly[i * W + j - 1]) / T(2) : T(0);
            const T gy = (i > 0 && i < H - 1) ? (ly[(i + 1) * W + j] - ly[(i - 1) * W + j]) / T(2) : T(0);
            g[j] = gx * gx;
            g[W + j] = gx * gy;
            g[2 * W + j] = gy * gy;
          }
          for (int64_t c = 0; c < 3; ++c) blur_row(g + c * W, taps, r, W, padb.data(), j3 + c * HW + i * W);
        }
      });
      T* po = out.data_ptr<T>() + t * 3 * HW;
      at::parallel_for(0, H, row_grain(W * (2 * r + 1)), [&](int64_t y0, int64_t y1) {
        Scratch<T> accb;
        accb.resize(3 * W);
        T* a = accb.data();
        for (int64_t i = y0; i < y1; ++i) {
          for (int64_t c = 0; c < 3; ++c) blur_column(j3 + c * HW, H, W, i, taps, r, a + c * W);
          for (int64_t j = 0; j < W; ++j) {
            const T jxx = a[j], jxy = a[W + j], jyy = a[2 * W + j];
            const T spread = std::sqrt((jxx - jyy) * (jxx - jyy) + T(4) * jxy * jxy);
            const T tr = std::max(jxx + jyy, T(1e-30));
            T c = spread / tr;
            c = c < T(0) ? T(0) : (c > T(1) ? T(1) : c);
            // the gradient's angle t = atan2(2 jxy, jxx - jyy) / 2 by its half-angle cosine and sine (atan2(0, 0)
            // = 0 where the tensor is isotropic; a sine of 0 counts as positive)
            const T c2 = spread > T(0) ? (jxx - jyy) / spread : T(1);
            const T ct = std::sqrt(std::max(T(0), (T(1) + c2) / T(2)));
            const T st = std::copysign(std::sqrt(std::max(T(0), (T(1) - c2) / T(2))), jxy < T(0) ? T(-1) : T(1));
            po[i * W + j] = pw == T(2) ? c * c : (pw == T(3) ? c * c * c : std::pow(c, pw));
            po[HW + i * W + j] = -st;
            po[2 * HW + i * W + j] = ct;
          }
        }
      });
    }
  });
  return out;
}

// A row of the taps' places, s steps along (tx, ty) from the pixels of row i, clamped to the image (a NaN
// direction, from a NaN sample, to its first pixel: every gather stays inside).
template <typename T>
void tap_places(const T* __restrict tx, const T* __restrict ty, T s, int64_t i, int64_t W, int64_t H,
                T* __restrict fx, T* __restrict fy) {
  const T xmax = static_cast<T>(W - 1), ymax = static_cast<T>(H - 1), fi = static_cast<T>(i);
  for (int64_t j = 0; j < W; ++j) {
    const T a = static_cast<T>(j) + s * tx[j], b = fi + s * ty[j];
    fx[j] = a > T(0) ? (a < xmax ? a : xmax) : T(0);
    fy[j] = b > T(0) ? (b < ymax ? b : ymax) : T(0);
  }
}

// A row of a step's Gaussian, exp(-d^2 inv) where the width sigma > 0, else 0.
template <typename T>
void step_weights(const T* __restrict sigma, const T* __restrict inv, T d2, int64_t W, T* __restrict out) {
  for (int64_t j = 0; j < W; ++j) out[j] = sigma[j] > T(0) ? exp_lanes(-d2 * inv[j]) : T(0);
}

// m = min(m, c) over a row: the least surety met so far along one way from each pixel.
template <typename T>
void running_min(const T* __restrict c, int64_t W, T* __restrict m) {
  for (int64_t j = 0; j < W; ++j) m[j] = c[j] < m[j] ? c[j] : m[j];
}

// A row of the taps' weights along an edge: the step's Gaussian g times the least coherence c on the way times the
// range weight of the luminance of the tap's tone-mapped colour (v0, v1, v2) against the pixel's, l.
template <typename T>
void tap_weights(const T* __restrict v0, const T* __restrict v1, const T* __restrict v2, const T* __restrict l,
                 const T* __restrict g, const T* __restrict c, T inv_range, int64_t W, T* __restrict out) {
  for (int64_t j = 0; j < W; ++j) {
    const T dl = lum(v0[j], v1[j], v2[j]) - l[j];
    out[j] = g[j] * c[j] * exp_lanes(-(dl * dl) * inv_range);
  }
}

// footprint._along_edges: M images x (M, T, 3, H, W) with their knees k (M, T) and per-pixel widths sigma
// (M, T, 1, H, W), along the directions (T, 3, H, W) they share -> (M, T, 3, H, W). Taps at whole steps
// s = +-1 .. ceil(2 max sigma) along (tx, ty), bilinear with the coordinates clamped to the image
// (grid_sample's border padding), each weighed by its Gaussian, the least coherence on the way to it (its
// own included) and the range weight of the luminance of its tone-mapped colour; the average blends in by the
// pixel's coherence and how far it is not a light. The images share the taps' places and corner weights.
at::Tensor along_edges_cpu(const at::Tensor& x_, const at::Tensor& k_, const at::Tensor& sigma_,
                           const at::Tensor& dir_, double range_sigma) {
  const char* op = "_along_edges";
  check_float(x_, "x", op);
  check_shape(x_, "x", op, 5);
  TORCH_CHECK_VALUE(x_.size(2) == 3, op, ": x must be (M, T, 3, H, W), got ", x_.sizes());
  const int64_t M = x_.size(0), Tn = x_.size(1), H = x_.size(3), W = x_.size(4), HW = H * W;
  TORCH_CHECK_VALUE(k_.sizes() == at::IntArrayRef({M, Tn}) && k_.scalar_type() == x_.scalar_type(), op,
                    ": k must be (M, T) = (", M, ", ", Tn, ") of x's dtype, got ", k_.sizes(), " ", k_.scalar_type());
  TORCH_CHECK_VALUE(sigma_.sizes() == at::IntArrayRef({M, Tn, 1, H, W}) && sigma_.scalar_type() == x_.scalar_type(),
                    op, ": sigma must be (M, T, 1, H, W) = (", M, ", ", Tn, ", 1, ", H, ", ", W, ") of x's dtype, got ",
                    sigma_.sizes(), " ", sigma_.scalar_type());
  TORCH_CHECK_VALUE(dir_.sizes() == at::IntArrayRef({Tn, 3, H, W}) && dir_.scalar_type() == x_.scalar_type(), op,
                    ": directions must be (T, 3, H, W) = (", Tn, ", 3, ", H, ", ", W, ") of x's dtype, got ",
                    dir_.sizes());
  TORCH_CHECK_VALUE(range_sigma > 0, op, ": range_sigma must be > 0, got ", range_sigma);
  const at::Tensor x = x_.contiguous(), kt = k_.contiguous(), sg = sigma_.contiguous(), dr = dir_.contiguous();
  at::Tensor out = at::empty_like(x, at::MemoryFormat::Contiguous);
  if (out.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "along_edges_cpu", [&] {
    using T = scalar_t;
    const T* ps = sg.data_ptr<T>();
    T reach = T(0);
    for (int64_t i = 0; i < M * Tn * HW; ++i) reach = std::max(reach, ps[i]);
    const int64_t R = std::max<int64_t>(1, static_cast<int64_t>(std::ceil(2.0 * static_cast<double>(reach))));
    const T inv_range = T(1) / static_cast<T>(2 * range_sigma * range_sigma);
    const int64_t V = 3 * M + 1;  // per pixel each image's y0 y1 y2, then the coherence
    Scratch<T> yb, tapb;
    yb.resize(M * 4 * HW);
    tapb.resize(V * HW);
    for (int64_t t = 0; t < Tn; ++t) {
      T* y = yb.data();  // (M, 4, H, W)
      T* tp = tapb.data();
      const T* coh = dr.data_ptr<T>() + t * 3 * HW;
      const T* tx = coh + HW;
      const T* ty = coh + 2 * HW;
      for (int64_t m = 0; m < M; ++m) {
        T* ym = y + m * 4 * HW;
        tone_mapped(x.data_ptr<T>() + (m * Tn + t) * 3 * HW, kt.data_ptr<T>()[m * Tn + t], H, W, ym);
        for (int64_t p = 0; p < HW; ++p)
          for (int64_t c = 0; c < 3; ++c) tp[V * p + 3 * m + c] = ym[c * HW + p];
      }
      for (int64_t p = 0; p < HW; ++p) tp[V * p + 3 * M] = coh[p];
      // a row at a time, in passes over its pixels that vectorise (positions, weights, exp, sums) around the
      // one that gathers the taps' corners
      at::parallel_for(0, H, row_grain(W * 4 * R * M), [&](int64_t y0, int64_t y1) {
        Scratch<T> rowb;
        rowb.resize((V + 4 + 7 * M) * W);
        T* __restrict fx = rowb.data();
        T* __restrict fy = fx + W;
        T* __restrict v = fy + W;           // V planes: the taps' values
        T* __restrict inv = v + V * W;      // M planes each: 1 / (2 sigma^2), the step's Gaussian,
        T* __restrict wd = inv + M * W;     // the numerators (3 planes), den and a tap's weight
        T* __restrict num = wd + M * W;
        T* __restrict den = num + 3 * M * W;
        T* __restrict wt = den + M * W;
        T* __restrict reach_min = wt + M * W;  // 2 planes: the least surety so far along each way
        for (int64_t i = y0; i < y1; ++i) {
          const int64_t row = i * W;
          const T* __restrict txr = tx + row;
          const T* __restrict tyr = ty + row;
          for (int64_t m = 0; m < M; ++m) {
            const T* __restrict sr = ps + (m * Tn + t) * HW + row;
            const T* ym = y + m * 4 * HW;
            for (int64_t j = 0; j < W; ++j) {
              inv[m * W + j] = T(1) / std::max(T(2) * sr[j] * sr[j], T(1e-30));
              for (int64_t c = 0; c < 3; ++c) num[(3 * m + c) * W + j] = ym[c * HW + row + j];
              den[m * W + j] = T(1);
            }
          }
          std::fill(reach_min, reach_min + 2 * W, T(1));
          for (int64_t d = 1; d <= R; ++d) {
            const T dd = static_cast<T>(d * d);
            for (int64_t m = 0; m < M; ++m) step_weights(ps + (m * Tn + t) * HW + row, inv + m * W, dd, W, wd + m * W);
            for (int64_t sgn = 1; sgn >= -1; sgn -= 2) {
              const T step = static_cast<T>(sgn * d);
              tap_places(txr, tyr, step, i, W, H, fx, fy);
              // the gather, its value count fixed at compile time for one image and for three
              auto gather = [&](auto count) {
                constexpr int64_t n = decltype(count)::value;
                const int64_t nv = n > 0 ? n : V;
                for (int64_t j = 0; j < W; ++j) {
                  const int64_t x0 = static_cast<int64_t>(fx[j]), yy0 = static_cast<int64_t>(fy[j]);  // >= 0
                  const int64_t x1 = std::min(x0 + 1, W - 1), yy1 = std::min(yy0 + 1, H - 1);
                  const T ax = fx[j] - static_cast<T>(x0), ay = fy[j] - static_cast<T>(yy0);
                  const T w00 = (T(1) - ax) * (T(1) - ay), w01 = ax * (T(1) - ay), w10 = (T(1) - ax) * ay,
                          w11 = ax * ay;
                  const T *c00 = tp + nv * (yy0 * W + x0), *c01 = tp + nv * (yy0 * W + x1),
                          *c10 = tp + nv * (yy1 * W + x0), *c11 = tp + nv * (yy1 * W + x1);
                  for (int64_t c = 0; c < nv; ++c)
                    v[c * W + j] = w00 * c00[c] + w01 * c01[c] + w10 * c10[c] + w11 * c11[c];
                }
              };
              if (V == 4)
                gather(std::integral_constant<int64_t, 4>());
              else if (V == 10)
                gather(std::integral_constant<int64_t, 10>());
              else
                gather(std::integral_constant<int64_t, 0>());
              running_min(v + 3 * M * W, W, reach_min + (sgn > 0 ? 0 : W));
              for (int64_t m = 0; m < M; ++m) {
                const T* vm = v + 3 * m * W;
                tap_weights(vm, vm + W, vm + 2 * W, y + (m * 4 + 3) * HW + row, wd + m * W,
                            reach_min + (sgn > 0 ? 0 : W), inv_range, W, wt + m * W);
                T* a0 = num + 3 * m * W;
                accumulate_weighted(a0, a0 + W, a0 + 2 * W, den + m * W, wt + m * W, vm, vm + W, vm + 2 * W, W);
              }
            }
          }
          for (int64_t m = 0; m < M; ++m) {
            const T k = kt.data_ptr<T>()[m * Tn + t];
            const T* ym = y + m * 4 * HW;
            T* po = out.data_ptr<T>() + (m * Tn + t) * 3 * HW;
            for (int64_t j = 0; j < W; ++j) {
              const int64_t p = row + j;
              const T blend = coh[p] * (T(1) - light_share(ym[3 * HW + p]));
              for (int64_t c = 0; c < 3; ++c) {
                const T o = ym[c * HW + p] + blend * (num[(3 * m + c) * W + j] / den[m * W + j] - ym[c * HW + p]);
                po[c * HW + p] = k * o / std::max(T(1) - o, T(1e-6));
              }
            }
          }
        }
      });
    }
  });
  return out;
}

// ------------------------------------------------------------------------------ same pixel
// denoise._box_mean of one (H, W) plane: the mean over the (2r+1)^2 box, the border replicated, summed
// along x then along y and divided once, in the same order as the PyTorch sums of shifted views (each
// pixel's first term assigned, the others added). Whole rows at a time, so the lanes vectorise.
template <typename T>
void box_mean_plane(const T* src, int64_t H, int64_t W, int64_t r, T* tmp, T* dst) {
  const T n = T((2 * r + 1) * (2 * r + 1));
  for (int64_t y = 0; y < H; ++y) {
    const T* s = src + y * W;
    T* t = tmp + y * W;
    for (int64_t k = -r; k <= r; ++k) {
      const int64_t lo = std::min<int64_t>(W, std::max<int64_t>(0, -k)), hi = std::max<int64_t>(lo, W - k);
      const int64_t mid = std::min(hi, W);
      if (k == -r) {
        for (int64_t x = 0; x < lo; ++x) t[x] = s[0];
        for (int64_t x = lo; x < mid; ++x) t[x] = s[x + k];
        for (int64_t x = mid; x < W; ++x) t[x] = s[W - 1];
      } else {
        for (int64_t x = 0; x < lo; ++x) t[x] += s[0];
        for (int64_t x = lo; x < mid; ++x) t[x] += s[x + k];
        for (int64_t x = mid; x < W; ++x) t[x] += s[W - 1];
      }
    }
  }
  for (int64_t y = 0; y < H; ++y) {
    T* o = dst + y * W;
    std::copy(tmp + clampi(y - r, H) * W, tmp + clampi(y - r, H) * W + W, o);
    for (int64_t k = -r + 1; k <= r; ++k) {
      const T* row = tmp + clampi(y + k, H) * W;
      for (int64_t x = 0; x < W; ++x) o[x] += row[x];
    }
    for (int64_t x = 0; x < W; ++x) o[x] = o[x] / n;
  }
}

// box_mean_plane of each of `planes` consecutive (H, W) planes, the planes side by side on the threads.
template <typename T>
void box_mean_planes(const T* src, int64_t planes, int64_t H, int64_t W, int64_t r, T* dst) {
  const int64_t HW = H * W;
  at::parallel_for(0, planes, 1, [&](int64_t c0, int64_t c1) {
    std::vector<T> t(HW);
    for (int64_t c = c0; c < c1; ++c) box_mean_plane(src + c * HW, H, W, r, t.data(), dst + c * HW);
  });
}

// footprint._box_mean: box_mean_planes of every (H, W) plane of x (..., H, W).
at::Tensor box_mean_cpu(const at::Tensor& x_, int64_t radius) {
  const char* op = "_box_mean";
  check_float(x_, "x", op);
  TORCH_CHECK_VALUE(x_.dim() >= 2, op, ": x must be (..., H, W), got ", x_.sizes());
  TORCH_CHECK_VALUE(radius >= 0, op, ": radius must be >= 0, got ", radius);
  const at::Tensor x = x_.contiguous();
  at::Tensor out = at::empty_like(x, at::MemoryFormat::Contiguous);
  const int64_t H = x.size(-2), W = x.size(-1);
  if (x.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "box_mean_cpu", [&] {
    box_mean_planes(x.data_ptr<scalar_t>(), x.numel() / (H * W), H, W, radius, out.data_ptr<scalar_t>());
  });
  return out;
}

// denoise._image_axes of world positions p (3, H, W): central differences (0 on the border columns / rows),
// their 3x3 means, and the normal equations' terms, step by step in the PyTorch stage's float operations.
template <typename T>
struct ImageAxes {
  std::vector<T> ax, a11, a12, a22, det;  // ax: gx (3 planes) then gy (3 planes)
  std::vector<char> solvable;
  int64_t HW;

  ImageAxes(const T* pp, int64_t H, int64_t W)
      : ax(6 * H * W), a11(H * W), a12(H * W), a22(H * W), det(H * W), solvable(H * W), HW(H * W) {
    std::vector<T> g(6 * HW, T(0));
    for (int64_t c = 0; c < 3; ++c) {
      const T* pc = pp + c * HW;
      T* gx = g.data() + c * HW;
      T* gy = g.data() + (3 + c) * HW;
      for (int64_t y = 0; y < H; ++y)
        for (int64_t x = 1; x + 1 < W; ++x) gx[y * W + x] = (pc[y * W + x + 1] - pc[y * W + x - 1]) / T(2);
      for (int64_t y = 1; y + 1 < H; ++y)
        for (int64_t x = 0; x < W; ++x) gy[y * W + x] = (pc[(y + 1) * W + x] - pc[(y - 1) * W + x]) / T(2);
    }
    box_mean_planes(g.data(), 6, H, W, 1, ax.data());
    const T* gx = ax.data();
    const T* gy = ax.data() + 3 * HW;
    for (int64_t i = 0; i < HW; ++i) {
      a11[i] = dot(gx, gx, i);
      a12[i] = dot(gx, gy, i);
      a22[i] = dot(gy, gy, i);
      const T d = a11[i] * a22[i] - a12[i] * a12[i];
      const T s = a11[i] + a22[i];
      solvable[i] = d > T(1e-12) * (s * s);
      det[i] = solvable[i] ? d : T(1);
    }
  }

  T dot(const T* a, const T* b, int64_t i) const {
    return a[i] * b[i] + a[HW + i] * b[HW + i] + a[2 * HW + i] * b[2 * HW + i];
  }

  // denoise._in_image_axes at pixel i of the offset (d0, d1, d2): u, v and whether it lies on the surface
  bool offset(int64_t i, T d0, T d1, T d2, T& uu, T& vv) const { return pixel(i).offset(d0, d1, d2, uu, vv); }

  // one pixel's terms, loaded once for the offsets tested against it
  struct Pixel {
    T gx0, gx1, gx2, gy0, gy1, gy2, a11, a12, a22, det;
    bool solvable;

    bool offset(T d0, T d1, T d2, T& uu, T& vv) const {
      const T b1 = gx0 * d0 + gx1 * d1 + gx2 * d2;
      const T b2 = gy0 * d0 + gy1 * d1 + gy2 * d2;
      uu = (a22 * b1 - a12 * b2) / det;
      vv = (a11 * b2 - a12 * b1) / det;
      const T r0 = (d0 - uu * gx0) - vv * gy0;
      const T r1 = (d1 - uu * gx1) - vv * gy1;
      const T r2 = (d2 - uu * gx2) - vv * gy2;
      return solvable & (r0 * r0 + r1 * r1 + r2 * r2 < T(0.125) * (a11 + a22));
    }
  };

  Pixel pixel(int64_t i) const {
    const T* gx = ax.data();
    const T* gy = ax.data() + 3 * HW;
    return {gx[i], gx[HW + i], gx[2 * HW + i], gy[i], gy[HW + i], gy[2 * HW + i], a11[i], a12[i], a22[i], det[i],
            solvable[i] != 0};
  }
};

// World positions p (3, H, W) and the other frames' others (K, 3, H, W) of its shape and dtype; radius >= 0.
void check_positions(const at::Tensor& p, const at::Tensor& o, int64_t radius, const char* op) {
  check_float(p, "p", op);
  check_shape(p, "p", op, 3);
  check_shape(o, "others", op, 4);
  TORCH_CHECK_VALUE(p.size(0) == 3, op, ": p must be (3, H, W), got ", p.sizes());
  TORCH_CHECK_VALUE(o.size(1) == 3 && o.size(2) == p.size(1) && o.size(3) == p.size(2) &&
                        o.scalar_type() == p.scalar_type(),
                    op, ": others must be (K, 3, H, W) of p's shape and dtype, got ", o.sizes());
  TORCH_CHECK_VALUE(radius >= 0, op, ": radius must be >= 0, got ", radius);
}

// denoise._same_pixel, step by step in its float operations.
at::Tensor same_pixel_cpu(const at::Tensor& p_, const at::Tensor& o_, double same_pixel, double still,
                          int64_t radius) {
  const char* op = "_same_pixel";
  check_positions(p_, o_, radius, op);
  const at::Tensor p = p_.contiguous(), o = o_.contiguous();
  const int64_t K = o.size(0), H = p.size(1), W = p.size(2), HW = H * W;
  at::Tensor out = at::zeros({K, 1, H, W}, p.options().dtype(at::kBool));
  if (HW == 0 || K == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "same_pixel_cpu", [&] {
    using T = scalar_t;
    const T* pp = p.data_ptr<T>();
    const ImageAxes<T> axes(pp, H, W);
    std::vector<T> u(HW), v(HW), w3(3 * HW), m3(3 * HW);
    std::vector<char> on(HW);
    bool* po = out.data_ptr<bool>();
    for (int64_t k = 0; k < K; ++k) {
      const T* pk = o.data_ptr<T>() + k * 3 * HW;
      at::parallel_for(0, H, row_grain(W * 20), [&](int64_t y0, int64_t y1) {
        for (int64_t i = y0 * W; i < y1 * W; ++i) {
          const T d0 = pk[i] - pp[i], d1 = pk[HW + i] - pp[HW + i], d2 = pk[2 * HW + i] - pp[2 * HW + i];
          T uu, vv;
          const bool ok = axes.offset(i, d0, d1, d2, uu, vv);
          const T w = ok ? T(1) : T(0);
          u[i] = uu;
          v[i] = vv;
          on[i] = ok;
          w3[i] = w;
          w3[HW + i] = uu * w;
          w3[2 * HW + i] = vv * w;
        }
      });
      box_mean_planes(w3.data(), 3, H, W, radius, m3.data());
      const T sp = T(same_pixel), st = T(still);
      for (int64_t i = 0; i < HW; ++i) {
        const T n = std::max(m3[i], T(1e-6));
        const bool is_still = std::abs(m3[HW + i]) < st * n && std::abs(m3[2 * HW + i]) < st * n;
        po[k * HW + i] = on[i] && is_still && std::abs(u[i]) < sp && std::abs(v[i]) < sp;
      }
    }
  });
  return out;
}

// One pixel (x, y) of _footprint_samples against one other frame: its 3x3 candidates about (qx, qy), where the
// footprint went (none outside the image), tested in the pixel's axes; nothing where it is not searched.
template <typename T>
void footprint_samples_pixel(const ImageAxes<T>& axes, const T* cc, const T* pk, const T* ak, const T* vk,
                             const bool* rk, int64_t x, int64_t y, int64_t qx, int64_t qy, int64_t H, int64_t W,
                             T* sk, T* nk) {
  const int64_t HW = H * W, i = y * W + x;
  if (!rk[i]) return;
  const typename ImageAxes<T>::Pixel px = axes.pixel(i);
  const T c0 = cc[i], c1 = cc[HW + i], c2 = cc[2 * HW + i];
  T s0 = T(0), s1 = T(0), s2 = T(0), cnt = T(0);
  for (int64_t dy = -1; dy <= 1; ++dy) {
    for (int64_t dx = -1; dx <= 1; ++dx) {
      const int64_t sx = qx + dx, sy = qy + dy;
      const bool inside = sx >= 0 && sx < W && sy >= 0 && sy < H;
      const int64_t j = clampi(sy, H) * W + clampi(sx, W);
      const T d0 = pk[j] - c0, d1 = pk[HW + j] - c1, d2 = pk[2 * HW + j] - c2;
      T uu, vv;
      const bool on = px.offset(d0, d1, d2, uu, vv);
      const bool hit = inside & (vk[j] > T(0)) & (std::abs(uu) < T(0.5)) & (std::abs(vv) < T(0.5)) & on;
      s0 += hit ? ak[j] : T(0);
      s1 += hit ? ak[HW + j] : T(0);
      s2 += hit ? ak[2 * HW + j] : T(0);
      cnt += hit ? T(1) : T(0);
    }
  }
  sk[i] = s0;
  sk[HW + i] = s1;
  sk[2 * HW + i] = s2;
  nk[i] = cnt;
}

#if defined(__AVX2__)
// footprint_samples_pixel of the eight pixels i .. i + 7 of one row whose candidates' centres are the pixels
// q[0 .. 7], every candidate inside the image (alike: q[l] = q[0] + l): the same float operations in eight
// lanes (float only).
template <typename T>
void footprint_samples_x8(const ImageAxes<T>& axes, const T* cc, const T* pk, const T* ak, const T* vk,
                          const bool* rk, int64_t i, const int32_t* q, bool alike, int64_t HW, int64_t W, T* sk,
                          T* nk) {
  static_assert(std::is_same_v<T, float>, "eight float lanes");
  const __m256i qv = _mm256_load_si256(reinterpret_cast<const __m256i*>(q));
  // the eight candidates at offset j from the centres
  auto at = [&](const float* plane, int64_t j) {
    return alike ? _mm256_loadu_ps(plane + q[0] + j) : _mm256_i32gather_ps(plane + j, qv, 4);
  };
  const float* gx = axes.ax.data();
  const float* gy = gx + 3 * HW;
  const __m256 gx0 = _mm256_loadu_ps(gx + i), gx1 = _mm256_loadu_ps(gx + HW + i);
  const __m256 gx2 = _mm256_loadu_ps(gx + 2 * HW + i), gy0 = _mm256_loadu_ps(gy + i);
  const __m256 gy1 = _mm256_loadu_ps(gy + HW + i), gy2 = _mm256_loadu_ps(gy + 2 * HW + i);
  const __m256 a11 = _mm256_loadu_ps(axes.a11.data() + i), a12 = _mm256_loadu_ps(axes.a12.data() + i);
  const __m256 a22 = _mm256_loadu_ps(axes.a22.data() + i), det = _mm256_loadu_ps(axes.det.data() + i);
  const __m256 lim = _mm256_mul_ps(_mm256_set1_ps(0.125f), _mm256_add_ps(a11, a22));
  auto byte_mask = [](const void* bytes) {  // eight bools or chars -> lanes all ones where non-zero
    const __m256i b = _mm256_cvtepu8_epi32(_mm_loadl_epi64(static_cast<const __m128i*>(bytes)));
    return _mm256_castsi256_ps(_mm256_xor_si256(_mm256_cmpeq_epi32(b, _mm256_setzero_si256()),
                                                _mm256_set1_epi32(-1)));
  };
  const __m256 solvable = byte_mask(axes.solvable.data() + i), searched = byte_mask(rk + i);
  const __m256 c0 = _mm256_loadu_ps(cc + i), c1 = _mm256_loadu_ps(cc + HW + i), c2 = _mm256_loadu_ps(cc + 2 * HW + i);
  const __m256 zero = _mm256_setzero_ps(), half = _mm256_set1_ps(0.5f), one = _mm256_set1_ps(1.0f);
  const __m256 magnitude = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff));
  __m256 s0 = zero, s1 = zero, s2 = zero, cnt = zero;
  for (int64_t dy = -1; dy <= 1; ++dy) {
    for (int64_t dx = -1; dx <= 1; ++dx) {
      const int64_t j = dy * W + dx;
      const __m256 d0 = _mm256_sub_ps(at(pk, j), c0);
      const __m256 d1 = _mm256_sub_ps(at(pk + HW, j), c1);
      const __m256 d2 = _mm256_sub_ps(at(pk + 2 * HW, j), c2);
      const __m256 b1 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(gx0, d0), _mm256_mul_ps(gx1, d1)),
                                      _mm256_mul_ps(gx2, d2));
      const __m256 b2 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(gy0, d0), _mm256_mul_ps(gy1, d1)),
                                      _mm256_mul_ps(gy2, d2));
      const __m256 uu = _mm256_div_ps(_mm256_sub_ps(_mm256_mul_ps(a22, b1), _mm256_mul_ps(a12, b2)), det);
      const __m256 vv = _mm256_div_ps(_mm256_sub_ps(_mm256_mul_ps(a11, b2), _mm256_mul_ps(a12, b1)), det);
      const __m256 r0 = _mm256_sub_ps(_mm256_sub_ps(d0, _mm256_mul_ps(uu, gx0)), _mm256_mul_ps(vv, gy0));
      const __m256 r1 = _mm256_sub_ps(_mm256_sub_ps(d1, _mm256_mul_ps(uu, gx1)), _mm256_mul_ps(vv, gy1));
      const __m256 r2 = _mm256_sub_ps(_mm256_sub_ps(d2, _mm256_mul_ps(uu, gx2)), _mm256_mul_ps(vv, gy2));
      const __m256 rr = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(r0, r0), _mm256_mul_ps(r1, r1)),
                                      _mm256_mul_ps(r2, r2));
      __m256 hit = _mm256_and_ps(solvable, _mm256_cmp_ps(rr, lim, _CMP_LT_OQ));
      hit = _mm256_and_ps(hit, _mm256_cmp_ps(at(vk, j), zero, _CMP_GT_OQ));
      hit = _mm256_and_ps(hit, _mm256_cmp_ps(_mm256_and_ps(uu, magnitude), half, _CMP_LT_OQ));
      hit = _mm256_and_ps(hit, _mm256_cmp_ps(_mm256_and_ps(vv, magnitude), half, _CMP_LT_OQ));
      s0 = _mm256_add_ps(s0, _mm256_and_ps(hit, at(ak, j)));
      s1 = _mm256_add_ps(s1, _mm256_and_ps(hit, at(ak + HW, j)));
      s2 = _mm256_add_ps(s2, _mm256_and_ps(hit, at(ak + 2 * HW, j)));
      cnt = _mm256_add_ps(cnt, _mm256_and_ps(hit, one));
    }
  }
  // a pixel not searched keeps its 0
  _mm256_storeu_ps(sk + i, _mm256_and_ps(searched, s0));
  _mm256_storeu_ps(sk + HW + i, _mm256_and_ps(searched, s1));
  _mm256_storeu_ps(sk + 2 * HW + i, _mm256_and_ps(searched, s2));
  _mm256_storeu_ps(nk + i, _mm256_and_ps(searched, cnt));
}
#endif

// denoise._footprint_samples, step by step in its float operations: per other frame, the albedo sum and the
// count of its samples inside each pixel's footprint, at the pixels searched (0 elsewhere, not computed).
std::tuple<at::Tensor, at::Tensor> footprint_samples_cpu(const at::Tensor& p_, const at::Tensor& o_,
                                                         const at::Tensor& a_, const at::Tensor& v_,
                                                         const at::Tensor& s_, int64_t radius) {
  const char* op = "_footprint_samples";
  check_positions(p_, o_, radius, op);
  const int64_t K = o_.size(0), H = p_.size(1), W = p_.size(2), HW = H * W;
  TORCH_CHECK_VALUE(a_.sizes() == o_.sizes() && a_.scalar_type() == p_.scalar_type(), op,
                    ": albedo must be shaped like others ", o_.sizes(), ", got ", a_.sizes());
  TORCH_CHECK_VALUE(v_.dim() == 3 && v_.size(0) == K && v_.size(1) == H && v_.size(2) == W &&
                        v_.scalar_type() == p_.scalar_type(),
                    op, ": valid must be (K, H, W) of p's dtype, got ", v_.sizes());
  TORCH_CHECK_VALUE(s_.sizes() == v_.sizes() && s_.scalar_type() == at::kBool, op,
                    ": search must be bool (K, H, W), got ", s_.scalar_type(), " ", s_.sizes());
  const at::Tensor p = p_.contiguous(), o = o_.contiguous(), a = a_.contiguous(), v = v_.contiguous();
  const at::Tensor search = s_.contiguous();
  at::Tensor sums = at::zeros({K, 3, H, W}, p.options());
  at::Tensor counts = at::zeros({K, 1, H, W}, p.options());
  if (HW == 0 || K == 0) return {sums, counts};
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "footprint_samples_cpu", [&] {
    using T = scalar_t;
    const T* pp = p.data_ptr<T>();
    const ImageAxes<T> axes(pp, H, W);
    // the footprint's centre: the 3x3 mean of the samples' positions
    std::vector<T> centre(3 * HW);
    box_mean_planes(pp, 3, H, W, 1, centre.data());
    const T* cc = centre.data();
    std::vector<T> w3(3 * HW), m3(3 * HW);
    for (int64_t k = 0; k < K; ++k) {
      const T* pk = o.data_ptr<T>() + k * 3 * HW;
      const T* ak = a.data_ptr<T>() + k * 3 * HW;
      const T* vk = v.data_ptr<T>() + k * HW;
      const bool* rk = search.data_ptr<bool>() + k * HW;
      T* sk = sums.data_ptr<T>() + k * 3 * HW;
      T* nk = counts.data_ptr<T>() + k * HW;
      // where the footprint went: the other frame's samples at the same pixels, averaged around
      at::parallel_for(0, H, row_grain(W * 20), [&](int64_t y0, int64_t y1) {
        for (int64_t i = y0 * W; i < y1 * W; ++i) {
          T uu, vv;
          const T d0 = pk[i] - cc[i], d1 = pk[HW + i] - cc[HW + i], d2 = pk[2 * HW + i] - cc[2 * HW + i];
          const bool on = axes.offset(i, d0, d1, d2, uu, vv);
          const T w = on ? vk[i] : T(0);
          w3[i] = w;
          w3[HW + i] = uu * w;
          w3[2 * HW + i] = vv * w;
        }
      });
      box_mean_planes(w3.data(), 3, H, W, radius, m3.data());
      at::parallel_for(0, H, row_grain(W * 60), [&](int64_t y0, int64_t y1) {
        std::vector<int64_t> qxs(W), qys(W);
        for (int64_t y = y0; y < y1; ++y) {
          for (int64_t x = 0; x < W; ++x) {
            const int64_t i = y * W + x;
            const T n = std::max(m3[i], T(1e-6));
            T fx = m3[i] > T(0) ? std::nearbyint(m3[HW + i] / n) : T(0);
            T fy = m3[i] > T(0) ? std::nearbyint(m3[2 * HW + i] / n) : T(0);
            // none where the positions overflow; beyond the image nothing is inside
            fx = std::isfinite(fx) ? std::min(std::max(fx, T(-W - 1)), T(W + 1)) : T(0);
            fy = std::isfinite(fy) ? std::min(std::max(fy, T(-H - 1)), T(H + 1)) : T(0);
            qxs[x] = x - static_cast<int64_t>(fx);
            qys[x] = y - static_cast<int64_t>(fy);
          }
          int64_t x = 0;
#if defined(__AVX2__)
          // eight pixels at once where their 3x3 candidates lie inside the image (gathered, by 32-bit indices,
          // where the eight did not move alike; else eight neighbours in memory)
          if constexpr (std::is_same_v<T, float>) {
            const bool indexable = 3 * HW < (int64_t(1) << 31);
            for (; indexable && x + 8 <= W; x += 8) {
              bool inside = true, alike = true;
              alignas(32) int32_t q[8];
              for (int64_t l = 0; l < 8; ++l) {
                inside = inside && qys[x + l] >= 1 && qys[x + l] + 1 < H && qxs[x + l] >= 1 && qxs[x + l] + 1 < W;
                q[l] = static_cast<int32_t>(qys[x + l] * W + qxs[x + l]);
                alike = alike && q[l] == q[0] + l;
              }
              if (inside) {
                footprint_samples_x8(axes, cc, pk, ak, vk, rk, y * W + x, q, alike, HW, W, sk, nk);
              } else {
                for (int64_t l = 0; l < 8; ++l)
                  footprint_samples_pixel(axes, cc, pk, ak, vk, rk, x + l, y, qxs[x + l], qys[x + l], H, W, sk, nk);
              }
            }
          }
#endif
          for (; x < W; ++x)
            footprint_samples_pixel(axes, cc, pk, ak, vk, rk, x, y, qxs[x], qys[x], H, W, sk, nk);
        }
      });
    }
  });
  return {sums, counts};
}

// ------------------------------------------------------------------------------ position flow
// align: the offsets (a, b) of a list as pairs, checked.
std::vector<std::pair<int64_t, int64_t>> offset_pairs(at::IntArrayRef offsets, const char* op) {
  TORCH_CHECK_VALUE(!offsets.empty() && offsets.size() % 2 == 0, op,
                    ": offsets must be a non-empty list of (dy, dx) pairs, got ", offsets.size(), " numbers");
  std::vector<std::pair<int64_t, int64_t>> out;
  for (size_t i = 0; i < offsets.size(); i += 2) out.emplace_back(offsets[i], offsets[i + 1]);
  return out;
}

void check_positions(const at::Tensor& to, const at::Tensor& source, const char* op) {
  check_float(to, "to", op);
  TORCH_CHECK_VALUE(to.dim() == 3 && to.size(0) >= 1, op, ": to must be (C, H, W), got ", to.sizes());
  TORCH_CHECK_VALUE(source.sizes() == to.sizes() && source.scalar_type() == to.scalar_type(), op,
                    ": source must be shaped and typed like to ", to.sizes(), ", got ", source.sizes(), " ",
                    source.scalar_type());
}

// The number of pixels of a row within r of each x: box_row_mean's divisors.
template <typename T>
std::vector<T> box_row_counts(int64_t W, int64_t r) {
  std::vector<T> n(W);
  for (int64_t x = 0; x < W; ++x) n[x] = T(std::min(W - 1, x + r) - std::max<int64_t>(0, x - r) + 1);
  return n;
}

// align._box along one row: the mean of src over the 2r + 1 pixels around each one that lie in the row (n:
// box_row_counts, so that the division runs on whole vectors).
template <typename T>
void box_row_mean(const T* src, int64_t W, int64_t r, const T* n, T* dst) {
  if (r == 3 && W > 6) {  // align._POOL's: each pixel's seven terms in one vector pass, in the same order
    const T* __restrict s = src;
    T* __restrict d = dst;
    for (int64_t x = 3; x < W - 3; ++x)
      d[x] = (((((s[x - 3] + s[x - 2]) + s[x - 1]) + s[x]) + s[x + 1]) + s[x + 2]) + s[x + 3];
    for (int64_t x : {int64_t(0), int64_t(1), int64_t(2), W - 3, W - 2, W - 1}) {
      T sum = T(0);
      for (int64_t k = std::max<int64_t>(-3, -x); k <= std::min<int64_t>(3, W - 1 - x); ++k) sum += s[x + k];
      d[x] = sum;
    }
    for (int64_t x = 0; x < W; ++x) d[x] /= n[x];
    return;
  }
  std::fill(dst, dst + W, T(0));
  for (int64_t k = -r; k <= r; ++k) {  // whole rows at a time, each pixel's terms in order
    const int64_t lo = std::max<int64_t>(0, -k), hi = std::min(W, W - k);
    for (int64_t x = lo; x < hi; ++x) dst[x] += src[x + k];
  }
  for (int64_t x = 0; x < W; ++x) dst[x] /= n[x];
}

// align._least_cost: per pixel, the offset (dy, dx) + offsets[i] whose cost (the L1 difference of the C
// channels) averaged over the (2 radius + 1)^2 box (along x, then along y; the pixels whose source lies in the
// frame, a mean of the costs over a mean of those pixels) is least, the first on a tie; 1e30 where the pixel's
// own source lies outside. Each task takes whole rows and the box rows around them, so every pixel's numbers are
// the same for any thread count.
template <typename T>
void least_offset_cost_rows(const T* to, const T* src, const int64_t* by, const int64_t* bx,
                            const std::vector<std::pair<int64_t, int64_t>>& offs, int64_t C, int64_t H,
                            int64_t W, int64_t r, const T* row_n, int64_t y0, int64_t y1, int64_t* oy,
                            int64_t* ox, T* oc) {
  // a function of its own, not the task's lambda: its sizes are locals, which the loops can keep in
  // registers and run in whole vectors (a captured reference is read again after every store)
  const int64_t HW = H * W;
  const int64_t h0 = std::max<int64_t>(0, y0 - r), h1 = std::min(H, y1 + r);
  std::vector<T> cost(W), count(W), mean((h1 - h0) * W), share((h1 - h0) * W), column(W), in(W);
  std::vector<int64_t> from(W);
  std::vector<char> full(h1 - h0);  // rows whose every source lies in the frame
  std::vector<T> inside((h1 - h0) * W);  // 1 where each pixel's own source lies in the frame, else 0
  std::vector<int32_t> pick((y1 - y0) * W);  // each pixel's offset of least cost so far
  // each row's runs of pixels that move alike, whose sources lie side by side: from runs[first[y - h0] + k]
  // to the next run's start (or the row's end)
  std::vector<int64_t> runs, first(h1 - h0 + 1);
  for (int64_t y = h0; y < h1; ++y) {
    first[y - h0] = static_cast<int64_t>(runs.size());
    for (int64_t x = 0; x < W; ++x)
      if (x == 0 || by[y * W + x] != by[y * W + x - 1] || bx[y * W + x] != bx[y * W + x - 1]) runs.push_back(x);
  }
  first[h1 - h0] = static_cast<int64_t>(runs.size());
  for (size_t i = 0; i < offs.size(); ++i) {
    const int64_t a = offs[i].first, b = offs[i].second;
    for (int64_t y = h0; y < h1; ++y) {
      bool all_inside = true;
      const int64_t start = first[y - h0], end = first[y - h0 + 1];
      if (end - start > W / 8) {  // runs too short for whole vectors: each pixel's source
        const int64_t* qy = by + y * W;
        const int64_t* qx = bx + y * W;
        for (int64_t x = 0; x < W; ++x) {
          const int64_t sy = y + qy[x] + a, sx = x + qx[x] + b;
          const bool in = sy >= 0 && sy < H && sx >= 0 && sx < W;
          from[x] = in ? sy * W + sx : y * W + x;  // (outside: any pixel, its cost is not counted)
          count[x] = in ? T(1) : T(0);
          all_inside = all_inside && in;
        }
        for (int64_t c = 0; c < C; ++c) {  // channel by channel, each pixel's terms in channel order
          const T* t = to + c * HW + y * W;
          const T* sc = src + c * HW;
          if (c == 0)
            for (int64_t x = 0; x < W; ++x) cost[x] = std::abs(t[x] - sc[from[x]]);
          else
            for (int64_t x = 0; x < W; ++x) cost[x] += std::abs(t[x] - sc[from[x]]);
        }
        for (int64_t x = 0; x < W; ++x) cost[x] = count[x] > T(0) ? cost[x] : T(0);
      } else {
        for (int64_t k = start; k < end; ++k) {  // each run's pixels in whole vectors
          const int64_t s0 = runs[k], s1 = k + 1 < end ? runs[k + 1] : W;
          const int64_t sy = y + by[y * W + s0] + a, shift = bx[y * W + s0] + b;
          const int64_t x0 = sy < 0 || sy >= H ? s1 : std::clamp<int64_t>(-shift, s0, s1);
          const int64_t x1 = sy < 0 || sy >= H ? s1 : std::clamp<int64_t>(W - shift, x0, s1);
          all_inside = all_inside && x0 == s0 && x1 == s1;
          std::fill(cost.begin() + s0, cost.begin() + x0, T(0));
          std::fill(cost.begin() + x1, cost.begin() + s1, T(0));
          std::fill(count.begin() + s0, count.begin() + s1, T(0));
          std::fill(count.begin() + x0, count.begin() + x1, T(1));
          for (int64_t c = 0; c < C && x0 < x1; ++c) {  // each pixel's terms in channel order
            const T* t = to + c * HW + y * W;
            const T* sc = src + c * HW + sy * W + shift;
            if (c == 0)
              for (int64_t x = x0; x < x1; ++x) cost[x] = std::abs(t[x] - sc[x]);
            else
              for (int64_t x = x0; x < x1; ++x) cost[x] += std::abs(t[x] - sc[x]);
          }
        }
      }
      std::copy(count.begin(), count.end(), inside.begin() + (y - h0) * W);
      box_row_mean(cost.data(), W, r, row_n, mean.data() + (y - h0) * W);
      full[y - h0] = all_inside;
      if (!all_inside) box_row_mean(count.data(), W, r, row_n, share.data() + (y - h0) * W);
    }
    for (int64_t y = y0; y < y1; ++y) {
      const int64_t lo = std::max<int64_t>(0, y - r), hi = std::min(H - 1, y + r);
      const T n = T(hi - lo + 1);
      bool every = true;
      for (int64_t k = lo; k <= hi; ++k) every = every && full[k - h0];
      if (hi - lo == 6) {  // align._POOL's: the seven rows in one vector pass, in the same order
        const T* __restrict m = mean.data() + (lo - h0) * W;
        T* __restrict col = column.data();
        for (int64_t x = 0; x < W; ++x)
          col[x] = (((((m[x] + m[W + x]) + m[2 * W + x]) + m[3 * W + x]) + m[4 * W + x]) + m[5 * W + x]) +
                   m[6 * W + x];
      } else {
        std::copy(mean.data() + (lo - h0) * W, mean.data() + (lo - h0 + 1) * W, column.data());
        for (int64_t k = lo + 1; k <= hi; ++k) {
          const T* row = mean.data() + (k - h0) * W;
          for (int64_t x = 0; x < W; ++x) column[x] += row[x];
        }
      }
      if (every) {  // the mean of ones, exactly
        std::fill(in.begin(), in.end(), n);
      } else {
        for (int64_t k = lo; k <= hi; ++k) {
          const T* row_in = share.data() + (k - h0) * W;
          if (full[k - h0])
            for (int64_t x = 0; x < W; ++x) in[x] = k == lo ? T(1) : in[x] + T(1);
          else
            for (int64_t x = 0; x < W; ++x) in[x] = k == lo ? row_in[x] : in[x] + row_in[x];
        }
      }
      // whole vectors: each pixel's cost, then the outside ones replaced, then the running least
      T* __restrict sum = column.data();
      const T* __restrict own = inside.data() + (y - h0) * W;
      const T* __restrict share_in = in.data();
      if (every)  // the count's mean is 1, exactly
        for (int64_t x = 0; x < W; ++x) sum[x] = sum[x] / n;
      else
        for (int64_t x = 0; x < W; ++x) sum[x] = (sum[x] / n) / (share_in[x] / n);
      for (int64_t x = 0; x < W; ++x) sum[x] = own[x] > T(0) ? sum[x] : T(1e30);  // align._OUTSIDE
      T* c = oc + y * W;
      int32_t* p = pick.data() + (y - y0) * W;
      if (i == 0) {
        std::copy(column.begin(), column.end(), c);
        std::fill(p, p + W, 0);
        continue;
      }
      const int32_t here = static_cast<int32_t>(i);
      const T* __restrict cost_x = column.data();
      T* __restrict least = c;
      int32_t* __restrict at = p;
      for (int64_t x = 0; x < W; ++x) {
        const bool better = cost_x[x] < least[x];
        least[x] = better ? cost_x[x] : least[x];
        at[x] = better ? here : at[x];
      }
    }
  }
  for (int64_t y = y0; y < y1; ++y)
    for (int64_t x = 0; x < W; ++x) {
      const auto& o = offs[pick[(y - y0) * W + x]];
      oy[y * W + x] = by[y * W + x] + o.first;
      ox[y * W + x] = bx[y * W + x] + o.second;
    }
}

template <typename T>
void least_offset_cost(const T* to, const T* src, const int64_t* by, const int64_t* bx,
                       const std::vector<std::pair<int64_t, int64_t>>& offs, int64_t C, int64_t H, int64_t W,
                       int64_t r, int64_t* oy, int64_t* ox, T* oc) {
  const std::vector<T> row_n = box_row_counts<T>(W, r);
  // a task's box rows beyond its own are done twice: tasks of at least 8 box heights, and at least a task a
  // thread where the frame has rows enough
  const int64_t grain = std::max<int64_t>(8 * (2 * r + 1), std::min(row_grain(W), H / at::get_num_threads()));
  at::parallel_for(0, H, grain, [&](int64_t y0, int64_t y1) {
    least_offset_cost_rows(to, src, by, bx, offs, C, H, W, r, row_n.data(), y0, y1, oy, ox, oc);
  });
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> least_offset_cost_cpu(
    const at::Tensor& to_, const at::Tensor& source_, const at::Tensor& dy_, const at::Tensor& dx_,
    at::IntArrayRef offsets, int64_t radius) {
  const char* op = "_least_offset_cost";
  check_positions(to_, source_, op);
  const int64_t H = to_.size(1), W = to_.size(2);
  for (auto* t : {&dy_, &dx_})
    TORCH_CHECK_VALUE(t->sizes() == at::IntArrayRef({H, W}) && t->scalar_type() == at::kLong, op,
                      ": dy and dx must be int64 (H, W) = ", at::IntArrayRef({H, W}), ", got ", t->sizes(),
                      " ", t->scalar_type());
  TORCH_CHECK_VALUE(radius >= 0, op, ": radius must be >= 0, got ", radius);
  const auto offs = offset_pairs(offsets, op);
  const at::Tensor to = to_.contiguous(), source = source_.contiguous();
  const at::Tensor dy = dy_.contiguous(), dx = dx_.contiguous();
  at::Tensor oy = at::empty({H, W}, dy.options()), ox = at::empty({H, W}, dy.options());
  at::Tensor oc = at::empty({H, W}, to.options());
  if (H * W == 0) return {oy, ox, oc};
  AT_DISPATCH_FLOATING_TYPES(to.scalar_type(), "least_offset_cost_cpu", [&] {
    least_offset_cost(to.data_ptr<scalar_t>(), source.data_ptr<scalar_t>(), dy.data_ptr<int64_t>(),
                      dx.data_ptr<int64_t>(), offs, to.size(0), H, W, radius, oy.data_ptr<int64_t>(),
                      ox.data_ptr<int64_t>(), oc.data_ptr<scalar_t>());
  });
  return {oy, ox, oc};
}

// One offset's costs over the grid: the L1 differences, summed channel by channel in channel order, between to at
// the grid pixels (tg: (C, N), gathered once for every offset) and source moved by (dy, dx), for the grid pixels
// whose source lies in the frame, into v; their count.
template <typename T>
int64_t offset_costs(const T* __restrict tg, const int64_t* __restrict py, const int64_t* __restrict px, int64_t N,
                     const T* __restrict src, int64_t C, int64_t H, int64_t W, int64_t dy, int64_t dx,
                     T* __restrict v, int64_t* __restrict at, int64_t* __restrict from) {
  int64_t n = 0;
  for (int64_t g = 0; g < N; ++g) {
    const int64_t sy = py[g] + dy, sx = px[g] + dx;
    if (sy < 0 || sy >= H || sx < 0 || sx >= W) continue;
    at[n] = g;
    from[n++] = sy * W + sx;
  }
  for (int64_t c = 0; c < C; ++c) {
    const T* __restrict t = tg + c * N;
    const T* __restrict sc = src + c * H * W;
    if (c == 0)
      for (int64_t g = 0; g < n; ++g) v[g] = std::abs(t[at[g]] - sc[from[g]]);
    else
      for (int64_t g = 0; g < n; ++g) v[g] += std::abs(t[at[g]] - sc[from[g]]);
  }
  return n;
}

// align._median_costs: for each offset, the lower median of the L1 differences between to at the grid pixels
// (ys, xs) and source moved by the offset, over those that stay in the frame (inf where none do). With keep > 0
// the first offsets (at least 25; the search lists the nearest first) are exact, and the keep-th least of their
// medians bounds the others: an offset whose costs lie above it for more than half the grid has a median above
// keep exact ones, so it cannot be among the keep least and comes back inf without its selection. Which offsets
// do is fixed by the list, not by the threads.
at::Tensor median_offset_costs_cpu(const at::Tensor& to_, const at::Tensor& source_, const at::Tensor& ys_,
                                   const at::Tensor& xs_, at::IntArrayRef offsets, int64_t keep) {
  const char* op = "_median_offset_costs";
  check_positions(to_, source_, op);
  TORCH_CHECK_VALUE(ys_.dim() == 1 && ys_.sizes() == xs_.sizes() && ys_.scalar_type() == at::kLong &&
                        xs_.scalar_type() == at::kLong,
                    op, ": ys and xs must be int64 (N,) alike, got ", ys_.sizes(), " and ", xs_.sizes());
  TORCH_CHECK_VALUE(keep >= 0, op, ": keep must be >= 0, got ", keep);
  const int64_t C = to_.size(0), H = to_.size(1), W = to_.size(2), HW = H * W, N = ys_.size(0);
  const auto offs = offset_pairs(offsets, op);
  const int64_t O = static_cast<int64_t>(offs.size());
  const at::Tensor to = to_.contiguous(), source = source_.contiguous();
  const at::Tensor ys = ys_.contiguous(), xs = xs_.contiguous();
  const int64_t* py = ys.data_ptr<int64_t>();
  const int64_t* px = xs.data_ptr<int64_t>();
  for (int64_t g = 0; g < N; ++g)
    TORCH_CHECK_VALUE(py[g] >= 0 && py[g] < H && px[g] >= 0 && px[g] < W, op, ": grid pixel ", g, " (", py[g],
                      ", ", px[g], ") lies outside the (", H, ", ", W, ") frame");
  at::Tensor out = at::empty({O}, to.options());
  AT_DISPATCH_FLOATING_TYPES(to.scalar_type(), "median_offset_costs_cpu", [&] {
    using T = scalar_t;
    const T *pt = to.data_ptr<T>(), *ps = source.data_ptr<T>();
    T* po = out.data_ptr<T>();
    const T inf = std::numeric_limits<T>::infinity();
    std::vector<T> tg(C * N);  // to at the grid, gathered once for every offset
    for (int64_t c = 0; c < C; ++c)
      for (int64_t g = 0; g < N; ++g) tg[c * N + g] = pt[c * HW + py[g] * W + px[g]];
    // offsets i0 .. i1, each median exact, or inf where more than half its costs lie above bound
    auto medians = [&](int64_t i0, int64_t i1, T bound) {
      at::parallel_for(i0, i1, 1, [&](int64_t j0, int64_t j1) {
        std::vector<T> v(N);
        std::vector<int64_t> at(N), from(N);
        for (int64_t i = j0; i < j1; ++i) {
          const int64_t n = offset_costs(tg.data(), py, px, N, ps, C, H, W, offs[i].first, offs[i].second,
                                         v.data(), at.data(), from.data());
          if (n == 0) {
            po[i] = inf;
            continue;
          }
          if (bound < inf) {
            int64_t within = 0;
            for (int64_t g = 0; g < n; ++g) within += v[g] <= bound;
            if (within <= (n - 1) / 2) {  // the lower median lies above bound
              po[i] = inf;
              continue;
            }
          }
          const auto mid = v.begin() + (n - 1) / 2;
          std::nth_element(v.begin(), mid, v.begin() + n);
          po[i] = *mid;
        }
      });
    };
    const int64_t exact = keep > 0 ? std::min(O, std::max<int64_t>(keep, 25)) : O;
    medians(0, exact, inf);
    if (exact < O) {
      std::vector<T> first(po, po + exact);
      std::nth_element(first.begin(), first.begin() + (keep - 1), first.end());
      medians(exact, O, first[keep - 1]);
    }
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(torchmanifold, CPU, m) {
  m.impl("_normalise_guard", &normalise_guard_cpu);
  m.impl("_normalise_guard_bounds", &normalise_guard_bounds_cpu);
  m.impl("_footprint_average", &footprint_average_cpu);
  m.impl("_kuwahara3", &kuwahara3_cpu);
  m.impl("_cv_blend", &cv_blend_cpu);
  m.impl("_cv_residuals", &cv_residuals_cpu);
  m.impl("_quantiles", &quantiles_cpu);
  m.impl("_cv_halves", &cv_halves_cpu);
  m.impl("_cv_halves_out", &cv_halves_out_cpu);
  m.impl("_cv_split", &cv_split_cpu);
  m.impl("_sanitize", &sanitize_cpu);
  m.impl("_normalised_blur", &normalised_blur_cpu);
  m.impl("_box_mean", &box_mean_cpu);
  m.impl("_window_bounds", &window_bounds_cpu);
  m.impl("_same_pixel", &same_pixel_cpu);
  m.impl("_footprint_samples", &footprint_samples_cpu);
  m.impl("_edge_directions", &edge_directions_cpu);
  m.impl("_along_edges", &along_edges_cpu);
  m.impl("_least_offset_cost", &least_offset_cost_cpu);
  m.impl("_median_offset_costs", &median_offset_costs_cpu);
}

}  // namespace cpu
}  // namespace torchmanifold
