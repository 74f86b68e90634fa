// Plumbing shared by the ops: errors as OrtStatus, tensor access, attributes, and the OrtCustomOp
// table built from a kernel class (threads and bands: runtime_support.h).
//
// A kernel class K provides
//   static constexpr const char* kName;  static constexpr size_t kInputs, kOutputs;
//   static OrtStatus* Create(const qf::ort::Api&, const OrtKernelInfo*, K** out);  // validates
//   OrtStatus* Compute(const qf::ort::Api&, OrtKernelContext*) const;  // thread-safe
// and optionally static ONNXTensorElementDataType input_type(size_t index) (default: float32).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
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

// ---- the OrtCustomOp table --------------------------------------------------------------------

// K::input_type(i) where the kernel declares it, else float32 for every input.
template <class K, class = void>
struct InputTypes {
  static ONNXTensorElementDataType of(size_t) { return ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT; }
};
template <class K>
struct InputTypes<K, std::void_t<decltype(K::input_type(size_t{}))>> {
  static ONNXTensorElementDataType of(size_t index) { return K::input_type(index); }
};

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
    op.GetInputType = [](const OrtCustomOp*, size_t index) { return InputTypes<K>::of(index); };
    op.GetInputTypeCount = [](const OrtCustomOp*) { return K::kInputs; };
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
