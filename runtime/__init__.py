"""Serving-side inference (numpy + onnxruntime + the custom-op library; no torch)."""

from quietframe.runtime.denoiser import (
    BufferError,
    Denoiser,
    DenoiseResult,
    ModelInfo,
    StateSpec,
)
from quietframe.runtime.registry import default_model_path, find_model, installed_models

__all__ = [
    "BufferError",
    "DenoiseResult",
    "Denoiser",
    "ModelInfo",
    "StateSpec",
    "default_model_path",
    "find_model",
    "installed_models",
]
