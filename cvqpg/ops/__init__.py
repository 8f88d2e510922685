"""Operations with fast kernels: each a package holding its PyTorch reference (`reference.py`), its CPU
kernels (`cpu.py`, Numba) and its GPU kernels (`gpu.py`, Triton) side by side, under the same names.

| op (package)  | public functions                                       | reference.py | cpu.py | gpu.py |
|---------------|--------------------------------------------------------|--------------|--------|--------|
| `rasterize`   | `rasterize`                                            | yes          | yes    | yes    |
| `field`       | `guarded_field`, `clamped_intensity`                   | yes          | yes    | —      |
| `propagation` | `propagate_planes`, `propagate_content`                | yes          | yes    | —      |
| `loss`        | `multiplane_loss`, `ssim_per_plane`, `standard_normal` | yes          | yes    | —      |

A package's `__init__` holds its public op and the autograd boundaries around the kernels; the tests
hold every kernel against its reference. One backend name picks all of them (`resolve_backend`):
`numba` (CPU kernels), `triton` (the GPU rasterizer; the other ops use their references there), or
`torch` (the references everywhere); `auto` is `numba` on the CPU and `triton` on CUDA.

`cpu.py` here holds what the ops' CPU kernels share; `kernel_cache` keys Numba's disk cache of all of
them on all their sources.
"""

from __future__ import annotations

import functools
import importlib.util
import os

import numpy as np
import torch
from torch import Tensor

from ..errors import ConfigError, choices_error
from . import kernel_cache

kernel_cache.register()  # before any kernel module defines its functions

BACKEND_NAMES = ("numba", "torch", "triton")


def cpu_array(tensor: Tensor) -> np.ndarray:
    """A tensor's values as a contiguous NumPy array on the CPU (no gradient), for the Numba kernels."""
    return tensor.detach().cpu().contiguous().numpy()


@functools.cache
def triton_installed() -> bool:
    """Whether the triton package is importable (CUDA builds of torch ship it)."""
    return importlib.util.find_spec("triton") is not None


def triton_interpreting() -> bool:
    """Whether Triton runs its kernels on the CPU through its interpreter (`TRITON_INTERPRET=1`, for tests)."""
    return os.environ.get("TRITON_INTERPRET") == "1"


def resolve_backend(backend: str, device: torch.device | str) -> str:
    """`auto` → the Numba kernels on the CPU, the Triton kernels on CUDA where Triton is installed,
    the PyTorch reference elsewhere."""
    kind = torch.device(device).type
    if backend == "auto":
        if kind == "cpu":
            return "numba"
        return "triton" if kind == "cuda" and triton_installed() else "torch"
    if backend not in BACKEND_NAMES:
        raise choices_error("backend", backend, ("auto", *BACKEND_NAMES))
    if backend == "numba" and kind != "cpu":
        raise ConfigError("`backend` numba runs on the CPU; use `backend` torch (or auto) with `device` cuda")
    if backend == "triton" and not triton_installed():
        raise ConfigError("`backend` triton needs the triton package: pip install triton, or use `backend` torch")
    if backend == "triton" and kind != "cuda" and not (kind == "cpu" and triton_interpreting()):
        raise ConfigError(f"`backend` triton runs on CUDA, not on {kind}; use `backend` numba or torch "
                          "with `device` cpu")
    return backend
