// The part of the onnxruntime C ABI that the quietframe ops use.
//
// The onnxruntime wheel ships no C headers, so by default this file declares the few types and
// function-table slots we need itself, from the facts written down in docs/ort-abi.md (which
// slot, which signature, how each was checked; the ABI is append-only: slots and struct offsets
// never move); tests/export/test_ops_abi.py exercises every slot listed in Slot below.
// Configure with -DORT_INCLUDE_DIR=<dir> to compile against the official onnxruntime_c_api.h
// instead; the static_asserts below then check our slot numbers and the OrtCustomOp layout
// against it.
#pragma once

#include <cstddef>
#include <cstdint>

#if QUIETFRAME_OFFICIAL_ORT_HEADERS

#include <onnxruntime_c_api.h>

#else  // our own declarations

extern "C" {

// Opaque handles owned by onnxruntime.
struct OrtStatus;
struct OrtApi;  // a table of function pointers, read by slot index (see qf::ort::Api)
struct OrtSessionOptions;
struct OrtCustomOpDomain;
struct OrtKernelInfo;
struct OrtKernelContext;
struct OrtValue;
struct OrtTensorTypeAndShapeInfo;

enum OrtErrorCode { ORT_OK = 0, ORT_FAIL = 1, ORT_INVALID_ARGUMENT = 2 };

enum ONNXTensorElementDataType {
  ONNX_TENSOR_ELEMENT_DATA_TYPE_UNDEFINED = 0,
  ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT = 1,
  ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64 = 7,
};

enum OrtCustomOpInputOutputCharacteristic {
  INPUT_OUTPUT_REQUIRED = 0,
  INPUT_OUTPUT_OPTIONAL = 1,
  INPUT_OUTPUT_VARIADIC = 2,
};

enum OrtMemType { OrtMemTypeDefault = 0 };

struct OrtApiBase {
  const OrtApi* (*GetApi)(uint32_t version);  // NULL when `version` is newer than the runtime
  const char* (*GetVersionString)(void);
};

// Field names follow the official header so that the registration code compiles against both.
struct OrtCustomOp {
  uint32_t version;
  void* (*CreateKernel)(const OrtCustomOp* op, const OrtApi* api, const OrtKernelInfo* info);
  const char* (*GetName)(const OrtCustomOp* op);
  const char* (*GetExecutionProviderType)(const OrtCustomOp* op);
  ONNXTensorElementDataType (*GetInputType)(const OrtCustomOp* op, size_t index);
  size_t (*GetInputTypeCount)(const OrtCustomOp* op);
  ONNXTensorElementDataType (*GetOutputType)(const OrtCustomOp* op, size_t index);
  size_t (*GetOutputTypeCount)(const OrtCustomOp* op);
  void (*KernelCompute)(void* kernel, OrtKernelContext* context);
  void (*KernelDestroy)(void* kernel);
  OrtCustomOpInputOutputCharacteristic (*GetInputCharacteristic)(const OrtCustomOp* op,
                                                                 size_t index);
  OrtCustomOpInputOutputCharacteristic (*GetOutputCharacteristic)(const OrtCustomOp* op,
                                                                  size_t index);
  OrtMemType (*GetInputMemoryType)(const OrtCustomOp* op, size_t index);
  int (*GetVariadicInputMinArity)(const OrtCustomOp* op);
  int (*GetVariadicInputHomogeneity)(const OrtCustomOp* op);
  int (*GetVariadicOutputMinArity)(const OrtCustomOp* op);
  int (*GetVariadicOutputHomogeneity)(const OrtCustomOp* op);
  OrtStatus* (*CreateKernelV2)(const OrtCustomOp* op, const OrtApi* api,
                               const OrtKernelInfo* info, void** kernel);
  OrtStatus* (*KernelComputeV2)(void* kernel, OrtKernelContext* context);
  // Read by onnxruntime only for version >= 17/18; we register version 16 and leave them NULL.
  void* InferOutputShapeFn;
  void* GetStartVersion;
  void* GetEndVersion;
  void* GetMayInplace;
  void* ReleaseMayInplace;
  void* GetAliasMap;
  void* ReleaseAliasMap;
};

}  // extern "C"

#endif  // QUIETFRAME_OFFICIAL_ORT_HEADERS

// OrtCustomOp layout on LP64 targets (docs/ort-abi.md), checked for both header variants.
#if UINTPTR_MAX == UINT64_MAX
static_assert(offsetof(OrtCustomOp, CreateKernel) == 8, "OrtCustomOp layout");
static_assert(offsetof(OrtCustomOp, GetInputType) == 32, "OrtCustomOp layout");
static_assert(offsetof(OrtCustomOp, KernelCompute) == 64, "OrtCustomOp layout");
static_assert(offsetof(OrtCustomOp, GetInputCharacteristic) == 80, "OrtCustomOp layout");
static_assert(offsetof(OrtCustomOp, GetInputMemoryType) == 96, "OrtCustomOp layout");
static_assert(offsetof(OrtCustomOp, GetVariadicOutputHomogeneity) == 128, "OrtCustomOp layout");
static_assert(offsetof(OrtCustomOp, CreateKernelV2) == 136, "OrtCustomOp layout");
static_assert(offsetof(OrtCustomOp, KernelComputeV2) == 144, "OrtCustomOp layout");
static_assert(sizeof(OrtCustomOp) == 208, "OrtCustomOp layout");
#endif

namespace qf::ort {

// API version we register with: onnxruntime >= 1.16.3 has it.
constexpr uint32_t kApiVersion = 16;
// First API version with KernelContext_ParallelFor (onnxruntime >= 1.17).
constexpr uint32_t kParallelForApiVersion = 17;

// Slot indices (0-based) in the OrtApi function table.
enum Slot : size_t {
  kCreateStatus = 0,
  kGetErrorCode = 1,
  kGetErrorMessage = 2,
  kCreateCustomOpDomain = 26,
  kCustomOpDomain_Add = 27,
  kAddCustomOpDomain = 28,
  kGetTensorMutableData = 51,
  kGetTensorElementType = 60,
  kGetDimensionsCount = 61,
  kGetDimensions = 62,
  kGetTensorTypeAndShape = 65,
  kKernelInfoGetAttribute_float = 85,
  kKernelInfoGetAttribute_int64 = 86,
  kKernelContext_GetInput = 90,
  kKernelContext_GetOutput = 91,
  kReleaseStatus = 93,
  kReleaseTensorTypeAndShapeInfo = 99,
  kReleaseCustomOpDomain = 101,
  kKernelContext_ParallelFor = 274,
};

using ParallelForFn = OrtStatus* (*)(const OrtKernelContext*, void (*fn)(void*, size_t),
                                     size_t total, size_t num_batch, void* user);

#if QUIETFRAME_OFFICIAL_ORT_HEADERS
// Our slot numbers must agree with the official table.
#define QF_ORT_CHECK_SLOT(name) \
  static_assert(offsetof(OrtApi, name) == k##name * sizeof(void*), "OrtApi slot of " #name)
QF_ORT_CHECK_SLOT(CreateStatus);
QF_ORT_CHECK_SLOT(GetErrorCode);
QF_ORT_CHECK_SLOT(GetErrorMessage);
QF_ORT_CHECK_SLOT(CreateCustomOpDomain);
QF_ORT_CHECK_SLOT(CustomOpDomain_Add);
QF_ORT_CHECK_SLOT(AddCustomOpDomain);
QF_ORT_CHECK_SLOT(GetTensorMutableData);
QF_ORT_CHECK_SLOT(GetTensorElementType);
QF_ORT_CHECK_SLOT(GetDimensionsCount);
QF_ORT_CHECK_SLOT(GetDimensions);
QF_ORT_CHECK_SLOT(GetTensorTypeAndShape);
QF_ORT_CHECK_SLOT(KernelInfoGetAttribute_float);
QF_ORT_CHECK_SLOT(KernelInfoGetAttribute_int64);
QF_ORT_CHECK_SLOT(KernelContext_GetInput);
QF_ORT_CHECK_SLOT(KernelContext_GetOutput);
QF_ORT_CHECK_SLOT(ReleaseStatus);
QF_ORT_CHECK_SLOT(ReleaseTensorTypeAndShapeInfo);
QF_ORT_CHECK_SLOT(ReleaseCustomOpDomain);
QF_ORT_CHECK_SLOT(KernelContext_ParallelFor);
#undef QF_ORT_CHECK_SLOT
// Calls through the named member: the compiler checks every signature.
#define QF_ORT_FN(api, name, type) ((api)->name)
#else
// Calls through the slot: the signature is ours, from docs/ort-abi.md.
using AnyFn = void (*)();
#define QF_ORT_FN(api, name, type) \
  (reinterpret_cast<type>(reinterpret_cast<const ::qf::ort::AnyFn*>(api)[::qf::ort::k##name]))
#endif

// Typed access to the functions of one OrtApi table (a pointer, cheap to copy).
class Api {
 public:
  constexpr explicit Api(const OrtApi* api = nullptr) : api_(api) {}
  const OrtApi* table() const { return api_; }

  OrtStatus* CreateStatus(OrtErrorCode code, const char* msg) const {
    return QF_ORT_FN(api_, CreateStatus, OrtStatus* (*)(OrtErrorCode, const char*))(code, msg);
  }
  OrtErrorCode GetErrorCode(const OrtStatus* s) const {
    return QF_ORT_FN(api_, GetErrorCode, OrtErrorCode (*)(const OrtStatus*))(s);
  }
  const char* GetErrorMessage(const OrtStatus* s) const {
    return QF_ORT_FN(api_, GetErrorMessage, const char* (*)(const OrtStatus*))(s);
  }
  void ReleaseStatus(OrtStatus* s) const {
    QF_ORT_FN(api_, ReleaseStatus, void (*)(OrtStatus*))(s);
  }
  OrtStatus* CreateCustomOpDomain(const char* domain, OrtCustomOpDomain** out) const {
    return QF_ORT_FN(api_, CreateCustomOpDomain,
                     OrtStatus* (*)(const char*, OrtCustomOpDomain**))(domain, out);
  }
  OrtStatus* CustomOpDomain_Add(OrtCustomOpDomain* domain, const OrtCustomOp* op) const {
    return QF_ORT_FN(api_, CustomOpDomain_Add,
                     OrtStatus* (*)(OrtCustomOpDomain*, const OrtCustomOp*))(domain, op);
  }
  OrtStatus* AddCustomOpDomain(OrtSessionOptions* options, OrtCustomOpDomain* domain) const {
    return QF_ORT_FN(api_, AddCustomOpDomain,
                     OrtStatus* (*)(OrtSessionOptions*, OrtCustomOpDomain*))(options, domain);
  }
  void ReleaseCustomOpDomain(OrtCustomOpDomain* domain) const {
    QF_ORT_FN(api_, ReleaseCustomOpDomain, void (*)(OrtCustomOpDomain*))(domain);
  }
  OrtStatus* KernelInfoGetAttribute_float(const OrtKernelInfo* info, const char* name,
                                          float* out) const {
    return QF_ORT_FN(api_, KernelInfoGetAttribute_float,
                     OrtStatus* (*)(const OrtKernelInfo*, const char*, float*))(info, name, out);
  }
  OrtStatus* KernelInfoGetAttribute_int64(const OrtKernelInfo* info, const char* name,
                                          int64_t* out) const {
    return QF_ORT_FN(api_, KernelInfoGetAttribute_int64,
                     OrtStatus* (*)(const OrtKernelInfo*, const char*, int64_t*))(info, name, out);
  }
  OrtStatus* KernelContext_GetInput(const OrtKernelContext* ctx, size_t index,
                                    const OrtValue** out) const {
    return QF_ORT_FN(api_, KernelContext_GetInput,
                     OrtStatus* (*)(const OrtKernelContext*, size_t, const OrtValue**))(
        ctx, index, out);
  }
  OrtStatus* KernelContext_GetOutput(OrtKernelContext* ctx, size_t index, const int64_t* dims,
                                     size_t dims_count, OrtValue** out) const {
    return QF_ORT_FN(api_, KernelContext_GetOutput,
                     OrtStatus* (*)(OrtKernelContext*, size_t, const int64_t*, size_t,
                                    OrtValue**))(ctx, index, dims, dims_count, out);
  }
  OrtStatus* GetTensorMutableData(OrtValue* value, void** out) const {
    return QF_ORT_FN(api_, GetTensorMutableData, OrtStatus* (*)(OrtValue*, void**))(value, out);
  }
  OrtStatus* GetTensorTypeAndShape(const OrtValue* value, OrtTensorTypeAndShapeInfo** out) const {
    return QF_ORT_FN(api_, GetTensorTypeAndShape,
                     OrtStatus* (*)(const OrtValue*, OrtTensorTypeAndShapeInfo**))(value, out);
  }
  OrtStatus* GetTensorElementType(const OrtTensorTypeAndShapeInfo* info,
                                  ONNXTensorElementDataType* out) const {
    return QF_ORT_FN(api_, GetTensorElementType,
                     OrtStatus* (*)(const OrtTensorTypeAndShapeInfo*,
                                    ONNXTensorElementDataType*))(info, out);
  }
  OrtStatus* GetDimensionsCount(const OrtTensorTypeAndShapeInfo* info, size_t* out) const {
    return QF_ORT_FN(api_, GetDimensionsCount,
                     OrtStatus* (*)(const OrtTensorTypeAndShapeInfo*, size_t*))(info, out);
  }
  OrtStatus* GetDimensions(const OrtTensorTypeAndShapeInfo* info, int64_t* dims,
                           size_t dims_len) const {
    return QF_ORT_FN(api_, GetDimensions,
                     OrtStatus* (*)(const OrtTensorTypeAndShapeInfo*, int64_t*, size_t))(
        info, dims, dims_len);
  }
  void ReleaseTensorTypeAndShapeInfo(OrtTensorTypeAndShapeInfo* info) const {
    QF_ORT_FN(api_, ReleaseTensorTypeAndShapeInfo, void (*)(OrtTensorTypeAndShapeInfo*))(info);
  }
  // Only valid on a table of version >= kParallelForApiVersion.
  ParallelForFn KernelContext_ParallelFor() const {
    return QF_ORT_FN(api_, KernelContext_ParallelFor, ParallelForFn);
  }

 private:
  const OrtApi* api_;
};

}  // namespace qf::ort
