// What the ops need from the process they run in: the onnxruntime API table and its ParallelFor,
// the CPU count, the cut of work into bands of rows, and the parallel-for that runs the bands.
// Set up once by RegisterCustomOps (register.cc); defined in runtime_support.cc.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <cstdint>

#include "ort_abi.h"
#include "simd.h"

namespace qf {

// Process-wide facts about the loaded onnxruntime, set once by RegisterCustomOps.
struct RuntimeInfo {
  ort::Api api;                               // the version-16 table
  ort::ParallelForFn parallel_for = nullptr;  // KernelContext_ParallelFor, NULL before ORT 1.17
};
const RuntimeInfo& runtime_info();
void init_runtime_info(const OrtApiBase* base);

// The CPUs this process may run on, or QUIETFRAME_OPS_NUM_THREADS: how finely work is cut, and
// the threads of the std::thread fallback (onnxruntime < 1.17 only).
int cpu_count();

// Whether the AVX2 loops run: true on an AVX2 build unless QUIETFRAME_OPS_SIMD=0 (read once),
// which runs the scalar references instead (to test them; results agree to float rounding).
bool simd_enabled();

// ---- bands: the parallel tasks ---------------------------------------------------------------

// Tasks per CPU: a few, so that uneven bands still balance.
constexpr int64_t kBandsPerCpu = 3;

// How many bands to cut `rows` rows of each of `images` images into: about kBandsPerCpu tasks
// per CPU over all images, but no band thinner than `min_rows_per_band` rows (a band re-reads
// the data at its edges, so each op sets how thin still pays). Every op's results are
// independent of the cut, hence of the thread count.
inline int64_t band_count(int64_t rows, int64_t images, int64_t min_rows_per_band) {
  const int64_t wanted = (kBandsPerCpu * cpu_count() + images - 1) / images;
  return std::clamp<int64_t>(wanted, 1, std::max<int64_t>(rows / min_rows_per_band, 1));
}

// First row of band `band` of `bands` (band `bands` starts at `rows`).
inline int64_t band_start(int64_t band, int64_t bands, int64_t rows) {
  return band * rows / bands;
}

// ---- parallel-for ----------------------------------------------------------------------------

// fn(user, i) for i in [0, count) on up to `threads` std::threads (<= 0: cpu_count()).
void parallel_for_threads(size_t count, void (*fn)(void*, size_t), void* user, int threads = 0);

// Runs fn(i) for i in [0, count), on onnxruntime's intra-op pool when the runtime offers it
// (>= 1.17) and there is a kernel context, else on our own threads (up to `threads`, <= 0:
// cpu_count()): training's C ABI (affinity_train_abi.cc) passes no context, and must not reach
// onnxruntime's pool even when a session in the same process registered the ops. Returns false
// if a task threw (only std::bad_alloc of its scratch memory can); the other tasks still run.
template <class Fn>
bool parallel_for(OrtKernelContext* ctx, size_t count, const Fn& fn, int threads = 0) {
  std::atomic<bool> failed{false};
  auto guarded = [&fn, &failed](size_t i) noexcept {
    try {
      fn(i);
    } catch (...) {
      failed.store(true, std::memory_order_relaxed);
    }
  };
  using Guarded = decltype(guarded);
  void (*trampoline)(void*, size_t) = [](void* user, size_t i) {
    (*static_cast<Guarded*>(user))(i);
  };
  if (count == 1) {
    guarded(0);
  } else if (count > 1) {
    OrtStatus* status = nullptr;
    const ort::ParallelForFn pf = ctx != nullptr ? runtime_info().parallel_for : nullptr;
    // num_batch = 0: onnxruntime schedules each index as one task (ours are coarse).
    if (pf != nullptr && (status = pf(ctx, trampoline, count, 0, &guarded)) == nullptr) {
      return !failed.load();
    }
    // Fails only up front (a minimal build without the kernel-context API): our own threads.
    if (status != nullptr) runtime_info().api.ReleaseStatus(status);
    parallel_for_threads(count, trampoline, &guarded, threads);
  }
  return !failed.load();
}

}  // namespace qf
