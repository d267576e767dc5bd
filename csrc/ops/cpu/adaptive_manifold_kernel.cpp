// CPU kernel of torchmanifold::adaptive_manifold (Gastal & Oliveira 2012), planar (B,C,H,W).
//
// Per image: one read of the guide builds the root manifold from block means (every manifold lives
// on the low-resolution grid). The tree is then built breadth first, one fused full-resolution
// pass per level for all of its nodes, row by row, split over groups of low-res block rows so that
// each task owns the low-res accumulator rows it writes:
//   internal levels first take M = sum r r^T of each node's cluster residuals r = guide - eta over
//     a sample of bands of rows (per-group partial sums over fixed groups, combined in order, so it
//     is independent of the thread count), and its split direction v by power iteration;
//   the pass: eta at the pixel (bilinear from the node's low-res manifold),
//     D = |guide - eta|^2, w = exp(-D / sigma_r^2), min D, P += w f, P0 += w (area means);
//     internal nodes also the cluster label (sign of v . r), theta = 1 - w and the masked area
//     sums that build both children;
//   low-res domain-transform blur of [P, P0] steered by the node's manifold.
// A last pass slices every node, S += w up(blur P), S0 += w up(blur P0), and writes S / S0 (input
// where S0 <= tiny/eps), optionally pulled towards the input by alpha: S is written once and S0
// never leaves the row.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>
#include <cstdio>
#include <cstdlib>
#include <ctime>

#include "ops/adaptive_manifold_common.h"
#include "ops/cpu/kernel_steps.h"
#include "ops/cpu/manifold_ops.h"
#include "ops/cpu/recursive_filter.h"
#include "ops/cpu/workspace.h"

namespace torchmanifold {
namespace cpu {
namespace {

// Rows per reduction chunk: fixed, so partial sums never depend on the thread count.
constexpr int64_t kReduceRows = 16;

// TORCHMANIFOLD_KERNEL_PROFILE=1 prints the wall time per phase to stderr; a development aid, off
// by default.
struct PhaseClock {
  bool on = std::getenv("TORCHMANIFOLD_KERNEL_PROFILE") != nullptr;
  double t = now();
  static double now() {
    timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
  }
  void lap(const char* what, int64_t id = 0) {
    if (!on) return;
    const double n = now();
    std::fprintf(stderr, "[am] %-14s node %3ld %8.2f ms\n", what, static_cast<long>(id), 1e3 * (n - t));
    t = n;
  }
};

// One image. The numbered comments refer to the fixed choices listed at the top of
// torchmanifold/ops/_reference.py, which this kernel matches.
template <typename T>
class ImageFilter {
 public:
  ImageFilter(const T* values, const T* guide, T* out, int64_t C, int64_t D, int64_t H, int64_t W,
              const FilterOptions& opt)
      : C_(C), D_(D), H_(H), W_(W), N_(H * W), opt_(opt),
        df_(downsample_factor(opt.sigma_s, opt.sigma_r)),
        Hl_((H + df_ - 1) / df_), Wl_((W + df_ - 1) / df_), Nl_(Hl_ * Wl_),
        // pixel passes run over groups of block rows: >= kReduceRows full-res rows each
        bpg_(std::max<int64_t>(1, kReduceRows / df_)), groups_((Hl_ + bpg_ - 1) / bpg_),
        gram_stride_(gram_band_stride(H, W)), ty_(H, Hl_, df_), tx_(W, Wl_, df_), f_in_(values),
        g_in_(guide), S_(out) {
    inv_r2_ = inverse_square<T>(opt.sigma_r);
    half_inv_r2_ = static_cast<T>(0.5 * static_cast<double>(inv_r2_));
    ss_low_ = opt.sigma_s / static_cast<double>(df_);
    sr_low_ = opt.sigma_r / std::sqrt(2.0);
  }

  void run() {
    prepare();
    clock_.lap("prepare");
    if (opt_.adjust_outliers) minD_.resize(N_);  // written by the root's pass, not cleared first

    // 7. Breadth first, one level at a time like the reference; one full-res pass per level
    // handles all of the level's nodes row by row (splat and, but for the leaves, split), so the
    // guide is read once per level. Every level's slice waits for one last pass that also
    // normalises each row (9., 10.): S is written once, S0 never leaves the row.
    std::vector<Node> level;
    level.push_back({1, std::move(root_eta_)});
    for (int64_t depth = 0; depth < opt_.tree_height && !level.empty(); ++depth)
      level = process_level(level, depth);
    slice_and_finish();
    clock_.lap("slice");
  }

 private:
  using Node = ManifoldNode<T>;

  using Sliced = LevelSlices<T>;

  template <typename F>
  void rows_parallel(int64_t work_per_row, const F& fn) {
    parallel_work(0, H_, W_ * work_per_row, fn);
  }

  // 2., 3., 6.: masks, sanitised samples, the per-channel offset c, the root manifold and gs.
  void prepare() {
    prepare_guide();
    clock_.lap("guide");
    prepare_values();
  }

  // 6. Block means of the guide for the root manifold, checking finiteness on them (the guide's
  // only full pass before the tree). Only a non-finite guide takes the masked route
  // h(down(mg g0)) / h(down(mg)) and builds gs at full resolution.
  void prepare_guide() {
    root_eta_.resize(D_ * Nl_);  // every task clears the block rows it sums into
    std::vector<uint8_t> block_ok(Hl_, 1);
    parallel_work(0, Hl_, df_ * W_ * 3 * D_, [&](int64_t b, int64_t e) {
      // channel by channel over the task's block rows: one long run of memory per channel (a
      // channel's rows are contiguous), which streams faster than D short ones per block row
      const int64_t i0 = b * df_, i1 = std::min(H_, e * df_);
      for (int64_t d = 0; d < D_; ++d) {
        T* sums = root_eta_.data() + d * Nl_;
        std::fill(sums + b * Wl_, sums + e * Wl_, T(0));
        for (int64_t i = i0; i < i1; ++i)
          block_sum_row(g_in_ + d * N_ + i * W_, W_, df_, Wl_, sums + (i / df_) * Wl_);
      }
      for (int64_t bi = b; bi < e; ++bi) {
        // A NaN or infinity makes its block's sum NaN or infinite, so finite sums prove finite
        // samples (an overflowing sum only sends the image down the masked route, which then
        // finds every pixel valid).
        bool ok = true;
        for (int64_t d = 0; d < D_; ++d) ok = ok && all_finite(root_eta_.data() + d * Nl_ + bi * Wl_, Wl_);
        block_ok[bi] = ok;
        to_block_means(root_eta_.data() + bi * Wl_, D_, std::min(H_, (bi + 1) * df_) - bi * df_);
      }
    });
    all_g_ = std::all_of(block_ok.begin(), block_ok.end(), [](uint8_t m) { return m != 0; });
    gs_ = g_in_;
    if (all_g_) {  // no guide mask: every pixel is valid
      lowpass_planes(root_eta_.data(), D_, Hl_, Wl_, ss_low_);
      return;
    }
    mg_.assign(N_, 1);
    rows_parallel(D_, [&](int64_t b, int64_t e) {
      for (int64_t d = 0; d < D_; ++d)
        for (int64_t i = b * W_; i < e * W_; ++i)
          if (!std::isfinite(g_in_[d * N_ + i])) mg_[i] = 0;
    });
    // [down(mg g0) planes, down(mg)], low-passed, then their ratio (0 where nothing is valid)
    Scratch<T> acc;
    acc.assign((D_ + 1) * Nl_, T(0));
    parallel_work(0, Hl_, df_ * W_ * 2 * (D_ + 1), [&](int64_t b, int64_t e) {
      std::vector<T> row(W_);
      for (int64_t bi = b; bi < e; ++bi) {
        const int64_t i0 = bi * df_, i1 = std::min(H_, i0 + df_);
        for (int64_t d = 0; d <= D_; ++d)
          for (int64_t i = i0; i < i1; ++i) {
            const uint8_t* m = mg_.data() + i * W_;
            const T* src = g_in_ + std::min(d, D_ - 1) * N_ + i * W_;
            for (int64_t j = 0; j < W_; ++j) row[j] = m[j] ? (d < D_ ? src[j] : T(1)) : T(0);
            block_sum_row(row.data(), W_, df_, Wl_, acc.data() + d * Nl_ + bi * Wl_);
          }
        to_block_means(acc.data() + bi * Wl_, D_ + 1, i1 - i0);
      }
    });
    lowpass_planes(acc.data(), D_ + 1, Hl_, Wl_, ss_low_);
    gs_buf_.resize(D_ * N_);
    masked_root_and_guide(acc.data(), g_in_, mg_.data(), D_, H_, W_, Hl_, Wl_, ty_, tx_, root_eta_.data(),
                          gs_buf_.data());
    gs_ = gs_buf_.data();
  }

  // planes rows of a low-res plane stack (stride Nl_), block row starting at p, covering `rows`
  // full-res rows: sums -> means over the pixels that exist in each block.
  void to_block_means(T* p, int64_t planes, int64_t rows) const {
    cpu::to_block_means(p, planes, rows, df_, W_, Wl_, Nl_);
  }

  void prepare_values() {
    // Values: finiteness, then c = clamp(0, lo, hi) over splat pixels (min/max are order
    // independent), and the splat mask ms.
    mv_.resize(N_);
    const int64_t chunks = (H_ + kReduceRows - 1) / kReduceRows;
    std::vector<T> lo(chunks * C_, std::numeric_limits<T>::infinity());
    std::vector<T> hi(chunks * C_, -std::numeric_limits<T>::infinity());
    std::vector<uint8_t> chunk_ok(chunks, 1);
    parallel_work(0, chunks, 3 * kReduceRows * W_ * C_, [&](int64_t b, int64_t e) {
      for (int64_t ch = b; ch < e; ++ch) {
        const int64_t p0 = ch * kReduceRows * W_, p1 = std::min(H_, (ch + 1) * kReduceRows) * W_;
        std::fill(mv_.data() + p0, mv_.data() + p1, uint8_t(1));
        for (int64_t c = 0; c < C_; ++c) {
          const T* x = f_in_ + c * N_;
          if (!all_finite(x + p0, p1 - p0)) {
            chunk_ok[ch] = 0;
            for (int64_t i = p0; i < p1; ++i)
              if (!std::isfinite(x[i])) mv_[i] = 0;
          }
        }
        for (int64_t c = 0; c < C_; ++c) {
          const T* x = f_in_ + c * N_;
          T l = lo[ch * C_ + c], h = hi[ch * C_ + c];
          if (chunk_ok[ch] && all_g_) {
            min_max(x + p0, p1 - p0, l, h);
          } else {
            for (int64_t i = p0; i < p1; ++i)
              if ((all_g_ || mg_[i]) && mv_[i]) l = std::min(l, x[i]), h = std::max(h, x[i]);
          }
          lo[ch * C_ + c] = l;
          hi[ch * C_ + c] = h;
        }
      }
    });
    all_v_ = std::all_of(chunk_ok.begin(), chunk_ok.end(), [](uint8_t m) { return m != 0; });
    f_s_ = f_in_;
    if (!all_v_) {
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
    c_ = channel_centres(lo, hi, chunks, C_);
    // ms (every mask is 1 when all samples are finite: no ms then). f' is made row by row where
    // it is splatted, and the root's cluster is the pixels with a finite guide (8.), so the
    // labels are first written by the root's split.
    if (!(all_g_ && all_v_)) {
      ms_.resize(N_);
      rows_parallel(2, [&](int64_t b, int64_t e) {
        for (int64_t i = b * W_; i < e * W_; ++i) ms_[i] = (all_g_ || mg_[i]) && mv_[i];
      });
    }
    if (opt_.tree_height > 2) label_.resize(N_);  // read by the splits below the root's
  }

  // f' = (f_s - c) ms at full-res row i into fp ((C, W)).
  void centred_values_row(int64_t i, T* fp) const {
    const int64_t row = i * W_;
    for (int64_t c = 0; c < C_; ++c) {
      const T* x = f_s_ + c * N_ + row;
      T* y = fp + c * W_;
      const T cc = c_[c];
      if (all_g_ && all_v_) {
        for (int64_t j = 0; j < W_; ++j) y[j] = x[j] - cc;
      } else {
        const uint8_t* m = ms_.data() + row;
        for (int64_t j = 0; j < W_; ++j) y[j] = m[j] ? x[j] - cc : T(0);
      }
    }
  }

  // The guide mask's row at offset `row`, or nullptr when every guide sample is finite.
  const uint8_t* guide_mask(int64_t row) const { return all_g_ ? nullptr : mg_.data() + row; }

  // The labels' row at offset `row`; nullptr below height 3, where no split reads them (at depth 0
  // in_cluster reads none).
  int32_t* labels(int64_t row) { return label_.size() > 0 ? label_.data() + row : nullptr; }

  // A band: the full-res rows from i on (before `end`, at most kBandRows) that share their
  // upsampled manifold rows, i.e. the same pair of low-res rows.
  static constexpr int64_t kBandRows = 4;
  int64_t band_rows(int64_t i, int64_t end) const {
    int64_t r = 1;
    while (r < kBandRows && i + r < end && ty_.i0[i + r] == ty_.i0[i] && ty_.i1[i + r] == ty_.i1[i]) ++r;
    return r;
  }

  // For the band of `rows` rows from full-res row i and every node k of the level (eta: their
  // manifolds through RowUpsamplers), at row (k kBandRows + r) of dist and proj (zeroed by the
  // caller):
  //   dist += |gs - up(eta_k)|^2;
  //   proj += v_k . (gs - c_k) when v is not empty (a splitting level): the guide's part of the
  //   projection v_k . (gs - up(eta_k)) = v_k . (gs - c_k) - up(v_k . (eta_k - c_k)), see
  //   projection_from_band. c_k (per channel, a value of the manifold) keeps a guide far from 0
  //   from costing precision.
  // A channel pair at a time over the band's rows: each channel's rows are one run of memory,
  // which streams faster than D rows a plane apart; a node's upsampled rows serve the whole band;
  // dist and proj are loaded and stored once per pair.
  void distance_band(std::vector<RowUpsampler<T>>& eta, int64_t i, int64_t rows,
                     const std::vector<std::vector<T>>& v, const std::vector<std::vector<T>>& c,
                     T* dist, T* proj) const {
    T fy[kBandRows];
    for (RowUpsampler<T>& e : eta) e.seek(i);
    for (int64_t r = 0; r < rows; ++r) fy[r] = ty_.f[i + r];
    const int64_t n = static_cast<int64_t>(eta.size());
    int64_t d = 0;
    for (; d + 2 <= D_; d += 2)
      for (int64_t k = 0; k < n; ++k) {
        const T* __restrict b0 = eta[k].base(d);
        const T* __restrict b1 = eta[k].base(d + 1);
        const T* __restrict e0 = eta[k].delta(d);
        const T* __restrict e1 = eta[k].delta(d + 1);
        for (int64_t r = 0; r < rows; ++r) {
          const T* __restrict g0 = gs_ + d * N_ + (i + r) * W_;
          const T* __restrict g1 = g0 + N_;
          T* __restrict ds = dist + (k * kBandRows + r) * W_;
          const T f = fy[r];
          for (int64_t j = 0; j < W_; ++j) {
            const T x0 = g0[j] - (b0[j] + f * e0[j]);
            const T x1 = g1[j] - (b1[j] + f * e1[j]);
            ds[j] = (ds[j] + x0 * x0) + x1 * x1;
          }
          if (v.empty()) continue;
          T* __restrict p = proj + (k * kBandRows + r) * W_;
          const T v0 = v[k][d], c0 = c[k][d], v1 = v[k][d + 1], c1 = c[k][d + 1];
          for (int64_t j = 0; j < W_; ++j) p[j] = (p[j] + v0 * (g0[j] - c0)) + v1 * (g1[j] - c1);
        }
      }
    for (; d < D_; ++d)
      for (int64_t k = 0; k < n; ++k) {
        const T* b = eta[k].base(d);
        const T* db = eta[k].delta(d);
        for (int64_t r = 0; r < rows; ++r) {
          const T* gr = gs_ + d * N_ + (i + r) * W_;
          T* ds = dist + (k * kBandRows + r) * W_;
          const T f = fy[r];
          for (int64_t j = 0; j < W_; ++j) {
            const T x = gr[j] - (b[j] + f * db[j]);
            ds[j] += x * x;
          }
          if (v.empty()) continue;
          T* p = proj + (k * kBandRows + r) * W_;
          const T vd = v[k][d], cd = c[k][d];
          for (int64_t j = 0; j < W_; ++j) p[j] += vd * (gr[j] - cd);
        }
      }
  }

  // The residual r = gs - up(eta) at full-res row i into res ((D, W)), for M. eta: the node's
  // manifold through a RowUpsampler.
  void residual_row(RowUpsampler<T>& eta, int64_t i, T* res) const {
    const int64_t row = i * W_;
    const T fy = eta.seek(i);
    for (int64_t d = 0; d < D_; ++d) {
      const T* __restrict gr = gs_ + d * N_ + row;
      const T* __restrict b = eta.base(d);
      const T* __restrict db = eta.delta(d);
      T* __restrict rr = res + d * W_;
      for (int64_t j = 0; j < W_; ++j) rr[j] = gr[j] - (b[j] + fy * db[j]);
    }
  }

  // out = the projection at full-res row i from its guide part (a row of distance_band's proj),
  // less up(v . (eta - c)): upsampling is linear, so the manifold's part is one low-res plane
  // (ve, through a RowUpsampler) instead of D.
  void projection_from_band(RowUpsampler<T>& ve, int64_t i, const T* guide_part, T* out) const {
    const T fy = ve.seek(i);
    const T* __restrict b = ve.base(0);
    const T* __restrict db = ve.delta(0);
    for (int64_t j = 0; j < W_; ++j) out[j] = guide_part[j] - (b[j] + fy * db[j]);
  }

  // A RowUpsampler per node of the level for a task's rows.
  std::vector<RowUpsampler<T>> upsamplers(const std::vector<const T*>& low, int64_t planes) const {
    return make_upsamplers(low, planes, Hl_, Wl_, W_, ty_, tx_);
  }

  // 8. Each node's split direction: M = sum r r^T over its cluster on the rows of every
  // gram_stride_-th band, in a pass over those rows ahead of the level's, so that the level's pass
  // can split too. Per-group partial sums in fixed groups of rows, combined in order: the
  // result does not depend on the thread count.
  std::vector<std::vector<T>> split_directions(const std::vector<Node>& level, int64_t depth) {
    const int64_t n = static_cast<int64_t>(level.size());
    const int64_t msize = D_ * (D_ + 1) / 2;  // upper triangle of M
    std::vector<double> mpart(opt_.power_iterations > 0 ? n * groups_ * msize : 0, 0.0);
    if (opt_.power_iterations > 0) {
      std::vector<const T*> eta_src(n);
      for (int64_t k = 0; k < n; ++k) eta_src[k] = level[k].eta.data();
      const int64_t group_rows = bpg_ * df_;
      const int64_t work = group_rows * W_ * n * (3 * D_ + D_ * D_ / 2) / gram_stride_ + 1;
      parallel_work(0, groups_, work, [&](int64_t gb, int64_t ge) {
        // res has D rounded up to 4 rows plus 4, the extra ones zero, for gram_upper_row's tiles
        std::vector<T> res(((D_ + 3) / 4 * 4 + 4) * W_, T(0)), mrow(n * msize);
        std::vector<RowUpsampler<T>> eta = upsamplers(eta_src, D_);
        for (int64_t grp = gb; grp < ge; ++grp) {
          std::fill(mrow.begin(), mrow.end(), T(0));
          const int64_t i0 = grp * group_rows, i1 = std::min(H_, i0 + group_rows);
          for (int64_t i = i0; i < i1; ++i) {
            if ((i / kGramBand) % gram_stride_ != 0) continue;  // not a sampled band
            for (int64_t k = 0; k < n; ++k) {
              residual_row(eta[k], i, res.data());
              accumulate_m(depth, level[k].id, i * W_, res.data(), mrow.data() + k * msize);
            }
          }
          for (int64_t k = 0; k < n; ++k)
            for (int64_t m = 0; m < msize; ++m)
              mpart[(k * groups_ + grp) * msize + m] = static_cast<double>(mrow[k * msize + m]);
        }
      });
    }
    std::vector<std::vector<T>> v(n);
    for (int64_t k = 0; k < n; ++k)
      v[k] = split_direction<T>(mpart.data() + k * groups_ * msize, groups_, D_, opt_.power_iterations);
    return v;
  }

  // A splitting level's setup (8.): each node's direction v, its centre c (the manifold's first
  // value, per channel, so a guide far from 0 costs no precision) and v . (eta - c) at low
  // resolution, which the projections of the level's pass subtract. Empty for the leaves.
  struct Split {
    std::vector<std::vector<T>> v, centre;
    Scratch<T> ve;  // (n, Hl, Wl)
  };

  Split split_setup(const std::vector<Node>& level, int64_t depth) {
    const int64_t n = static_cast<int64_t>(level.size());
    Split sp;
    sp.v = split_directions(level, depth);
    sp.centre.resize(n);
    sp.ve.resize(n * Nl_);
    for (int64_t k = 0; k < n; ++k) {
      sp.centre[k].resize(D_);
      for (int64_t d = 0; d < D_; ++d) sp.centre[k][d] = level[k].eta[d * Nl_];
    }
    parallel_work(0, n * Hl_, 2 * D_ * Wl_, [&](int64_t b, int64_t e) {  // tasks of low-res rows
      for (int64_t t = b; t < e; ++t) {
        const int64_t k = t / Hl_, r0 = (t % Hl_) * Wl_;
        T* out = sp.ve.data() + k * Nl_ + r0;
        const T* eta = level[k].eta.data() + r0;
        std::fill(out, out + Wl_, T(0));
        for (int64_t d = 0; d < D_; ++d) {
          const T vd = sp.v[k][d], cd = sp.centre[k][d];
          for (int64_t q = 0; q < Wl_; ++q) out[q] += vd * (eta[d * Nl_ + q] - cd);
        }
      }
    });
    clock_.lap("split dir", depth);
    return sp;
  }

  // 7. Node k at full-res row i (block row bi): w = exp(-D / sigma_r^2) into the level's weights,
  // min D, and the splat P += down(ms w f'), P0 += down(ms w). dr: the row's D; fp: f' ((C, W));
  // ws: W scratch. Returns the row's w.
  const T* splat_row(int64_t k, int64_t depth, int64_t i, int64_t bi, const T* dr, const T* fp, T* ws,
                     Sliced& sl) {
    const int64_t row = i * W_;
    T* wr = sl.w.data() + k * N_ + row;
    exp_neg_scaled_row(dr, inv_r2_, wr, W_);
    // the splat weights: w, or 0 where the pixel is not a splat pixel
    const T* wsplat = wr;
    if (!(all_g_ && all_v_)) {
      const uint8_t* sr = ms_.data() + row;
      for (int64_t j = 0; j < W_; ++j) ws[j] = sr[j] ? wr[j] : T(0);
      wsplat = ws;
    }
    if (opt_.adjust_outliers) update_min_distance(depth, dr, minD_.data() + row, W_);
    T* pk = sl.P.data() + k * (C_ + 1) * Nl_;
    for (int64_t c = 0; c < C_; ++c)
      block_dot_row(wsplat, fp + c * W_, W_, df_, Wl_, pk + c * Nl_ + bi * Wl_);
    block_sum_row(wsplat, W_, df_, Wl_, pk + C_ * Nl_ + bi * Wl_);
    return wr;
  }

  // 8. The children's sums of node k at full-res row i (block row bi): Q's side planes get
  // down(T gs) and down(T) for T = t0 (-) and t1 (+).
  void children_sums_row(int64_t k, int64_t i, int64_t bi, const T* t0, const T* t1, T* Q) const {
    const int64_t qside = (D_ + 1) * Nl_;
    T* q = Q + k * 2 * qside;
    for (int64_t d = 0; d < D_; ++d) {
      const T* gr = gs_ + d * N_ + i * W_;
      block_dot2_row(t0, t1, gr, W_, df_, Wl_, q + d * Nl_ + bi * Wl_, q + qside + d * Nl_ + bi * Wl_);
    }
    block_sum_row(t0, W_, df_, Wl_, q + D_ * Nl_ + bi * Wl_);
    block_sum_row(t1, W_, df_, Wl_, q + qside + D_ * Nl_ + bi * Wl_);
  }

  // The level's pass over full-res rows, a group of block rows per task: every node splats
  // (splat_row); at a splitting level it also splits its cluster (split_sides) and sums the
  // children's manifolds (children_sums_row) into Q ([node][side][D + 1][Nl]). The distances
  // and projections' guide parts are computed a band of rows at a time for all nodes.
  void level_pass(const std::vector<Node>& level, int64_t depth, bool leaf, const Split& sp, Sliced& sl,
                  Scratch<T>& Q) {
    const int64_t n = static_cast<int64_t>(level.size());
    // The labels a split writes are read only by the next level's split.
    const bool keep_labels = depth + 2 < opt_.tree_height;
    std::vector<const T*> eta_src(n), ve_src(leaf ? 0 : n);
    for (int64_t k = 0; k < n; ++k) eta_src[k] = level[k].eta.data();
    for (int64_t k = 0; k < static_cast<int64_t>(ve_src.size()); ++k) ve_src[k] = sp.ve.data() + k * Nl_;
    sl.n = n;
    sl.w.resize(n * N_);
    sl.P.resize(n * (C_ + 1) * Nl_);  // each task clears the block rows it splats into
    if (!leaf) Q.resize(n * 2 * (D_ + 1) * Nl_);  // each task clears the block rows it sums into
    const int64_t group_px = bpg_ * df_ * W_ * n;
    // work per pixel and node (grain only): distances ~8 per guide channel, splats ~4 per value
    // channel, a split ~6 more per guide channel
    const int64_t work = group_px * (8 * D_ + 4 * C_ + (leaf ? 0 : 6 * D_));
    parallel_work(0, groups_, work, [&](int64_t gb, int64_t ge) {
      // per node, the current band's distances and (splitting levels) projections' guide parts
      std::vector<T> dist(n * kBandRows * W_), proj(leaf ? 0 : n * kBandRows * W_);
      std::vector<T> ws(W_), fp(C_ * W_), t0(leaf ? 0 : W_), t1(leaf ? 0 : W_);
      std::vector<RowUpsampler<T>> eta = upsamplers(eta_src, D_);
      std::vector<RowUpsampler<T>> ve_up = upsamplers(ve_src, 1);
      const int64_t task_end = std::min(H_, ge * bpg_ * df_);
      int64_t band_start = 0, band_n = 0;  // the current band's rows
      for (int64_t bi = gb * bpg_; bi < std::min(Hl_, ge * bpg_); ++bi) {
        const int64_t i0 = bi * df_, i1 = std::min(H_, i0 + df_);
        for (int64_t p = 0; p < n * (C_ + 1); ++p)
          std::fill_n(sl.P.data() + p * Nl_ + bi * Wl_, Wl_, T(0));
        for (int64_t p = 0; !leaf && p < n * 2 * (D_ + 1); ++p)
          std::fill_n(Q.data() + p * Nl_ + bi * Wl_, Wl_, T(0));
        for (int64_t i = i0; i < i1; ++i) {
          centred_values_row(i, fp.data());
          if (i >= band_start + band_n) {
            band_start = i;
            band_n = band_rows(i, task_end);
            std::fill(dist.begin(), dist.end(), T(0));
            std::fill(proj.begin(), proj.end(), T(0));
            distance_band(eta, i, band_n, sp.v, sp.centre, dist.data(), proj.data());
          }
          for (int64_t k = 0; k < n; ++k) {
            const int64_t band_row = (k * kBandRows + i - band_start) * W_;
            const T* wr = splat_row(k, depth, i, bi, dist.data() + band_row, fp.data(), ws.data(), sl);
            if (leaf) continue;
            projection_from_band(ve_up[k], i, proj.data() + band_row, t0.data());
            split_sides(depth, static_cast<int32_t>(level[k].id), keep_labels, labels(i * W_), guide_mask(i * W_),
                        wr, t0.data(), t1.data(), W_);
            children_sums_row(k, i, bi, t0.data(), t1.data(), Q.data());
          }
        }
        for (int64_t k = 0; k < n; ++k) to_block_means(sl.P.data() + k * (C_ + 1) * Nl_ + bi * Wl_, C_ + 1, i1 - i0);
        for (int64_t side = 0; !leaf && side < 2 * n; ++side)
          to_block_means(Q.data() + side * (D_ + 1) * Nl_ + bi * Wl_, D_ + 1, i1 - i0);
      }
    });
  }

  // One level of the tree (7., 8.): splat every node, blur, keep the slices for the last pass and,
  // but for the leaves, return the children.
  std::vector<Node> process_level(const std::vector<Node>& level, int64_t depth) {
    const bool leaf = depth + 1 >= opt_.tree_height;
    const Split sp = leaf ? Split() : split_setup(level, depth);
    Sliced sl;
    Scratch<T> Q;
    level_pass(level, depth, leaf, sp, sl, Q);
    clock_.lap("pass", depth);
    blur_level(level, sl.P.data(), C_ + 1, D_, Hl_, Wl_, ss_low_, sr_low_);
    sliced_.push_back(std::move(sl));
    clock_.lap("blur", depth);
    if (leaf) return {};
    std::vector<Node> next = children(level, Q, D_, Hl_, Wl_, ss_low_);
    clock_.lap("children", depth);
    return next;
  }

  // m += sum over the row's cluster pixels of r r^T (upper triangle, row-major). The reference
  // scales r by 1/max|r| against overflow; the direction and the collapse test do not depend on
  // it, and here a float32 r is squared in float32 per row, then summed in double.
  void accumulate_m(int64_t depth, int64_t id, int64_t row, T* res, T* m) const {
    const int32_t* lr = depth > 0 ? label_.data() + row : nullptr;
    const uint8_t* mg = guide_mask(row);
    const int32_t id32 = static_cast<int32_t>(id);
    int32_t out = 0;  // pixels of the row outside the cluster (none at the root, usually)
    if (!(depth == 0 && all_g_))
      for (int64_t j = 0; j < W_; ++j) out += !in_cluster(depth, lr, mg, id32, j);
    for (int64_t d = 0; d < D_ && out > 0; ++d) {
      T* rr = res + d * W_;  // res is scratch now: mask it
      for (int64_t j = 0; j < W_; ++j) rr[j] = in_cluster(depth, lr, mg, id32, j) ? rr[j] : T(0);
    }
    gram_upper_row(res, D_, W_, m);
  }

  // The last pass: row by row, S and S0 (s0, W scratch) from every level's slices in the order of
  // the tree (7.), then 9., 10.
  void slice_and_finish() {
    int64_t nodes = 0;
    for (const Sliced& l : sliced_) nodes += l.n;
    // work per pixel (grain only): the normalisation's ~12 operations per channel plus the slices'
    // ~4 per channel and node
    rows_parallel(20 + 12 * C_ + 4 * (C_ + 1) * nodes, [&](int64_t b, int64_t e) {
      std::vector<T> s0(W_), alpha(W_);
      std::vector<std::vector<RowUpsampler<T>>> up = slice_upsamplers(sliced_, C_, Hl_, Wl_, W_, ty_, tx_);
      for (int64_t i = b; i < e; ++i) {
        for (size_t l = 0; l < sliced_.size(); ++l)
          for (int64_t k = 0; k < sliced_[l].n; ++k)
            slice_row(up[l][k], sliced_[l].w.data() + k * N_ + i * W_, i, l == 0 && k == 0, S_ + i * W_, C_,
                      N_, W_, s0.data());
        finish_row(i, s0.data(), alpha.data());
      }
    });
  }

  // 9., 10. Full-res row i, in place (S_ is the output tensor); s0: the row's S0; alpha: W scratch.
  // Pixels whose S0 is below the floor keep the input.
  void finish_row(int64_t i, const T* s0, T* alpha) {
    const int64_t row = i * W_;
    if (opt_.adjust_outliers)
      outlier_alpha_row(minD_.data() + row, half_inv_r2_, mv_.data() + row, alpha, W_);
    // A row where every S0 clears the floor (nearly every row) and no adjustment follows needs
    // no input.
    const bool reads_input = !all_above_floor(s0, W_) || opt_.adjust_outliers;
    normalise_row(S_ + row, N_, s0, reads_input ? f_s_ + row : nullptr, N_,
                  opt_.adjust_outliers ? alpha : nullptr, c_, C_, W_);
  }

  const int64_t C_, D_, H_, W_, N_;
  const FilterOptions opt_;
  const int64_t df_, Hl_, Wl_, Nl_, bpg_, groups_;
  const int64_t gram_stride_;  // 8. M sums the rows of every gram_stride_-th band
  const Taps<T> ty_, tx_;
  const T* f_in_;
  const T* g_in_;
  T* S_;  // the output buffer accumulates S
  T inv_r2_, half_inv_r2_;
  double ss_low_, sr_low_;
  bool all_g_ = true, all_v_ = true;

  const T* f_s_ = nullptr;  // values with non-finite entries set to 0
  const T* gs_ = nullptr;   // sanitised guide
  std::vector<T> c_;
  Scratch<T> root_eta_;  // 6. the root manifold, (D, Hl, Wl), moved into the tree
  Scratch<T> fs_buf_, gs_buf_, minD_;
  std::vector<Sliced> sliced_;  // every level so far, for the last pass
  Scratch<uint8_t> mg_, mv_, ms_;
  Scratch<int32_t> label_;
  PhaseClock clock_;
};

// (K, B, C, H, W): every image b at every spatial sigma k (tree height tree_heights[k], or
// tree_heights[0] for all), the images side by side (for_each_image), the costliest first. op names
// the caller in messages.
at::Tensor filter_images(const char* op, const at::Tensor& values, const at::Tensor& guide,
                         c10::ArrayRef<double> sigma_s, double sigma_r, c10::ArrayRef<int64_t> tree_heights,
                         int64_t power_iterations, bool adjust_outliers) {
  check_height_count(op, tree_heights, sigma_s.size());
  for (size_t k = 0; k < sigma_s.size(); ++k)
    check_adaptive_manifold_args(values, guide, sigma_s[k], sigma_r, height_of(tree_heights, k),
                                 power_iterations);
  TORCH_CHECK_VALUE(values.device().is_cpu(), op, ": values and guide must be CPU tensors for this kernel, got ",
                    values.device());
  const at::Tensor f = values.contiguous();
  const at::Tensor g = guide.contiguous();
  const int64_t K = static_cast<int64_t>(sigma_s.size());
  const int64_t B = f.size(0), C = f.size(1), H = f.size(2), W = f.size(3), D = g.size(1);
  at::Tensor out = at::empty({K, B, C, H, W}, f.options());
  if (out.numel() == 0) return out;
  const std::vector<int64_t> order = costliest_first(sigma_s, tree_heights, sigma_r);
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "adaptive_manifold_cpu", [&] {
    for_each_image(K * B, [&](int64_t item) {
      const int64_t k = order[item / B], b = item % B;
      const FilterOptions opt{sigma_s[k], sigma_r, height_of(tree_heights, k), power_iterations,
                              adjust_outliers};
      ImageFilter<scalar_t> filt(f.data_ptr<scalar_t>() + b * C * H * W, g.data_ptr<scalar_t>() + b * D * H * W,
                                 out.data_ptr<scalar_t>() + (k * B + b) * C * H * W, C, D, H, W, opt);
      filt.run();
    });
  });
  return out;
}

at::Tensor adaptive_manifold_cpu(const at::Tensor& values, const at::Tensor& guide,
                                 double sigma_s, double sigma_r, int64_t tree_height,
                                 int64_t power_iterations, bool adjust_outliers) {
  return filter_images("adaptive_manifold", values, guide, {sigma_s}, sigma_r, {tree_height},
                       power_iterations, adjust_outliers)[0];
}

at::Tensor adaptive_manifold_bandwidths_cpu(const at::Tensor& values, const at::Tensor& guide,
                                            c10::ArrayRef<double> sigma_s, double sigma_r,
                                            c10::ArrayRef<int64_t> tree_height, int64_t power_iterations,
                                            bool adjust_outliers) {
  TORCH_CHECK_VALUE(!sigma_s.empty(), "_adaptive_manifold_bandwidths: sigma_s must hold at least one sigma");
  return filter_images("_adaptive_manifold_bandwidths", values, guide, sigma_s, sigma_r, tree_height,
                       power_iterations, adjust_outliers);
}

}  // namespace

TORCH_LIBRARY_IMPL(torchmanifold, CPU, m) {
  m.impl("adaptive_manifold", &adaptive_manifold_cpu);
  m.impl("_adaptive_manifold_bandwidths", &adaptive_manifold_bandwidths_cpu);
}

}  // namespace cpu
}  // namespace torchmanifold
