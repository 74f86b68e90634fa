// Library entry point: RegisterCustomOps adds the ai.quietframe domain (every op of ops.h) to a
// SessionOptions. The only exported symbol (see exports.map). Threads and runtime facts live in
// runtime_support.cc.
#include <mutex>
#include <string>
#include <utility>
#include <vector>

#include "kernel_support.h"
#include "ops.h"
#include "runtime_support.h"
#include "simd.h"

namespace qf {
namespace {

constexpr const char* kDomain = "ai.quietframe";

// Each RegisterCustomOps call creates one domain that its SessionOptions points to; they are
// released when the library is unloaded. (Created on first use: loading the library runs no
// code compiled for the target CPU level, see RegisterCustomOps.)
class DomainRegistry {
 public:
  ~DomainRegistry() {
    const std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& [api, domain] : domains_) api.ReleaseCustomOpDomain(domain);
  }
  void keep(const ort::Api& api, OrtCustomOpDomain* domain) {
    const std::lock_guard<std::mutex> lock(mutex_);
    domains_.emplace_back(api, domain);
  }

 private:
  std::mutex mutex_;
  std::vector<std::pair<ort::Api, OrtCustomOpDomain*>> domains_;
};

DomainRegistry& domains() {
  static DomainRegistry registry;
  return registry;
}

OrtStatus* register_ops(OrtSessionOptions* options, const OrtApiBase* base) {
  using ort::Api;
  const OrtApi* table = base->GetApi(ort::kApiVersion);
  if (table == nullptr) {
    // Too old for us; version 1 of the table still creates a status (and nothing older exists).
    const OrtApi* oldest = base->GetApi(1);
    const std::string message = std::string("quietframe ops need onnxruntime >= 1.16.3 (C API ") +
                                std::to_string(ort::kApiVersion) + "), this is " +
                                base->GetVersionString();
    return oldest ? Api(oldest).CreateStatus(ORT_FAIL, message.c_str()) : nullptr;
  }
  init_runtime_info(base);
  const Api api(table);
  OrtCustomOpDomain* domain = nullptr;
  if (OrtStatus* s = api.CreateCustomOpDomain(kDomain, &domain)) return s;
  OrtStatus* status = nullptr;
  for (const OrtCustomOp* op : {bilateral_splat_op(), bilateral_slice_op(), backward_warp_op(),
                                affinity_filter_op(), affinity_temporal_filter_op(),
                                upsample_bilinear_op(), nbg_accumulate_op(), nbg_features_op(),
                                nbg_blend_op(), nbg_blend_pass_op(), nbg_blend_noise_op(),
                                pixel_aligned_op(), resampled_trust_op(),
                                albedo_prefilter_op()}) {
    if (status == nullptr) status = api.CustomOpDomain_Add(domain, op);
  }
  if (status == nullptr) status = api.AddCustomOpDomain(options, domain);
  if (status != nullptr) {
    api.ReleaseCustomOpDomain(domain);
    return status;
  }
  domains().keep(api, domain);
  return nullptr;
}

}  // namespace
}  // namespace qf

// The entry point is compiled for any x86-64 CPU: on one without the instructions this build
// targets (AVX2 and FMA by default) it returns an error instead of crashing on the first one.
#if QF_HAVE_AVX2 && defined(__x86_64__) && defined(__GNUC__)
#define QF_ANY_X86_64 __attribute__((target("arch=x86-64")))
#else
#define QF_ANY_X86_64
#endif

extern "C" __attribute__((visibility("default"))) QF_ANY_X86_64 OrtStatus* RegisterCustomOps(
    OrtSessionOptions* options, const OrtApiBase* base) {
#if QF_HAVE_AVX2 && defined(__x86_64__) && defined(__GNUC__)
  __builtin_cpu_init();
  if (!__builtin_cpu_supports("avx2") || !__builtin_cpu_supports("fma")) {
    const OrtApi* table = base->GetApi(1);
    return table ? qf::ort::Api(table).CreateStatus(
                       ORT_FAIL,
                       "libquietframe_ops was built for CPUs with AVX2 and FMA (x86-64-v3), this "
                       "one has not: rebuild it with -DQUIETFRAME_ARCH=x86-64")
                 : nullptr;
  }
#endif
  return qf::register_ops(options, base);
}
