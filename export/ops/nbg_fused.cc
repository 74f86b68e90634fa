// The NBG denoiser's per-pixel glue, fused (quietframe.model.nbg_fused is the reference):
//
//   NBGAccumulate(radiance (N,3,H,W), warped (N,8,H,W), inside (N,1,H,W), depth (N,1,H,W),
//                 normal (N,3,H,W), reset (N)) -> accumulated (N,3,H,W), state (N,8,H,W)
//     the temporal accumulation after the history's reprojection (NBG §4.6,
//     model/temporal.accumulate): the disocclusion test, the 1/n-then-fixed current weight, the
//     blend and the new state (radiance, depth, normal, history length).
//   NBGFeatures(radiance (N,3,H,W), safe_albedo (N,3,H,W), albedo (N,3,H,W), normal (N,3,H,W),
//               depth (N,1,H,W), depth_scale (N,1,1,1)) -> features (N,10,H,W)
//     GuideNet's input (paper §5, model/nbg.guide_features) from the demodulated radiance; the
//     frame's depth scale is an input so that a tiled run feeds the frame's (runtime/statistics).
//   NBGBlend(logits (N,6,H,W), safe_albedo (N,3,H,W), sliced0, sliced1, sliced2 (N,3,H,W))
//     -> denoised (N,3,H,W)
//     the softmax of GuideNet's blend logits (channels 3..5) weighting the three sliced grids,
//     remodulated by the albedo.
//   NBGBlendPass(logits (N,8,H,W), safe_albedo (N,3,H,W), sliced0, sliced1, sliced2,
//                accumulated, frame (N,3,H,W)) -> denoised (N,3,H,W)
//     the same with NBGConfig.passthrough: the softmax of channels 3..7 also weighs the
//     accumulated irradiance and the frame's own (one body with NBGBlend: BlendKernel).
//
// Each was 15–30 element-wise onnxruntime nodes, every one a pass over full-frame tensors
// (about a third of nbg-2l-3g's time); here one pass per op. The arithmetic is the reference's,
// operation by operation and in its order (no FMA contraction, -ffp-contract=off), so results
// agree with it to float rounding (powf and expf are the only library calls). Parallel over
// bands of rows; every pixel is independent, so results do not depend on the thread count.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>

#include "kernel_support.h"
#include "ops.h"
#include "runtime_support.h"

namespace qf {
namespace {

constexpr int64_t kMinRowsPerBand = 8;

// Runs body(n, first, end) over bands of pixels [first, end) of each image's H·W plane.
template <class Body>
OrtStatus* for_pixel_bands(const ort::Api& api, const char* op, OrtKernelContext* ctx,
                           int64_t N, int64_t H, int64_t W, const Body& body) {
  const int64_t bands = band_count(H, N, kMinRowsPerBand);
  auto task = [&](size_t i) {
    const int64_t n = static_cast<int64_t>(i) / bands, band = static_cast<int64_t>(i) % bands;
    body(n, band_start(band, bands, H) * W, band_start(band + 1, bands, H) * W);
  };
  return run_tasks(api, op, ctx, N * bands, task);
}

// torch.clamp on one float: NaN stays NaN.
inline float clamp_min(float x, float lo) { return x < lo ? lo : x; }
inline float clamp_max(float x, float hi) { return x > hi ? hi : x; }

// ---- NBGAccumulate ---------------------------------------------------------------------------

struct AccumulateAttributes {
  float depth_tolerance = 0;     // |d_prev - d| <= tol · max(d, 1e-6)
  float normal_min_dot = 0;      // n_prev · n > dot · |n_prev| |n|
  float min_current_weight = 0;  // the current frame's weight after 1/min_current_weight frames
};

OrtStatus* read_accumulate(const ort::Api& api, const char* op, const OrtKernelInfo* info,
                           AccumulateAttributes* a) {
  if (OrtStatus* s = get_float_attribute(api, op, info, "depth_tolerance", &a->depth_tolerance)) {
    return s;
  }
  if (OrtStatus* s = get_float_attribute(api, op, info, "normal_min_dot", &a->normal_min_dot)) {
    return s;
  }
  if (OrtStatus* s =
          get_float_attribute(api, op, info, "min_current_weight", &a->min_current_weight)) {
    return s;
  }
  if (!(a->min_current_weight > 0 && a->min_current_weight <= 1)) {
    return op_error(api, op, "min_current_weight must be in (0, 1], got " +
                                 format_float(a->min_current_weight));
  }
  return nullptr;
}

// One band of pixels [first, end) of one image (planes P apart). A function of its own with
// __restrict pointers (no output aliases an input): the loop vectorises.
void accumulate_pixels(const AccumulateAttributes& a, int64_t P, int64_t first, int64_t end,
                       const float* __restrict rad, const float* __restrict warped,
                       const float* __restrict inside, const float* __restrict depth,
                       const float* __restrict normal, float not_reset, float* __restrict out,
                       float* __restrict st) {
  const float max_count = 1.0f / a.min_current_weight;
  const float tolerance = a.depth_tolerance, min_dot = a.normal_min_dot;
  const float min_weight = a.min_current_weight;
  const float* __restrict prev[3] = {warped, warped + P, warped + 2 * P};
  const float* __restrict prev_depth = warped + 3 * P;
  const float* __restrict pn0 = warped + 4 * P;
  const float* __restrict pn1 = warped + 5 * P;
  const float* __restrict pn2 = warped + 6 * P;
  const float* __restrict prev_count = warped + 7 * P;
  const float* __restrict cn0 = normal;
  const float* __restrict cn1 = normal + P;
  const float* __restrict cn2 = normal + 2 * P;
  float* __restrict count_out = st + 7 * P;
  float* __restrict keep_out = st + 3 * P;  // scratch for keep, overwritten by depth below
  for (int64_t p = first; p < end; ++p) {
    const float d = depth[p];
    // model/temporal.history_valid
    const bool depth_ok = std::fabs(prev_depth[p] - d) <= clamp_min(d, 1e-6f) * tolerance;
    const float wn0 = pn0[p], wn1 = pn1[p], wn2 = pn2[p];
    const float n0 = cn0[p], n1 = cn1[p], n2 = cn2[p];
    const float dot = wn0 * n0 + wn1 * n1 + wn2 * n2;
    const float lengths = std::sqrt(wn0 * wn0 + wn1 * wn1 + wn2 * wn2) *
                          std::sqrt(n0 * n0 + n1 * n1 + n2 * n2);
    const bool normal_ok = dot > lengths * min_dot;
    const float valid = (depth_ok && normal_ok) ? 1.0f : 0.0f;
    const float keep = inside[p] * valid * not_reset;
    // model/temporal.history_weights: n = keep·clamp(n_prev, 0, 1/w) + 1, α = max(1/n, w)
    const float count = keep * clamp_max(clamp_min(prev_count[p], 0.0f), max_count) + 1.0f;
    count_out[p] = count;
    keep_out[p] = clamp_min(1.0f / count, min_weight);  // α
  }
  for (int64_t c = 0; c < 3; ++c) {
    const float* __restrict r = rad + c * P;
    const float* __restrict h = prev[c];
    float* __restrict o = out + c * P;
    float* __restrict so = st + c * P;
    for (int64_t p = first; p < end; ++p) {
      const float alpha = keep_out[p];
      const float v = alpha * r[p] + (1.0f - alpha) * h[p];
      o[p] = v;
      so[p] = v;
    }
  }
  std::copy(depth + first, depth + end, st + 3 * P + first);
  for (int64_t c = 0; c < 3; ++c) {
    std::copy(normal + c * P + first, normal + c * P + end, st + (4 + c) * P + first);
  }
}

struct NBGAccumulate : Kernel<NBGAccumulate, AccumulateAttributes, read_accumulate> {
  static constexpr const char* kName = "NBGAccumulate";
  static constexpr const char* kInputNames[] = {"radiance", "warped", "inside",
                                                "depth",    "normal", "reset"};
  static constexpr size_t kOutputs = 2;

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<6>& in) const {
    const Shape& rs = in[0].shape;
    // radiance, warped, inside, depth, normal
    if (OrtStatus* s = check_image_inputs(api, kName, kInputNames, in, {3, 8, 1, 1, 3})) return s;
    const Shape& reset_shape = in[5].shape;
    if (reset_shape.rank != 1 || reset_shape[0] != rs[0]) {
      return op_error(api, kName, "reset must be (N,) = (" + std::to_string(rs[0]) + ",), got " +
                                      reset_shape.str());
    }
    const int64_t N = rs[0], H = rs[2], W = rs[3], P = H * W;
    const Shape state_shape = with_channels(rs, 8);
    float* acc = nullptr;
    float* state = nullptr;
    if (OrtStatus* s = get_float_output(api, kName, ctx, 0, "accumulated", rs, &acc)) return s;
    if (OrtStatus* s = get_float_output(api, kName, ctx, 1, "state", state_shape, &state)) {
      return s;
    }
    const AccumulateAttributes a = attributes_;
    auto body = [&](int64_t n, int64_t first, int64_t end) {
      accumulate_pixels(a, P, first, end, in[0].data + n * 3 * P, in[1].data + n * 8 * P,
                        in[2].data + n * P, in[3].data + n * P, in[4].data + n * 3 * P,
                        1.0f - in[5].data[n], acc + n * 3 * P, state + n * 8 * P);
    };
    return for_pixel_bands(api, kName, ctx, N, H, W, body);
  }
};

// ---- NBGFeatures -----------------------------------------------------------------------------

struct FeaturesAttributes {
  float exponent = 0;  // the LDR map's gamma exponent (1/2.2)
};

OrtStatus* read_features(const ort::Api& api, const char* op, const OrtKernelInfo* info,
                         FeaturesAttributes* a) {
  return get_float_attribute(api, op, info, "exponent", &a->exponent);
}

struct NBGFeatures : Kernel<NBGFeatures, FeaturesAttributes, read_features> {
  static constexpr const char* kName = "NBGFeatures";
  static constexpr const char* kInputNames[] = {"radiance", "safe_albedo", "albedo",
                                                "normal",   "depth",       "depth_scale"};
  static constexpr size_t kOutputs = 1;

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<6>& in) const {
    const Shape& rs = in[0].shape;
    // radiance, safe_albedo, albedo, normal, depth
    if (OrtStatus* s = check_image_inputs(api, kName, kInputNames, in, {3, 3, 3, 3, 1})) return s;
    const Shape& ss = in[5].shape;
    if (ss.rank != 4 || ss[0] != rs[0] || ss[1] != 1 || ss[2] != 1 || ss[3] != 1) {
      return op_error(api, kName, "depth_scale must be (N, 1, 1, 1), got " + ss.str());
    }
    const int64_t N = rs[0], H = rs[2], W = rs[3], P = H * W;
    const Shape fs = with_channels(rs, 10);
    float* features = nullptr;
    if (OrtStatus* s = get_float_output(api, kName, ctx, 0, "features", fs, &features)) return s;
    const float exponent = attributes_.exponent;
    auto body = [&](int64_t n, int64_t first, int64_t end) {
      const float* __restrict rad = in[0].data + n * 3 * P;
      const float* __restrict safe = in[1].data + n * 3 * P;
      const float* __restrict albedo = in[2].data + n * 3 * P;
      const float* __restrict normal = in[3].data + n * 3 * P;
      const float* __restrict depth = in[4].data + n * P;
      const float scale = in[5].data[n];
      float* __restrict out = features + n * 10 * P;
      for (int64_t c = 0; c < 3; ++c) {
        const float* __restrict r = rad + c * P;
        const float* __restrict s = safe + c * P;
        float* __restrict o = out + c * P;
        // ldr: Reinhard x / (1 + x) of the remodulated radiance, then gamma (its own loop, so
        // the rest vectorises)
        for (int64_t p = first; p < end; ++p) {
          const float x = clamp_min(r[p] * s[p], 0.0f);
          o[p] = x / (x + 1.0f);
        }
        for (int64_t p = first; p < end; ++p) o[p] = std::pow(o[p], exponent);
        const float* __restrict al = albedo + c * P;
        float* __restrict oa = out + (3 + c) * P;
        for (int64_t p = first; p < end; ++p) oa[p] = clamp_max(clamp_min(al[p], 0.0f), 1.0f);
        const float* __restrict nm = normal + c * P;
        float* __restrict on = out + (6 + c) * P;
        for (int64_t p = first; p < end; ++p) {
          on[p] = (clamp_max(clamp_min(nm[p], -1.0f), 1.0f) + 1.0f) * 0.5f;
        }
      }
      float* __restrict od = out + 9 * P;
      for (int64_t p = first; p < end; ++p) {
        const float rel = depth[p] / scale;  // scene-unit free
        od[p] = rel / (rel + 1.0f);
      }
    };
    return for_pixel_bands(api, kName, ctx, N, H, W, body);
  }
};

// ---- NBGBlend, NBGBlendPass ------------------------------------------------------------------

constexpr int64_t kGrids = 3;

// The blend of `kCandidates` images (the kGrids sliced grids, then NBGBlendPass's two
// pass-through candidates): inputs logits (N, kGrids + kCandidates, H, W), safe_albedo, then the candidates (N, 3, H, W);
// the candidates' weights are the softmax of the logits after GuideNet's kGrids guides. K names
// the op and its inputs.
template <class K, int64_t kCandidates>
struct BlendKernel : Kernel<K, NoAttributes, read_no_attributes> {
  static constexpr size_t kOutputs = 1;
  static constexpr size_t kInputs = 2 + kCandidates;

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<kInputs>& in) const {
    static_assert(std::size(K::kInputNames) == kInputs, "logits, safe_albedo, the candidates");
    constexpr int64_t kLogits = kGrids + kCandidates;
    int64_t channels[kInputs];  // logits, safe_albedo, the candidates
    channels[0] = kLogits;
    std::fill(channels + 1, channels + kInputs, int64_t{3});
    if (OrtStatus* s = check_image_inputs(api, K::kName, K::kInputNames, in, channels)) return s;
    const Shape& ls = in[0].shape;
    const int64_t N = ls[0], H = ls[2], W = ls[3], P = H * W;
    float* denoised = nullptr;
    if (OrtStatus* s =
            get_float_output(api, K::kName, ctx, 0, "denoised", with_channels(ls, 3), &denoised)) {
      return s;
    }
    auto body = [&](int64_t n, int64_t first, int64_t end) {
      const float* logits = in[0].data + (n * kLogits + kGrids) * P;  // the blend logits
      const float* safe = in[1].data + n * 3 * P;
      const float* candidate[kCandidates];
      for (int64_t g = 0; g < kCandidates; ++g) candidate[g] = in[2 + g].data + n * 3 * P;
      float* out = denoised + n * 3 * P;
      for (int64_t p = first; p < end; ++p) {
        // model/nbg.channel_softmax: the max subtracted, so a large logit cannot overflow exp
        float peak = logits[p];
        for (int64_t g = 1; g < kCandidates; ++g) peak = std::max(peak, logits[g * P + p]);
        float e[kCandidates];
        float sum = 0.0f;
        for (int64_t g = 0; g < kCandidates; ++g) {
          e[g] = std::exp(logits[g * P + p] - peak);
          sum += e[g];
        }
        for (int64_t g = 0; g < kCandidates; ++g) e[g] = e[g] / sum;
        for (int64_t c = 0; c < 3; ++c) {
          float v = 0.0f;
          for (int64_t g = 0; g < kCandidates; ++g) v = v + e[g] * candidate[g][c * P + p];
          out[c * P + p] = v * safe[c * P + p];
        }
      }
    };
    return for_pixel_bands(api, K::kName, ctx, N, H, W, body);
  }
};

struct NBGBlend : BlendKernel<NBGBlend, kGrids> {
  static constexpr const char* kName = "NBGBlend";
  static constexpr const char* kInputNames[] = {"logits", "safe_albedo", "sliced0", "sliced1",
                                                "sliced2"};
};

struct NBGBlendPass : BlendKernel<NBGBlendPass, kGrids + 2> {
  static constexpr const char* kName = "NBGBlendPass";
  static constexpr const char* kInputNames[] = {"logits",  "safe_albedo", "sliced0",
                                                "sliced1", "sliced2",     "accumulated",
                                                "frame"};
};

}  // namespace

const OrtCustomOp* nbg_accumulate_op() { return CustomOp<NBGAccumulate>::get(); }
const OrtCustomOp* nbg_features_op() { return CustomOp<NBGFeatures>::get(); }
const OrtCustomOp* nbg_blend_op() { return CustomOp<NBGBlend>::get(); }
const OrtCustomOp* nbg_blend_pass_op() { return CustomOp<NBGBlendPass>::get(); }

}  // namespace qf
