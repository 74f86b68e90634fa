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
//     accumulated irradiance and the frame's own.
//   NBGBlendNoise(logits (N,8,H,W), safe_albedo (N,3,H,W), sliced0, sliced1, sliced2,
//                 accumulated, frame (N,3,H,W), state (N,8,H,W), spp (1) or (N),
//                 noise_scale (5), noise_shift (5)) -> denoised (N,3,H,W)
//     NBGBlendPass with NBGConfig.noise_blend: the blend logits first moved by the pixel's noise
//     level, from the image's spp and the state's history length (channel 7).
//   The three blends are one body (BlendKernel), the logits read through a policy.
//
// Each was 15–30 element-wise onnxruntime nodes, every one a pass over full-frame tensors
// (about a third of nbg-2l-3g's time); here one pass per op. The arithmetic is the reference's,
// operation by operation and in its order (no FMA contraction, -ffp-contract=off), so results
// agree with it to float rounding (powf is the only library call; the blends' exp and log2
// are ours, within 1 ulp, so that their loops vectorise). Parallel over bands of rows; every
// pixel is independent, so results do not depend on the thread count.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
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
// std::max on values (std::max's reference result keeps a loop of it from vectorising).
inline float max_of(float a, float b) { return a < b ? b : a; }

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

// ---- NBGBlend, NBGBlendPass, NBGBlendNoise ---------------------------------------------------

constexpr int64_t kGrids = 3;
constexpr int64_t kPassThrough = 2;  // the accumulated irradiance, the frame's
// Pixels a blend takes at a time: its softmax and its weighted sum are each a loop over the
// block that vectorises, and the block's weights (kCandidates × 1 KiB) stay in L1 between them.
constexpr int64_t kBlendBlock = 256;

template <int64_t kCandidates>
using BlockPlanes = float[kCandidates][kBlendBlock];

// A value's bits as another type of their size (memcpy: defined for every value; vectorises).
template <class To, class From>
inline To bits_as(From v) {
  static_assert(sizeof(To) == sizeof(From), "same size");
  To out;
  std::memcpy(&out, &v, sizeof out);
  return out;
}

// e^x with no library call, so that a loop of it vectorises (std::exp is a call per element):
// Cody–Waite reduction x = n·ln2 + r, |r| <= ln2/2 (ln2 in two parts, n·hi exact), Cephes's
// expf polynomial for e^r, and n put into the exponent bits. Within 1 ulp of exp over every
// float in [-87.3, 0] (torch's own exp is within 1 ulp too); below, where exp is subnormal
// (under 1.2e-38), a rough subnormal, and 0 from -87.7 on; x above 88 is taken as 88, NaN stays
// NaN. Plain operations in a fixed order (no FMA contraction), so vector and scalar loops, and
// AVX2 and baseline x86-64 builds, give the same bits.
inline float exp_approx(float x) {
  x = clamp_max(clamp_min(x, -88.0f), 88.0f);  // |n| <= 127: 2^n is a float (0 at n = -127)
  constexpr float kRound = 12582912.0f;  // 1.5 · 2^23: adding it rounds to an integer
  const float shifted = x * 1.44269504f + kRound;  // n in the low bits of the mantissa
  const float n = shifted - kRound;
  float r = x - n * 0.693359375f;  // exact (Sterbenz; n · 0.693359375 has 16 bits)
  r = r - n * -2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * (r * r) + r + 1.0f;
  const float two_n = bits_as<float>((bits_as<uint32_t>(shifted) << 23) + 0x3f800000u);
  return p * two_n;
}

// log2(x) rounded to float, x in [1, 2^127]: x = 2^e · m with m in [√½, √2), ln m = 2·atanh(t),
// t = (m - 1) / (m + 1), |t| <= 0.172, by its series to t^13 in double (relative error under
// 1e-11). So the float is log2's correctly rounded one but for rare near-ties (19 of the 84M
// floats in [1, 1024]), as torch.log2's is: the noise level scales logits (a logit of 90 by
// up to 90 · scale), so its last bit would show in the weights.
inline float log2_rounded(float x) {
  const uint32_t b = bits_as<uint32_t>(x);
  uint32_t mantissa = (b & 0x7fffffu) | 0x3f800000u;  // [1, 2)
  const uint32_t high = mantissa > 0x3fb504f3u ? 1u : 0u;  // above √2: halve m, e + 1
  mantissa -= high << 23;
  const int32_t e = static_cast<int32_t>((b >> 23) + high) - 127;
  const double m = bits_as<float>(mantissa);
  const double t = (m - 1.0) / (m + 1.0), s = t * t;
  double p = 1.0 / 13;
  p = p * s + 1.0 / 11;
  p = p * s + 1.0 / 9;
  p = p * s + 1.0 / 7;
  p = p * s + 1.0 / 5;
  p = p * s + 1.0 / 3;
  const double ln_m = 2.0 * t + 2.0 * t * s * p;
  return static_cast<float>(e + ln_m * 1.4426950408889634);  // 1 / ln 2
}

// model/nbg.noise_level of a pixel's samples (spp · history length).
inline float noise_level(float samples) {
  constexpr float kLog2Range = 10.0f;  // NOISE_LOG2_RANGE
  // From 1024 samples on the level is 1; the bound keeps log2's input finite. NaN passes.
  const float x = clamp_max(clamp_min(samples, 1.0f), 1024.0f);
  const float level = clamp_max(clamp_min(log2_rounded(x) / kLog2Range, 0.0f), 1.0f);
  return x != x ? x : level;  // NaN samples: a NaN level, as torch's
}

// Whether x[0, m) are all one value (and not NaN).
inline bool uniform(const float* x, int64_t m) {
  const float first = x[0];
  int same = 1;
  for (int64_t i = 0; i < m; ++i) same &= x[i] == first ? 1 : 0;
  return same != 0;
}

// How a blend reads its logits: a policy, made per image and band, names the inputs it reads
// after the candidates (kInputs) and checks them; `block` points it at a block of pixels, and
// `at(g, i)` is candidate g's logit at pixel i of the block, inlined into the softmax's loop.
// PlainLogits: GuideNet's as they are (NBGBlend, NBGBlendPass).
template <int64_t kCandidates>
class PlainLogits {
 public:
  static constexpr size_t kInputs = 0;

  template <size_t n>
  static OrtStatus* check(const ort::Api&, const char*, const char* const*, const FloatInputs<n>&,
                          size_t) {
    return nullptr;
  }

  template <size_t n>
  PlainLogits(const FloatInputs<n>&, size_t, int64_t, int64_t) {}

  // Pixels [p, p + m) of the image's blend-logit planes (P apart).
  void block(const float* logits, int64_t P, int64_t p, int64_t) {
    for (int64_t g = 0; g < kCandidates; ++g) rows_[g] = logits + g * P + p;
  }

  float at(int64_t g, int64_t i) const { return rows_[g][i]; }

 protected:
  const float* rows_[kCandidates] = {};
};

// NBGBlendNoise's: each logit moved by its pixel's noise level (model/nbg.modulate_logits),
// from the image's spp and the state's history length (channel 7).
template <int64_t kCandidates>
class NoiseLogits : public PlainLogits<kCandidates> {
 public:
  static constexpr size_t kInputs = 4;  // state, spp, noise_scale, noise_shift
  static constexpr int64_t kStateChannels = 8;
  static constexpr int64_t kCountChannel = 7;

  // `first`: the index of the state among the op's inputs, after the images.
  template <size_t n>
  static OrtStatus* check(const ort::Api& api, const char* op, const char* const* names,
                          const FloatInputs<n>& in, size_t first) {
    const Shape& image = in[0].shape;
    if (OrtStatus* s = check_planes_like(api, op, names[first], in[first].shape, kStateChannels,
                                         image)) {
      return s;
    }
    const Shape& spp = in[first + 1].shape;
    if (spp.rank != 1 || (spp[0] != 1 && spp[0] != image[0])) {
      return op_error(api, op, std::string(names[first + 1]) + " must be (1,) or (N,) = (" +
                                   std::to_string(image[0]) + ",), got " + spp.str());
    }
    for (size_t i = first + 2; i < first + 4; ++i) {
      const Shape& shape = in[i].shape;
      if (shape.rank != 1 || shape[0] != kCandidates) {
        return op_error(api, op, std::string(names[i]) + " must be (" +
                                     std::to_string(kCandidates) +
                                     ",), one per blend candidate, got " + shape.str());
      }
    }
    return nullptr;
  }

  template <size_t n>
  NoiseLogits(const FloatInputs<n>& in, size_t first, int64_t image, int64_t P)
      : PlainLogits<kCandidates>(in, first, image, P),
        count_(in[first].data + (image * kStateChannels + kCountChannel) * P),
        spp_(in[first + 1].data[in[first + 1].shape[0] == 1 ? 0 : image]) {
    std::copy(in[first + 2].data, in[first + 2].data + kCandidates, scale_);
    std::copy(in[first + 3].data, in[first + 3].data + kCandidates, shift_);
  }

  void block(const float* logits, int64_t P, int64_t p, int64_t m) {
    PlainLogits<kCandidates>::block(logits, P, p, m);
    const float* count = count_ + p;
    if (uniform(count, m)) {  // most blocks: one history length, one log2
      std::fill(level_, level_ + m, noise_level(spp_ * count[0]));
    } else {
      for (int64_t i = 0; i < m; ++i) level_[i] = noise_level(spp_ * count[i]);
    }
  }

  // l (1 + scale · level) + shift · level, in that order
  float at(int64_t g, int64_t i) const {
    const float level = level_[i];
    const float t = this->rows_[g][i] * (1.0f + scale_[g] * level);
    return t + shift_[g] * level;
  }

 private:
  const float* count_;  // the image's history lengths
  float spp_;
  float scale_[kCandidates], shift_[kCandidates];
  float level_[kBlendBlock];  // the block's
};

// model/nbg.channel_softmax of a block's logits into `w`: the max subtracted, so that a large
// logit cannot overflow exp. One loop over the pixels, the candidates unrolled in it (GCC jammed
// per-candidate loops over the pixels into ones it did not vectorise).
template <int64_t kCandidates, class Logits>
void softmax_block(const Logits& logits, int64_t m, BlockPlanes<kCandidates>& __restrict w) {
  for (int64_t i = 0; i < m; ++i) {
    float l[kCandidates];
    for (int64_t g = 0; g < kCandidates; ++g) l[g] = logits.at(g, i);
    float peak = l[0];
    for (int64_t g = 1; g < kCandidates; ++g) peak = max_of(peak, l[g]);
    float sum = 0.0f;
    for (int64_t g = 0; g < kCandidates; ++g) {
      l[g] = exp_approx(l[g] - peak);
      sum = sum + l[g];
    }
    for (int64_t g = 0; g < kCandidates; ++g) w[g][i] = l[g] / sum;
  }
}

// The weighted sum of the candidates over pixels [p, p + m), remodulated; per colour channel, so
// that every load is contiguous.
template <int64_t kCandidates>
void blend_block(const BlockPlanes<kCandidates>& w, const float* const (&candidate)[kCandidates],
                 const float* safe, float* out, int64_t P, int64_t p, int64_t m) {
  for (int64_t c = 0; c < 3; ++c) {
    const int64_t at = c * P + p;
    const float* s = safe + at;
    float* o = out + at;
    for (int64_t i = 0; i < m; ++i) {
      float sum = 0.0f;
      for (int64_t g = 0; g < kCandidates; ++g) sum = sum + w[g][i] * candidate[g][at + i];
      o[i] = sum * s[i];
    }
  }
}

// The blend of `kCandidates` images (the kGrids sliced grids, then the pass-through candidates
// of NBGBlendPass and NBGBlendNoise): inputs logits (N, kGrids + kCandidates, H, W),
// safe_albedo, the candidates (N, 3, H, W), then the Logits policy's; the candidates' weights
// are the softmax of the logits after GuideNet's kGrids guides, as Logits reads them. K names
// the op and its inputs. One body for the three ops.
template <class K, int64_t kCandidates, template <int64_t> class LogitsPolicy = PlainLogits>
struct BlendKernel : Kernel<K, NoAttributes, read_no_attributes> {
  using Logits = LogitsPolicy<kCandidates>;
  static constexpr size_t kOutputs = 1;
  static constexpr size_t kImages = 2 + kCandidates;  // logits, safe_albedo, the candidates
  static constexpr size_t kInputs = kImages + Logits::kInputs;

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<kInputs>& in) const {
    static_assert(std::size(K::kInputNames) == kInputs, "the images, then the policy's inputs");
    constexpr int64_t kLogits = kGrids + kCandidates;
    int64_t channels[kImages];
    channels[0] = kLogits;
    std::fill(channels + 1, channels + kImages, int64_t{3});
    if (OrtStatus* s = check_image_inputs(api, K::kName, K::kInputNames, in, channels)) return s;
    if (OrtStatus* s = Logits::check(api, K::kName, K::kInputNames, in, kImages)) return s;
    const Shape& ls = in[0].shape;
    const int64_t N = ls[0], H = ls[2], W = ls[3], P = H * W;
    float* denoised = nullptr;
    if (OrtStatus* s =
            get_float_output(api, K::kName, ctx, 0, "denoised", with_channels(ls, 3), &denoised)) {
      return s;
    }
    auto body = [&](int64_t n, int64_t first, int64_t end) {
      Logits reader(in, kImages, n, P);
      const float* logits = in[0].data + (n * kLogits + kGrids) * P;  // the blend logits
      const float* safe = in[1].data + n * 3 * P;
      const float* candidate[kCandidates];
      for (int64_t g = 0; g < kCandidates; ++g) candidate[g] = in[2 + g].data + n * 3 * P;
      float* out = denoised + n * 3 * P;
      BlockPlanes<kCandidates> weights;
      for (int64_t p = first; p < end; p += kBlendBlock) {
        const int64_t m = std::min(kBlendBlock, end - p);
        reader.block(logits, P, p, m);
        softmax_block<kCandidates>(reader, m, weights);
        blend_block<kCandidates>(weights, candidate, safe, out, P, p, m);
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

struct NBGBlendPass : BlendKernel<NBGBlendPass, kGrids + kPassThrough> {
  static constexpr const char* kName = "NBGBlendPass";
  static constexpr const char* kInputNames[] = {"logits",  "safe_albedo", "sliced0",
                                                "sliced1", "sliced2",     "accumulated",
                                                "frame"};
};

struct NBGBlendNoise : BlendKernel<NBGBlendNoise, kGrids + kPassThrough, NoiseLogits> {
  static constexpr const char* kName = "NBGBlendNoise";
  static constexpr const char* kInputNames[] = {"logits",      "safe_albedo", "sliced0",
                                                "sliced1",     "sliced2",     "accumulated",
                                                "frame",       "state",       "spp",
                                                "noise_scale", "noise_shift"};
};

}  // namespace

const OrtCustomOp* nbg_accumulate_op() { return CustomOp<NBGAccumulate>::get(); }
const OrtCustomOp* nbg_features_op() { return CustomOp<NBGFeatures>::get(); }
const OrtCustomOp* nbg_blend_op() { return CustomOp<NBGBlend>::get(); }
const OrtCustomOp* nbg_blend_pass_op() { return CustomOp<NBGBlendPass>::get(); }
const OrtCustomOp* nbg_blend_noise_op() { return CustomOp<NBGBlendNoise>::get(); }

}  // namespace qf
