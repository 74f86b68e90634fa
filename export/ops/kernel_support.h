// Plumbing shared by the ops: errors as OrtStatus, tensor access, attributes, and the OrtCustomOp
// table built from a kernel class (threads and bands: runtime_support.h).
//
// A kernel class K derives from Kernel<K, Attributes, read> (below) and declares
//   static constexpr const char* kName;
//   static constexpr const char* kInputNames[];  // every input, in order: their count too
//   static constexpr size_t kOutputs;            // float32 outputs
//   OrtStatus* Run(const qf::ort::Api&, OrtKernelContext*, const FloatInputs<n>&) const;
// and optionally static constexpr size_t kFloatInputs (the inputs from that index on are
// int64; default: every input is float32). Kernel gives it Create (the attributes read and
// checked once, at kernel creation, kept in `attributes_`) and Compute (the float32 inputs
// read, then Run; const, so thread-safe).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <iterator>
#include <stdexcept>
#include <string>
#include <type_traits>

#include "ort_abi.h"
#include "runtime_support.h"

namespace qf {

// ---- errors -----------------------------------------------------------------------------------

// "<op>: <message>" as an OrtStatus with code INVALID_ARGUMENT (or `code`).
inline OrtStatus* op_error(const ort::Api& api, const char* op, const std::string& message,
                           OrtErrorCode code = ORT_INVALID_ARGUMENT) {
  const std::string text = std::string(op) + ": " + message;
  return api.CreateStatus(code, text.c_str());
}

// Wraps a status returned by onnxruntime so that its message names the op and what we did.
inline OrtStatus* op_error_from(const ort::Api& api, const char* op, const std::string& doing,
                                OrtStatus* cause) {
  const std::string text =
      std::string(op) + ": " + doing + ": " + api.GetErrorMessage(cause);
  const OrtErrorCode code = api.GetErrorCode(cause);
  api.ReleaseStatus(cause);
  return api.CreateStatus(code == ORT_OK ? ORT_FAIL : code, text.c_str());
}

#define QF_RETURN_IF_ORT_ERROR(api, op, doing, expr)              \
  do {                                                            \
    if (OrtStatus* qf_status_ = (expr)) {                         \
      return ::qf::op_error_from((api), (op), (doing), qf_status_); \
    }                                                             \
  } while (0)

// A float as an error message shows it: every digit a float32 has.
inline std::string format_float(double v) {
  char text[32];
  std::snprintf(text, sizeof text, "%.9g", v);
  return text;
}

// ---- tensors ----------------------------------------------------------------------------------

constexpr size_t kMaxRank = 8;

struct Shape {
  size_t rank = 0;
  std::array<int64_t, kMaxRank> dims{};
  int64_t operator[](size_t i) const { return dims[i]; }
  std::string str() const {
    std::string s = "(";
    for (size_t i = 0; i < rank; ++i) s += (i ? ", " : "") + std::to_string(dims[i]);
    return s + ")";
  }
};

// Input `index` of element type `want` (`type_name` for the error message): data and shape.
// `name` is used in error messages.
inline OrtStatus* get_input(const ort::Api& api, const char* op, OrtKernelContext* ctx,
                            size_t index, const char* name, ONNXTensorElementDataType want,
                            const char* type_name, const void** data, Shape* shape) {
  const std::string what = std::string("reading input '") + name + "'";
  const OrtValue* value = nullptr;
  QF_RETURN_IF_ORT_ERROR(api, op, what, api.KernelContext_GetInput(ctx, index, &value));
  if (value == nullptr) return op_error(api, op, std::string("input '") + name + "' is missing");
  OrtTensorTypeAndShapeInfo* info = nullptr;
  QF_RETURN_IF_ORT_ERROR(api, op, what, api.GetTensorTypeAndShape(value, &info));
  ONNXTensorElementDataType type = ONNX_TENSOR_ELEMENT_DATA_TYPE_UNDEFINED;
  OrtStatus* status = api.GetTensorElementType(info, &type);
  if (status == nullptr) status = api.GetDimensionsCount(info, &shape->rank);
  if (status == nullptr && shape->rank <= kMaxRank) {
    status = api.GetDimensions(info, shape->dims.data(), shape->rank);
  }
  api.ReleaseTensorTypeAndShapeInfo(info);
  if (status != nullptr) return op_error_from(api, op, what, status);
  if (type != want) {
    return op_error(api, op, std::string("input '") + name + "' must be " + type_name);
  }
  if (shape->rank > kMaxRank) {
    return op_error(api, op, std::string("input '") + name + "' has too many dimensions");
  }
  void* ptr = nullptr;
  QF_RETURN_IF_ORT_ERROR(api, op, what,
                         api.GetTensorMutableData(const_cast<OrtValue*>(value), &ptr));
  *data = ptr;
  return nullptr;
}

// A float32 input tensor: data and shape.
inline OrtStatus* get_float_input(const ort::Api& api, const char* op, OrtKernelContext* ctx,
                                  size_t index, const char* name, const float** data,
                                  Shape* shape) {
  const void* ptr = nullptr;
  if (OrtStatus* s = get_input(api, op, ctx, index, name, ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT,
                               "float32", &ptr, shape)) {
    return s;
  }
  *data = static_cast<const float*>(ptr);
  return nullptr;
}

// An int64 scalar input (shape [] or [1]), e.g. a kernel size that may change between runs.
inline OrtStatus* get_int64_scalar_input(const ort::Api& api, const char* op,
                                         OrtKernelContext* ctx, size_t index, const char* name,
                                         int64_t* out) {
  const void* ptr = nullptr;
  Shape shape;
  if (OrtStatus* s = get_input(api, op, ctx, index, name, ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64,
                               "int64", &ptr, &shape)) {
    return s;
  }
  if (!(shape.rank == 0 || (shape.rank == 1 && shape[0] == 1))) {
    return op_error(api, op,
                    std::string("input '") + name +
                        "' must be one int64 (shape [] or [1]), got " + shape.str());
  }
  *out = *static_cast<const int64_t*>(ptr);
  return nullptr;
}

// Allocates output `index` with the given shape and returns its data.
inline OrtStatus* get_float_output(const ort::Api& api, const char* op, OrtKernelContext* ctx,
                                   size_t index, const char* name, const Shape& shape,
                                   float** data) {
  const std::string what = std::string("allocating output '") + name + "' " + shape.str();
  OrtValue* value = nullptr;
  QF_RETURN_IF_ORT_ERROR(api, op, what,
                         api.KernelContext_GetOutput(ctx, index, shape.dims.data(), shape.rank,
                                                     &value));
  void* ptr = nullptr;
  QF_RETURN_IF_ORT_ERROR(api, op, what, api.GetTensorMutableData(value, &ptr));
  *data = static_cast<float*>(ptr);
  return nullptr;
}

// A float32 input as read: data and shape.
struct FloatInput {
  const float* data = nullptr;
  Shape shape;
};
template <size_t n>
using FloatInputs = std::array<FloatInput, n>;

// The float32 inputs 0 … n-1, named `names`.
template <size_t n>
inline OrtStatus* get_float_inputs(const ort::Api& api, const char* op, OrtKernelContext* ctx,
                                   const char* const* names, FloatInputs<n>* out) {
  for (size_t i = 0; i < n; ++i) {
    FloatInput& input = (*out)[i];
    if (OrtStatus* s = get_float_input(api, op, ctx, i, names[i], &input.data, &input.shape)) {
      return s;
    }
  }
  return nullptr;
}

// `shape` (input `name`) must be (N, C, H, W) with every size >= 1.
inline OrtStatus* check_planes(const ort::Api& api, const char* op, const char* name,
                               const Shape& shape) {
  if (shape.rank == 4 && shape[0] >= 1 && shape[1] >= 1 && shape[2] >= 1 && shape[3] >= 1) {
    return nullptr;
  }
  return op_error(api, op, std::string(name) +
                               " must be (N, C, H, W) with every size >= 1, got " + shape.str());
}

// `shape` (input `name`) must be (N, channels, H, W) of the (N, C, H, W) image `like`.
inline OrtStatus* check_planes_like(const ort::Api& api, const char* op, const char* name,
                                    const Shape& shape, int64_t channels, const Shape& like) {
  const int64_t N = like[0], H = like[2], W = like[3];
  if (shape.rank == 4 && shape[0] == N && shape[1] == channels && shape[2] == H &&
      shape[3] == W) {
    return nullptr;
  }
  const std::string c = std::to_string(channels);
  return op_error(api, op, std::string(name) + " must be (N, " + c + ", H, W) = (" +
                               std::to_string(N) + ", " + c + ", " + std::to_string(H) + ", " +
                               std::to_string(W) + ") like the image, got " + shape.str());
}

// A (N, C, H, W) input's channel count left to the op (the image an op filters).
constexpr int64_t kAnyChannels = -1;

// The first inputs of `in`, named `names`, are planes of one image: input 0 is (N, C, H, W) with
// every size >= 1, and input i is (N, channels[i], H, W) with input 0's N, H and W (input 0
// too: its C must be channels[0], unless that is kAnyChannels).
template <size_t n, size_t k>
inline OrtStatus* check_image_inputs(const ort::Api& api, const char* op, const char* const* names,
                                     const FloatInputs<n>& in, const int64_t (&channels)[k]) {
  static_assert(k >= 1 && k <= n, "channels: one per checked input, input 0 first");
  const Shape& image = in[0].shape;
  if (OrtStatus* s = check_planes(api, op, names[0], image)) return s;
  for (size_t i = channels[0] == kAnyChannels ? 1 : 0; i < k; ++i) {
    if (OrtStatus* s = check_planes_like(api, op, names[i], in[i].shape, channels[i], image)) {
      return s;
    }
  }
  return nullptr;
}

// A per-image scalar input (`name`, of any rank): one value for every image, or one per image of
// `images`; *count is how many it holds (index value n as data[*count == 1 ? 0 : n]).
inline OrtStatus* check_per_image(const ort::Api& api, const char* op, const char* name,
                                  const Shape& shape, int64_t images, int64_t* count) {
  *count = 1;
  for (size_t i = 0; i < shape.rank; ++i) *count *= shape[i];
  if (*count != 1 && *count != images) {
    return op_error(api, op, std::string(name) + " must hold 1 or N = " +
                                 std::to_string(images) + " values, got " + shape.str());
  }
  return nullptr;
}

// The (N, channels, H, W) shape of an output that goes with the (N, C, H, W) `image`.
inline Shape with_channels(const Shape& image, int64_t channels) {
  Shape out = image;
  out.dims[1] = channels;
  return out;
}

// Runs task(i) for i in [0, count) (parallel_for); `failure` is the error if a task threw.
template <class Task>
inline OrtStatus* run_tasks(const ort::Api& api, const char* op, OrtKernelContext* ctx,
                            int64_t count, const Task& task,
                            const char* failure = "a worker task failed") {
  if (!parallel_for(ctx, static_cast<size_t>(count), task)) {
    return op_error(api, op, failure, ORT_FAIL);
  }
  return nullptr;
}

// ---- attributes -------------------------------------------------------------------------------

inline OrtStatus* get_int_attribute(const ort::Api& api, const char* op, const OrtKernelInfo* info,
                                    const char* name, int64_t* out) {
  if (OrtStatus* s = api.KernelInfoGetAttribute_int64(info, name, out)) {
    return op_error_from(api, op,
                         std::string("attribute '") + name + "' (int) is missing or not an int", s);
  }
  return nullptr;
}

inline OrtStatus* get_float_attribute(const ort::Api& api, const char* op,
                                      const OrtKernelInfo* info, const char* name, float* out) {
  if (OrtStatus* s = api.KernelInfoGetAttribute_float(info, name, out)) {
    return op_error_from(
        api, op, std::string("attribute '") + name + "' (float) is missing or not a float", s);
  }
  return nullptr;
}

// A kernel with no attributes.
struct NoAttributes {};
inline OrtStatus* read_no_attributes(const ort::Api&, const char*, const OrtKernelInfo*,
                                     NoAttributes*) {
  return nullptr;
}

// How many of K's inputs there are, and how many of them (the first ones) are float32: all of
// them unless K declares kFloatInputs (the rest are int64).
template <class K, class = void>
struct InputCounts {
  static constexpr size_t kAll = std::size(K::kInputNames);
  static constexpr size_t kFloat = kAll;
};
template <class K>
struct InputCounts<K, std::void_t<decltype(K::kFloatInputs)>> {
  static constexpr size_t kAll = std::size(K::kInputNames);
  static constexpr size_t kFloat = K::kFloatInputs;
};

// What every kernel shares: `Read` reads and checks the attributes once (its errors name the
// op) and the kernel keeps them; each run reads the float32 inputs, then K::Run.
template <class K, class Attributes,
          OrtStatus* (*Read)(const ort::Api&, const char*, const OrtKernelInfo*, Attributes*)>
class Kernel {
 public:
  static OrtStatus* Create(const ort::Api& api, const OrtKernelInfo* info, K** out) {
    Attributes attributes{};
    if (OrtStatus* s = Read(api, K::kName, info, &attributes)) return s;
    K* kernel = new K();
    static_cast<Kernel*>(kernel)->attributes_ = attributes;  // before any run: never changes
    *out = kernel;
    return nullptr;
  }

  OrtStatus* Compute(const ort::Api& api, OrtKernelContext* ctx) const {
    FloatInputs<InputCounts<K>::kFloat> in;
    if (OrtStatus* s = get_float_inputs(api, K::kName, ctx, K::kInputNames, &in)) return s;
    return static_cast<const K*>(this)->Run(api, ctx, in);
  }

 protected:
  Attributes attributes_{};
};

// ---- the OrtCustomOp table --------------------------------------------------------------------

template <class K>
class CustomOp {
 public:
  static const OrtCustomOp* get() {
    static const OrtCustomOp op = make();
    return &op;
  }

 private:
  struct Holder {
    ort::Api api;
    K* kernel;
  };

  static OrtCustomOp make() {
    OrtCustomOp op{};  // every field zero / NULL, including those of later API versions
    op.version = ort::kApiVersion;
    op.CreateKernel = &CreateV1;
    op.GetName = [](const OrtCustomOp*) { return K::kName; };
    op.GetExecutionProviderType = [](const OrtCustomOp*) -> const char* { return nullptr; };
    op.GetInputType = [](const OrtCustomOp*, size_t index) {
      return index < InputCounts<K>::kFloat ? ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT
                                            : ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64;
    };
    op.GetInputTypeCount = [](const OrtCustomOp*) { return InputCounts<K>::kAll; };
    op.GetOutputType = [](const OrtCustomOp*, size_t) {
      return ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT;
    };
    op.GetOutputTypeCount = [](const OrtCustomOp*) { return K::kOutputs; };
    op.KernelCompute = &ComputeV1;
    op.KernelDestroy = [](void* p) {
      Holder* h = static_cast<Holder*>(p);
      if (h != nullptr) delete h->kernel;
      delete h;
    };
    op.GetInputCharacteristic = [](const OrtCustomOp*, size_t) { return INPUT_OUTPUT_REQUIRED; };
    op.GetOutputCharacteristic = [](const OrtCustomOp*, size_t) { return INPUT_OUTPUT_REQUIRED; };
    op.GetInputMemoryType = [](const OrtCustomOp*, size_t) { return OrtMemTypeDefault; };
    op.GetVariadicInputMinArity = [](const OrtCustomOp*) { return 1; };
    op.GetVariadicInputHomogeneity = [](const OrtCustomOp*) { return 1; };
    op.GetVariadicOutputMinArity = [](const OrtCustomOp*) { return 1; };
    op.GetVariadicOutputHomogeneity = [](const OrtCustomOp*) { return 1; };
    op.CreateKernelV2 = &CreateV2;
    op.KernelComputeV2 = &ComputeV2;
    return op;
  }

  // onnxruntime >= 1.17: errors travel back as OrtStatus (a Python exception).
  static OrtStatus* CreateV2(const OrtCustomOp*, const OrtApi* table, const OrtKernelInfo* info,
                             void** out) {
    const ort::Api api(table);
    *out = nullptr;
    try {
      K* kernel = nullptr;
      if (OrtStatus* s = K::Create(api, info, &kernel)) return s;
      *out = new Holder{api, kernel};
      return nullptr;
    } catch (const std::exception& e) {
      return op_error(api, K::kName, std::string("kernel creation failed: ") + e.what(), ORT_FAIL);
    }
  }

  static OrtStatus* ComputeV2(void* p, OrtKernelContext* ctx) {
    const Holder* h = static_cast<const Holder*>(p);
    try {
      return h->kernel->Compute(h->api, ctx);
    } catch (const std::exception& e) {
      return op_error(h->api, K::kName, e.what(), ORT_FAIL);
    }
  }

  // onnxruntime 1.16 calls these instead: no status can be returned, so errors are thrown as
  // std::runtime_error (what the official C++ wrapper did for V1 ops); onnxruntime catches it
  // and reports a failed session creation or run.
  static void* CreateV1(const OrtCustomOp* op, const OrtApi* table, const OrtKernelInfo* info) {
    void* kernel = nullptr;
    throw_if_error(ort::Api(table), CreateV2(op, table, info, &kernel));
    return kernel;
  }

  static void ComputeV1(void* p, OrtKernelContext* ctx) {
    throw_if_error(static_cast<const Holder*>(p)->api, ComputeV2(p, ctx));
  }

  static void throw_if_error(const ort::Api& api, OrtStatus* status) {
    if (status == nullptr) return;
    const std::string message = api.GetErrorMessage(status);
    api.ReleaseStatus(status);
    throw std::runtime_error(message);
  }
};

}  // namespace qf
