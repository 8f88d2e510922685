"""Operations with fast kernels: each a package holding its PyTorch reference (`reference.py`), its CPU
kernels (`cpu.py`, Numba) and its GPU kernels (`gpu.py`, Triton) side by side, under the same names.

| op (package)  | public functions                                       | reference.py | cpu.py | gpu.py |
|---------------|--------------------------------------------------------|--------------|--------|--------|
| `rasterize`   | `rasterize`                                            | yes          | yes    | yes    |
| `field`       | `guarded_field`, `clamped_intensity`                   | yes          | yes    | —      |
| `display`     | `shown_field`                                          | yes          | yes    | —      |
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

import numpy as np
from torch import Tensor

from ..config import BACKEND_NAMES, resolve_backend, triton_installed, triton_interpreting
from . import kernel_cache

kernel_cache.register()  # before any kernel module defines its functions


def cpu_array(tensor: Tensor) -> np.ndarray:
    """A tensor's values as a contiguous NumPy array on the CPU (no gradient), for the Numba kernels."""
    return tensor.detach().cpu().contiguous().numpy()


__all__ = ["BACKEND_NAMES", "cpu_array", "resolve_backend", "triton_installed", "triton_interpreting"]
