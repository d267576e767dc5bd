// Schema of the adaptive-manifold filter op. Kernels register per device in cpu/ (and cuda/);
// Python registers the fake (shape) kernel, autograd and a pure-PyTorch kernel for other devices.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(torchmanifold, m) {
  // values (B, C, H, W) and guide (B, D, H, W), same floating dtype (float32/float64) and device,
  // contiguous. The guide is already scaled to units where sigma_r applies to every channel.
  // Returns the filtered values (B, C, H, W), same dtype.
  m.def(
      "adaptive_manifold(Tensor values, Tensor guide, float sigma_s, float sigma_r, int tree_height, "
      "int power_iterations, bool adjust_outliers) -> Tensor");
  // Private (the denoiser's bandwidth candidates): the same filter at each of K spatial sigmas, with
  // one tree height for all or one per sigma -> (K, B, C, H, W), each slice the bits adaptive_manifold
  // gives at that sigma and height. The CPU kernel runs
  // the K B images side by side, one per thread, when there are at least as many images as threads:
  // one image's passes scale poorly on few cores (1.35x on 2), independent images nearly 2x.
  m.def(
      "_adaptive_manifold_bandwidths(Tensor values, Tensor guide, float[] sigma_s, float sigma_r, "
      "int[] tree_height, int power_iterations, bool adjust_outliers) -> Tensor");
}
