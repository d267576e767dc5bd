// CPU kernel of torchmanifold::adaptive_manifold (Gastal & Oliveira 2012), planar (B,C,H,W).
//
// Per image, the manifold tree is walked depth first (pre-order: k, 2k, 2k+1). For every node two
// fused full-resolution passes run, both split over low-resolution block rows so that each task
// owns the low-res accumulator rows it writes:
//   pass A (splat): eta at the pixel (root: full res; else bilinear from the low-res manifold),
//     D = |guide - eta|^2, w = exp(-D / sigma_r^2), min D, P += w f, P0 += w (area means);
//   low-res domain-transform blur of [P, P0] steered by the node's manifold;
//   power iteration on the residuals of the node's cluster (per-chunk partial sums over fixed
//     chunks, combined in order, so it is independent of the thread count);
//   pass B (slice + split): S += w up(blur P), S0 += w up(blur P0); for internal nodes the
//     cluster label, theta = 1 - w and the masked area sums that build both children.
// Output S / S0 (input where S0 == 0), optionally pulled towards the input by alpha.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "ops/cpu/manifold_ops.h"
#include "ops/cpu/recursive_filter.h"

namespace torchmanifold {
namespace cpu {
namespace {

// Rows per reduction chunk: fixed, so partial sums never depend on the thread count.
constexpr int64_t kReduceRows = 8;

struct Options {
  double sigma_s, sigma_r;
  int64_t tree_height, power_iterations;
  bool adjust_outliers;
};

// One image. The numbered comments refer to the fixed choices listed at the top of
// torchmanifold/ops/_reference.py, which this kernel matches.
template <typename T>
class ImageFilter {
 public:
  ImageFilter(const T* values, const T* guide, T* out, int64_t C, int64_t D, int64_t H, int64_t W,
              const Options& opt)
      : C_(C), D_(D), H_(H), W_(W), N_(H * W), opt_(opt),
        df_(downsample_factor(opt.sigma_s, opt.sigma_r)),
        Hl_((H + df_ - 1) / df_), Wl_((W + df_ - 1) / df_), Nl_(Hl_ * Wl_),
        ty_(H, Hl_, df_), tx_(W, Wl_, df_), f_in_(values), g_in_(guide), out_(out) {
    const double fmax = static_cast<double>(std::numeric_limits<T>::max());
    const double r2 = opt.sigma_r * opt.sigma_r;
    inv_r2_ = static_cast<T>(r2 > 0 ? std::min(1.0 / r2, fmax) : fmax);
    half_inv_r2_ = static_cast<T>(0.5 * static_cast<double>(inv_r2_));
    ss_low_ = opt.sigma_s / static_cast<double>(df_);
    sr_low_ = opt.sigma_r / std::sqrt(2.0);
  }

  void run() {
    prepare();
    w_.assign(N_, T(0));
    S_.assign(C_ * N_, T(0));
    S0_.assign(N_, T(0));
    minD_.assign(N_, std::numeric_limits<T>::infinity());

    // 7. Depth first, pre-order (k, 2k, 2k+1): each node depends only on its parent, so this
    // equals the reference's breadth-first levels. Entries own their low-res manifold.
    struct Entry {
      int64_t id;
      std::vector<T> eta;
    };
    std::vector<Entry> stack;
    stack.push_back({1, {}});
    while (!stack.empty()) {
      Entry e = std::move(stack.back());
      stack.pop_back();
      process_node(e.id, e.eta, stack);
    }
    finish();
  }

 private:
  template <typename F>
  void rows_parallel(int64_t work_per_row, const F& fn) {
    at::parallel_for(0, H_, grain_for(W_ * work_per_row), fn);
  }

  // 2., 3., 6.: masks, sanitised samples, the per-channel offset c, the root manifold and gs.
  void prepare() {
    mg_.assign(N_, 1);
    mv_.assign(N_, 1);
    rows_parallel(C_ + D_, [&](int64_t b, int64_t e) {
      for (int64_t c = 0; c < C_; ++c)
        for (int64_t i = b * W_; i < e * W_; ++i)
          if (!std::isfinite(f_in_[c * N_ + i])) mv_[i] = 0;
      for (int64_t d = 0; d < D_; ++d)
        for (int64_t i = b * W_; i < e * W_; ++i)
          if (!std::isfinite(g_in_[d * N_ + i])) mg_[i] = 0;
    });
    const bool all_g = std::all_of(mg_.begin(), mg_.end(), [](uint8_t m) { return m != 0; });
    const bool all_v = std::all_of(mv_.begin(), mv_.end(), [](uint8_t m) { return m != 0; });

    f_s_ = f_in_;
    if (!all_v) {
      fs_buf_.resize(C_ * N_);
      rows_parallel(C_, [&](int64_t b, int64_t e) {
        for (int64_t c = 0; c < C_; ++c)
          for (int64_t i = b * W_; i < e * W_; ++i) {
            const T x = f_in_[c * N_ + i];
            fs_buf_[c * N_ + i] = std::isfinite(x) ? x : T(0);
          }
      });
      f_s_ = fs_buf_.data();
    }
    ms_.resize(N_);
    for (int64_t i = 0; i < N_; ++i) ms_[i] = mg_[i] & mv_[i];

    // 3. c = lo + (hi - lo) / 2 over splat pixels; min/max are order independent.
    const int64_t chunks = (H_ + kReduceRows - 1) / kReduceRows;
    std::vector<T> lo(chunks * C_, std::numeric_limits<T>::infinity());
    std::vector<T> hi(chunks * C_, -std::numeric_limits<T>::infinity());
    at::parallel_for(0, chunks, grain_for(kReduceRows * W_ * C_), [&](int64_t b, int64_t e) {
      for (int64_t ch = b; ch < e; ++ch) {
        const int64_t p0 = ch * kReduceRows * W_, p1 = std::min(H_, (ch + 1) * kReduceRows) * W_;
        for (int64_t c = 0; c < C_; ++c) {
          T l = lo[ch * C_ + c], h = hi[ch * C_ + c];
          const T* x = f_s_ + c * N_;
          for (int64_t i = p0; i < p1; ++i)
            if (ms_[i]) l = std::min(l, x[i]), h = std::max(h, x[i]);
          lo[ch * C_ + c] = l;
          hi[ch * C_ + c] = h;
        }
      }
    });
    c_.assign(C_, T(0));
    for (int64_t c = 0; c < C_; ++c) {
      T l = std::numeric_limits<T>::infinity(), h = -l;
      for (int64_t ch = 0; ch < chunks; ++ch) l = std::min(l, lo[ch * C_ + c]), h = std::max(h, hi[ch * C_ + c]);
      const T mid = l + (h - l) / T(2);
      c_[c] = std::isfinite(mid) ? mid : T(0);
    }
    fp_.resize(C_ * N_);
    rows_parallel(C_, [&](int64_t b, int64_t e) {
      for (int64_t c = 0; c < C_; ++c) {
        const T* x = f_s_ + c * N_;
        T* y = fp_.data() + c * N_;
        const T cc = c_[c];
        for (int64_t i = b * W_; i < e * W_; ++i) y[i] = ms_[i] ? x[i] - cc : T(0);
      }
    });

    // 6. eta_1 = h(mg g0) / h(mg); with a fully finite guide h(1) == 1 exactly, so eta_1 = h(g).
    gs_ = g_in_;
    if (all_g) {
      eta1_.assign(g_in_, g_in_ + D_ * N_);
      lowpass_planes(eta1_.data(), D_, H_, W_, opt_.sigma_s);
    } else {
      eta1_.resize((D_ + 1) * N_);
      rows_parallel(D_ + 1, [&](int64_t b, int64_t e) {
        for (int64_t d = 0; d < D_; ++d)
          for (int64_t i = b * W_; i < e * W_; ++i) {
            const T x = g_in_[d * N_ + i];
            eta1_[d * N_ + i] = mg_[i] && std::isfinite(x) ? x : T(0);
          }
        for (int64_t i = b * W_; i < e * W_; ++i) eta1_[D_ * N_ + i] = mg_[i] ? T(1) : T(0);
      });
      lowpass_planes(eta1_.data(), D_ + 1, H_, W_, opt_.sigma_s);
      gs_buf_.resize(D_ * N_);
      rows_parallel(2 * D_, [&](int64_t b, int64_t e) {
        const T* den = eta1_.data() + D_ * N_;
        for (int64_t d = 0; d < D_; ++d)
          for (int64_t i = b * W_; i < e * W_; ++i) {
            T& eta = eta1_[d * N_ + i];
            eta = den[i] > T(0) ? eta / den[i] : T(0);
            const T x = g_in_[d * N_ + i];
            // An invalid guide pixel sits on the root manifold; the valid channels of a
            // partially finite pixel are kept only where the whole pixel is valid.
            gs_buf_[d * N_ + i] = mg_[i] ? x : eta;
          }
      });
      eta1_.resize(D_ * N_);
      gs_ = gs_buf_.data();
    }
    // 8. The root's cluster is the pixels with a finite guide; label 0 is never a node.
    if (opt_.tree_height > 1) {
      label_.resize(N_);
      for (int64_t i = 0; i < N_; ++i) label_[i] = mg_[i] ? 1 : 0;
    }
  }

  template <typename Stack>
  void process_node(int64_t id, std::vector<T>& eta_low, Stack& stack) {
    const bool root = id == 1;
    int64_t depth = 0;
    for (int64_t k = id; k > 1; k >>= 1) ++depth;
    const bool leaf = depth + 1 >= opt_.tree_height;
    if (root) eta_low.assign(D_ * Nl_, T(0));
    if (!leaf) R_.resize(D_ * N_);
    std::vector<T> rmax(Hl_, T(0));  // per block row: max |r| over the cluster

    // ---- pass A: D, w, min D, splat P = down(ms w f'), P0 = down(ms w) ----
    std::vector<T> P((C_ + 1) * Nl_, T(0));
    at::parallel_for(0, Hl_, grain_for(df_ * W_ * (D_ + C_ + 4)), [&](int64_t b, int64_t e) {
      std::vector<T> eta(root ? 0 : D_ * W_), tmp(D_ * Wl_), dist(W_), ws(W_);
      for (int64_t bi = b; bi < e; ++bi) {
        const int64_t i0 = bi * df_, i1 = std::min(H_, i0 + df_);
        T rm = T(0);
        for (int64_t i = i0; i < i1; ++i) {
          const int64_t row = i * W_;
          if (root) {
            for (int64_t d = 0; d < D_; ++d)
              block_sum_row(eta1_.data() + d * N_ + row, W_, df_, Wl_,
                            eta_low.data() + d * Nl_ + bi * Wl_);
          } else {
            upsample_row(eta_low.data(), D_, Hl_, Wl_, i, W_, ty_, tx_, tmp.data(), eta.data());
          }
          std::fill(dist.begin(), dist.end(), T(0));
          const int32_t* lr = leaf ? nullptr : label_.data() + row;
          for (int64_t d = 0; d < D_; ++d) {
            const T* gr = gs_ + d * N_ + row;
            const T* er = root ? eta1_.data() + d * N_ + row : eta.data() + d * W_;
            if (leaf) {
              for (int64_t j = 0; j < W_; ++j) {
                const T r = gr[j] - er[j];
                dist[j] += r * r;
              }
            } else {
              T* rr = R_.data() + d * N_ + row;
              for (int64_t j = 0; j < W_; ++j) {
                const T r = gr[j] - er[j];
                rr[j] = r;
                dist[j] += r * r;
              }
              for (int64_t j = 0; j < W_; ++j)
                if (lr[j] == id) rm = std::max(rm, std::abs(rr[j]));
            }
          }
          T* wr = w_.data() + row;
          const uint8_t* sr = ms_.data() + row;
          T* mr = minD_.data() + row;
          for (int64_t j = 0; j < W_; ++j) {
            const T w = exp_nonpositive(-dist[j] * inv_r2_);
            wr[j] = w;
            ws[j] = sr[j] ? w : T(0);
            mr[j] = std::min(mr[j], dist[j]);
          }
          for (int64_t c = 0; c < C_; ++c)
            block_dot_row(ws.data(), fp_.data() + c * N_ + row, W_, df_, Wl_,
                          P.data() + c * Nl_ + bi * Wl_);
          block_sum_row(ws.data(), W_, df_, Wl_, P.data() + C_ * Nl_ + bi * Wl_);
        }
        rmax[bi] = rm;
        // Area means over the pixels that exist in each block.
        const int64_t rows = i1 - i0;
        for (int64_t bj = 0; bj < Wl_; ++bj) {
          const T cnt = static_cast<T>(rows * (std::min(W_, (bj + 1) * df_) - bj * df_));
          for (int64_t c = 0; c <= C_; ++c) P[c * Nl_ + bi * Wl_ + bj] /= cnt;
          if (root)
            for (int64_t d = 0; d < D_; ++d) eta_low[d * Nl_ + bi * Wl_ + bj] /= cnt;
        }
      }
    });

    // ---- low-res blur of [P, P0] steered by the node's manifold ----
    {
      std::vector<T> ah(Nl_), av(Nl_);
      domain_transform_coefficients(eta_low.data(), D_, Hl_, Wl_, ss_low_, sr_low_, ah.data(),
                                    av.data());
      domain_transform_planes(P.data(), C_ + 1, Hl_, Wl_, ah.data(), av.data());
    }

    // ---- 8. split direction ----
    std::vector<T> v;
    if (!leaf) {
      T scale = T(0);
      for (T m : rmax) scale = std::max(scale, m);
      v = split_direction(id, scale > T(0) ? T(1) / scale : T(1));
    }

    // ---- pass B: slice; internal nodes also label, theta and the children's sums ----
    std::vector<T> Q;  // [side][D + 1][Nl]: down(T gs) planes then down(T)
    const int64_t qside = (D_ + 1) * Nl_;
    if (!leaf) Q.assign(2 * qside, T(0));
    at::parallel_for(0, Hl_, grain_for(df_ * W_ * (D_ + C_ + 4)), [&](int64_t b, int64_t e) {
      std::vector<T> up((C_ + 1) * W_), tmp((C_ + 1) * Wl_), t0(W_), t1(W_);
      for (int64_t bi = b; bi < e; ++bi) {
        const int64_t i0 = bi * df_, i1 = std::min(H_, i0 + df_);
        for (int64_t i = i0; i < i1; ++i) {
          const int64_t row = i * W_;
          upsample_row(P.data(), C_ + 1, Hl_, Wl_, i, W_, ty_, tx_, tmp.data(), up.data());
          const T* wr = w_.data() + row;
          for (int64_t c = 0; c <= C_; ++c) {
            T* s = (c < C_ ? S_.data() + c * N_ : S0_.data()) + row;
            const T* u = up.data() + c * W_;
            for (int64_t j = 0; j < W_; ++j) s[j] += wr[j] * u[j];
          }
          if (leaf) continue;
          // t0 first holds the projection v . r, then theta on the - side.
          std::fill(t0.begin(), t0.end(), T(0));
          for (int64_t d = 0; d < D_; ++d) {
            const T* rr = R_.data() + d * N_ + row;
            const T vd = v[d];
            for (int64_t j = 0; j < W_; ++j) t0[j] += vd * rr[j];
          }
          int32_t* lr = label_.data() + row;
          for (int64_t j = 0; j < W_; ++j) {
            const bool in = lr[j] == id;
            const bool plus = t0[j] >= T(0);
            const T theta = T(1) - wr[j];
            t0[j] = in && !plus ? theta : T(0);
            t1[j] = in && plus ? theta : T(0);
            if (in) lr[j] = static_cast<int32_t>(2 * id + (plus ? 1 : 0));
          }
          for (int64_t d = 0; d < D_; ++d) {
            const T* gr = gs_ + d * N_ + row;
            block_dot_row(t0.data(), gr, W_, df_, Wl_, Q.data() + d * Nl_ + bi * Wl_);
            block_dot_row(t1.data(), gr, W_, df_, Wl_, Q.data() + qside + d * Nl_ + bi * Wl_);
          }
          block_sum_row(t0.data(), W_, df_, Wl_, Q.data() + D_ * Nl_ + bi * Wl_);
          block_sum_row(t1.data(), W_, df_, Wl_, Q.data() + qside + D_ * Nl_ + bi * Wl_);
        }
        if (leaf) continue;
        const int64_t rows = i1 - i0;
        for (int64_t bj = 0; bj < Wl_; ++bj) {
          const T cnt = static_cast<T>(rows * (std::min(W_, (bj + 1) * df_) - bj * df_));
          for (int64_t s = 0; s < 2; ++s)
            for (int64_t d = 0; d <= D_; ++d) Q[s * qside + d * Nl_ + bi * Wl_ + bj] /= cnt;
        }
      }
    });
    if (leaf) return;

    // ---- children: eta = h(down(T gs)) / h(down(T)), the parent's manifold where 0/0 ----
    std::vector<T> kids[2];
    for (int64_t s = 0; s < 2; ++s) {
      T* q = Q.data() + s * qside;
      const T* q0 = q + D_ * Nl_;
      // Pruned when sum(T) == 0 (T >= 0, so any positive block mean means a positive sum).
      if (!std::any_of(q0, q0 + Nl_, [](T x) { return x > T(0); })) continue;
      lowpass_planes(q, D_ + 1, Hl_, Wl_, ss_low_);
      std::vector<T>& eta = kids[s];
      eta.resize(D_ * Nl_);
      for (int64_t d = 0; d < D_; ++d)
        for (int64_t i = 0; i < Nl_; ++i)
          eta[d * Nl_ + i] = q0[i] > T(0) ? q[d * Nl_ + i] / q0[i] : eta_low[d * Nl_ + i];
    }
    // Push + first so the - child (2k) is processed first.
    for (int64_t s = 1; s >= 0; --s)
      if (!kids[s].empty()) stack.push_back({2 * id + s, std::move(kids[s])});
  }

  // 8. Power iteration on M = sum over the cluster of rs rs^T (rs = r / max|r|) without forming
  // M: each step is one pass u = sum rs (rs . v). Per-chunk partials, fixed chunks, fixed order.
  std::vector<T> split_direction(int64_t id, T inv_scale) {
    const T eps = std::numeric_limits<T>::epsilon();
    std::vector<double> v(D_, 1.0 / std::sqrt(static_cast<double>(D_)));
    std::vector<double> diag(D_, 0.0);
    bool collapsed = false;
    const int64_t chunks = (H_ + kReduceRows - 1) / kReduceRows;
    // per chunk: u (D) then diag (D)
    std::vector<double> part(chunks * 2 * D_);
    for (int64_t it = 0; it < opt_.power_iterations; ++it) {
      const bool first = it == 0;
      std::vector<T> vt(D_);
      for (int64_t d = 0; d < D_; ++d) vt[d] = static_cast<T>(v[d]);
      at::parallel_for(0, chunks, grain_for(kReduceRows * W_ * 3 * D_), [&](int64_t b, int64_t e) {
        std::vector<T> proj(W_), acc(2 * D_);
        for (int64_t ch = b; ch < e; ++ch) {
          std::fill(acc.begin(), acc.end(), T(0));
          for (int64_t i = ch * kReduceRows; i < std::min(H_, (ch + 1) * kReduceRows); ++i) {
            const int64_t row = i * W_;
            const int32_t* lr = label_.data() + row;
            std::fill(proj.begin(), proj.end(), T(0));
            for (int64_t d = 0; d < D_; ++d) {
              const T* rr = R_.data() + d * N_ + row;
              const T vd = vt[d];
              for (int64_t j = 0; j < W_; ++j) proj[j] += vd * (rr[j] * inv_scale);
            }
            for (int64_t j = 0; j < W_; ++j)
              if (lr[j] != id) proj[j] = T(0);
            for (int64_t d = 0; d < D_; ++d) {
              const T* rr = R_.data() + d * N_ + row;
              T s = T(0);
              for (int64_t j = 0; j < W_; ++j) s += proj[j] * (rr[j] * inv_scale);
              acc[d] += s;
              if (first) {
                T q = T(0);
                for (int64_t j = 0; j < W_; ++j) {
                  const T x = lr[j] == id ? rr[j] * inv_scale : T(0);
                  q += x * x;
                }
                acc[D_ + d] += q;
              }
            }
          }
          for (int64_t k = 0; k < 2 * D_; ++k) part[ch * 2 * D_ + k] = static_cast<double>(acc[k]);
        }
      });
      std::vector<double> u(D_, 0.0);
      for (int64_t ch = 0; ch < chunks; ++ch)
        for (int64_t d = 0; d < D_; ++d) {
          u[d] += part[ch * 2 * D_ + d];
          if (first) diag[d] += part[ch * 2 * D_ + D_ + d];
        }
      double trace = 0, norm = 0;
      for (int64_t d = 0; d < D_; ++d) trace += diag[d], norm += u[d] * u[d];
      norm = std::sqrt(norm);
      const bool bad = !(norm > static_cast<double>(eps) * trace) || !std::isfinite(norm);
      collapsed = collapsed || bad;
      if (!bad)
        for (int64_t d = 0; d < D_; ++d) v[d] = u[d] / norm;
    }
    std::vector<T> out(D_, T(0));
    if (collapsed) {  // split on the channel with the largest spread (first on ties)
      int64_t k = 0;
      for (int64_t d = 1; d < D_; ++d)
        if (diag[d] > diag[k]) k = d;
      out[k] = T(1);
    } else {
      for (int64_t d = 0; d < D_; ++d) out[d] = static_cast<T>(v[d]);
    }
    return out;
  }

  // 9., 10.
  void finish() {
    rows_parallel(C_ + 2, [&](int64_t b, int64_t e) {
      for (int64_t i = b * W_; i < e * W_; ++i) {
        const T s0 = S0_[i];
        const T alpha = opt_.adjust_outliers && mv_[i] ? exp_nonpositive(-minD_[i] * half_inv_r2_)
                                                       : T(1);
        for (int64_t c = 0; c < C_; ++c) {
          const T fs = f_s_[c * N_ + i];
          T g = s0 > T(0) ? c_[c] + S_[c * N_ + i] / s0 : fs;
          if (opt_.adjust_outliers) g = fs + alpha * (g - fs);
          out_[c * N_ + i] = g;
        }
      }
    });
  }

  const int64_t C_, D_, H_, W_, N_;
  const Options opt_;
  const int64_t df_, Hl_, Wl_, Nl_;
  const Taps<T> ty_, tx_;
  const T* f_in_;
  const T* g_in_;
  T* out_;
  T inv_r2_, half_inv_r2_;
  double ss_low_, sr_low_;

  const T* f_s_ = nullptr;  // values with non-finite entries set to 0
  const T* gs_ = nullptr;   // sanitised guide
  std::vector<T> fs_buf_, gs_buf_, fp_, c_;
  std::vector<uint8_t> mg_, mv_, ms_;
  std::vector<T> eta1_, R_, w_, minD_, S_, S0_;
  std::vector<int32_t> label_;
};

at::Tensor adaptive_manifold_cpu(const at::Tensor& values, const at::Tensor& guide,
                                 double sigma_s, double sigma_r, int64_t tree_height,
                                 int64_t power_iterations, bool adjust_outliers) {
  // ValueError / TypeError in Python, each naming the argument and what was expected.
  TORCH_CHECK_VALUE(values.dim() == 4, "adaptive_manifold: values must be (B, C, H, W), got ",
                    values.dim(), " dims");
  TORCH_CHECK_VALUE(guide.dim() == 4, "adaptive_manifold: guide must be (B, D, H, W), got ",
                    guide.dim(), " dims");
  TORCH_CHECK_VALUE(values.size(0) == guide.size(0) && values.size(2) == guide.size(2) &&
                        values.size(3) == guide.size(3),
                    "adaptive_manifold: guide must match values in B, H, W; got values ",
                    values.sizes(), " and guide ", guide.sizes());
  TORCH_CHECK_VALUE(guide.size(1) >= 1,
                    "adaptive_manifold: guide must have at least one channel, got ", guide.sizes());
  TORCH_CHECK_TYPE(values.scalar_type() == at::kFloat || values.scalar_type() == at::kDouble,
                   "adaptive_manifold: values must be float32 or float64, got ",
                   values.scalar_type());
  TORCH_CHECK_TYPE(guide.scalar_type() == values.scalar_type(),
                   "adaptive_manifold: guide must have the dtype of values (", values.scalar_type(),
                   "), got ", guide.scalar_type());
  TORCH_CHECK_VALUE(values.device().is_cpu() && guide.device().is_cpu(),
                    "adaptive_manifold: values and guide must be CPU tensors for this kernel, got ",
                    values.device(), " and ", guide.device());
  TORCH_CHECK_VALUE(std::isfinite(sigma_s) && sigma_s > 0,
                    "adaptive_manifold: sigma_s must be a finite number > 0, got ", sigma_s);
  TORCH_CHECK_VALUE(std::isfinite(sigma_r) && sigma_r > 0,
                    "adaptive_manifold: sigma_r must be a finite number > 0, got ", sigma_r);
  TORCH_CHECK_VALUE(tree_height >= 1 && tree_height <= 30,
                    "adaptive_manifold: tree_height must be in [1, 30], got ", tree_height);
  TORCH_CHECK_VALUE(power_iterations >= 0,
                    "adaptive_manifold: power_iterations must be >= 0, got ", power_iterations);
  const at::Tensor f = values.contiguous();
  const at::Tensor g = guide.contiguous();
  at::Tensor out = at::empty_like(f);
  const int64_t B = f.size(0), C = f.size(1), H = f.size(2), W = f.size(3), D = g.size(1);
  if (out.numel() == 0) return out;
  const Options opt{sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers};
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "adaptive_manifold_cpu", [&] {
    for (int64_t b = 0; b < B; ++b) {
      ImageFilter<scalar_t> filt(f.data_ptr<scalar_t>() + b * C * H * W,
                                 g.data_ptr<scalar_t>() + b * D * H * W,
                                 out.data_ptr<scalar_t>() + b * C * H * W, C, D, H, W, opt);
      filt.run();
    }
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(torchmanifold, CPU, m) {
  m.impl("adaptive_manifold", &adaptive_manifold_cpu);
}

}  // namespace cpu
}  // namespace torchmanifold
