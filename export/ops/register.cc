// Library entry point: RegisterCustomOps adds the ai.quietframe domain (BilateralSplat,
// BilateralSlice, BackwardWarp) to a SessionOptions. The only exported symbol (see exports.map).
#include <sched.h>

#include <algorithm>
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "grid_common.h"
#include "kernel_support.h"

namespace qf {

const OrtCustomOp* backward_warp_op();  // backward_warp.cc

namespace {

constexpr const char* kDomain = "ai.quietframe";
constexpr int kMaxThreads = 64;

RuntimeInfo g_runtime;
std::once_flag g_runtime_once;

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

int detect_cpu_count() {
  if (const char* text = std::getenv("QUIETFRAME_OPS_NUM_THREADS")) {
    const int requested = std::atoi(text);
    if (requested > 0) return std::min(requested, kMaxThreads);
  }
  int cpus = static_cast<int>(std::thread::hardware_concurrency());
#ifdef CPU_COUNT
  cpu_set_t set;
  if (sched_getaffinity(0, sizeof set, &set) == 0) cpus = CPU_COUNT(&set);
#endif
  return std::clamp(cpus, 1, kMaxThreads);
}

// onnxruntime "1.16.3" -> 16, the newest C API version it serves (asking GetApi for a newer one
// also answers NULL, but logs an error first).
int api_version_of(const char* version) {
  int major = 0, minor = 0;
  if (version == nullptr || std::sscanf(version, "%d.%d", &major, &minor) != 2 || major != 1) {
    return 0;
  }
  return minor;
}

}  // namespace

const RuntimeInfo& runtime_info() { return g_runtime; }

void init_runtime_info(const OrtApiBase* base) {
  std::call_once(g_runtime_once, [base] {
    g_runtime.api = ort::Api(base->GetApi(ort::kApiVersion));
    const int served = api_version_of(base->GetVersionString());
    if (served >= static_cast<int>(ort::kParallelForApiVersion)) {
      if (const OrtApi* newer = base->GetApi(ort::kParallelForApiVersion)) {
        g_runtime.parallel_for = ort::Api(newer).KernelContext_ParallelFor();
      }
    }
  });
}

int cpu_count() {
  static const int count = detect_cpu_count();
  return count;
}

void parallel_for_threads(size_t count, void (*fn)(void*, size_t), void* user) {
  const size_t threads = std::min(count, static_cast<size_t>(cpu_count()));
  std::atomic<size_t> next{0};
  auto work = [&] {
    for (size_t i = next.fetch_add(1); i < count; i = next.fetch_add(1)) fn(user, i);
  };
  std::vector<std::thread> pool;
  pool.reserve(threads);
  for (size_t t = 1; t < threads; ++t) {
    try {
      pool.emplace_back(work);
    } catch (const std::exception&) {
      break;  // no more threads to be had: the ones we have (and this one) do the rest
    }
  }
  work();
  for (std::thread& thread : pool) thread.join();
}

}  // namespace qf

namespace qf {
namespace {

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
  OrtStatus* status = api.CustomOpDomain_Add(domain, bilateral_splat_op());
  if (status == nullptr) status = api.CustomOpDomain_Add(domain, bilateral_slice_op());
  if (status == nullptr) status = api.CustomOpDomain_Add(domain, backward_warp_op());
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
