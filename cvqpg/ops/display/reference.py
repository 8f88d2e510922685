"""The shown field's PyTorch reference (method.md §8): a hologram's clamped SLM field shown on a display
(`cvqpg.display`: its encoding, phase levels and canvas) in the dark padded array its propagation takes."""

from __future__ import annotations

from torch import Tensor

from ...display import Display
from ...patterns import canvas_offset, displayed_field
from ..field.reference import Grid, slm_field


def shown_field(hologram: Tensor, grid: Grid, display: Display) -> Tensor:
    """The field [C, P_H, P_W] that `display` shows for a hologram [C, H, W], its canvas placed in the dark array
    so that the hologram lies where `grid` crops the planes (differentiable: `patterns.displayed_field`)."""
    canvas_field = displayed_field(slm_field(hologram), display)
    canvas_h, canvas_w = canvas_field.shape[-2:]
    inner_top, inner_left = canvas_offset((canvas_h, canvas_w), (grid.height, grid.width))
    top, left = grid.top - inner_top, grid.left - inner_left
    padded = canvas_field.new_zeros(canvas_field.shape[0], grid.padded_height, grid.padded_width)
    padded[:, top:top + canvas_h, left:left + canvas_w] = canvas_field
    return padded
