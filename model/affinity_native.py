"""Training's native affinity kernels: the C++ forward and backward of eq. 4 + 6 and 7 + 8.

The custom-op library (export/ops) carries, besides the onnxruntime ops, a small C ABI
(export/ops/affinity_train_abi.cc): the served AffinityFilter / AffinityTemporalFilter code as
training's forward (bit-identical to the shipped op) and their gradients with respect to every
input but temporal_on (export/ops/affinity_backward.h), on contiguous float32 CPU buffers.
This module loads it with ctypes and wraps it for torch tensors; quietframe.model.affinity_kernels
routes its custom ops here when `enabled()` (the reference `spatial_math` / `temporal_math` stays
the spec and the tests' oracle).

Which kernels training uses: QUIETFRAME_TRAIN_KERNELS = "auto" | "native" | "reference", else
DEFAULT_KERNELS below ("auto": native where available), the one switch. Float64 (gradcheck)
and non-CPU tensors always take the reference. Threads: torch's intra-op count
(torch.set_num_threads, training's --threads) unless a call gives `threads`; results do not
depend on it.
"""

from __future__ import annotations

import ctypes
import functools
import os

import torch
from torch import Tensor

from quietframe.runtime.ops_library import ops_library_path

KERNELS_ENV = "QUIETFRAME_TRAIN_KERNELS"
# The switch: the kernels used when QUIETFRAME_TRAIN_KERNELS is unset. "auto": native where the
# library has them (3.5-11x faster steps, docs/affinity-training-kernels.md), else the reference;
# "native" insists (an error where it cannot run).
DEFAULT_KERNELS = "auto"
KERNEL_CHOICES = ("auto", "reference", "native")
ABI_VERSION = 1  # kQfTrainAbiVersion of affinity_train_abi.cc
MAX_KERNEL_SIZE = 31  # as affinity_kernels.MAX_KERNEL_SIZE and the C++ kMaxKernelSize
MAX_DILATION = 65536  # the C++ kMaxDilation

_F = ctypes.POINTER(ctypes.c_float)


class _Args(ctypes.Structure):
    """QfAffinityArgs of affinity_train_abi.cc."""

    _fields_ = [(name, _F) for name in (
        "radiance", "features", "bandwidth", "center", "prev_output", "prev_features",
        "temporal_bandwidth", "temporal_on")] + [(name, ctypes.c_int64) for name in (
            "n", "c", "d", "h", "w", "kernel_size", "dilation", "temporal_kernel_size")] + [
        ("epsilon", ctypes.c_float), ("threads", ctypes.c_int32)]


class _Grads(ctypes.Structure):
    """QfAffinityGrads of affinity_train_abi.cc."""

    _fields_ = [(name, _F) for name in (
        "grad_output", "radiance", "features", "bandwidth", "center", "prev_output",
        "prev_features", "temporal_bandwidth")]


@functools.lru_cache(maxsize=4)
def _load(path: str) -> ctypes.CDLL | str:
    """The library at `path` with its training ABI typed, or why it cannot be used."""
    try:
        lib = ctypes.CDLL(path)
        version, supported = lib.qf_affinity_train_abi_version, lib.qf_affinity_train_supported
    except (OSError, AttributeError) as e:
        return f"{path} has no affinity training ABI ({e}); rebuild export/ops"
    version.restype = supported.restype = ctypes.c_int32
    if version() != ABI_VERSION:
        return f"{path} has training ABI version {version()}, this module needs {ABI_VERSION}"
    if not supported():
        return f"{path} was built for CPUs with AVX2 and FMA, this one has not"
    lib.qf_affinity_forward.argtypes = [ctypes.POINTER(_Args), _F]
    lib.qf_affinity_backward.argtypes = [ctypes.POINTER(_Args), ctypes.POINTER(_Grads)]
    lib.qf_affinity_forward.restype = lib.qf_affinity_backward.restype = ctypes.c_int32
    return lib


def _library() -> ctypes.CDLL | str:
    try:
        path = ops_library_path()
    except FileNotFoundError as e:
        return str(e)
    return _load(str(path))


def unavailable_reason() -> str | None:
    """None if the native kernels can run here, else why not."""
    lib = _library()
    return lib if isinstance(lib, str) else None


def available() -> bool:
    return unavailable_reason() is None


def selected() -> str:
    """The kernels training asked for: QUIETFRAME_TRAIN_KERNELS, else DEFAULT_KERNELS."""
    choice = os.environ.get(KERNELS_ENV, "") or DEFAULT_KERNELS
    if choice not in KERNEL_CHOICES:
        raise ValueError(f"{KERNELS_ENV} must be one of {KERNEL_CHOICES}, got {choice!r}")
    return choice


def enabled(*tensors: Tensor) -> bool:
    """Whether affinity_kernels' ops run natively on these tensors: native selected, and all
    of them float32 on the CPU (anything else, e.g. gradcheck's float64, takes the reference)."""
    choice = selected()
    if choice == "reference":
        return False
    if not all(t.dtype == torch.float32 and t.device.type == "cpu" for t in tensors):
        return False
    reason = unavailable_reason()
    if reason is not None and choice == "native":
        raise RuntimeError(f"{KERNELS_ENV}=native but the native kernels cannot run: {reason}")
    return reason is None


# ---- calls ------------------------------------------------------------------------------------


def _size(name: str, size: int) -> int:
    if not (isinstance(size, int) and 1 <= size <= MAX_KERNEL_SIZE and size % 2 == 1):
        raise ValueError(f"{name} must be an odd int in [1, {MAX_KERNEL_SIZE}], got {size!r}")
    return size


def _pointer(t: Tensor):
    return ctypes.cast(t.data_ptr(), _F)


def _prepare(named: dict[str, Tensor], temporal: bool) -> list[Tensor]:
    """The inputs as contiguous float32 CPU tensors, their shapes checked like the C++ ops'."""
    for name, t in named.items():
        if t.dtype != torch.float32 or t.device.type != "cpu":
            raise TypeError(f"{name} must be a float32 CPU tensor, got {t.dtype} on {t.device}")
    radiance, features = named["radiance"], named["features"]
    if radiance.dim() != 4 or min(radiance.shape) < 1:
        raise ValueError(f"radiance must be (N, C, H, W) with every size >= 1, "
                         f"got {tuple(radiance.shape)}")
    n, c, h, w = radiance.shape
    d = features.shape[1] if features.dim() == 4 else 0
    expected = {"radiance": (n, c, h, w), "features": (n, d, h, w), "bandwidth": (n, 1, h, w),
                "center": (n, 1, h, w)}
    if temporal:
        expected |= {"prev_output": (n, c, h, w), "prev_features": (n, d, h, w),
                     "temporal_bandwidth": (n, 1, h, w), "temporal_on": (n,)}
    if d < 1:
        raise ValueError(f"features must be (N, D, H, W) like the radiance, "
                         f"got {tuple(features.shape)}")
    for name, shape in expected.items():
        if tuple(named[name].shape) != shape:
            raise ValueError(f"{name} must be {shape}, got {tuple(named[name].shape)}")
    if h * w > 2**31 - 17:
        raise ValueError("images of more than 2^31 pixels are not supported")
    return [named[name].detach().contiguous() for name in expected]


def _args(tensors: list[Tensor], kernel_size: int, dilation: int, temporal_kernel_size: int,
          eps: float, threads: int | None) -> _Args:
    if not (isinstance(dilation, int) and 1 <= dilation <= MAX_DILATION):
        raise ValueError(f"dilation must be an int in [1, {MAX_DILATION}], got {dilation!r}")
    if not (eps >= 0 and eps < float("inf")):
        raise ValueError(f"eps must be a finite number >= 0, got {eps!r}")
    n, c, h, w = tensors[0].shape
    pointers = [_pointer(t) for t in tensors] + [None] * (8 - len(tensors))
    return _Args(*pointers, n, c, tensors[1].shape[1], h, w, _size("kernel_size", kernel_size),
                 dilation, temporal_kernel_size, eps,
                 torch.get_num_threads() if threads is None else threads)


def _check(status: int, what: str) -> None:
    if status != 0:
        raise RuntimeError(f"native affinity {what} failed (status {status}: "
                           f"{'invalid argument' if status == 1 else 'out of memory'})")


def _forward(tensors: list[Tensor], args: _Args) -> Tensor:
    lib = _library()
    if isinstance(lib, str):
        raise RuntimeError(lib)
    out = torch.empty_like(tensors[0])
    _check(lib.qf_affinity_forward(ctypes.byref(args), _pointer(out)), "forward")
    return out


def _backward(grad: Tensor, tensors: list[Tensor], args: _Args) -> tuple[Tensor, ...]:
    lib = _library()
    if isinstance(lib, str):
        raise RuntimeError(lib)
    if grad.dtype != torch.float32 or tuple(grad.shape) != tuple(tensors[0].shape):
        raise ValueError(f"the output gradient must be float32 {tuple(tensors[0].shape)}, "
                         f"got {grad.dtype} {tuple(grad.shape)}")
    grad = grad.detach().contiguous()
    # one gradient per input but temporal_on (C++ writes every element)
    grads = tuple(torch.empty_like(t) for t in tensors[:7])
    pointers = [_pointer(g) for g in grads] + [None] * (7 - len(grads))
    _check(lib.qf_affinity_backward(ctypes.byref(args), ctypes.byref(_Grads(_pointer(grad),
                                                                            *pointers))),
           "backward")
    return grads


def _spatial(radiance, features, bandwidth, center) -> list[Tensor]:
    return _prepare({"radiance": radiance, "features": features, "bandwidth": bandwidth,
                     "center": center}, temporal=False)


def _temporal(radiance, features, bandwidth, center, prev_output, prev_features,
              temporal_bandwidth, temporal_on) -> list[Tensor]:
    return _prepare({"radiance": radiance, "features": features, "bandwidth": bandwidth,
                     "center": center, "prev_output": prev_output,
                     "prev_features": prev_features, "temporal_bandwidth": temporal_bandwidth,
                     "temporal_on": temporal_on}, temporal=True)


def spatial_forward(radiance: Tensor, features: Tensor, bandwidth: Tensor, center: Tensor,
                    kernel_size: int, dilation: int, eps: float,
                    threads: int | None = None) -> Tensor:
    """eq. 4 + 6, as ai.quietframe::AffinityFilter computes it."""
    tensors = _spatial(radiance, features, bandwidth, center)
    return _forward(tensors, _args(tensors, kernel_size, dilation, 0, eps, threads))


def spatial_backward(grad: Tensor, radiance: Tensor, features: Tensor, bandwidth: Tensor,
                     center: Tensor, kernel_size: int, dilation: int, eps: float,
                     threads: int | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """∂ℓ/∂(radiance, features, bandwidth, center) of spatial_forward for ∂ℓ/∂output = grad."""
    tensors = _spatial(radiance, features, bandwidth, center)
    return _backward(grad, tensors, _args(tensors, kernel_size, dilation, 0, eps, threads))


def temporal_forward(radiance: Tensor, features: Tensor, bandwidth: Tensor, center: Tensor,
                     prev_output: Tensor, prev_features: Tensor, temporal_bandwidth: Tensor,
                     temporal_on: Tensor, kernel_size: int, dilation: int,
                     temporal_kernel_size: int, eps: float,
                     threads: int | None = None) -> Tensor:
    """eq. 7 + 8, as ai.quietframe::AffinityTemporalFilter computes it."""
    tensors = _temporal(radiance, features, bandwidth, center, prev_output, prev_features,
                        temporal_bandwidth, temporal_on)
    size = _size("temporal_kernel_size", temporal_kernel_size)
    return _forward(tensors, _args(tensors, kernel_size, dilation, size, eps, threads))


def temporal_backward(grad: Tensor, radiance: Tensor, features: Tensor, bandwidth: Tensor,
                      center: Tensor, prev_output: Tensor, prev_features: Tensor,
                      temporal_bandwidth: Tensor, temporal_on: Tensor, kernel_size: int,
                      dilation: int, temporal_kernel_size: int, eps: float,
                      threads: int | None = None) -> tuple[Tensor, ...]:
    """∂ℓ/∂(radiance, features, bandwidth, center, prev_output, prev_features,
    temporal_bandwidth) of temporal_forward for ∂ℓ/∂output = grad (temporal_on gets none)."""
    tensors = _temporal(radiance, features, bandwidth, center, prev_output, prev_features,
                        temporal_bandwidth, temporal_on)
    size = _size("temporal_kernel_size", temporal_kernel_size)
    return _backward(grad, tensors, _args(tensors, kernel_size, dilation, size, eps, threads))
