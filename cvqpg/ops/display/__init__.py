"""The field a display shows (method.md §8): the public op and its autograd boundary.

| op            | reference.py (PyTorch)   | cpu.py (Numba)                                |
|---------------|--------------------------|-----------------------------------------------|
| `shown_field` | `shown_field` (autograd) | `shown_field`, `shown_field_backward`         |

The backend is the rasterizer's (`cvqpg.ops.resolve_backend`): the Numba kernels with `numba` for the phase-only
displays, the PyTorch formulas otherwise (`torch`, `triton`, and the complex field on a canvas).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...display import DPAC_SLOPE_AMPLITUDE, Display
from ...patterns import canvas_offset, level_phases
from .. import cpu_array, resolve_backend
from ..field.reference import Grid
from . import cpu, reference

__all__ = ["shown_field"]


def _tables(display: Display) -> tuple:
    """The kernels' view of the phase levels: whether uniform, the phase of each level (float32), and the lookup
    table's phases modulo 2π sorted (float64) with their levels."""
    phases = level_phases(display)
    ordered, order = torch.sort(torch.remainder(phases.double(), 2 * torch.pi))
    return display.lut is None, phases.numpy(), ordered.numpy(), order.numpy()


class _FusedShown(torch.autograd.Function):
    """`reference.shown_field` of a phase-only display as one pass each way (`cpu`)."""

    @staticmethod
    def forward(ctx, hologram: Tensor, grid: Grid, display: Display) -> Tensor:
        ctx.save_for_backward(hologram)
        ctx.grid, ctx.display = grid, display
        channels, height, width = hologram.shape
        canvas = display.canvas_for(height, width)
        out = hologram.new_zeros(channels, grid.padded_height, grid.padded_width)
        inner_top, inner_left = canvas_offset(canvas, (height, width))
        if canvas != (height, width):  # the canvas beyond the hologram shows gray level 0
            top, left = grid.top - inner_top, grid.left - inner_left
            out[:, top:top + canvas[0], left:left + canvas[1]] = torch.polar(torch.ones(()), level_phases(display)[0])
        uniform, phases, ordered, order = _tables(display)
        cpu.shown_field(cpu_array(hologram), display.encoding == "dpac", display.levels, uniform, phases, ordered,
                        order, grid.top, grid.left, out.numpy())
        return out

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None]:
        (hologram,) = ctx.saved_tensors
        grid, display = ctx.grid, ctx.display
        uniform, phases, ordered, order = _tables(display)
        gradient = torch.empty_like(hologram)
        cpu.shown_field_backward(cpu_array(hologram), cpu_array(grad), display.encoding == "dpac", display.levels,
                                 uniform, phases, ordered, order, DPAC_SLOPE_AMPLITUDE, grid.top, grid.left,
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
