// PixelAligned(motion (N,2,H,W)) -> aligned (N,1,H,W), attribute tolerance (float, > 0)
//
// 1 where the pixel and its 3×3 neighbours all move by the same whole number of pixels, else 0:
// quietframe.model.temporal.pixel_aligned (as the float mask `aligned_mask`), in two steps:
//   alike(q)   = whole(q) and spread(q) <= tolerance, where
//     whole(q)  = max over the two components of |m - round(m)| <= tolerance,
//     spread(q) = max over the components of (max - min of m over q's 3×3 window);
//   aligned(p) = 1 where alike(q) for every q of p's 3×3 window.
// Windows hold only the pixels inside the frame (the reference's max pools pad with -inf); a NaN
// anywhere in a window makes it not alike (torch's max pool propagates NaN, and NaN compares
// false). The affinity tier tests this at every pixel of every frame to fade a resampled history
// (affinity.fade_resampled), NBG inside ResampledTrust below, and the aligned accumulation and
// the output history to keep a history only where it is exact: as ~15 onnxruntime nodes over
// full-resolution planes it cost ~15 ms of nbg-2l-3g's ~450 at 720p on a slow machine.
//
// ResampledTrust(motion (N,2,H,W), previous_count (N,1,H,W), floor (N or 1 values))
//   -> trust (N,1,H,W), attributes tolerance (as above), min_weight (> 0), max_count (> 0)
//
// quietframe.model.temporal.resampled_trust: the share of NBG's reprojected history to keep so
// that the current frame weighs at least `floor` where the motion is not pixel-aligned,
//   share = min((1/floor - 1) / max(clamp(count, 0, max_count), 1e-6), 1) if floor > min_weight,
//           else 1;
//   trust = aligned + (1 - aligned) · share,
// each step in float32 in the reference's order (bit-identical; a NaN count gives NaN, as
// there). As the aligned test plus ~8 onnxruntime nodes over full-resolution planes the share
// cost nbg-2l-3g ~3% of its 720p time; here it is one pass after the test.
//
// Parallel over bands of rows of each image; a band computes `alike` for its rows and one row
// above and below into scratch, so results do not depend on the thread count.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include "kernel_support.h"
#include "ops.h"
#include "runtime_support.h"

namespace qf {
namespace {

constexpr int64_t kMinRowsPerBand = 16;

struct AlignedAttributes {
  float tolerance = 0;
};

OrtStatus* read_aligned(const ort::Api& api, const char* op, const OrtKernelInfo* info,
                        AlignedAttributes* a) {
  if (OrtStatus* s = get_float_attribute(api, op, info, "tolerance", &a->tolerance)) return s;
  if (!(a->tolerance > 0 && a->tolerance < 0.5f)) {
    return op_error(api, op, "tolerance must be in (0, 0.5), got " + format_float(a->tolerance));
  }
  return nullptr;
}

// alike(y, x) of one image (components u, v planes of W × H).
inline bool alike_at(const float* u, const float* v, int64_t H, int64_t W, int64_t y, int64_t x,
                     float tolerance) {
  const float cu = u[y * W + x], cv = v[y * W + x];
  if (!(std::fabs(cu - std::nearbyint(cu)) <= tolerance &&
        std::fabs(cv - std::nearbyint(cv)) <= tolerance)) {
    return false;  // not whole (or NaN)
  }
  const int64_t y0 = std::max<int64_t>(y - 1, 0), y1 = std::min<int64_t>(y + 1, H - 1);
  const int64_t x0 = std::max<int64_t>(x - 1, 0), x1 = std::min<int64_t>(x + 1, W - 1);
  float hu = cu, lu = cu, hv = cv, lv = cv;
  bool nan = false;
  for (int64_t yy = y0; yy <= y1; ++yy) {
    for (int64_t xx = x0; xx <= x1; ++xx) {
      const float a = u[yy * W + xx], b = v[yy * W + xx];
      nan |= std::isnan(a) || std::isnan(b);
      hu = a > hu ? a : hu;
      lu = a < lu ? a : lu;
      hv = b > hv ? b : hv;
      lv = b < lv ? b : lv;
    }
  }
  // the reference's spread: max + (-min), per component, then the larger of the two
  return !nan && (hu + (-lu)) <= tolerance && (hv + (-lv)) <= tolerance;
}

void aligned_band(const float* motion, float* out, int64_t H, int64_t W, int64_t ya, int64_t yb,
                  float tolerance, std::vector<uint8_t>& scratch) {
  const float* u = motion;
  const float* v = motion + H * W;
  const int64_t ra = std::max<int64_t>(ya - 1, 0), rb = std::min<int64_t>(yb + 1, H);
  scratch.assign(static_cast<size_t>((rb - ra) * W), 0);
  for (int64_t y = ra; y < rb; ++y) {
    uint8_t* row = scratch.data() + (y - ra) * W;
    for (int64_t x = 0; x < W; ++x) row[x] = alike_at(u, v, H, W, y, x, tolerance) ? 1 : 0;
  }
  for (int64_t y = ya; y < yb; ++y) {
    const int64_t y0 = std::max<int64_t>(y - 1, 0), y1 = std::min<int64_t>(y + 1, H - 1);
    float* dst = out + y * W;
    for (int64_t x = 0; x < W; ++x) {
      const int64_t x0 = std::max<int64_t>(x - 1, 0), x1 = std::min<int64_t>(x + 1, W - 1);
      uint8_t all = 1;
      for (int64_t yy = y0; yy <= y1; ++yy) {
        const uint8_t* row = scratch.data() + (yy - ra) * W;
        for (int64_t xx = x0; xx <= x1; ++xx) all &= row[xx];
      }
      dst[x] = all ? 1.0f : 0.0f;
    }
  }
}

struct PixelAligned : Kernel<PixelAligned, AlignedAttributes, read_aligned> {
  static constexpr const char* kName = "PixelAligned";
  static constexpr const char* kInputNames[] = {"motion"};
  static constexpr size_t kOutputs = 1;

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<1>& in) const {
    const Shape& ms = in[0].shape;
    if (ms.rank != 4 || ms[1] != 2) {
      return op_error(api, kName, "motion must be (N, 2, H, W), got " + ms.str());
    }
    const int64_t N = ms[0], H = ms[2], W = ms[3];
    float* out = nullptr;
    if (OrtStatus* s = get_float_output(api, kName, ctx, 0, "aligned", with_channels(ms, 1),
                                        &out)) {
      return s;
    }
    if (N == 0 || H == 0 || W == 0) return nullptr;
    const float tolerance = attributes_.tolerance;
    const float* motion = in[0].data;
    const int64_t bands = band_count(H, N, kMinRowsPerBand);
    auto task = [&](size_t i) {
      const int64_t n = static_cast<int64_t>(i) / bands, band = static_cast<int64_t>(i) % bands;
      std::vector<uint8_t> scratch;
      aligned_band(motion + n * 2 * H * W, out + n * H * W, H, W, band_start(band, bands, H),
                   band_start(band + 1, bands, H), tolerance, scratch);
    };
    return run_tasks(api, kName, ctx, N * bands, task);
  }
};

struct TrustAttributes {
  float tolerance = 0;
  float min_weight = 0;  // temporal.MIN_CURRENT_WEIGHT: a floor at or below it keeps everything
  float max_count = 0;   // 1 / MIN_CURRENT_WEIGHT: the longest history the share reads
};

OrtStatus* read_trust(const ort::Api& api, const char* op, const OrtKernelInfo* info,
                      TrustAttributes* a) {
  AlignedAttributes aligned;
  if (OrtStatus* s = read_aligned(api, op, info, &aligned)) return s;
  a->tolerance = aligned.tolerance;
  if (OrtStatus* s = get_float_attribute(api, op, info, "min_weight", &a->min_weight)) return s;
  if (OrtStatus* s = get_float_attribute(api, op, info, "max_count", &a->max_count)) return s;
  if (!(a->min_weight > 0 && a->min_weight < 1)) {
    return op_error(api, op, "min_weight must be in (0, 1), got " + format_float(a->min_weight));
  }
  if (!(a->max_count > 0)) {
    return op_error(api, op, "max_count must be > 0, got " + format_float(a->max_count));
  }
  return nullptr;
}

// trust over rows [ya, yb) of one image, `out` holding the aligned mask there (0 or 1).
void trust_rows(const float* count, float* out, int64_t W, int64_t ya, int64_t yb, float floor,
                const TrustAttributes& a) {
  float* dst = out + ya * W;
  const float* c = count + ya * W;
  const int64_t m = (yb - ya) * W;
  if (!(floor > a.min_weight)) {  // a + (1 - a) · 1
    std::fill(dst, dst + m, 1.0f);
    return;
  }
  const float numerator = 1.0f / floor - 1.0f;
  for (int64_t i = 0; i < m; ++i) {
    // std::max/min with the value first keep a NaN, as torch's clamp does
    const float clamped = std::min(std::max(c[i], 0.0f), a.max_count);
    const float share = std::min(numerator / std::max(clamped, 1e-6f), 1.0f);
    const float aligned = dst[i];
    dst[i] = aligned + (1.0f - aligned) * share;
  }
}

struct ResampledTrust : Kernel<ResampledTrust, TrustAttributes, read_trust> {
  static constexpr const char* kName = "ResampledTrust";
  static constexpr const char* kInputNames[] = {"motion", "previous_count", "floor"};
  static constexpr size_t kOutputs = 1;

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<3>& in) const {
    if (OrtStatus* s = check_image_inputs(api, kName, kInputNames, in, {2, 1})) return s;
    const Shape& ms = in[0].shape;
    const int64_t N = ms[0], H = ms[2], W = ms[3];
    int64_t floors = 0;
    if (OrtStatus* s = check_per_image(api, kName, "floor", in[2].shape, N, &floors)) return s;
    float* out = nullptr;
    if (OrtStatus* s = get_float_output(api, kName, ctx, 0, "trust", with_channels(ms, 1),
                                        &out)) {
      return s;
    }
    if (N == 0 || H == 0 || W == 0) return nullptr;
    const TrustAttributes a = attributes_;
    const float* motion = in[0].data;
    const int64_t bands = band_count(H, N, kMinRowsPerBand);
    auto task = [&](size_t i) {
      const int64_t n = static_cast<int64_t>(i) / bands, band = static_cast<int64_t>(i) % bands;
      const int64_t ya = band_start(band, bands, H), yb = band_start(band + 1, bands, H);
      std::vector<uint8_t> scratch;
      aligned_band(motion + n * 2 * H * W, out + n * H * W, H, W, ya, yb, a.tolerance, scratch);
      trust_rows(in[1].data + n * H * W, out + n * H * W, W, ya, yb,
                 in[2].data[floors == 1 ? 0 : n], a);
    };
    return run_tasks(api, kName, ctx, N * bands, task);
  }
};

}  // namespace

const OrtCustomOp* resampled_trust_op() { return CustomOp<ResampledTrust>::get(); }

const OrtCustomOp* pixel_aligned_op() { return CustomOp<PixelAligned>::get(); }

}  // namespace qf
