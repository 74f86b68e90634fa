// AffinityFilter(radiance (N,C,H,W), features (N,D,H,W), bandwidth (N,1,H,W), center (N,1,H,W),
//                kernel_size (int64, [] or [1])) -> output (N,C,H,W)
// attributes: dilation (int >= 1), epsilon (float >= 0, default 1e-10)
//
// One dilated affinity kernel of Işık et al. 2021 (eq. 4 + 6), the reference being
// quietframe.model.affinity_kernels.spatial_affinity_filter; the math and its rules are in
// affinity_common.h and docs/affinity-math.md. The kernel size is an input, so a session can
// change it from one run to the next without a new graph.
#include <cstdint>

#include "affinity_common.h"
#include "kernel_support.h"
#include "ops.h"

namespace qf {
namespace {

class AffinityFilter {
 public:
  static constexpr const char* kName = "AffinityFilter";
  static constexpr size_t kInputs = 5;
  static constexpr size_t kOutputs = 1;

  static ONNXTensorElementDataType input_type(size_t index) {
    return index == 4 ? ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64 : ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT;
  }

  static OrtStatus* Create(const ort::Api& api, const OrtKernelInfo* info, AffinityFilter** out) {
    affinity::Attributes attributes;
    if (OrtStatus* s = affinity::read_attributes(api, kName, info, &attributes)) return s;
    *out = new AffinityFilter(attributes);
    return nullptr;
  }

  OrtStatus* Compute(const ort::Api& api, OrtKernelContext* ctx) const {
    affinity::Job job;
    Shape rs, fs;
    if (OrtStatus* s = affinity::read_spatial_inputs(api, kName, ctx, &job, &rs, &fs)) return s;
    int64_t size = 0;
    if (OrtStatus* s = get_int64_scalar_input(api, kName, ctx, 4, "kernel_size", &size)) return s;
    if (OrtStatus* s = affinity::kernel_radius(api, kName, "kernel_size", size, &job.radius)) {
      return s;
    }
    job.dilation = attributes_.dilation;
    job.epsilon = attributes_.epsilon;
    return affinity::run(api, kName, ctx, &job, rs);
  }

 private:
  explicit AffinityFilter(const affinity::Attributes& attributes) : attributes_(attributes) {}
  affinity::Attributes attributes_;
};

}  // namespace

const OrtCustomOp* affinity_filter_op() { return CustomOp<AffinityFilter>::get(); }

}  // namespace qf
