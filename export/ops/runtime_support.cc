// Process-wide runtime facts (runtime_support.h): the onnxruntime API table and ParallelFor, the
// CPU count, the SIMD switch, and the std::thread fallback of parallel_for.
#include "runtime_support.h"

#include <sched.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <mutex>
#include <thread>
#include <vector>

namespace qf {
namespace {

constexpr int kMaxThreads = 64;

RuntimeInfo g_runtime;
std::once_flag g_runtime_once;

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

bool simd_enabled() {
  static const bool enabled = [] {
    const char* text = std::getenv("QUIETFRAME_OPS_SIMD");
    return QF_HAVE_AVX2 && !(text != nullptr && std::strcmp(text, "0") == 0);
  }();
  return enabled;
}

void parallel_for_threads(size_t count, void (*fn)(void*, size_t), void* user, int max_threads) {
  const int wanted = max_threads > 0 ? std::min(max_threads, kMaxThreads) : cpu_count();
  const size_t threads = std::min(count, static_cast<size_t>(wanted));
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
