// What every kernel of torchmanifold::adaptive_manifold shares, whatever its device: the argument
// checks, the tree-height limit, the low-resolution grid's downsampling factor and the sampling of
// the split's M. The numbered steps are those of torchmanifold/ops/_reference.py; the Python
// reference and checks (torchmanifold/_checks.py) use the same numbers.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <cmath>
#include <cstdint>

namespace torchmanifold {

// Largest tree height (torchmanifold._checks.MAX_TREE_HEIGHT). Cluster labels are int32 heap ids:
// nodes at depth d have ids in [2^d, 2^(d+1)), so a tree of height H writes labels below 2^H; H <= 30
// keeps them clear of the sign bit with one bit to spare. Memory does not bound H: empty clusters are
// pruned, so a level never has more nodes than the image has pixels.
constexpr int64_t kMaxTreeHeight = 30;

// 4. The downsampling factor of the low-resolution grid, the rule of the authors' code and OpenCV's
// amFilter: df = max(1, 2^floor(log2(min(sigma_s / kLowResSigma, kRangeDownsample sigma_r)))).
// sigma_s / df then lands in [kLowResSigma, 2 kLowResSigma) low-res pixels; a narrow range kernel
// (small sigma_r) downsamples less. Their kLowResSigma is 4; 2 halves the grid for sigma_s 4 to 16
// at the same accuracy against the brute-force filter (sigma_s 8 and 16: within 0.1 dB; 4 and 6:
// 0.1-0.8 dB less, at 39-43 dB) and the same denoising (docs/adaptive-manifolds.md, "The
// low-resolution grid").
constexpr double kLowResSigma = 2.0;
constexpr double kRangeDownsample = 256.0;
// 2^kMaxDownsampleLog2 caps df so that the shift below stays inside an int64 (any image is smaller).
constexpr int kMaxDownsampleLog2 = 30;

inline int64_t downsample_factor(double sigma_s, double sigma_r) {
  const double m = std::min(sigma_s / kLowResSigma, kRangeDownsample * sigma_r);
  if (!(m >= 2.0)) return 1;
  const int e = std::min(kMaxDownsampleLog2, static_cast<int>(std::floor(std::log2(m))));
  return int64_t(1) << e;
}

// 8. The split's M = sum r r^T takes the rows of every s-th band of kGramBand rows,
// s = max(1, floor(H W / kGramSamples)): still >= kGramSamples (2^17) samples for a D x D matrix,
// where the full sum costs D^2 / 2 multiply-adds a pixel and a read of the guide. At 1 MP with 17
// guide channels this sampling moved PSNR against the exact filter by less than 0.3 dB (see
// _reference.py). Bands, not single rows: a channel's band is one run of memory, which streams
// faster than rows far apart.
constexpr int64_t kGramBand = 4;
constexpr int64_t kGramSamples = int64_t(1) << 17;
inline int64_t gram_band_stride(int64_t H, int64_t W) {
  return std::max<int64_t>(1, H * W / kGramSamples);
}

// The op's argument checks, shared by every device's kernel (the device itself is the kernel's
// check). ValueError / TypeError in Python, each naming the argument and what was expected, in the
// words of torchmanifold/_checks.py.
inline void check_adaptive_manifold_args(const at::Tensor& values, const at::Tensor& guide,
                                         double sigma_s, double sigma_r, int64_t tree_height,
                                         int64_t power_iterations) {
  TORCH_CHECK_VALUE(values.dim() == 4, "adaptive_manifold: values must be (B, C, H, W), got shape ",
                    values.sizes());
  TORCH_CHECK_VALUE(guide.dim() == 4, "adaptive_manifold: guide must be (B, D, H, W), got shape ",
                    guide.sizes());
  TORCH_CHECK_VALUE(values.size(0) == guide.size(0) && values.size(2) == guide.size(2) &&
                        values.size(3) == guide.size(3),
                    "adaptive_manifold: guide must share B, H, W with values ", values.sizes(),
                    ", got ", guide.sizes());
  TORCH_CHECK_VALUE(guide.size(1) >= 1, "adaptive_manifold: guide must have D >= 1 channels, got ",
                    guide.sizes());
  TORCH_CHECK_TYPE(values.scalar_type() == at::kFloat || values.scalar_type() == at::kDouble,
                   "adaptive_manifold: values must have dtype float32, float64, got ",
                   values.scalar_type());
  TORCH_CHECK_VALUE(guide.scalar_type() == values.scalar_type(),
                    "adaptive_manifold: guide must have the dtype of values (", values.scalar_type(),
                    "), got ", guide.scalar_type());
  TORCH_CHECK_VALUE(guide.device() == values.device(),
                    "adaptive_manifold: guide must be on the device of values (", values.device(),
                    "), got ", guide.device());
  TORCH_CHECK_VALUE(std::isfinite(sigma_s) && sigma_s > 0,
                    "adaptive_manifold: sigma_s must be a finite number > 0, got ", sigma_s);
  TORCH_CHECK_VALUE(std::isfinite(sigma_r) && sigma_r > 0,
                    "adaptive_manifold: sigma_r must be a finite number > 0, got ", sigma_r);
  TORCH_CHECK_VALUE(tree_height >= 1 && tree_height <= kMaxTreeHeight,
                    "adaptive_manifold: tree_height must be an int in [1, ", kMaxTreeHeight, "], got ",
                    tree_height);
  TORCH_CHECK_VALUE(power_iterations >= 0,
                    "adaptive_manifold: power_iterations must be an int >= 0, got ", power_iterations);
}

}  // namespace torchmanifold
