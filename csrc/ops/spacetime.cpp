// Schema of the joint space-time adaptive-manifold op (torchmanifold.ops.temporal, mode "spacetime").
// Kernels register per device in cpu/; Python registers the fake kernel, autograd and the pure-PyTorch
// kernel for other devices (torchmanifold/ops/_registrations.py).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(torchmanifold, m) {
  // values (B, T, C, H, W) and guide (B, T, D, H, W): a window of T frames; weights (Q, T): each
  // query's non-negative time weight of every frame; query_guide (B, Q, D, H, W): the guide the
  // manifolds of query q follow. Same floating dtype (float32/float64) and device, guides already
  // scaled to units where sigma_r applies to every channel. Returns (B, Q, C, H, W), same dtype.
  m.def(
      "spacetime_adaptive_manifold(Tensor values, Tensor guide, Tensor weights, Tensor query_guide, "
      "float sigma_s, float sigma_r, int tree_height, int power_iterations, bool adjust_outliers) -> Tensor");
  // Private (the denoiser's bandwidth candidates): the same at each of K spatial sigmas, with one tree
  // height for all or one per sigma -> (K, B, Q, C, H, W), each slice the bits of
  // spacetime_adaptive_manifold at that sigma and height; on CPU the K B Q images run side by side, one
  // per thread, when there are at least as many as threads.
  m.def(
      "_spacetime_adaptive_manifold_bandwidths(Tensor values, Tensor guide, Tensor weights, Tensor query_guide, "
      "float[] sigma_s, float sigma_r, int[] tree_height, int power_iterations, bool adjust_outliers) "
      "-> Tensor");
}
