// Schemas of the denoiser's fused frame-step kernels (torchmanifold/pipeline/_fast.py dispatches to them;
// torchmanifold/pipeline/denoise.py's PyTorch stages are the reference each one matches and the fallback
// on other devices). Private ops: the pipeline's internals, not a public API. All tensors are
// contiguous-or-made-so, float32 or float64, one device.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(torchmanifold, m) {
  // _Filter.normalise at frame queries: out = den > min_support ? num / den : values * mask (min_support:
  // denoise._min_support of the dtype), then (radius > 0) clamped to the range of the valid (mask > 0)
  // values in the (2 radius + 1)^2 box around each pixel (_Filter._guard). num/values (N, C, H, W),
  // den/mask (N, 1, H, W) -> (N, C, H, W).
  m.def("_normalise_guard(Tensor num, Tensor den, Tensor values, Tensor mask, int radius) -> Tensor");
  // The same where a query mixes a window of frames: fallback (N, C, H, W) replaces values * mask, and the
  // bounds are box maxima of hi and nlo (N, C, H, W), the window's largest valid value and largest minus
  // valid value at each pixel (-max where the window has none).
  m.def("_normalise_guard_bounds(Tensor num, Tensor den, Tensor fallback, Tensor hi, Tensor nlo, int radius) "
        "-> Tensor");
  // denoise._footprint_average after its knee: x (T, 3, H, W) clamped at 0 (NaN kept), k (T,) the tone-mapping
  // knee of each frame (PyTorch computes it, so the frame means are its bits) -> (T, 3, H, W); a light's border
  // between adjacent pixels drops the range weight as there (unseen_border: beside a lone lit neighbour too).
  m.def("_footprint_average(Tensor x, Tensor k, float sigma, float range_sigma, float unseen_border=0.) "
        "-> Tensor");
  // denoise._log_radiance's 3x3 Kuwahara filter (replicate borders) of x (N, C, H, W) -> (N, C, H, W).
  m.def("_kuwahara3(Tensor x) -> Tensor");
  // The end of denoise._select_bandwidth at frame queries: the weighted squared residuals of the K
  // predictions preds (K, T, 3, H, W) against e (T, 3, H, W), times weight (T, 1, H, W), pooled by a
  // Gaussian of blur_sigma normalised by the blurred mask (T, 1, H, W); each candidate's excess over the
  // least error, in standard errors (denoise._excess_error_z2), gives weights exp(-z^2 / 2 softness^2)
  // (softness > 0) that blend fulls (K, T, 3, H, W) -> (T, 3, H, W). A candidate is left out where its
  // prediction is NaN (no support) unless every one's is, and where its error exceeds error_cut times the
  // least. others (J, K + 1, T, H, W): neighbouring queries' residual planes (_cv_residuals), pooled with the
  // query's own under weights other_weights (J, T, H, W) relative to its 1 (selection._excess_error_z2).
  m.def("_cv_blend(Tensor preds, Tensor fulls, Tensor e, Tensor weight, Tensor mask, float blur_sigma, "
        "float softness, float error_cut, Tensor? others=None, Tensor? other_weights=None) -> Tensor");
  // _cv_blend's residual planes of one query, what its neighbours' blends borrow: (K + 1, T, H, W), the K
  // candidates' weighted squared residuals (a NaN prediction takes the worst held one), then the mask.
  m.def("_cv_residuals(Tensor preds, Tensor e, Tensor weight, Tensor mask) -> Tensor");
  // torch.quantile(v.double(), q, dim=1) (linear): v (R, N) float32/float64 -> (R, len(q)) float64.
  m.def("_quantiles(Tensor v, float[] q) -> Tensor");
  // denoise._select_bandwidth's stack for one op call: e (T, 3, H, W), mask (T, 1, H, W) -> (T, 8, H, W): per
  // checkerboard half [e * m, m], m = mask * half.
  m.def("_cv_halves(Tensor e, Tensor mask) -> Tensor");
  // The same written into out, a workspace the caller reuses across calls (fresh pages cost more than the pass).
  m.def("_cv_halves_out(Tensor e, Tensor mask, Tensor(a!) out) -> ()");
  // The op's output on that stack, y (T, 8, H, W) -> the prediction from the other half (T, 3, H, W; NaN
  // where that half's den is at most min_support), and both halves' sums num (T, 3, H, W), den (T, 1, H, W).
  m.def("_cv_split(Tensor y) -> (Tensor, Tensor, Tensor)");
  // denoise._sanitize's finite check: c (T, C, H, W), f (T, D, H, W) -> c and f with non-finite values 0,
  // mask (T, 1, H, W) (1 where all of a pixel's values are finite), counts int64 (3,): non-finite colour
  // values, non-finite feature values, masked pixels.
  m.def("_sanitize(Tensor c, Tensor f) -> (Tensor, Tensor, Tensor, Tensor)");
  // denoise._normalised_blur: blur(x w) / blur(w) (footprint_blur, sigma > 0) for x (T, C, H, W) and
  // weights w (T, 1, H, W), x where blur(w) <= 1e-8 -> (T, C, H, W).
  m.def("_normalised_blur(Tensor x, Tensor weight, float sigma) -> Tensor");
  // _Filter.window_bounds: values (T, C, H, W), mask (T, 1, H, W) -> at each query w the largest valid value of
  // the frames starts[w] .. starts[w] + lengths[w] - 1 and the largest minus valid value, (Q, C, H, W) each
  // (-max of the dtype where none is valid; NaN where one is, as torch.amax).
  m.def("_window_bounds(Tensor values, Tensor mask, int[] starts, int[] lengths) -> (Tensor, Tensor)");
  // footprint._box_mean: the mean of x (..., H, W) over the (2 radius + 1)^2 box around each pixel, the border
  // replicated, each plane summed along x, then along y, divided once.
  m.def("_box_mean(Tensor x, int radius) -> Tensor");
  // denoise._same_pixel: world positions p (3, H, W) against others (K, 3, H, W) -> bool (K, 1, H, W), where
  // the other sample lies within same_pixel pixels along each image axis, on the surface, and the mean
  // offset over the (2 radius + 1)^2 pixels around stays under still pixels.
  m.def("_same_pixel(Tensor p, Tensor others, float same_pixel, float still, int radius) -> Tensor");
  // denoise._footprint_samples: world positions p (3, H, W) of one sample per pixel against the other
  // frames' others (K, 3, H, W) with their albedo (K, 3, H, W) and valid (K, H, W) -> the albedo sum
  // (K, 3, H, W) and the count (K, 1, H, W) of the other frames' samples inside each pixel's footprint,
  // 0 where search (bool (K, H, W)) is false (radius: the flow's pooling).
  m.def("_footprint_samples(Tensor p, Tensor others, Tensor albedo, Tensor valid, Tensor search, "
        "int radius) -> (Tensor, Tensor)");
  // footprint._edge_directions after its knee: x (T, 3, H, W), k (T,) -> (T, 3, H, W), each pixel's
  // coherence^power and edge direction (tx, ty) from the structure tensor blurred over tensor_sigma.
  m.def("_edge_directions(Tensor x, Tensor k, float tensor_sigma, float power) -> Tensor");
  // footprint._along_edges after its knees, of M images along one set of directions: x (M, T, 3, H, W), k
  // (M, T), the per-pixel widths sigma (M, T, 1, H, W), the directions (T, 3, H, W) of _edge_directions ->
  // (M, T, 3, H, W).
  m.def("_along_edges(Tensor x, Tensor k, Tensor sigma, Tensor directions, float range_sigma) -> Tensor");
  // align._least_cost: matched fields to and source (C, H, W), per-pixel offsets dy, dx (int64 (H, W)) and
  // offsets (a flat list of (dy, dx) pairs) -> per pixel the offset dy + a, dx + b whose L1
  // difference averaged over the (2 radius + 1)^2 box (the pixels whose source lies in the frame; 1e30 where
  // the pixel's own does not) is least (the first on a tie): dy, dx, cost.
  m.def("_least_offset_cost(Tensor to, Tensor source, Tensor dy, Tensor dx, int[] offsets, int radius) "
        "-> (Tensor, Tensor, Tensor)");
  // align._median_costs: to and source (C, H, W), grid pixels ys, xs (int64 (N,)), offsets (a
  // flat list of (dy, dx) pairs) -> (O,) the lower median over the grid of each offset's L1
  // differences (those inside the frame; inf where none is). keep > 0: inf also for offsets whose median is
  // certainly above keep others' (the keep least, by median then order, are exact).
  m.def("_median_offset_costs(Tensor to, Tensor source, Tensor ys, Tensor xs, int[] offsets, int keep=0) "
        "-> Tensor");
}
