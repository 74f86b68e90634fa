"""Serving-side inference (numpy + onnxruntime + the custom-op library; no torch)."""

from quietframe.runtime.buffers import BUFFER_CHANNELS, BUFFER_NAMES, BufferError, MissingBuffers
from quietframe.runtime.denoiser import Denoiser, DenoiseResult, ModelInfo, StateSpec
from quietframe.runtime.registry import default_model_path, find_model, installed_models

__all__ = [
    "BUFFER_CHANNELS",
    "BUFFER_NAMES",
    "BufferError",
    "DenoiseResult",
    "Denoiser",
    "MissingBuffers",
    "ModelInfo",
    "StateSpec",
    "default_model_path",
    "find_model",
    "installed_models",
]
