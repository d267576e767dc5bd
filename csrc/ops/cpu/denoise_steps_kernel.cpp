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
#include <limits>
#include <vector>

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

// max that propagates NaN from either side, as torch.maximum does
template <typename T>
inline T nan_max(T a, T b) {
  return (a != a || a > b) ? a : b;
}

inline int64_t clampi(int64_t i, int64_t n) { return i < 0 ? 0 : (i >= n ? n - 1 : i); }

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
// Max over a window of 2r + 1 samples (-inf beyond the ends) of every position of a row, by van Herk /
// Gil-Werman: running maxima from each block start (g) and to each block end (h) of the padded row; a
// window is the suffix of one block and the prefix of the next. Exact, so it equals the sparse table of
// denoise._window_max bit for bit. Rows are vectors of `width` lanes (a column pass moves whole rows).
template <typename T>
void window_max_rows(const T* src, int64_t n, int64_t r, int64_t width, T* dst, T* g, T* h) {
  const int64_t len = n + 2 * r, w = 2 * r + 1;
  const T ninf = -std::numeric_limits<T>::infinity();
  auto p = [&](int64_t i, int64_t x) { return (i < r || i >= r + n) ? ninf : src[(i - r) * width + x]; };
  for (int64_t i = 0; i < len; ++i) {
    T* gi = g + i * width;
    if (i % w == 0) {
      for (int64_t x = 0; x < width; ++x) gi[x] = p(i, x);
    } else {
      const T* gp = gi - width;
      for (int64_t x = 0; x < width; ++x) gi[x] = nan_max(gp[x], p(i, x));
    }
  }
  for (int64_t i = len - 1; i >= 0; --i) {
    T* hi = h + i * width;
    if (i % w == w - 1 || i == len - 1) {
      for (int64_t x = 0; x < width; ++x) hi[x] = p(i, x);
    } else {
      const T* hn = hi + width;
      for (int64_t x = 0; x < width; ++x) hi[x] = nan_max(hn[x], p(i, x));
    }
  }
  for (int64_t j = 0; j < n; ++j) {
    const T* a = h + j * width;
    const T* b = g + (j + 2 * r) * width;
    T* d = dst + j * width;
    for (int64_t x = 0; x < width; ++x) d[x] = nan_max(a[x], b[x]);
  }
}

// (2r+1)^2 box max of an (H, W) plane: rows (dim 3) first, then columns, as denoise._box_max.
template <typename T>
void box_max_plane(const T* src, int64_t H, int64_t W, int64_t r, T* dst) {
  std::vector<T> tmp(H * W), g((std::max(H, W) + 2 * r) * W), h(g.size());
  for (int64_t y = 0; y < H; ++y)  // a row is a column of one lane
    window_max_rows(src + y * W, W, r, 1, tmp.data() + y * W, g.data(), h.data());
  window_max_rows(tmp.data(), H, r, W, dst, g.data(), h.data());
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
    T* po = out.data_ptr<T>();
    at::Tensor bounds;  // (N, C, 2, H, W): box max of valid values, box max of minus valid values
    T* pb = nullptr;
    if (radius > 0) {
      bounds = at::empty({N, C, 2, H, W}, num.options());
      pb = bounds.data_ptr<T>();
      const T big = std::numeric_limits<T>::max();
      at::parallel_for(0, N * C * 2, 1, [&](int64_t b0, int64_t b1) {
        std::vector<T> src(HW);
        for (int64_t b = b0; b < b1; ++b) {
          const int64_t n = b / (2 * C), c = (b / 2) % C;
          const T sign = (b % 2) ? T(-1) : T(1);
          const T* v = pv + (n * C + c) * HW;
          const T* m = pm + n * HW;
          for (int64_t i = 0; i < HW; ++i) src[i] = m[i] > T(0) ? sign * v[i] : -big;
          box_max_plane(src.data(), H, W, radius, pb + b * HW);
        }
      });
    }
    at::parallel_for(0, N * H, row_grain(W), [&](int64_t r0, int64_t r1) {
      for (int64_t row = r0; row < r1; ++row) {
        const int64_t n = row / H, y = row % H;
        const T* d = pd + n * HW + y * W;
        const T* m = pm + n * HW + y * W;
        for (int64_t c = 0; c < C; ++c) {
          const int64_t off = (n * C + c) * HW + y * W;
          const T* a = pn + off;
          const T* v = pv + off;
          T* o = po + off;
          for (int64_t x = 0; x < W; ++x) o[x] = d[x] > T(1e-8) ? a[x] / d[x] : v[x] * m[x];
          if (pb) {
            const T* hi = pb + ((n * C + c) * 2) * HW + y * W;
            const T* nlo = hi + HW;
            const T half_big = -std::numeric_limits<T>::max() / T(2);
            for (int64_t x = 0; x < W; ++x) {
              if (!(hi[x] > half_big)) continue;  // no valid sample in the box: unguarded
              T z = o[x];
              const T lo = -nlo[x];
              z = (z != z || z > lo) ? z : lo;         // torch.maximum(out, lo)
              z = (z != z || z < hi[x]) ? z : hi[x];   // torch.minimum(., hi)
              o[x] = z;
            }
          }
        }
      }
    });
  });
  return out;
}

// ------------------------------------------------------------------------- footprint average
// Per frame, the sum of f(pixel) over its rows: per-row double partials added in row order.
template <typename T, typename F>
double frame_sum(int64_t H, int64_t W, const F& f) {
  std::vector<double> rows(H);
  at::parallel_for(0, H, row_grain(W), [&](int64_t y0, int64_t y1) {
    for (int64_t y = y0; y < y1; ++y) {
      double s = 0;
      for (int64_t x = 0; x < W; ++x) s += static_cast<double>(f(y * W + x));
      rows[y] = s;
    }
  });
  double s = 0;
  for (double r : rows) s += r;
  return s;
}

at::Tensor footprint_average_cpu(const at::Tensor& x_, double sigma, double knee, double range_sigma) {
  const char* op = "_footprint_average";
  check_float(x_, "x", op);
  check_shape(x_, "x", op, 4);
  TORCH_CHECK_VALUE(x_.size(1) == 3, op, ": x must be (T, 3, H, W), got ", x_.sizes());
  TORCH_CHECK_VALUE(sigma > 0 && range_sigma > 0, op, ": sigma and range_sigma must be > 0");
  const at::Tensor x = x_.contiguous();
  const int64_t Tn = x.size(0), H = x.size(2), W = x.size(3), HW = H * W;
  at::Tensor out = at::empty_like(x, at::MemoryFormat::Contiguous);
  if (out.numel() == 0) return out;
  const int64_t r = std::max<int64_t>(1, static_cast<int64_t>(std::ceil(3 * sigma)));
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "footprint_average_cpu", [&] {
    using T = scalar_t;
    std::vector<T> ws((2 * r + 1) * (2 * r + 1));
    for (int64_t dy = -r; dy <= r; ++dy)
      for (int64_t dx = -r; dx <= r; ++dx)
        ws[(dy + r) * (2 * r + 1) + dx + r] =
            static_cast<T>(std::exp(-static_cast<double>(dx * dx + dy * dy) / (2 * sigma * sigma)));
    const T inv_den = static_cast<T>(2 * (range_sigma * range_sigma));
    std::vector<T> yb(4 * HW);  // y (3 planes) and its luminance
    for (int64_t t = 0; t < Tn; ++t) {
      const T* px = x.data_ptr<T>() + t * 3 * HW;
      T* po = out.data_ptr<T>() + t * 3 * HW;
      auto cl = [](T v) { return v < T(0) ? T(0) : v; };  // clamp_min(0), NaN kept
      const double s = frame_sum<T>(H, W, [&](int64_t i) {
        return lum(cl(px[i]), cl(px[HW + i]), cl(px[2 * HW + i]));
      });
      T mean = static_cast<T>(s / static_cast<double>(HW));
      mean = (mean != mean || mean > T(1e-12)) ? mean : T(1e-12);
      const T k = static_cast<T>(knee) * mean;
      T* y = yb.data();
      at::parallel_for(0, H, row_grain(W), [&](int64_t y0, int64_t y1) {
        for (int64_t i = y0 * W; i < y1 * W; ++i) {
          const T a = cl(px[i]), b = cl(px[HW + i]), c = cl(px[2 * HW + i]);
          y[i] = a / (k + a);
          y[HW + i] = b / (k + b);
          y[2 * HW + i] = c / (k + c);
          y[3 * HW + i] = lum(y[i], y[HW + i], y[2 * HW + i]);
        }
      });
      at::parallel_for(0, H, row_grain(W * (2 * r + 1) * (2 * r + 1) / 4), [&](int64_t y0, int64_t y1) {
        std::vector<T> num(3 * W), den(W);
        for (int64_t row = y0; row < y1; ++row) {
          std::fill(num.begin(), num.end(), T(0));
          std::fill(den.begin(), den.end(), T(0));
          const T* ly = y + 3 * HW + row * W;
          for (int64_t dy = -r; dy <= r; ++dy) {
            const int64_t sy = clampi(row + dy, H) * W;
            for (int64_t dx = -r; dx <= r; ++dx) {
              const T wsp = ws[(dy + r) * (2 * r + 1) + dx + r];
              for (int64_t xx = 0; xx < W; ++xx) {
                const int64_t j = sy + clampi(xx + dx, W);
                const T d = y[3 * HW + j] - ly[xx];
                const T w = wsp * std::exp(-(d * d) / inv_den);
                num[xx] += w * y[j];
                num[W + xx] += w * y[HW + j];
                num[2 * W + xx] += w * y[2 * HW + j];
                den[xx] += w;
              }
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
constexpr int64_t kMaxBandwidths = 64;  // the per-pixel softmax weights live on the stack

at::Tensor cv_blend_cpu(const at::Tensor& preds_, const at::Tensor& fulls_, const at::Tensor& e_,
                        const at::Tensor& weight_, const at::Tensor& mask_, double blur_sigma, double softness) {
  const char* op = "_cv_blend";
  check_float(e_, "e", op);
  check_shape(preds_, "preds", op, 5);
  check_shape(e_, "e", op, 4);
  const int64_t K = preds_.size(0), Tn = e_.size(0), H = e_.size(2), W = e_.size(3), HW = H * W;
  TORCH_CHECK_VALUE(e_.size(1) == 3, op, ": e must be (T, 3, H, W), got ", e_.sizes());
  TORCH_CHECK_VALUE(K >= 1 && preds_.sizes() == at::IntArrayRef({K, Tn, 3, H, W}) && fulls_.sizes() == preds_.sizes(),
                    op, ": preds and fulls must be (K, T, 3, H, W) = (K, ", e_.sizes(), "), got ", preds_.sizes(),
                    " and ", fulls_.sizes());
  TORCH_CHECK_VALUE(weight_.sizes() == at::IntArrayRef({Tn, 1, H, W}) && mask_.sizes() == weight_.sizes(), op,
                    ": weight and mask must be (T, 1, H, W), got ", weight_.sizes(), " and ", mask_.sizes());
  for (auto* p : {&preds_, &fulls_, &weight_, &mask_})
    TORCH_CHECK_VALUE(p->scalar_type() == e_.scalar_type(), op, ": inputs must share e's dtype");
  TORCH_CHECK_VALUE(K <= kMaxBandwidths, op, ": at most ", kMaxBandwidths, " bandwidths, got ", K);
  TORCH_CHECK_VALUE(blur_sigma > 0 && softness > 0, op, ": blur_sigma and softness must be > 0");
  const at::Tensor preds = preds_.contiguous(), fulls = fulls_.contiguous(), e = e_.contiguous(),
                   weight = weight_.contiguous(), mask = mask_.contiguous();
  at::Tensor out = at::empty_like(e, at::MemoryFormat::Contiguous);
  if (out.numel() == 0) return out;
  const int64_t r = std::max<int64_t>(1, static_cast<int64_t>(std::ceil(3 * blur_sigma)));
  AT_DISPATCH_FLOATING_TYPES(e.scalar_type(), "cv_blend_cpu", [&] {
    using T = scalar_t;
    // taps as denoise.footprint_blur builds them, in T
    std::vector<T> taps(2 * r + 1);
    const T two_s2 = static_cast<T>(2 * blur_sigma * blur_sigma);
    T tsum = 0;
    for (int64_t i = -r; i <= r; ++i) {
      const T f = static_cast<T>(i);
      taps[i + r] = std::exp(-(f * f) / two_s2);
    }
    for (T v : taps) tsum += v;
    for (T& v : taps) v = v / tsum;
    const T* pp = preds.data_ptr<T>();
    const T* pf = fulls.data_ptr<T>();
    const T* pe = e.data_ptr<T>();
    const T* pw = weight.data_ptr<T>();
    const T* pm = mask.data_ptr<T>();
    T* po = out.data_ptr<T>();
    // pass 1: the rows of the K error planes and the mask plane of every frame, blurred along x
    const int64_t P = (K + 1) * Tn;  // plane p < K*T: error of prediction p / T at frame p % T; then masks
    std::vector<T> hb(P * HW);
    at::parallel_for(0, P * H, row_grain(W * (2 * r + 1)), [&](int64_t r0, int64_t r1) {
      std::vector<T> src(W);
      for (int64_t pr = r0; pr < r1; ++pr) {
        const int64_t p = pr / H, y = pr % H;
        if (p < K * Tn) {
          const int64_t kk = p / Tn, t = p % Tn;
          const T* q = pp + (kk * Tn + t) * 3 * HW + y * W;
          const T* v = pe + t * 3 * HW + y * W;
          const T* w = pw + t * HW + y * W;
          for (int64_t x = 0; x < W; ++x) {
            const T d0 = q[x] - v[x], d1 = q[HW + x] - v[HW + x], d2 = q[2 * HW + x] - v[2 * HW + x];
            src[x] = (d0 * d0 + d1 * d1 + d2 * d2) * w[x];
          }
        } else {
          std::copy(pm + (p - K * Tn) * HW + y * W, pm + (p - K * Tn) * HW + (y + 1) * W, src.begin());
        }
        T* o = hb.data() + p * HW + y * W;
        for (int64_t x = 0; x < W; ++x) {
          T s = 0;
          for (int64_t i = -r; i <= r; ++i) s += taps[i + r] * src[clampi(x + i, W)];
          o[x] = s;
        }
      }
    });
    // pass 2: blur along y, normalise by the pooled mask, softmax over the K bandwidths, blend
    at::parallel_for(0, Tn * H, row_grain(W * (2 * r + 1) * (K + 1)), [&](int64_t r0, int64_t r1) {
      std::vector<T> err(K * W), pool(W);
      auto vblur = [&](int64_t p, int64_t y, T* dst) {
        std::fill(dst, dst + W, T(0));
        for (int64_t i = -r; i <= r; ++i) {
          const T* s = hb.data() + p * HW + clampi(y + i, H) * W;
          const T tap = taps[i + r];
          for (int64_t x = 0; x < W; ++x) dst[x] += tap * s[x];
        }
      };
      for (int64_t row = r0; row < r1; ++row) {
        const int64_t t = row / H, y = row % H;
        vblur(K * Tn + t, y, pool.data());
        for (int64_t x = 0; x < W; ++x) pool[x] = (pool[x] != pool[x] || pool[x] > T(1e-6)) ? pool[x] : T(1e-6);
        for (int64_t kk = 0; kk < K; ++kk) {
          T* ek = err.data() + kk * W;
          vblur(kk * Tn + t, y, ek);
          for (int64_t x = 0; x < W; ++x) ek[x] = ek[x] / pool[x];
        }
        for (int64_t x = 0; x < W; ++x) {
          T least = err[x];
          for (int64_t kk = 1; kk < K; ++kk) least = std::min(least, err[kk * W + x]);
          least = (least != least || least > T(1e-30)) ? least : T(1e-30);
          const T scale = static_cast<T>(softness) * least;
          T zmax = -std::numeric_limits<T>::infinity();
          for (int64_t kk = 0; kk < K; ++kk) zmax = std::max(zmax, -err[kk * W + x] / scale);
          T wsum = 0;
          T wk[kMaxBandwidths];
          for (int64_t kk = 0; kk < K; ++kk) {
            wk[kk] = std::exp(-err[kk * W + x] / scale - zmax);
            wsum += wk[kk];
          }
          const int64_t i = y * W + x;
          for (int64_t c = 0; c < 3; ++c) {
            T s = 0;
            for (int64_t kk = 0; kk < K; ++kk) s += pf[((kk * Tn + t) * 3 + c) * HW + i] * (wk[kk] / wsum);
            po[(t * 3 + c) * HW + i] = s;
          }
        }
      }
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(torchmanifold, CPU, m) {
  m.impl("_normalise_guard", &normalise_guard_cpu);
  m.impl("_footprint_average", &footprint_average_cpu);
  m.impl("_kuwahara3", &kuwahara3_cpu);
  m.impl("_cv_blend", &cv_blend_cpu);
}

}  // namespace cpu
}  // namespace torchmanifold
