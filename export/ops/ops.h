// Every op of the library, one source file each; register.cc adds them to the ai.quietframe
// domain.
#pragma once

#include "ort_abi.h"

namespace qf {

const OrtCustomOp* bilateral_splat_op();          // bilateral_splat.cc
const OrtCustomOp* bilateral_slice_op();          // bilateral_slice.cc
const OrtCustomOp* backward_warp_op();            // backward_warp.cc
const OrtCustomOp* affinity_filter_op();          // affinity_filter.cc
const OrtCustomOp* affinity_temporal_filter_op();  // affinity_temporal_filter.cc
const OrtCustomOp* upsample_bilinear_op();          // upsample_bilinear.cc
const OrtCustomOp* nbg_accumulate_op();             // nbg_fused.cc
const OrtCustomOp* nbg_features_op();               // nbg_fused.cc
const OrtCustomOp* nbg_blend_op();                  // nbg_fused.cc
const OrtCustomOp* nbg_blend_pass_op();             // nbg_fused.cc
const OrtCustomOp* nbg_blend_noise_op();            // nbg_fused.cc
const OrtCustomOp* pixel_aligned_op();              // pixel_aligned.cc
const OrtCustomOp* resampled_trust_op();            // pixel_aligned.cc
const OrtCustomOp* albedo_prefilter_op();           // albedo_prefilter.cc

}  // namespace qf
