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

class AffinityTemporalFilter {
 public:
  static constexpr const char* kName = "AffinityTemporalFilter";
  static constexpr size_t kInputs = 10;
  static constexpr size_t kOutputs = 1;

  static ONNXTensorElementDataType input_type(size_t index) {
    return index >= 8 ? ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64 : ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT;
  }

  static OrtStatus* Create(const ort::Api& api, const OrtKernelInfo* info,
                           AffinityTemporalFilter** out) {
    affinity::Attributes attributes;
    if (OrtStatus* s = affinity::read_attributes(api, kName, info, &attributes)) return s;
    *out = new AffinityTemporalFilter(attributes);
    return nullptr;
  }

  OrtStatus* Compute(const ort::Api& api, OrtKernelContext* ctx) const {
    affinity::Job job;
    Shape rs, fs, os, ps, bs, ts;
    if (OrtStatus* s = affinity::read_spatial_inputs(api, kName, ctx, &job, &rs, &fs)) return s;
    if (OrtStatus* s = get_float_input(api, kName, ctx, 4, "prev_output", &job.prev_output, &os)) {
      return s;
    }
    if (OrtStatus* s =
            get_float_input(api, kName, ctx, 5, "prev_features", &job.prev_features, &ps)) {
      return s;
    }
    if (OrtStatus* s = get_float_input(api, kName, ctx, 6, "temporal_bandwidth",
                                       &job.temporal_bandwidth, &bs)) {
      return s;
    }
    if (OrtStatus* s = get_float_input(api, kName, ctx, 7, "temporal_on", &job.temporal_on, &ts)) {
      return s;
    }
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

 private:
  explicit AffinityTemporalFilter(const affinity::Attributes& attributes)
      : attributes_(attributes) {}
  affinity::Attributes attributes_;
};

}  // namespace

const OrtCustomOp* affinity_temporal_filter_op() {
  return CustomOp<AffinityTemporalFilter>::get();
}

}  // namespace qf
