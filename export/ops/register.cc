// Library entry point: RegisterCustomOps adds the ai.quietframe domain (BilateralSplat,
// BilateralSlice) to a SessionOptions. The only exported symbol (see exports.map).
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
namespace {

constexpr const char* kDomain = "ai.quietframe";
constexpr int kMaxThreads = 64;

RuntimeInfo g_runtime;
std::once_flag g_runtime_once;

// Each RegisterCustomOps call creates one domain that its SessionOptions points to; they are
// released when the library is unloaded.
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

DomainRegistry g_domains;

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

extern "C" __attribute__((visibility("default"))) OrtStatus* RegisterCustomOps(
    OrtSessionOptions* options, const OrtApiBase* base) {
  using qf::ort::Api;
  const OrtApi* table = base->GetApi(qf::ort::kApiVersion);
  if (table == nullptr) {
    // Too old for us; version 1 of the table still creates a status (and nothing older exists).
    const OrtApi* oldest = base->GetApi(1);
    const std::string message = std::string("quietframe ops need onnxruntime >= 1.16.3 (C API ") +
                                std::to_string(qf::ort::kApiVersion) + "), this is " +
                                base->GetVersionString();
    return oldest ? Api(oldest).CreateStatus(ORT_FAIL, message.c_str()) : nullptr;
  }
  qf::init_runtime_info(base);
  const Api api(table);
  OrtCustomOpDomain* domain = nullptr;
  if (OrtStatus* s = api.CreateCustomOpDomain(qf::kDomain, &domain)) return s;
  OrtStatus* status = api.CustomOpDomain_Add(domain, qf::bilateral_splat_op());
  if (status == nullptr) status = api.CustomOpDomain_Add(domain, qf::bilateral_slice_op());
  if (status == nullptr) status = api.AddCustomOpDomain(options, domain);
  if (status != nullptr) {
    api.ReleaseCustomOpDomain(domain);
    return status;
  }
  qf::g_domains.keep(api, domain);
  return nullptr;
}
