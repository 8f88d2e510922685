"""The SLM field and the clamped intensity (method.md §3): the public ops and their autograd boundaries.

| op                  | reference.py (PyTorch)                    | cpu.py (Numba)                                    |
|---------------------|-------------------------------------------|---------------------------------------------------|
| `guarded_field`     | `guarded_field`, `guarded_field_backward` | `guarded_field`, `guarded_field_backward`         |
| `clamped_intensity` | `clamped_intensity` (autograd)            | `clamped_intensity`, `clamped_intensity_backward` |

The backend is the rasterizer's (`cvqpg.ops.resolve_backend`): the Numba kernels with `numba`, the
PyTorch formulas otherwise (`torch`, and `triton` on CUDA, where no fused kernel exists yet).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .. import cpu_array, resolve_backend
from . import cpu, reference
from .reference import Grid, guard_tapers, guard_window, pad_with_guard_band, slm_field

__all__ = ["Grid", "clamped_intensity", "guard_tapers", "guard_window", "guarded_field", "pad_with_guard_band",
           "slm_field"]


class _GuardedField(torch.autograd.Function):
    """`reference.guarded_field` with a backward over the content alone (`reference.guarded_field_backward`):
    autograd through the composition would run its backward over the whole padded array, in several
    passes. `fused` runs both directions as the one-pass CPU kernels."""

    @staticmethod
    def forward(ctx, hologram: Tensor, grid: Grid, fused: bool) -> Tensor:
        ctx.save_for_backward(hologram)
        ctx.grid, ctx.fused = grid, fused
        if not fused:
            return reference.guarded_field(hologram, grid)
        rows, cols = guard_tapers(grid, hologram.device)
        field = hologram.new_empty(hologram.shape[0], grid.padded_height, grid.padded_width)
        cpu.guarded_field(cpu_array(hologram), rows.numpy(), cols.numpy(), grid.top, grid.left, field.numpy())
        return field

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None]:
        (hologram,) = ctx.saved_tensors
        grid = ctx.grid
        if not ctx.fused:
            return reference.guarded_field_backward(hologram, grad, grid), None, None
        gradient = torch.empty_like(hologram)
        cpu.guarded_field_backward(cpu_array(hologram), cpu_array(grad), grid.top, grid.left, gradient.numpy())
        return gradient, None, None


def guarded_field(hologram: Tensor, grid: Grid, backend: str = "auto") -> Tensor:
    """SLM field [C, P_H, P_W] of a hologram [C, H, W]: guard band, window and clamped amplitude (method.md §3).

    `backend` picks the PyTorch formulas or the fused CPU kernels, as it picks the rasterizer.
    """
    return _GuardedField.apply(hologram, grid, resolve_backend(backend, hologram.device) == "numba")


class _FusedIntensity(torch.autograd.Function):
    """`clamp(|u|², 0, 1)` of a complex array and its gradient `2·u·g` (where |u|² ≤ 1), one pass each."""

    @staticmethod
    def forward(ctx, field: Tensor) -> Tensor:
        ctx.save_for_backward(field)
        intensity = torch.empty(field.shape, dtype=field.real.dtype)
        width = field.shape[-1]
        cpu.clamped_intensity(cpu_array(field).reshape(-1, width), intensity.numpy().reshape(-1, width))
        return intensity

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        (field,) = ctx.saved_tensors
        gradient = torch.empty_like(field)
        width = field.shape[-1]
        cpu.clamped_intensity_backward(cpu_array(field).reshape(-1, width), cpu_array(grad).reshape(-1, width),
                                       gradient.numpy().reshape(-1, width))
        return gradient


def clamped_intensity(field: Tensor, backend: str = "auto") -> Tensor:
    """Intensity `clamp(|u|², 0, 1)` of a complex field (method.md §3), through the backend's formulas."""
    if resolve_backend(backend, field.device) == "numba":
        return _FusedIntensity.apply(field)
    return reference.clamped_intensity(field)
