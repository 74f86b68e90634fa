// AffinityTemporalFilter(radiance (N,C,H,W), features (N,D,H,W), bandwidth (N,1,H,W),
//                        center (N,1,H,W), prev_output (N,C,H,W), prev_features (N,D,H,W),
//                        temporal_bandwidth (N,1,H,W), temporal_on (N), kernel_size (int64),
//                        temporal_kernel_size (int64)) -> output (N,C,H,W)
// attributes: dilation (int >= 1, of the spatial kernel), epsilon (float >= 0, default 1e-10)
//
// The last spatial kernel normalised jointly with the temporal kernel over the warped previous
// output (Işık et al. 2021, eq. 7 + 8); the reference is
// quietframe.model.affinity_kernels.temporal_affinity_filter. prev_output and prev_features are
// already warped to this frame; temporal_on[n] = 0 (first frame, cut) turns the temporal term
// off, and the result then equals AffinityFilter's bit for bit.
#include <cstdint>

#include "affinity_common.h"
#include "kernel_support.h"
#include "ops.h"

namespace qf {
namespace {

struct AffinityTemporalFilter
    : Kernel<AffinityTemporalFilter, affinity::Attributes, affinity::read_attributes> {
  static constexpr const char* kName = "AffinityTemporalFilter";
  static constexpr const char* kInputNames[] = {
      "radiance",           "features",    "bandwidth",   "center",
      "prev_output",        "prev_features",
      "temporal_bandwidth", "temporal_on", "kernel_size", "temporal_kernel_size"};
  static constexpr size_t kFloatInputs = 8;  // the two kernel sizes are int64
  static constexpr size_t kOutputs = 1;

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<8>& in) const {
    affinity::Job job;
    if (OrtStatus* s = affinity::read_spatial_inputs(api, kName, in.data(), &job)) return s;
    job.prev_output = in[4].data;
    job.prev_features = in[5].data;
    job.temporal_bandwidth = in[6].data;
    job.temporal_on = in[7].data;
    const Shape& rs = in[0].shape;
    const Shape &os = in[4].shape, &ps = in[5].shape, &bs = in[6].shape, &ts = in[7].shape;
    using affinity::nchw;
    using affinity::same_nhw;
    if (!same_nhw(os, rs, job.C)) {
      return op_error(api, kName, "prev_output must be " + nchw(rs, std::to_string(job.C)) +
                                      " like the radiance, got " + os.str());
    }
    if (!same_nhw(ps, rs, job.D)) {
      return op_error(api, kName, "prev_features must be " + nchw(rs, std::to_string(job.D)) +
                                      " like the features, got " + ps.str());
    }
    if (!same_nhw(bs, rs, 1)) {
      return op_error(api, kName,
                      "temporal_bandwidth must be " + nchw(rs, "1") + ", got " + bs.str());
    }
    if (ts.rank != 1 || ts[0] != rs[0]) {
      return op_error(api, kName, "temporal_on must be (N) = (" + std::to_string(rs[0]) +
                                      "), got " + ts.str());
    }
    int64_t size = 0, temporal_size = 0;
    if (OrtStatus* s = get_int64_scalar_input(api, kName, ctx, 8, "kernel_size", &size)) {
      return s;
    }
    if (OrtStatus* s = get_int64_scalar_input(api, kName, ctx, 9, "temporal_kernel_size",
                                              &temporal_size)) {
      return s;
    }
    if (OrtStatus* s = affinity::kernel_radius(api, kName, "kernel_size", size, &job.radius)) {
      return s;
    }
    if (OrtStatus* s = affinity::kernel_radius(api, kName, "temporal_kernel_size", temporal_size,
                                               &job.temporal_radius)) {
      return s;
    }
    job.dilation = attributes_.dilation;
    job.epsilon = attributes_.epsilon;
    return affinity::run(api, kName, ctx, &job, rs);
  }
};

}  // namespace

const OrtCustomOp* affinity_temporal_filter_op() {
  return CustomOp<AffinityTemporalFilter>::get();
}

}  // namespace qf
