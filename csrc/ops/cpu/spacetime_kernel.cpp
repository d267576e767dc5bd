// CPU kernel of torchmanifold::spacetime_adaptive_manifold: the joint space-time filter of a window
// of frames into one query frame, for every query (torchmanifold/ops/temporal.py's
// spacetime_adaptive_manifold_torch is the reference it matches, step by step).
//
// Per image and query: the manifolds are built from the query's guide exactly as the spatial kernel
// builds them from its guide (root from block means, breadth-first tree, splits by power iteration
// on M = sum r r^T over every s-th band of rows). What differs is the splat: every frame t with a
// time weight tau_t > 0 splats its own samples with its own guide's weight,
//   P += down(tau_t ms_t exp(-|g_t - eta|^2 / sigma_r^2) f'_t), P0 += down(the same weights),
// summed over the frames before the one blur per node; the slice weights, min D, the clusters and
// the children follow the query guide. Where nothing slices, the output is the time-weighted mean of
// the pixel's finite samples.
//
// Work is split over fixed groups of low-res block rows (each task owns the low-res rows it writes)
// and M over fixed groups summed in order, so the result does not depend on the thread count.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "ops/adaptive_manifold_common.h"
#include "ops/cpu/manifold_ops.h"
#include "ops/cpu/recursive_filter.h"
#include "ops/cpu/workspace.h"

namespace torchmanifold {
namespace cpu {
namespace {

// Full-res rows per task group at least: fixed, so partial sums never depend on the thread count.
constexpr int64_t kGroupRows = 16;

struct SpacetimeOptions {
  double sigma_s, sigma_r;
  int64_t tree_height, power_iterations;
  bool adjust_outliers;
};

// One frame of the window that splats (tau > 0).
template <typename T>
struct Frame {
  const T* f;  // (C, H, W) values
  const T* g;  // (D, H, W) guide
  T tau;
  bool all_finite;  // every value and guide sample finite: no mask
  Scratch<uint8_t> ms;  // (H, W) splat mask when not all_finite
};

// Power iteration u = M v, v = u / |u| from ones / sqrt(D) on the D x D matrix M (row-major); the
// channel of largest spread (first on ties) when |u| <= eps trace(M) or |u| is not finite at any step.
template <typename T>
std::vector<T> dominant_direction(const std::vector<double>& M, int64_t D, int64_t iterations) {
  std::vector<double> v(D, 1.0 / std::sqrt(static_cast<double>(D))), u(D);
  std::vector<T> out(D, T(0));
  double trace = 0;
  for (int64_t d = 0; d < D; ++d) trace += M[d * D + d];
  const double eps = static_cast<double>(std::numeric_limits<T>::epsilon());
  bool collapsed = false;
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

template <typename T>
class SpacetimeFilter {
 public:
  // values/guide: the image's T frames ((T, C, H, W) / (T, D, H, W)); tau: (T,) this query's time
  // weights; query: (D, H, W); out: (C, H, W).
  SpacetimeFilter(const T* values, const T* guide, const T* tau, int64_t frames, const T* query, T* out,
                  int64_t C, int64_t D, int64_t H, int64_t W, const SpacetimeOptions& opt)
      : C_(C), D_(D), H_(H), W_(W), N_(H * W), opt_(opt), df_(downsample_factor(opt.sigma_s, opt.sigma_r)),
        Hl_((H + df_ - 1) / df_), Wl_((W + df_ - 1) / df_), Nl_(Hl_ * Wl_),
        bpg_(std::max<int64_t>(1, kGroupRows / df_)), groups_((Hl_ + bpg_ - 1) / bpg_),
        gram_stride_(gram_band_stride(H, W)), ty_(H, Hl_, df_), tx_(W, Wl_, df_), q_in_(query), S_(out),
        frames_(frames) {
    const double fmax = static_cast<double>(std::numeric_limits<T>::max());
    const double r2 = opt.sigma_r * opt.sigma_r;
    inv_r2_ = static_cast<T>(r2 > 0 ? std::min(1.0 / r2, fmax) : fmax);
    half_inv_r2_ = static_cast<T>(0.5 * static_cast<double>(inv_r2_));
    ss_low_ = opt.sigma_s / static_cast<double>(df_);
    sr_low_ = opt.sigma_r / std::sqrt(2.0);
    for (int64_t t = 0; t < frames; ++t) {
      f_all_.push_back(values + t * C * N_);
      tau_all_.push_back(tau[t]);
      if (tau[t] > T(0)) {
        act_.emplace_back();
        act_.back().f = values + t * C * N_;
        act_.back().g = guide + t * D * N_;
        act_.back().tau = tau[t];
      }
    }
  }

  void run() {
    if (act_.empty()) {  // no frame splats: every pixel takes the fallback, 0 (no weighted sample)
      std::fill(S_, S_ + C_ * N_, T(0));
      return;
    }
    prepare_query();
    prepare_frames();
    if (opt_.adjust_outliers) minD_.resize(N_);
    if (opt_.tree_height > 2) label_.resize(N_);
    std::vector<Node> level;
    level.push_back({1, std::move(root_eta_)});
    for (int64_t depth = 0; depth < opt_.tree_height && !level.empty(); ++depth)
      level = process_level(level, depth);
    slice_and_finish();
  }

 private:
  struct Node {
    int64_t id;  // heap id: children 2 id, 2 id + 1
    Scratch<T> eta;  // (D, Hl, Wl)
  };
  struct Sliced {
    int64_t n = 0;
    Scratch<T> w, P;  // (n, H, W) slice weights, (n, C + 1, Hl, Wl) blurred splats
  };

  template <typename F>
  void rows_parallel(int64_t work_per_row, const F& fn) {
    parallel_work(0, H_, W_ * work_per_row, fn);
  }

  // Block sums of the block row bi in `planes` planes (stride Nl_) -> means over the pixels that
  // exist in each block (a partial edge block averages fewer, as avg_pool2d with ceil_mode).
  void block_means(T* p, int64_t planes, int64_t bi) const {
    const int64_t rows = std::min(H_, (bi + 1) * df_) - bi * df_;
    const T full = static_cast<T>(rows * df_), last = static_cast<T>(rows * (W_ - (Wl_ - 1) * df_));
    for (int64_t c = 0; c < planes; ++c) {
      T* q = p + c * Nl_ + bi * Wl_;
      for (int64_t bj = 0; bj + 1 < Wl_; ++bj) q[bj] /= full;
      q[Wl_ - 1] /= last;
    }
  }

  // Up(eta) of `planes` planes at full-res row i into out ((planes, W)).
  static void eta_row(RowUpsampler<T>& up, int64_t planes, int64_t i, int64_t W, T* out) {
    const T fy = up.seek(i);
    for (int64_t d = 0; d < planes; ++d) {
      const T* __restrict b = up.base(d);
      const T* __restrict db = up.delta(d);
      T* __restrict o = out + d * W;
      for (int64_t j = 0; j < W; ++j) o[j] = b[j] + fy * db[j];
    }
  }

  // dist[j] = sum_d (g[d][j] - e[d][j])^2 for a row (g: row of a (D, H, W) guide at offset `row`).
  void distance_row(const T* g, int64_t row, const T* e, T* dist) const {
    std::fill(dist, dist + W_, T(0));
    for (int64_t d = 0; d < D_; ++d) {
      const T* __restrict gr = g + d * N_ + row;
      const T* __restrict er = e + d * W_;
      for (int64_t j = 0; j < W_; ++j) {
        const T x = gr[j] - er[j];
        dist[j] += x * x;
      }
    }
  }

  std::vector<RowUpsampler<T>> upsamplers(const std::vector<const T*>& low, int64_t planes) const {
    std::vector<RowUpsampler<T>> ups;
    ups.reserve(low.size());
    for (const T* l : low) {
      ups.emplace_back(planes, Hl_, Wl_, W_, ty_, tx_);
      ups.back().reset(l);
    }
    return ups;
  }

  // 2., 6. of the reference on the query guide: its mask, the root manifold
  // h(down(mq q0)) / h(down(mq)) (h(down(q)) when every sample is finite) and gs, the guide with
  // non-finite pixels put on the root manifold.
  void prepare_query() {
    std::vector<uint8_t> ok(H_, 1);
    rows_parallel(D_, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i)
        for (int64_t d = 0; d < D_; ++d) ok[i] = ok[i] && all_finite(q_in_ + d * N_ + i * W_, W_);
    });
    all_q_ = std::all_of(ok.begin(), ok.end(), [](uint8_t m) { return m != 0; });
    const int64_t planes = all_q_ ? D_ : D_ + 1;
    if (!all_q_) {
      mq_.resize(N_);
      rows_parallel(D_, [&](int64_t b, int64_t e) {
        for (int64_t i = b * W_; i < e * W_; ++i) {
          bool m = true;
          for (int64_t d = 0; d < D_; ++d) m = m && std::isfinite(q_in_[d * N_ + i]);
          mq_[i] = m;
        }
      });
    }
    Scratch<T> acc;
    acc.resize(planes * Nl_);
    parallel_work(0, Hl_, df_ * W_ * 2 * planes, [&](int64_t b, int64_t e) {
      std::vector<T> row(W_);
      for (int64_t bi = b; bi < e; ++bi) {
        for (int64_t p = 0; p < planes; ++p) std::fill_n(acc.data() + p * Nl_ + bi * Wl_, Wl_, T(0));
        for (int64_t i = bi * df_; i < std::min(H_, (bi + 1) * df_); ++i)
          for (int64_t p = 0; p < planes; ++p) {
            const T* src = q_in_ + std::min(p, D_ - 1) * N_ + i * W_;
            if (all_q_) {
              block_sum_row(src, W_, df_, Wl_, acc.data() + p * Nl_ + bi * Wl_);
              continue;
            }
            const uint8_t* m = mq_.data() + i * W_;
            for (int64_t j = 0; j < W_; ++j) row[j] = m[j] ? (p < D_ ? src[j] : T(1)) : T(0);
            block_sum_row(row.data(), W_, df_, Wl_, acc.data() + p * Nl_ + bi * Wl_);
          }
        block_means(acc.data(), planes, bi);
      }
    });
    lowpass_planes(acc.data(), planes, Hl_, Wl_, ss_low_);
    gs_ = q_in_;
    if (all_q_) {
      root_eta_ = std::move(acc);
      return;
    }
    root_eta_.resize(D_ * Nl_);
    const T* den = acc.data() + D_ * Nl_;
    for (int64_t d = 0; d < D_; ++d)
      for (int64_t i = 0; i < Nl_; ++i)
        root_eta_[d * Nl_ + i] = den[i] > T(0) ? acc[d * Nl_ + i] / den[i] : T(0);
    gs_buf_.resize(D_ * N_);
    rows_parallel(3 * D_, [&](int64_t b, int64_t e) {
      std::vector<T> tmp(Wl_), up(W_);
      for (int64_t i = b; i < e; ++i)
        for (int64_t d = 0; d < D_; ++d) {
          upsample_row(root_eta_.data() + d * Nl_, 1, Hl_, Wl_, i, W_, ty_, tx_, tmp.data(), up.data());
          const uint8_t* m = mq_.data() + i * W_;
          const T* src = q_in_ + d * N_ + i * W_;
          T* dst = gs_buf_.data() + d * N_ + i * W_;
          for (int64_t j = 0; j < W_; ++j) dst[j] = m[j] ? src[j] : up[j];
        }
    });
    gs_ = gs_buf_.data();
  }

  // 2., 3. over the splatting frames: each frame's splat mask (finite values and guide), and
  // c = lo + (hi - lo) / 2 per channel over every splat sample of every frame.
  void prepare_frames() {
    const int64_t nf = static_cast<int64_t>(act_.size());
    std::vector<T> lo(nf * H_ * C_), hi(nf * H_ * C_);
    for (int64_t a = 0; a < nf; ++a) {
      Frame<T>& fr = act_[a];
      std::vector<uint8_t> ok(H_, 1);
      rows_parallel(C_ + D_, [&](int64_t b, int64_t e) {
        for (int64_t i = b; i < e; ++i) {
          for (int64_t c = 0; c < C_; ++c) ok[i] = ok[i] && all_finite(fr.f + c * N_ + i * W_, W_);
          for (int64_t d = 0; d < D_; ++d) ok[i] = ok[i] && all_finite(fr.g + d * N_ + i * W_, W_);
        }
      });
      fr.all_finite = std::all_of(ok.begin(), ok.end(), [](uint8_t m) { return m != 0; });
      if (!fr.all_finite) fr.ms.resize(N_);
      rows_parallel(3 * C_ + D_, [&](int64_t b, int64_t e) {
        for (int64_t i = b; i < e; ++i) {
          const int64_t row = i * W_;
          uint8_t* m = fr.all_finite ? nullptr : fr.ms.data() + row;
          if (m) {
            std::fill(m, m + W_, uint8_t(1));
            for (int64_t c = 0; c < C_; ++c)
              for (int64_t j = 0; j < W_; ++j) m[j] = m[j] && std::isfinite(fr.f[c * N_ + row + j]);
            for (int64_t d = 0; d < D_; ++d)
              for (int64_t j = 0; j < W_; ++j) m[j] = m[j] && std::isfinite(fr.g[d * N_ + row + j]);
          }
          for (int64_t c = 0; c < C_; ++c) {
            T l = std::numeric_limits<T>::infinity(), h = -l;
            const T* x = fr.f + c * N_ + row;
            if (!m)
              min_max(x, W_, l, h);
            else
              for (int64_t j = 0; j < W_; ++j)
                if (m[j]) l = std::min(l, x[j]), h = std::max(h, x[j]);
            lo[(a * H_ + i) * C_ + c] = l;
            hi[(a * H_ + i) * C_ + c] = h;
          }
        }
      });
    }
    c_.assign(C_, T(0));
    for (int64_t c = 0; c < C_; ++c) {
      T l = std::numeric_limits<T>::infinity(), h = -l;
      for (int64_t r = 0; r < nf * H_; ++r) l = std::min(l, lo[r * C_ + c]), h = std::max(h, hi[r * C_ + c]);
      const T mid = l + (h - l) / T(2);
      c_[c] = std::isfinite(mid) ? mid : T(0);
    }
  }

  bool in_cluster(int64_t depth, const int32_t* lr, int32_t id, int64_t row, int64_t j) const {
    return depth == 0 ? all_q_ || mq_[row + j] != 0 : lr[j] == id;
  }

  // 8. Each node's split direction from M = sum r r^T, r = gs - up(eta) on its cluster, over the
  // rows of every gram_stride_-th band: partial sums per fixed group of rows, added in order.
  std::vector<std::vector<T>> split_directions(const std::vector<Node>& level, int64_t depth) {
    const int64_t n = static_cast<int64_t>(level.size());
    const int64_t msize = D_ * (D_ + 1) / 2;
    std::vector<std::vector<T>> v(n);
    if (opt_.power_iterations <= 0) {
      for (auto& x : v) x.assign(D_, static_cast<T>(1.0 / std::sqrt(static_cast<double>(D_))));
      return v;
    }
    std::vector<double> mpart(n * groups_ * msize, 0.0);
    std::vector<const T*> src(n);
    for (int64_t k = 0; k < n; ++k) src[k] = level[k].eta.data();
    const int64_t group_rows = bpg_ * df_;
    parallel_work(0, groups_, group_rows * W_ * n * (3 * D_ + D_ * D_ / 2) / gram_stride_ + 1,
                  [&](int64_t gb, int64_t ge) {
      // gram_upper_row reads D rounded up to 4 rows plus 4, the extra ones zero
      std::vector<T> res(((D_ + 3) / 4 * 4 + 4) * W_, T(0)), mrow(n * msize);
      std::vector<RowUpsampler<T>> eta = upsamplers(src, D_);
      for (int64_t grp = gb; grp < ge; ++grp) {
        std::fill(mrow.begin(), mrow.end(), T(0));
        for (int64_t i = grp * group_rows; i < std::min(H_, (grp + 1) * group_rows); ++i) {
          if ((i / kGramBand) % gram_stride_ != 0) continue;
          const int64_t row = i * W_;
          const int32_t* lr = depth > 0 ? label_.data() + row : nullptr;
          for (int64_t k = 0; k < n; ++k) {
            eta_row(eta[k], D_, i, W_, res.data());
            const int32_t id = static_cast<int32_t>(level[k].id);
            for (int64_t d = 0; d < D_; ++d) {
              T* r = res.data() + d * W_;
              const T* g = gs_ + d * N_ + row;
              for (int64_t j = 0; j < W_; ++j) r[j] = in_cluster(depth, lr, id, row, j) ? g[j] - r[j] : T(0);
            }
            gram_upper_row(res.data(), D_, W_, mrow.data() + k * msize);
          }
        }
        for (int64_t k = 0; k < n; ++k)
          for (int64_t m = 0; m < msize; ++m)
            mpart[(k * groups_ + grp) * msize + m] = static_cast<double>(mrow[k * msize + m]);
      }
    });
    for (int64_t k = 0; k < n; ++k) {
      std::vector<double> M(D_ * D_, 0.0), tri(msize, 0.0);
      for (int64_t g = 0; g < groups_; ++g)
        for (int64_t m = 0; m < msize; ++m) tri[m] += mpart[(k * groups_ + g) * msize + m];
      int64_t m = 0;
      for (int64_t a = 0; a < D_; ++a)
        for (int64_t b = a; b < D_; ++b, ++m) M[a * D_ + b] = M[b * D_ + a] = tri[m];
      v[k] = dominant_direction<T>(M, D_, opt_.power_iterations);
    }
    return v;
  }

  // One level: per node the slice weight w (query guide), min D, the splats of every frame, the
  // blur, and (internal levels) the split into the children's manifolds.
  std::vector<Node> process_level(std::vector<Node>& level, int64_t depth) {
    const int64_t n = static_cast<int64_t>(level.size());
    const bool leaf = depth + 1 >= opt_.tree_height;
    const bool keep_labels = depth + 2 < opt_.tree_height;
    std::vector<std::vector<T>> v;
    if (!leaf) v = split_directions(level, depth);
    const int64_t nf = static_cast<int64_t>(act_.size());
    const int64_t pnode = (C_ + 1) * Nl_, qside = (D_ + 1) * Nl_;
    Sliced sl;
    sl.n = n;
    sl.w.resize(n * N_);
    sl.P.resize(n * pnode);  // each task clears the block rows it sums into
    Scratch<T> Q;            // [node][side][D + 1][Nl]: down(theta gs) planes then down(theta)
    if (!leaf) Q.resize(n * 2 * qside);
    std::vector<const T*> src(n);
    for (int64_t k = 0; k < n; ++k) src[k] = level[k].eta.data();
    const int64_t work = bpg_ * df_ * W_ * n * ((nf + 1) * (3 * D_ + 8) + 2 * nf * C_ + (leaf ? 0 : 4 * D_));
    parallel_work(0, groups_, work, [&](int64_t gb, int64_t ge) {
      std::vector<T> e(D_ * W_), dist(W_), ws(W_), fp(C_ * W_), t0(W_), t1(W_);
      std::vector<RowUpsampler<T>> eta = upsamplers(src, D_);
      for (int64_t bi = gb * bpg_; bi < std::min(Hl_, ge * bpg_); ++bi) {
        for (int64_t p = 0; p < n * (C_ + 1); ++p) std::fill_n(sl.P.data() + p * Nl_ + bi * Wl_, Wl_, T(0));
        for (int64_t p = 0; !leaf && p < n * 2 * (D_ + 1); ++p)
          std::fill_n(Q.data() + p * Nl_ + bi * Wl_, Wl_, T(0));
        for (int64_t i = bi * df_; i < std::min(H_, (bi + 1) * df_); ++i) {
          const int64_t row = i * W_;
          for (int64_t k = 0; k < n; ++k) {
            eta_row(eta[k], D_, i, W_, e.data());
            // the query's weight: slices, min D and the split
            distance_row(gs_, row, e.data(), dist.data());
            T* wr = sl.w.data() + k * N_ + row;
            exp_neg_scaled_row(dist.data(), inv_r2_, wr, W_);
            if (opt_.adjust_outliers) {
              T* mr = minD_.data() + row;
              if (depth == 0)
                std::copy(dist.begin(), dist.end(), mr);
              else
                for (int64_t j = 0; j < W_; ++j) mr[j] = std::min(mr[j], dist[j]);
            }
            // every frame splats with its own guide's weight times its time weight
            T* pk = sl.P.data() + k * pnode;
            for (int64_t a = 0; a < nf; ++a) {
              const Frame<T>& fr = act_[a];
              const uint8_t* m = fr.all_finite ? nullptr : fr.ms.data() + row;
              distance_row(fr.g, row, e.data(), ws.data());
              exp_neg_scaled_row(ws.data(), inv_r2_, ws.data(), W_);
              if (m)  // a select, not a product: the distance to a non-finite guide is NaN
                for (int64_t j = 0; j < W_; ++j) ws[j] = m[j] ? ws[j] * fr.tau : T(0);
              else
                for (int64_t j = 0; j < W_; ++j) ws[j] *= fr.tau;
              for (int64_t c = 0; c < C_; ++c) {
                const T* x = fr.f + c * N_ + row;
                T* y = fp.data() + c * W_;
                const T cc = c_[c];
                if (m)
                  for (int64_t j = 0; j < W_; ++j) y[j] = m[j] ? x[j] - cc : T(0);
                else
                  for (int64_t j = 0; j < W_; ++j) y[j] = x[j] - cc;
                block_dot_row(ws.data(), y, W_, df_, Wl_, pk + c * Nl_ + bi * Wl_);
              }
              block_sum_row(ws.data(), W_, df_, Wl_, pk + C_ * Nl_ + bi * Wl_);
            }
            if (leaf) continue;
            // the split: side of v . (gs - eta), theta = 1 - w on the cluster
            const int32_t id = static_cast<int32_t>(level[k].id);
            int32_t* lr = label_.size() > 0 ? label_.data() + row : nullptr;
            std::fill(t0.begin(), t0.end(), T(0));
            for (int64_t d = 0; d < D_; ++d) {
              const T vd = v[k][d];
              const T* g = gs_ + d * N_ + row;
              const T* er = e.data() + d * W_;
              for (int64_t j = 0; j < W_; ++j) t0[j] += vd * (g[j] - er[j]);
            }
            for (int64_t j = 0; j < W_; ++j) {
              const bool in = in_cluster(depth, lr, id, row, j);
              const bool plus = t0[j] >= T(0);
              const T theta = T(1) - wr[j];
              t0[j] = in && !plus ? theta : T(0);
              t1[j] = in && plus ? theta : T(0);
              if (!keep_labels) continue;
              if (in)
                lr[j] = 2 * id + (plus ? 1 : 0);
              else if (depth == 0)
                lr[j] = 0;  // label 0 is never a node
            }
            T* q = Q.data() + k * 2 * qside;
            for (int64_t d = 0; d < D_; ++d) {
              const T* g = gs_ + d * N_ + row;
              block_dot_row(t0.data(), g, W_, df_, Wl_, q + d * Nl_ + bi * Wl_);
              block_dot_row(t1.data(), g, W_, df_, Wl_, q + qside + d * Nl_ + bi * Wl_);
            }
            block_sum_row(t0.data(), W_, df_, Wl_, q + D_ * Nl_ + bi * Wl_);
            block_sum_row(t1.data(), W_, df_, Wl_, q + qside + D_ * Nl_ + bi * Wl_);
          }
        }
        block_means(sl.P.data(), n * (C_ + 1), bi);
        if (!leaf) block_means(Q.data(), n * 2 * (D_ + 1), bi);
      }
    });
    for (int64_t k = 0; k < n; ++k) {
      Scratch<T> ah, av;
      ah.resize(Nl_);
      av.resize(Nl_);
      domain_transform_coefficients(level[k].eta.data(), D_, Hl_, Wl_, ss_low_, sr_low_, ah.data(), av.data());
      domain_transform_planes(sl.P.data() + k * pnode, C_ + 1, Hl_, Wl_, ah.data(), av.data());
    }
    sliced_.push_back(std::move(sl));
    std::vector<Node> next;
    if (leaf) return next;

    // children: eta = h(down(theta gs)) / h(down(theta)), the parent's manifold where 0/0; a child
    // with no mass (theta >= 0, so any positive block mean means a positive sum) is pruned
    std::vector<int64_t> made;
    for (int64_t c = 0; c < 2 * n; ++c) {
      const T* q0 = Q.data() + c * qside + D_ * Nl_;
      if (std::any_of(q0, q0 + Nl_, [](T x) { return x > T(0); })) made.push_back(c);
    }
    lowpass_planes(Q.data(), 2 * n * (D_ + 1), Hl_, Wl_, ss_low_);
    for (int64_t c : made) {
      next.push_back({2 * level[c / 2].id + c % 2, Scratch<T>()});
      next.back().eta.resize(D_ * Nl_);
    }
    const int64_t m = static_cast<int64_t>(made.size());
    parallel_work(0, m * D_, 2 * Nl_, [&](int64_t b, int64_t e) {
      for (int64_t t = b; t < e; ++t) {
        const int64_t c = made[t / D_], d = t % D_;
        const T* q = Q.data() + c * qside + d * Nl_;
        const T* q0 = Q.data() + c * qside + D_ * Nl_;
        const T* parent = level[c / 2].eta.data() + d * Nl_;
        T* eta = next[t / D_].eta.data() + d * Nl_;
        for (int64_t i = 0; i < Nl_; ++i) eta[i] = q0[i] > T(0) ? q[i] / q0[i] : parent[i];
      }
    });
    return next;
  }

  // S = sum over levels and nodes of w up(blur P), S0 likewise; out = c + S / S0 where S0 clears the
  // floor, else the time-weighted mean of the pixel's finite samples; then the outlier pull.
  void slice_and_finish() {
    int64_t nodes = 0;
    for (const Sliced& l : sliced_) nodes += l.n;
    const T s0_floor = std::numeric_limits<T>::min() / std::numeric_limits<T>::epsilon();
    rows_parallel(20 + 12 * C_ + 4 * (C_ + 1) * nodes, [&](int64_t b, int64_t e) {
      std::vector<T> s0(W_), fb(C_ * W_), alpha(W_), up(W_);
      std::vector<uint8_t> has(W_);
      std::vector<std::vector<RowUpsampler<T>>> ups;
      for (const Sliced& l : sliced_) {
        std::vector<const T*> blurred(l.n);
        for (int64_t k = 0; k < l.n; ++k) blurred[k] = l.P.data() + k * (C_ + 1) * Nl_;
        ups.push_back(upsamplers(blurred, C_ + 1));
      }
      for (int64_t i = b; i < e; ++i) {
        const int64_t row = i * W_;
        std::fill(s0.begin(), s0.end(), T(0));
        for (int64_t c = 0; c < C_; ++c) std::fill_n(S_ + c * N_ + row, W_, T(0));
        for (size_t l = 0; l < sliced_.size(); ++l)
          for (int64_t k = 0; k < sliced_[l].n; ++k) {
            RowUpsampler<T>& u = ups[l][k];
            const T fy = u.seek(i);
            const T* wr = sliced_[l].w.data() + k * N_ + row;
            for (int64_t c = 0; c <= C_; ++c) {
              T* s = c < C_ ? S_ + c * N_ + row : s0.data();
              const T* bb = u.base(c);
              const T* db = u.delta(c);
              for (int64_t j = 0; j < W_; ++j) s[j] += wr[j] * (bb[j] + fy * db[j]);
            }
          }
        int64_t low = 0;
        for (int64_t j = 0; j < W_; ++j) low += !(s0[j] > s0_floor);
        if (low == 0 && !opt_.adjust_outliers) {
          for (int64_t c = 0; c < C_; ++c) {
            T* out = S_ + c * N_ + row;
            for (int64_t j = 0; j < W_; ++j) out[j] = c_[c] + out[j] / s0[j];
          }
          continue;
        }
        fallback_row(row, fb.data(), has.data());
        if (opt_.adjust_outliers) {
          exp_neg_scaled_row(minD_.data() + row, half_inv_r2_, alpha.data(), W_);
          for (int64_t j = 0; j < W_; ++j) alpha[j] = has[j] ? alpha[j] : T(1);
        }
        for (int64_t c = 0; c < C_; ++c) {
          T* out = S_ + c * N_ + row;
          const T* f = fb.data() + c * W_;
          for (int64_t j = 0; j < W_; ++j) {
            const T mean = c_[c] + out[j] / (s0[j] > s0_floor ? s0[j] : T(1));
            out[j] = s0[j] > s0_floor ? mean : f[j];
          }
          if (opt_.adjust_outliers)
            for (int64_t j = 0; j < W_; ++j) out[j] = f[j] + alpha[j] * (out[j] - f[j]);
        }
      }
    });
  }

  // The time-weighted mean of the finite samples of every frame at a row (0 where there is none)
  // and whether every channel has one. c_ must be set (the early exit in run() needs no fallback).
  void fallback_row(int64_t row, T* fb, uint8_t* has) const {
    std::vector<T> num(W_), den(W_);
    std::fill(has, has + W_, uint8_t(1));
    for (int64_t c = 0; c < C_; ++c) {
      const T cc = c_[c];  // about c: constant values come back exactly
      std::fill(num.begin(), num.end(), T(0));
      std::fill(den.begin(), den.end(), T(0));
      for (int64_t t = 0; t < frames_; ++t) {
        const T tau = tau_all_[t];
        const T* x = f_all_[t] + c * N_ + row;
        for (int64_t j = 0; j < W_; ++j) {
          const bool fin = std::isfinite(x[j]);
          num[j] += fin ? tau * (x[j] - cc) : T(0);
          den[j] += fin ? tau : T(0);
        }
      }
      T* y = fb + c * W_;
      for (int64_t j = 0; j < W_; ++j) {
        y[j] = den[j] > T(0) ? cc + num[j] / den[j] : T(0);
        has[j] = has[j] && den[j] > T(0);
      }
    }
  }

  const int64_t C_, D_, H_, W_, N_;
  const SpacetimeOptions opt_;
  const int64_t df_, Hl_, Wl_, Nl_, bpg_, groups_, gram_stride_;
  const Taps<T> ty_, tx_;
  const T* q_in_;
  T* S_;  // the output accumulates S
  const int64_t frames_;
  T inv_r2_, half_inv_r2_;
  double ss_low_, sr_low_;
  bool all_q_ = true;
  std::vector<Frame<T>> act_;  // the frames with tau > 0, in order
  std::vector<const T*> f_all_;  // every frame's values, for the fallback
  std::vector<T> tau_all_;
  std::vector<T> c_;
  const T* gs_ = nullptr;
  Scratch<T> root_eta_, gs_buf_, minD_;
  Scratch<uint8_t> mq_;
  Scratch<int32_t> label_;
  std::vector<Sliced> sliced_;
};

at::Tensor spacetime_adaptive_manifold_cpu(const at::Tensor& values, const at::Tensor& guide,
                                           const at::Tensor& weights, const at::Tensor& query_guide,
                                           double sigma_s, double sigma_r, int64_t tree_height,
                                           int64_t power_iterations, bool adjust_outliers) {
  constexpr const char* op = "spacetime_adaptive_manifold: ";
  TORCH_CHECK_VALUE(values.dim() == 5, op, "values must be (B, T, C, H, W), got shape ", values.sizes());
  TORCH_CHECK_VALUE(guide.dim() == 5, op, "guide must be (B, T, D, H, W), got shape ", guide.sizes());
  TORCH_CHECK_VALUE(weights.dim() == 2, op, "weights must be (Q, T), got shape ", weights.sizes());
  TORCH_CHECK_VALUE(query_guide.dim() == 5, op, "query_guide must be (B, Q, D, H, W), got shape ",
                    query_guide.sizes());
  const int64_t B = values.size(0), T = values.size(1), C = values.size(2), H = values.size(3),
                W = values.size(4), D = guide.size(2), Q = weights.size(0);
  TORCH_CHECK_VALUE(guide.size(0) == B && guide.size(1) == T && guide.size(3) == H && guide.size(4) == W,
                    op, "guide must match values in B, T, H, W; got values ", values.sizes(), " and guide ",
                    guide.sizes());
  TORCH_CHECK_VALUE(D >= 1, op, "guide must have at least one channel, got ", guide.sizes());
  TORCH_CHECK_VALUE(weights.size(1) == T, op, "weights must have one weight per frame (T=", T, "), got ",
                    weights.sizes());
  TORCH_CHECK_VALUE(query_guide.size(0) == B && query_guide.size(1) == Q && query_guide.size(2) == D &&
                        query_guide.size(3) == H && query_guide.size(4) == W,
                    op, "query_guide must be (B, Q, D, H, W) = (", B, ", ", Q, ", ", D, ", ", H, ", ", W,
                    "), got ", query_guide.sizes());
  TORCH_CHECK_TYPE(values.scalar_type() == at::kFloat || values.scalar_type() == at::kDouble, op,
                   "values must be float32 or float64, got ", values.scalar_type());
  for (const at::Tensor* t : {&guide, &weights, &query_guide})
    TORCH_CHECK_TYPE(t->scalar_type() == values.scalar_type(), op,
                     "guide, weights and query_guide must have the dtype of values (", values.scalar_type(),
                     "), got ", t->scalar_type());
  TORCH_CHECK_VALUE(values.device().is_cpu() && guide.device().is_cpu() && weights.device().is_cpu() &&
                        query_guide.device().is_cpu(),
                    op, "every tensor must be on the CPU for this kernel");
  TORCH_CHECK_VALUE(std::isfinite(sigma_s) && sigma_s > 0, op, "sigma_s must be a finite number > 0, got ",
                    sigma_s);
  TORCH_CHECK_VALUE(std::isfinite(sigma_r) && sigma_r > 0, op, "sigma_r must be a finite number > 0, got ",
                    sigma_r);
  TORCH_CHECK_VALUE(tree_height >= 1 && tree_height <= 30, op, "tree_height must be in [1, 30], got ",
                    tree_height);
  TORCH_CHECK_VALUE(power_iterations >= 0, op, "power_iterations must be >= 0, got ", power_iterations);
  TORCH_CHECK_VALUE(weights.numel() == 0 || (weights.isfinite().all().item<bool>() &&
                                             weights.ge(0).all().item<bool>()),
                    op, "weights must be finite and >= 0");
  const at::Tensor f = values.contiguous(), g = guide.contiguous(), w = weights.contiguous(),
                   q = query_guide.contiguous();
  at::Tensor out = at::empty({B, Q, C, H, W}, values.options());
  if (out.numel() == 0) return out;
  const SpacetimeOptions opt{sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers};
  const int64_t N = H * W;
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "spacetime_adaptive_manifold_cpu", [&] {
    for (int64_t b = 0; b < B; ++b)
      for (int64_t k = 0; k < Q; ++k) {
        SpacetimeFilter<scalar_t> filt(f.data_ptr<scalar_t>() + b * T * C * N,
                                       g.data_ptr<scalar_t>() + b * T * D * N, w.data_ptr<scalar_t>() + k * T,
                                       T, q.data_ptr<scalar_t>() + (b * Q + k) * D * N,
                                       out.data_ptr<scalar_t>() + (b * Q + k) * C * N, C, D, H, W, opt);
        filt.run();
      }
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(torchmanifold, CPU, m) {
  m.impl("spacetime_adaptive_manifold", &spacetime_adaptive_manifold_cpu);
}

}  // namespace cpu
}  // namespace torchmanifold
