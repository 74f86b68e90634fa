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

struct AffinityFilter
    : Kernel<AffinityFilter, affinity::Attributes, affinity::read_attributes> {
  static constexpr const char* kName = "AffinityFilter";
  static constexpr const char* kInputNames[] = {"radiance", "features", "bandwidth", "center",
                                                "kernel_size"};
  static constexpr size_t kFloatInputs = 4;  // kernel_size is int64
  static constexpr size_t kOutputs = 1;

  OrtStatus* Run(const ort::Api& api, OrtKernelContext* ctx, const FloatInputs<4>& in) const {
    affinity::Job job;
    if (OrtStatus* s = affinity::read_spatial_inputs(api, kName, in.data(), &job)) return s;
    int64_t size = 0;
    if (OrtStatus* s = get_int64_scalar_input(api, kName, ctx, 4, "kernel_size", &size)) return s;
    if (OrtStatus* s = affinity::kernel_radius(api, kName, "kernel_size", size, &job.radius)) {
      return s;
    }
    job.dilation = attributes_.dilation;
    job.epsilon = attributes_.epsilon;
    return affinity::run(api, kName, ctx, &job, in[0].shape);
  }
};

}  // namespace

const OrtCustomOp* affinity_filter_op() { return CustomOp<AffinityFilter>::get(); }

}  // namespace qf
