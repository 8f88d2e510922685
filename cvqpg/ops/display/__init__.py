"""The field a display shows (method.md §8): the public op and its autograd boundary.

| op            | reference.py (PyTorch)   | cpu.py (Numba)                                |
|---------------|--------------------------|-----------------------------------------------|
| `shown_field` | `shown_field` (autograd) | `shown_field`, `shown_field_backward`         |

The backend is the rasterizer's (`cvqpg.ops.resolve_backend`): the Numba kernels with `numba` for the phase-only
displays, the PyTorch formulas otherwise (`torch`, `triton`, and the complex field on a canvas).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from ...display import DPAC_SLOPE_AMPLITUDE, Display
from ...patterns import canvas_offset, level_phases
from .. import cpu_array, resolve_backend
from ..field.reference import Grid
from . import cpu, reference

__all__ = ["shown_field"]


@functools.lru_cache(maxsize=8)
def _tables(display: Display) -> tuple:
    """The kernels' view of the phase levels: whether uniform, the field e^{iθ} each level shows (complex64), and the
    lookup table's phases modulo 2π sorted (float64) with their levels; made once per display."""
    phases = level_phases(display)
    ordered, order = torch.sort(torch.remainder(phases.double(), 2 * torch.pi))
    fields = np.empty(display.levels, dtype=np.complex64)
    cpu.level_fields(phases.numpy(), fields)
    return display.lut is None, fields, ordered.numpy(), order.numpy()


class _FusedShown(torch.autograd.Function):
    """`reference.shown_field` of a phase-only display as one pass each way (`cpu`); the forward pass keeps the
    gray level of each pixel (uint16) for the backward one."""

    @staticmethod
    def forward(ctx, hologram: Tensor, grid: Grid, display: Display) -> Tensor:
        channels, height, width = hologram.shape
        canvas = display.canvas_for(height, width)
        inner_top, inner_left = canvas_offset(canvas, (height, width))
        placed = (grid.top - inner_top, grid.left - inner_left, *canvas)
        background = complex(torch.polar(torch.ones(()), level_phases(display)[0]))  # beyond the hologram: level 0
        uniform, fields, ordered, order = _tables(display)
        out = hologram.new_empty(channels, grid.padded_height, grid.padded_width)
        grays = torch.empty(hologram.shape, dtype=torch.int16)  # read as uint16: up to 2^16 levels
        cpu.shown_field(cpu_array(hologram), display.encoding == "dpac", display.levels, uniform,
                        cpu.LEVEL_MARGIN * display.levels, fields, ordered, order, grid.top, grid.left, placed,
                        background, out.numpy(), grays.numpy().view(np.uint16))
        ctx.save_for_backward(hologram, grays)
        ctx.grid, ctx.display = grid, display
        return out

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None]:
        hologram, grays = ctx.saved_tensors
        grid, display = ctx.grid, ctx.display
        _, fields, _, _ = _tables(display)
        gradient = torch.empty_like(hologram)
        cpu.shown_field_backward(cpu_array(hologram), grays.numpy().view(np.uint16), cpu_array(grad),
                                 display.encoding == "dpac", fields, DPAC_SLOPE_AMPLITUDE, grid.top, grid.left,
                                 gradient.numpy())
        return gradient, None, None


def shown_field(hologram: Tensor, grid: Grid, display: Display, backend: str = "auto") -> Tensor:
    """The field [C, P_H, P_W] that `display` shows for a hologram [C, H, W] in the dark padded array of `grid`
    (the hologram where `grid` crops the planes): its clamped SLM field encoded, quantised and placed on the
    canvas (`cvqpg.display`). `backend` picks the PyTorch formulas or the fused CPU kernels, as it picks the
    rasterizer."""
    if display.phase_only and resolve_backend(backend, hologram.device) == "numba":
        return _FusedShown.apply(hologram, grid, display)
    return reference.shown_field(hologram, grid, display)
