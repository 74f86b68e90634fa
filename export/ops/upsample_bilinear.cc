// UpsampleBilinear(image (N,C,h,w), like (*,*,H,W)) -> output (N,C,H,W)
//
// Bilinear resampling of `image` to the height and width of `like` (only its shape is read), as
// quietframe.model.resample.upsample_bilinear = F.interpolate(image, size=(H, W),
// mode="bilinear", align_corners=False) on the CPU, per axis in float:
//   scale = in / out;  s = max(scale·(o + 0.5) - 0.5, 0);  i0 = min(floor(s), in - 1);
//   i1 = i0 + 1 if i0 < in - 1 else i0;  λ1 = clamp(s - i0, 0, 1);  λ0 = 1 - λ1
//   out[y][x] = (img[y0][x0]·λx0 + img[y0][x1]·λx1)·λy0 + (img[y1][x0]·λx0 + img[y1][x1]·λx1)·λy1
// (the reference's order: across a row first, then down; results agree with it to float
// rounding). The affinity model predicts its kernel parameters at half resolution and this op
// brings them to the frame: 32 full-resolution planes per frame, where onnxruntime's generic
// Resize cost about 12% of the model's time (docs/affinity.md).
//
// Separable: each input row a band needs is interpolated across once into a scratch row (two
// rows kept per plane, as consecutive output rows share theirs), then each output row is the
// λy-weighted sum of two scratch rows, a loop the compiler vectorises. Parallel over bands of
// output rows of every (n, c) plane; a pixel's value does not depend on the bands, so results are
// independent of the thread count.
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

// Output rows per band at least: a band interpolates its first input rows anew.
constexpr int64_t kMinRowsPerBand = 16;

// One axis: for each output index, the two source indices and their weights.
struct AxisTable {
  std::vector<int32_t> i0, i1;
  std::vector<float> w0, w1;

  AxisTable(int64_t in, int64_t out) : i0(out), i1(out), w0(out), w1(out) {
    const float scale = static_cast<float>(in) / static_cast<float>(out);
    for (int64_t o = 0; o < out; ++o) {
      float s = scale * (static_cast<float>(o) + 0.5f) - 0.5f;
      s = s < 0.0f ? 0.0f : s;
      const int64_t a = std::min<int64_t>(static_cast<int64_t>(s), in - 1);
      const float l1 = std::clamp(s - static_cast<float>(a), 0.0f, 1.0f);
      i0[o] = static_cast<int32_t>(a);
      i1[o] = static_cast<int32_t>(a < in - 1 ? a + 1 : a);
      w0[o] = 1.0f - l1;
      w1[o] = l1;
    }
  }
};

struct UpsampleJob {
  const float* image;  // (N, C, h, w)
  float* out;          // (N, C, H, W)
  int64_t planes, h, w, H, W, bands;
  const AxisTable* xs;
  const AxisTable* ys;
};

// Input row `row` of `plane` interpolated across into `dst` (W values).
inline void across(const UpsampleJob& j, const float* plane, int64_t row, float* dst) {
  const float* src = plane + row * j.w;
  const int32_t* i0 = j.xs->i0.data();
  const int32_t* i1 = j.xs->i1.data();
  const float* w0 = j.xs->w0.data();
  const float* w1 = j.xs->w1.data();
  for (int64_t x = 0; x < j.W; ++x) dst[x] = src[i0[x]] * w0[x] + src[i1[x]] * w1[x];
}

// Rows [ya, yb) of one plane; `scratch` holds 2·W floats.
void upsample_band(const UpsampleJob& j, int64_t plane_index, int64_t ya, int64_t yb,
                   float* scratch) {
  const float* plane = j.image + plane_index * j.h * j.w;
  float* out = j.out + plane_index * j.H * j.W;
  float* rows[2] = {scratch, scratch + j.W};
  int64_t held[2] = {-1, -1};  // input row in each scratch row
  auto row_of = [&](int64_t row) -> const float* {
    for (int k = 0; k < 2; ++k) {
      if (held[k] == row) return rows[k];
    }
    // replace the row that the coming output rows no longer need (the lower index)
    const int k = held[0] < held[1] ? 0 : 1;
    across(j, plane, row, rows[k]);
    held[k] = row;
    return rows[k];
  };
  for (int64_t y = ya; y < yb; ++y) {
    const int64_t r0 = j.ys->i0[y], r1 = j.ys->i1[y];
    const float wy0 = j.ys->w0[y], wy1 = j.ys->w1[y];
    const float* a = row_of(r0);
    const float* b = row_of(r1);  // evicts a row below r0, never r0's
    float* dst = out + y * j.W;
    for (int64_t x = 0; x < j.W; ++x) dst[x] = a[x] * wy0 + b[x] * wy1;
  }
}

struct UpsampleBilinear : Kernel<UpsampleBilinear, NoAttributes, read_no_attributes> {
  static constexpr const char* kName = "UpsampleBilinear";
  static constexpr const char* kInputNames[] = {"image", "like"};  // like: the output's size
  static constexpr size_t kOutputs = 1;

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<2>& in) const {
    const float* image = in[0].data;
    const Shape &is = in[0].shape, &ls = in[1].shape;
    if (is.rank != 4 || is[2] < 1 || is[3] < 1) {
      return op_error(api, kName, "image must be (N, C, h, w) with h, w >= 1, got " + is.str());
    }
    if (ls.rank != 4 || ls[2] < 1 || ls[3] < 1) {
      return op_error(api, kName,
                      "like must be (N, C, H, W) with H, W >= 1 (its size is the output's), got " +
                          ls.str());
    }
    if (is[2] > INT32_MAX || is[3] > INT32_MAX) {
      return op_error(api, kName, "image rows and columns must be below 2^31, got " + is.str());
    }
    Shape os = is;
    os.dims[2] = ls[2];
    os.dims[3] = ls[3];
    UpsampleJob job{image, nullptr, is[0] * is[1], is[2], is[3], ls[2], ls[3], 1, nullptr,
                    nullptr};
    if (OrtStatus* s = get_float_output(api, kName, ctx, 0, "output", os, &job.out)) return s;
    if (job.planes == 0) return nullptr;
    const AxisTable xs(job.w, job.W), ys(job.h, job.H);
    job.xs = &xs;
    job.ys = &ys;
    job.bands = band_count(job.H, job.planes, kMinRowsPerBand);
    const UpsampleJob& j = job;
    auto task = [&j](size_t i) {
      const int64_t plane = static_cast<int64_t>(i) / j.bands;
      const int64_t band = static_cast<int64_t>(i) % j.bands;
      std::vector<float> scratch(2 * j.W);
      upsample_band(j, plane, band_start(band, j.bands, j.H), band_start(band + 1, j.bands, j.H),
                    scratch.data());
    };
    return run_tasks(api, kName, ctx, job.planes * job.bands, task);
  }
};

}  // namespace

const OrtCustomOp* upsample_bilinear_op() { return CustomOp<UpsampleBilinear>::get(); }

}  // namespace qf
