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
#include <cstring>
#include <limits>
#include <vector>

#include "ops/adaptive_manifold_common.h"
#include "ops/cpu/kernel_steps.h"
#include "ops/cpu/manifold_ops.h"
#include "ops/cpu/recursive_filter.h"
#include "ops/cpu/workspace.h"

namespace torchmanifold {
namespace cpu {
namespace {

// Full-res rows per task group at least: fixed, so partial sums never depend on the thread count.
constexpr int64_t kGroupRows = 16;

// One frame of the window that splats (tau > 0).
template <typename T>
struct Frame {
  const T* f;  // (C, H, W) values
  const T* g;  // (D, H, W) guide
  T tau;
  bool all_finite;  // every value and guide sample finite: no mask
  Scratch<uint8_t> ms;  // (H, W) splat mask when not all_finite
};

template <typename T>
class SpacetimeFilter {
 public:
  // values/guide: the image's T frames ((T, C, H, W) / (T, D, H, W)); tau: (T,) this query's time
  // weights; query: (D, H, W); out: (C, H, W).
  // query_frame: the frame whose guide is the query's, bit for bit (-1: none).
  SpacetimeFilter(const T* values, const T* guide, const T* tau, int64_t frames, const T* query,
                  int64_t query_frame, T* out, int64_t C, int64_t D, int64_t H, int64_t W,
                  const FilterOptions& opt)
      : C_(C), D_(D), H_(H), W_(W), N_(H * W), opt_(opt), df_(downsample_factor(opt.sigma_s, opt.sigma_r)),
        Hl_((H + df_ - 1) / df_), Wl_((W + df_ - 1) / df_), Nl_(Hl_ * Wl_),
        bpg_(std::max<int64_t>(1, kGroupRows / df_)), groups_((Hl_ + bpg_ - 1) / bpg_),
        gram_stride_(gram_band_stride(H, W)), ty_(H, Hl_, df_), tx_(W, Wl_, df_), q_in_(query), S_(out),
        frames_(frames) {
    inv_r2_ = inverse_square<T>(opt.sigma_r);
    half_inv_r2_ = static_cast<T>(0.5 * static_cast<double>(inv_r2_));
    ss_low_ = opt.sigma_s / static_cast<double>(df_);
    sr_low_ = opt.sigma_r / std::sqrt(2.0);
    for (int64_t t = 0; t < frames; ++t) {
      f_all_.push_back(values + t * C * N_);
      tau_all_.push_back(tau[t]);
      if (tau[t] > T(0)) {
        if (t == query_frame) query_act_ = static_cast<int64_t>(act_.size());
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
  using Node = ManifoldNode<T>;
  using Sliced = LevelSlices<T>;

  template <typename F>
  void rows_parallel(int64_t work_per_row, const F& fn) {
    parallel_work(0, H_, W_ * work_per_row, fn);
  }

  // Block sums of the block row bi in `planes` planes (stride Nl_) -> means over the pixels that
  // exist in each block (a partial edge block averages fewer, as avg_pool2d with ceil_mode).
  void block_means(T* p, int64_t planes, int64_t bi) const {
    to_block_means(p + bi * Wl_, planes, std::min(H_, (bi + 1) * df_) - bi * df_, df_, W_, Wl_, Nl_);
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
    channel_sum_row<true>(g + row, e, nullptr, dist);
  }

  // out[j] = sum_d v[d] (g[d][j] - e[d][j]) (g: the (D, H, W) guide from the row's first pixel).
  void projection_row(const T* g, const T* e, const T* v, T* out) const {
    channel_sum_row<false>(g, e, v, out);
  }

  // Four 32-byte vectors of pixels sum every channel in registers, instead of loading and storing out
  // per channel; each pixel adds its channels in the same order, so the bits are those of a plain loop.
  template <bool kSquare>
  void channel_sum_row(const T* g, const T* e, const T* v, T* out) const {
    typedef T vec __attribute__((vector_size(32)));
    typedef T vec_u __attribute__((vector_size(32), aligned(sizeof(T)), may_alias));  // unaligned views
    constexpr int64_t L = 32 / sizeof(T), kTile = 4 * L;
    auto term = [&](int64_t d, auto x) { return kSquare ? x * x : v[d] * x; };
    int64_t j0 = 0;
    for (; j0 + kTile <= W_; j0 += kTile) {
      vec acc[4] = {};
      for (int64_t d = 0; d < D_; ++d)
        for (int q = 0; q < 4; ++q) {
          const int64_t j = j0 + q * L;
          acc[q] += term(d, *reinterpret_cast<const vec_u*>(g + d * N_ + j) -
                                *reinterpret_cast<const vec_u*>(e + d * W_ + j));
        }
      for (int q = 0; q < 4; ++q) *reinterpret_cast<vec_u*>(out + j0 + q * L) = acc[q];
    }
    std::fill(out + j0, out + W_, T(0));
    for (int64_t d = 0; d < D_; ++d)
      for (int64_t j = j0; j < W_; ++j) out[j] += term(d, g[d * N_ + j] - e[d * W_ + j]);
  }

  std::vector<RowUpsampler<T>> upsamplers(const std::vector<const T*>& low, int64_t planes) const {
    return make_upsamplers(low, planes, Hl_, Wl_, W_, ty_, tx_);
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
    gs_buf_.resize(D_ * N_);
    masked_root_and_guide(acc.data(), q_in_, mq_.data(), D_, H_, W_, Hl_, Wl_, ty_, tx_, root_eta_.data(),
                          gs_buf_.data());
    gs_ = gs_buf_.data();
  }

  // 2., 3. over the splatting frames: each frame's splat mask (finite values and guide), and
  // c = clamp(0, lo, hi) per channel over every splat sample of every frame.
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
    c_ = channel_centres(lo, hi, nf * H_, C_);
  }

  // The query guide's mask at the row at offset `row`, nullptr when every query sample is finite.
  const uint8_t* query_mask(int64_t row) const { return all_q_ ? nullptr : mq_.data() + row; }

  // 8. Each node's split direction from M = sum r r^T, r = gs - up(eta) on its cluster, over the
  // rows of every gram_stride_-th band: partial sums per fixed group of rows, added in order.
  std::vector<std::vector<T>> split_directions(const std::vector<Node>& level, int64_t depth) {
    const int64_t n = static_cast<int64_t>(level.size());
    const int64_t msize = D_ * (D_ + 1) / 2;
    std::vector<std::vector<T>> v(n);
    if (opt_.power_iterations <= 0) {  // no M to sum
      for (auto& x : v) x = split_direction<T>(nullptr, 0, D_, 0);
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
          const uint8_t* mq = query_mask(row);
          for (int64_t k = 0; k < n; ++k) {
            eta_row(eta[k], D_, i, W_, res.data());
            const int32_t id = static_cast<int32_t>(level[k].id);
            for (int64_t d = 0; d < D_; ++d) {
              T* r = res.data() + d * W_;
              const T* g = gs_ + d * N_ + row;
              for (int64_t j = 0; j < W_; ++j) r[j] = in_cluster(depth, lr, mq, id, j) ? g[j] - r[j] : T(0);
            }
            gram_upper_row(res.data(), D_, W_, mrow.data() + k * msize);
          }
        }
        for (int64_t k = 0; k < n; ++k)
          for (int64_t m = 0; m < msize; ++m)
            mpart[(k * groups_ + grp) * msize + m] = static_cast<double>(mrow[k * msize + m]);
      }
    });
    for (int64_t k = 0; k < n; ++k)
      v[k] = split_direction<T>(mpart.data() + k * groups_ * msize, groups_, D_, opt_.power_iterations);
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
      std::vector<T> e(D_ * W_), dist(W_), ws(W_), fp(nf * C_ * W_), t0(W_), t1(W_);
      std::vector<RowUpsampler<T>> eta = upsamplers(src, D_);
      for (int64_t bi = gb * bpg_; bi < std::min(Hl_, ge * bpg_); ++bi) {
        for (int64_t p = 0; p < n * (C_ + 1); ++p) std::fill_n(sl.P.data() + p * Nl_ + bi * Wl_, Wl_, T(0));
        for (int64_t p = 0; !leaf && p < n * 2 * (D_ + 1); ++p)
          std::fill_n(Q.data() + p * Nl_ + bi * Wl_, Wl_, T(0));
        for (int64_t i = bi * df_; i < std::min(H_, (bi + 1) * df_); ++i) {
          const int64_t row = i * W_;
          centred_rows(row, fp.data());
          for (int64_t k = 0; k < n; ++k) {
            eta_row(eta[k], D_, i, W_, e.data());
            // the query's weight: slices, min D and the split
            distance_row(gs_, row, e.data(), dist.data());
            T* wr = sl.w.data() + k * N_ + row;
            exp_neg_scaled_row(dist.data(), inv_r2_, wr, W_);
            if (opt_.adjust_outliers) update_min_distance(depth, dist.data(), minD_.data() + row, W_);
            // every frame splats with its own guide's weight times its time weight
            T* pk = sl.P.data() + k * pnode;
            for (int64_t a = 0; a < nf; ++a) {
              const Frame<T>& fr = act_[a];
              const uint8_t* m = fr.all_finite ? nullptr : fr.ms.data() + row;
              if (a == query_act_ && all_q_ && fr.all_finite) {  // the same guide: the query's weight
                std::copy(wr, wr + W_, ws.data());
              } else {
                distance_row(fr.g, row, e.data(), ws.data());
                exp_neg_scaled_row(ws.data(), inv_r2_, ws.data(), W_);
              }
              if (m)  // a select, not a product: the distance to a non-finite guide is NaN
                for (int64_t j = 0; j < W_; ++j) ws[j] = m[j] ? ws[j] * fr.tau : T(0);
              else
                for (int64_t j = 0; j < W_; ++j) ws[j] *= fr.tau;
              const T* y = fp.data() + a * C_ * W_;
              for (int64_t c = 0; c < C_; ++c)
                block_dot_row(ws.data(), y + c * W_, W_, df_, Wl_, pk + c * Nl_ + bi * Wl_);
              block_sum_row(ws.data(), W_, df_, Wl_, pk + C_ * Nl_ + bi * Wl_);
            }
            if (leaf) continue;
            // the split: side of v . (gs - eta), theta = 1 - w on the cluster
            const int32_t id = static_cast<int32_t>(level[k].id);
            int32_t* lr = label_.size() > 0 ? label_.data() + row : nullptr;
            projection_row(gs_ + row, e.data(), v[k].data(), t0.data());
            split_sides(depth, id, keep_labels, lr, query_mask(row), wr, t0.data(), t1.data(), W_);
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
    blur_level(level, sl.P.data(), C_ + 1, D_, Hl_, Wl_, ss_low_, sr_low_);
    sliced_.push_back(std::move(sl));
    if (leaf) return {};
    return children(level, Q, D_, Hl_, Wl_, ss_low_);
  }

  // Each splatting frame's values at the row at offset `row`, about the channel centres and 0 where the
  // frame's splat mask is 0: fp ((frames, C, W)), shared by every node of a level.
  void centred_rows(int64_t row, T* fp) const {
    for (size_t a = 0; a < act_.size(); ++a) {
      const Frame<T>& fr = act_[a];
      const uint8_t* m = fr.all_finite ? nullptr : fr.ms.data() + row;
      for (int64_t c = 0; c < C_; ++c) {
        const T* x = fr.f + c * N_ + row;
        T* y = fp + (static_cast<int64_t>(a) * C_ + c) * W_;
        const T cc = c_[c];
        if (m)
          for (int64_t j = 0; j < W_; ++j) y[j] = m[j] ? x[j] - cc : T(0);
        else
          for (int64_t j = 0; j < W_; ++j) y[j] = x[j] - cc;
      }
    }
  }

  // S = sum over levels and nodes of w up(blur P), S0 likewise; out = c + S / S0 where S0 clears the
  // floor, else the time-weighted mean of the pixel's finite samples; then the outlier pull.
  void slice_and_finish() {
    int64_t nodes = 0;
    for (const Sliced& l : sliced_) nodes += l.n;
    rows_parallel(20 + 12 * C_ + 4 * (C_ + 1) * nodes, [&](int64_t b, int64_t e) {
      std::vector<T> s0(W_), fb(C_ * W_), alpha(W_);
      std::vector<uint8_t> has(W_);
      std::vector<std::vector<RowUpsampler<T>>> ups = slice_upsamplers(sliced_, C_, Hl_, Wl_, W_, ty_, tx_);
      for (int64_t i = b; i < e; ++i) {
        const int64_t row = i * W_;
        std::fill(s0.begin(), s0.end(), T(0));
        for (int64_t c = 0; c < C_; ++c) std::fill_n(S_ + c * N_ + row, W_, T(0));
        for (size_t l = 0; l < sliced_.size(); ++l)
          for (int64_t k = 0; k < sliced_[l].n; ++k)
            slice_row(ups[l][k], sliced_[l].w.data() + k * N_ + row, i, false, S_ + row, C_, N_, W_,
                      s0.data());
        if (all_above_floor(s0.data(), W_) && !opt_.adjust_outliers) {
          normalise_row<T>(S_ + row, N_, s0.data(), nullptr, 0, nullptr, c_, C_, W_);
          continue;
        }
        fallback_row(row, fb.data(), has.data());
        if (opt_.adjust_outliers)
          outlier_alpha_row(minD_.data() + row, half_inv_r2_, has.data(), alpha.data(), W_);
        normalise_row(S_ + row, N_, s0.data(), fb.data(), W_, opt_.adjust_outliers ? alpha.data() : nullptr, c_, C_,
                      W_);
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
  const FilterOptions opt_;
  const int64_t df_, Hl_, Wl_, Nl_, bpg_, groups_, gram_stride_;
  const Taps<T> ty_, tx_;
  const T* q_in_;
  T* S_;  // the output accumulates S
  const int64_t frames_;
  T inv_r2_, half_inv_r2_;
  double ss_low_, sr_low_;
  bool all_q_ = true;
  std::vector<Frame<T>> act_;  // the frames with tau > 0, in order
  int64_t query_act_ = -1;     // the one of them whose guide is the query's (-1: none)
  std::vector<const T*> f_all_;  // every frame's values, for the fallback
  std::vector<T> tau_all_;
  std::vector<T> c_;
  const T* gs_ = nullptr;
  Scratch<T> root_eta_, gs_buf_, minD_;
  Scratch<uint8_t> mq_;
  Scratch<int32_t> label_;
  std::vector<Sliced> sliced_;
};

// The op's checks, for one sigma_s.
void check_spacetime_args(const at::Tensor& values, const at::Tensor& guide, const at::Tensor& weights,
                          const at::Tensor& query_guide, double sigma_s, double sigma_r, int64_t tree_height,
                          int64_t power_iterations) {
  constexpr const char* op = "spacetime_adaptive_manifold: ";
  TORCH_CHECK_VALUE(values.dim() == 5, op, "values must be (B, T, C, H, W), got shape ", values.sizes());
  TORCH_CHECK_VALUE(guide.dim() == 5, op, "guide must be (B, T, D, H, W), got shape ", guide.sizes());
  TORCH_CHECK_VALUE(weights.dim() == 2, op, "weights must be (Q, T), got shape ", weights.sizes());
  TORCH_CHECK_VALUE(query_guide.dim() == 5, op, "query_guide must be (B, Q, D, H, W), got shape ",
                    query_guide.sizes());
  const int64_t B = values.size(0), T = values.size(1), H = values.size(3), W = values.size(4),
                D = guide.size(2), Q = weights.size(0);
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
}

// (K, B, Q, C, H, W): every window b, query q and spatial sigma k (tree height tree_heights[k], or
// tree_heights[0] for all), the images side by side (for_each_image), the costliest first. op names
// the caller in messages.
at::Tensor spacetime_images(const char* op, const at::Tensor& values, const at::Tensor& guide,
                            const at::Tensor& weights, const at::Tensor& query_guide,
                            c10::ArrayRef<double> sigma_s, double sigma_r,
                            c10::ArrayRef<int64_t> tree_heights, int64_t power_iterations,
                            bool adjust_outliers) {
  check_height_count(op, tree_heights, sigma_s.size());
  for (size_t k = 0; k < sigma_s.size(); ++k)
    check_spacetime_args(values, guide, weights, query_guide, sigma_s[k], sigma_r, height_of(tree_heights, k),
                         power_iterations);
  const int64_t K = static_cast<int64_t>(sigma_s.size());
  const int64_t B = values.size(0), T = values.size(1), C = values.size(2), H = values.size(3),
                W = values.size(4), D = guide.size(2), Q = weights.size(0);
  const at::Tensor f = values.contiguous(), g = guide.contiguous(), w = weights.contiguous(),
                   q = query_guide.contiguous();
  at::Tensor out = at::empty({K, B, Q, C, H, W}, values.options());
  if (out.numel() == 0) return out;
  const std::vector<int64_t> order = costliest_first(sigma_s, tree_heights, sigma_r);
  const int64_t N = H * W;
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "spacetime_adaptive_manifold_cpu", [&] {
    // A query at a frame's time has that frame's guide: its splat weights are the slice weights
    std::vector<int64_t> query_frame(B * Q, -1);
    for (int64_t bq = 0; bq < B * Q; ++bq) {
      const scalar_t* qg = q.data_ptr<scalar_t>() + bq * D * N;
      for (int64_t t = 0; t < T && query_frame[bq] < 0; ++t)
        if (std::memcmp(g.data_ptr<scalar_t>() + (bq / Q * T + t) * D * N, qg, D * N * sizeof(scalar_t)) == 0)
          query_frame[bq] = t;
    }
    for_each_image(K * B * Q, [&](int64_t item) {
      const int64_t s = order[item / (B * Q)], b = item / Q % B, k = item % Q;
      const FilterOptions opt{sigma_s[s], sigma_r, height_of(tree_heights, s), power_iterations,
                              adjust_outliers};
      SpacetimeFilter<scalar_t> filt(f.data_ptr<scalar_t>() + b * T * C * N,
                                     g.data_ptr<scalar_t>() + b * T * D * N, w.data_ptr<scalar_t>() + k * T,
                                     T, q.data_ptr<scalar_t>() + (b * Q + k) * D * N, query_frame[b * Q + k],
                                     out.data_ptr<scalar_t>() + ((s * B + b) * Q + k) * C * N, C, D, H, W, opt);
      filt.run();
    });
  });
  return out;
}

at::Tensor spacetime_adaptive_manifold_cpu(const at::Tensor& values, const at::Tensor& guide,
                                           const at::Tensor& weights, const at::Tensor& query_guide,
                                           double sigma_s, double sigma_r, int64_t tree_height,
                                           int64_t power_iterations, bool adjust_outliers) {
  return spacetime_images("spacetime_adaptive_manifold", values, guide, weights, query_guide, {sigma_s},
                          sigma_r, {tree_height}, power_iterations, adjust_outliers)[0];
}

at::Tensor spacetime_adaptive_manifold_bandwidths_cpu(const at::Tensor& values, const at::Tensor& guide,
                                                      const at::Tensor& weights, const at::Tensor& query_guide,
                                                      c10::ArrayRef<double> sigma_s, double sigma_r,
                                                      c10::ArrayRef<int64_t> tree_height,
                                                      int64_t power_iterations, bool adjust_outliers) {
  TORCH_CHECK_VALUE(!sigma_s.empty(),
                    "_spacetime_adaptive_manifold_bandwidths: sigma_s must hold at least one sigma");
  return spacetime_images("_spacetime_adaptive_manifold_bandwidths", values, guide, weights, query_guide,
                          sigma_s, sigma_r, tree_height, power_iterations, adjust_outliers);
}

}  // namespace

TORCH_LIBRARY_IMPL(torchmanifold, CPU, m) {
  m.impl("spacetime_adaptive_manifold", &spacetime_adaptive_manifold_cpu);
  m.impl("_spacetime_adaptive_manifold_bandwidths", &spacetime_adaptive_manifold_bandwidths_cpu);
}

}  // namespace cpu
}  // namespace torchmanifold
