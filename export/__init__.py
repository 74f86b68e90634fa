"""Export of trained models to ONNX (quietframe.export.onnx_export, needs torch) and the C++
custom-op library's sources (export/ops). Serving does not import this package: the library's
locator lives in quietframe.runtime.ops_library."""

from quietframe.runtime.ops_library import OPS_DOMAIN, ops_library_path

__all__ = ["OPS_DOMAIN", "ops_library_path"]
