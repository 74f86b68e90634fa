// Training's C ABI to the affinity kernels (Işık et al. 2021, eq. 4, 6, 7, 8): the forward of
// AffinityFilter / AffinityTemporalFilter (the same qf::affinity code, so training's forward is
// bit-identical to the served op) and its gradients (affinity_backward.h), on contiguous float32
// NCHW buffers given as raw pointers. quietframe.model.affinity_native loads these symbols with
// ctypes; they need no onnxruntime (RegisterCustomOps need never have run) and never use its
// thread pool: work runs on the library's own threads, at most `threads` of them.
//
// Every function returns a QfStatus. The caller validates shapes (the Python wrapper does); the
// checks here only keep a wrong call from reading or writing out of bounds.
#include <algorithm>
#include <climits>
#include <cmath>
#include <cstdint>
#include <new>
#include <vector>

#include "affinity_backward.h"
#include "affinity_common.h"
#include "runtime_support.h"
#include "simd.h"

extern "C" {

// Layout shared with quietframe/model/affinity_native.py (ctypes); bump kQfTrainAbiVersion on any
// change. The temporal pointers are null and temporal_kernel_size 0 for AffinityFilter.
struct QfAffinityArgs {
  const float* radiance;            // (N, C, H, W)
  const float* features;            // (N, D, H, W)
  const float* bandwidth;           // (N, 1, H, W)
  const float* center;              // (N, 1, H, W)
  const float* prev_output;         // (N, C, H, W)
  const float* prev_features;       // (N, D, H, W)
  const float* temporal_bandwidth;  // (N, 1, H, W)
  const float* temporal_on;         // (N)
  int64_t n, c, d, h, w;
  int64_t kernel_size, dilation, temporal_kernel_size;
  float epsilon;
  int32_t threads;  // <= 0: cpu_count() (QUIETFRAME_OPS_NUM_THREADS or the CPUs)
};

// ∂ℓ/∂output in, the gradients out (each shaped like its input; the temporal ones null for
// AffinityFilter). Every plane is written, zeros included.
struct QfAffinityGrads {
  const float* grad_output;   // (N, C, H, W)
  float* radiance;
  float* features;
  float* bandwidth;
  float* center;
  float* prev_output;
  float* prev_features;
  float* temporal_bandwidth;
};

enum QfStatus : int32_t { kQfOk = 0, kQfInvalidArgument = 1, kQfFailed = 2 };

}  // extern "C"

namespace qf::affinity {
namespace {

constexpr int32_t kQfTrainAbiVersion = 1;

bool odd_size(int64_t size) { return size >= 1 && size <= kMaxKernelSize && size % 2 == 1; }

// The Job of a call, or false if the arguments cannot describe a valid one.
bool make_job(const QfAffinityArgs& a, float* out, Job* j) {
  const bool temporal = a.temporal_kernel_size != 0;
  if (a.radiance == nullptr || a.features == nullptr || a.bandwidth == nullptr ||
      a.center == nullptr || out == nullptr) {
    return false;
  }
  if (temporal && (a.prev_output == nullptr || a.prev_features == nullptr ||
                   a.temporal_bandwidth == nullptr || a.temporal_on == nullptr ||
                   !odd_size(a.temporal_kernel_size))) {
    return false;
  }
  if (a.n < 1 || a.c < 1 || a.d < 1 || a.h < 1 || a.w < 1 || a.h * a.w > INT32_MAX - 16 ||
      !odd_size(a.kernel_size) || a.dilation < 1 || a.dilation > kMaxDilation ||
      !(std::isfinite(a.epsilon) && a.epsilon >= 0.0f)) {
    return false;
  }
  j->radiance = a.radiance;
  j->features = a.features;
  j->bandwidth = a.bandwidth;
  j->center = a.center;
  if (temporal) {
    j->prev_output = a.prev_output;
    j->prev_features = a.prev_features;
    j->temporal_bandwidth = a.temporal_bandwidth;
    j->temporal_on = a.temporal_on;
    j->temporal_radius = (a.temporal_kernel_size - 1) / 2;
  }
  j->out = out;
  j->C = a.c;
  j->D = a.d;
  j->H = a.h;
  j->W = a.w;
  j->radius = (a.kernel_size - 1) / 2;
  j->dilation = a.dilation;
  j->epsilon = a.epsilon;
  // band_count's cut for `threads` CPUs (results do not depend on it)
  const int64_t cpus = a.threads > 0 ? a.threads : cpu_count();
  const int64_t wanted = (kBandsPerCpu * cpus + a.n - 1) / a.n;
  j->bands = std::clamp<int64_t>(wanted, 1, std::max<int64_t>(a.h / kMinRowsPerBand, 1));
  return true;
}

}  // namespace
}  // namespace qf::affinity

// Compiled for any x86-64 CPU like RegisterCustomOps: whether this build's instructions (AVX2
// and FMA by default) run here. Call it before the others.
#if QF_HAVE_AVX2 && defined(__x86_64__) && defined(__GNUC__)
#define QF_ANY_X86_64 __attribute__((target("arch=x86-64")))
#else
#define QF_ANY_X86_64
#endif

#define QF_EXPORT extern "C" __attribute__((visibility("default")))

QF_EXPORT QF_ANY_X86_64 int32_t qf_affinity_train_abi_version() {
  return qf::affinity::kQfTrainAbiVersion;
}

QF_EXPORT QF_ANY_X86_64 int32_t qf_affinity_train_supported() {
#if QF_HAVE_AVX2 && defined(__x86_64__) && defined(__GNUC__)
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") ? 1 : 0;
#else
  return 1;
#endif
}

// out (N, C, H, W) = the op's output.
QF_EXPORT int32_t qf_affinity_forward(const QfAffinityArgs* args, float* out) {
  using namespace qf::affinity;
  Job j;
  if (args == nullptr || !make_job(*args, out, &j)) return kQfInvalidArgument;
  auto task = [&j](size_t i) { filter_band(j, static_cast<int64_t>(i)); };
  const size_t tasks = static_cast<size_t>(args->n * j.bands);
  return qf::parallel_for(nullptr, tasks, task, args->threads) ? kQfOk : kQfFailed;
}

// Every gradient of the op at `args` for ∂ℓ/∂output = grads->grad_output.
QF_EXPORT int32_t qf_affinity_backward(const QfAffinityArgs* args, const QfAffinityGrads* grads) {
  using namespace qf::affinity;
  if (args == nullptr || grads == nullptr) return kQfInvalidArgument;
  const bool temporal = args->temporal_kernel_size != 0;
  if (grads->grad_output == nullptr || grads->radiance == nullptr || grads->features == nullptr ||
      grads->bandwidth == nullptr || grads->center == nullptr ||
      (temporal && (grads->prev_output == nullptr || grads->prev_features == nullptr ||
                    grads->temporal_bandwidth == nullptr))) {
    return kQfInvalidArgument;
  }
  try {
    // pass 1's scratch: the forward's output, then g / D; its denominator, then h
    std::vector<float> gD(static_cast<size_t>(args->n * args->c * args->h * args->w));
    std::vector<float> h(static_cast<size_t>(args->n * args->h * args->w));
    GradJob g;
    if (!make_job(*args, gD.data(), &g.fwd)) return kQfInvalidArgument;
    g.fwd.denominator = h.data();
    g.grad_out = grads->grad_output;
    g.gD = gD.data();
    g.h = h.data();
    g.gL = grads->radiance;
    g.gF = grads->features;
    g.gA = grads->bandwidth;
    g.gC = grads->center;
    if (temporal) {
      g.gO = grads->prev_output;
      g.gPF = grads->prev_features;
      g.gB = grads->temporal_bandwidth;
    }
    const size_t tasks = static_cast<size_t>(args->n * g.fwd.bands);
    auto prepare = [&g](size_t i) { prepare_band(g, static_cast<int64_t>(i)); };
    if (!qf::parallel_for(nullptr, tasks, prepare, args->threads)) return kQfFailed;
    auto gradients = [&g](size_t i) { grad_band(g, static_cast<int64_t>(i)); };
    if (!qf::parallel_for(nullptr, tasks, gradients, args->threads)) return kQfFailed;
  } catch (const std::bad_alloc&) {
    return kQfFailed;
  }
  return kQfOk;
}
