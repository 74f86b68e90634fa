// AlbedoPrefilter(albedo (N,C,H,W), spp (N or 1 values)) -> albedo (N,C,H,W)
//   attributes sigma_at_one_spp (float, > 0), exponent (float, > 0), radius (int, 1..16)
//
// quietframe.model.albedo_prefilter.albedo_blur: the albedo blurred by a Gaussian of width
//   σ = sigma_at_one_spp · s^(-exponent) px, s = the image's spp (below 1 or NaN: 1),
// before the learned tiers demodulate by it. At a few samples per pixel the albedo is a few
// point samples of the texture under the pixel; remodulation would put that sampling noise back
// into the output. Taps w_i = exp(-(i/σ)²/2) for i in [-radius, radius], normalised to sum 1
// (σ under 1e-3 px: the identity); rows first, then columns, edges replicated, each sum taken
// from -radius to +radius in the reference's order. Parity with the reference is to float
// rounding (the taps' exp), not bit for bit.
//
// Parallel over (image, channel, band of rows) in each pass; the row pass writes a scratch
// plane that the column pass reads, so results do not depend on the thread count.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kernel_support.h"
#include "ops.h"
#include "runtime_support.h"

namespace qf {
namespace {

constexpr int64_t kMinRowsPerBand = 16;
constexpr int64_t kMaxRadius = 16;
constexpr float kIdentityBelowSigma = 1e-3f;

struct PrefilterAttributes {
  float sigma_at_one_spp = 0;
  float exponent = 0;
  int64_t radius = 0;
};

OrtStatus* read_prefilter(const ort::Api& api, const char* op, const OrtKernelInfo* info,
                          PrefilterAttributes* a) {
  if (OrtStatus* s = get_float_attribute(api, op, info, "sigma_at_one_spp",
                                         &a->sigma_at_one_spp)) {
    return s;
  }
  if (OrtStatus* s = get_float_attribute(api, op, info, "exponent", &a->exponent)) return s;
  if (OrtStatus* s = get_int_attribute(api, op, info, "radius", &a->radius)) return s;
  if (!(a->sigma_at_one_spp > 0 && std::isfinite(a->sigma_at_one_spp))) {
    return op_error(api, op, "sigma_at_one_spp must be a finite float > 0, got " +
                                 format_float(a->sigma_at_one_spp));
  }
  if (!(a->exponent > 0 && std::isfinite(a->exponent))) {
    return op_error(api, op, "exponent must be a finite float > 0, got " +
                                 format_float(a->exponent));
  }
  if (a->radius < 1 || a->radius > kMaxRadius) {
    return op_error(api, op, "radius must be in [1, " + std::to_string(kMaxRadius) + "], got " +
                                 std::to_string(a->radius));
  }
  return nullptr;
}

// The normalised taps for one image's spp, as the reference computes them in float32.
std::vector<float> taps_for(float spp, const PrefilterAttributes& a) {
  const float s = spp >= 1.0f ? spp : 1.0f;  // NaN fails the test: 1, as torch.where there
  const float sigma = a.sigma_at_one_spp * std::pow(s, -a.exponent);
  const int64_t count = 2 * a.radius + 1;
  std::vector<float> taps(static_cast<size_t>(count), 0.0f);
  if (!(sigma > kIdentityBelowSigma)) {
    taps[static_cast<size_t>(a.radius)] = 1.0f;
    return taps;
  }
  float sum = 0.0f;
  for (int64_t i = 0; i < count; ++i) {
    const float r = static_cast<float>(i - a.radius) / sigma;
    taps[static_cast<size_t>(i)] = std::exp(-0.5f * (r * r));
    sum += taps[static_cast<size_t>(i)];
  }
  for (float& t : taps) t /= sum;
  return taps;
}

// Rows [ya, yb) of one plane, blurred along x or y, edges replicated. Each output pixel sums
// its taps from -radius to +radius in order; the loops run tap by tap over a whole row so the
// compiler can vectorise them (the edge columns of the x pass take the clamped reads).
void blur_rows(const float* __restrict src, float* __restrict dst, int64_t H, int64_t W,
               int64_t ya, int64_t yb, const std::vector<float>& taps, int64_t radius,
               bool along_x) {
  for (int64_t y = ya; y < yb; ++y) {
    float* __restrict out = dst + y * W;
    std::fill(out, out + W, 0.0f);
    for (int64_t i = -radius; i <= radius; ++i) {
      const float t = taps[static_cast<size_t>(i + radius)];
      if (!along_x) {
        const float* __restrict row = src + std::clamp<int64_t>(y + i, 0, H - 1) * W;
        for (int64_t x = 0; x < W; ++x) out[x] = out[x] + t * row[x];
        continue;
      }
      const float* __restrict row = src + y * W;
      const int64_t lo = std::min<int64_t>(std::max<int64_t>(-i, 0), W);
      const int64_t hi = std::max<int64_t>(std::min<int64_t>(W - i, W), lo);
      auto edge = [&](int64_t x) { return row[std::clamp<int64_t>(x + i, 0, W - 1)]; };
      for (int64_t x = 0; x < lo; ++x) out[x] = out[x] + t * edge(x);
      for (int64_t x = lo; x < hi; ++x) out[x] = out[x] + t * row[x + i];
      for (int64_t x = hi; x < W; ++x) out[x] = out[x] + t * edge(x);
    }
  }
}

struct AlbedoPrefilter : Kernel<AlbedoPrefilter, PrefilterAttributes, read_prefilter> {
  static constexpr const char* kName = "AlbedoPrefilter";
  static constexpr const char* kInputNames[] = {"albedo", "spp"};
  static constexpr size_t kOutputs = 1;

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<2>& in) const {
    if (OrtStatus* s = check_image_inputs(api, kName, kInputNames, in, {kAnyChannels})) return s;
    const Shape& as = in[0].shape;
    const int64_t N = as[0], C = as[1], H = as[2], W = as[3];
    int64_t values = 0;
    if (OrtStatus* s = check_per_image(api, kName, "spp", in[1].shape, N, &values)) return s;
    float* out = nullptr;
    if (OrtStatus* s = get_float_output(api, kName, ctx, 0, "albedo", as, &out)) return s;
    const PrefilterAttributes a = attributes_;
    std::vector<std::vector<float>> taps;
    for (int64_t n = 0; n < N; ++n) taps.push_back(taps_for(in[1].data[values == 1 ? 0 : n], a));
    // the row pass's output, every element written before the column pass reads it
    std::unique_ptr<float[]> rows(new float[static_cast<size_t>(N * C * H * W)]);
    const int64_t bands = band_count(H, N * C, kMinRowsPerBand);
    const float* albedo = in[0].data;
    for (const bool along_x : {true, false}) {
      const float* src = along_x ? albedo : rows.get();
      float* dst = along_x ? rows.get() : out;
      auto task = [&](size_t i) {
        const int64_t plane = static_cast<int64_t>(i) / bands;
        const int64_t band = static_cast<int64_t>(i) % bands;
        blur_rows(src + plane * H * W, dst + plane * H * W, H, W, band_start(band, bands, H),
                  band_start(band + 1, bands, H), taps[static_cast<size_t>(plane / C)], a.radius,
                  along_x);
      };
      if (OrtStatus* s = run_tasks(api, kName, ctx, N * C * bands, task)) return s;
    }
    return nullptr;
  }
};

}  // namespace

const OrtCustomOp* albedo_prefilter_op() { return CustomOp<AlbedoPrefilter>::get(); }

}  // namespace qf
