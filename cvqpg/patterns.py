"""The patterns a display is sent and the field it shows (method.md §8): the checkerboard of double-phase
amplitude coding (DPAC), the bare phase, the SLM's phase levels or lookup table with a straight-through gradient,
and the SLM's canvas, for a `cvqpg.display.Display`. Gradients are defined on purpose where the encoding has
none (method.md §8)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .display import DPAC_SLOPE_AMPLITUDE, PHASE_ENCODINGS, TWO_PI, Display, Encoding
from .errors import choices_error


def checkerboard(height: int, width: int, device: torch.device | str = "cpu") -> Tensor:
    """Bool [H, W], true where row + column is odd."""
    rows = torch.arange(height, device=device)[:, None]
    cols = torch.arange(width, device=device)[None, :]
    return (rows + cols) % 2 == 1


class _DpacOffset(torch.autograd.Function):
    """arccos(A) of amplitudes A ∈ [0, 1], whose slope is held at its value at `DPAC_SLOPE_AMPLITUDE` above it."""

    @staticmethod
    def forward(ctx, amplitude: Tensor) -> Tensor:
        ctx.save_for_backward(amplitude)
        return torch.arccos(amplitude.clamp(0.0, 1.0))

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        (amplitude,) = ctx.saved_tensors
        held = amplitude.clamp(0.0, DPAC_SLOPE_AMPLITUDE)
        return -grad * torch.rsqrt(1 - held * held)


def dpac_offset(amplitude: Tensor) -> Tensor:
    """The double-phase offset arccos(A) (rad) of amplitudes in [0, 1], differentiable everywhere: where A nears
    1 its slope −1/√(1 − A²) grows without bound, so above `DPAC_SLOPE_AMPLITUDE` it keeps its value there."""
    return _DpacOffset.apply(amplitude)


def double_phase(field: Tensor) -> Tensor:
    """DPAC of a field [C, H, W] with |field| ≤ 1: phase φ ± arccos(A) on the two checkerboard halves (rad, in
    [0, 2π)). Each pair of neighbours averages to A·e^{iφ}. The gradient through the wrap at 2π is 1."""
    offset = dpac_offset(field.abs())
    phase = field.angle()
    odd = checkerboard(field.shape[-2], field.shape[-1], field.device)
    return torch.remainder(torch.where(odd, phase + offset, phase - offset), TWO_PI)


def encode(field: Tensor, encoding: Encoding) -> Tensor:
    """Phase-only pattern (rad, [0, 2π)) of a field [C, H, W]: DPAC, or its bare phase (amplitude dropped)."""
    if encoding == "dpac":
        return double_phase(field)
    if encoding == "phase":
        return torch.remainder(field.angle(), TWO_PI)
    raise choices_error("encoding", encoding, PHASE_ENCODINGS)


def level_phases(display: Display, device: torch.device | str = "cpu") -> Tensor:
    """The phase (rad, float32) each gray level shows [levels]: the lookup table, else 2πg/levels."""
    if display.lut is not None:
        return torch.tensor(display.lut, dtype=torch.float32, device=device)
    return torch.arange(display.levels, device=device, dtype=torch.float32) * (TWO_PI / display.levels)


def quantise(phase: Tensor, display: Display) -> Tensor:
    """Gray levels (int64) of phases (rad): the level whose phase lies nearest on the circle. With uniform levels
    g ↔ 2πg/levels, rounding and wrapping at 2π; with a lookup table, the nearest of its phases modulo 2π."""
    if display.lut is None:
        return torch.remainder(torch.round(phase / TWO_PI * display.levels), display.levels).to(torch.int64)
    table = torch.remainder(level_phases(display, phase.device).double(), TWO_PI)
    ordered, order = torch.sort(table)
    wrapped = torch.remainder(phase.detach().double(), TWO_PI)
    above = torch.searchsorted(ordered, wrapped).remainder(len(ordered))
    below = (above - 1).remainder(len(ordered))

    def distance(index: Tensor) -> Tensor:
        gap = torch.remainder(wrapped - ordered[index], TWO_PI)
        return torch.minimum(gap, TWO_PI - gap)

    return order[torch.where(distance(below) <= distance(above), below, above)]


class _StraightThrough(torch.autograd.Function):
    """The value of `shown`, exactly, with the gradient of `phase`: the identity."""

    @staticmethod
    def forward(ctx, phase: Tensor, shown: Tensor) -> Tensor:
        return shown

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:
        return grad, None


def shown_phase(phase: Tensor, display: Display) -> tuple[Tensor, Tensor]:
    """The gray levels of phases [..] (rad) and the phases they show, whose gradient is the identity (the
    straight-through rule: the quantiser's own derivative is 0 almost everywhere)."""
    gray = quantise(phase, display)
    return gray, _StraightThrough.apply(phase, level_phases(display, phase.device)[gray])


def canvas_offset(canvas: tuple[int, int], pattern: tuple[int, int]) -> tuple[int, int]:
    """(top, left) px of a (H, W) pattern centred on a (H, W) canvas."""
    return (canvas[0] - pattern[0]) // 2, (canvas[1] - pattern[1]) // 2


def place_on_canvas(pattern: Tensor, canvas: tuple[int, int], fill: float | complex = 0.0) -> Tensor:
    """[C, H, W] → [C, canvas H, canvas W]: centred, the rest of the canvas at `fill` (differentiable)."""
    channels, height, width = pattern.shape
    if canvas == (height, width):
        return pattern
    top, left = canvas_offset(canvas, (height, width))
    placed = pattern.new_full((channels, *canvas), fill)
    placed[:, top:top + height, left:left + width] = pattern
    return placed


@dataclass
class PhasePattern:
    """A phase-only pattern on an SLM canvas, per colour channel: what the SLM is sent."""

    gray: Tensor  # [C, canvas H, canvas W] int64 levels
    phase_rad: Tensor  # [C, canvas H, canvas W] the unquantised phase on the canvas (rad)
    shown_rad: Tensor  # [C, canvas H, canvas W] the phase the gray levels show (rad), with straight-through gradient

    @property
    def field(self) -> Tensor:
        """e^{iθ} of the shown phase θ: the field the SLM shows under unit illumination."""
        return torch.polar(torch.ones_like(self.shown_rad), self.shown_rad)


def phase_pattern(field: Tensor, display: Display) -> PhasePattern:
    """The phase-only pattern that a phase-only `display` is sent for an SLM field [C, H, W] (|field| ≤ 1): its
    encoding, placed on the canvas (the rest at gray level 0), quantised to the display's levels."""
    canvas = display.canvas_for(field.shape[-2], field.shape[-1])
    phase = place_on_canvas(encode(field, display.encoding), canvas)
    gray, shown = shown_phase(phase, display)
    if canvas != tuple(field.shape[-2:]):  # the canvas beyond the hologram shows gray level 0
        top, left = canvas_offset(canvas, tuple(field.shape[-2:]))
        inside = torch.zeros(canvas, dtype=torch.bool, device=field.device)
        inside[top:top + field.shape[-2], left:left + field.shape[-1]] = True
        gray = torch.where(inside, gray, 0)
        shown = torch.where(inside, shown, level_phases(display, field.device)[0])
    return PhasePattern(gray, phase, shown)


def displayed_field(field: Tensor, display: Display) -> Tensor:
    """The complex field [C, canvas H, canvas W] that `display` shows for an SLM field [C, H, W] (|field| ≤ 1):
    the phase-only pattern's e^{iθ}, or the complex field itself, on the canvas (the complex one dark beyond the
    hologram). Differentiable (`phase_pattern`)."""
    if display.phase_only:
        return phase_pattern(field, display).field
    return place_on_canvas(field, display.canvas_for(field.shape[-2], field.shape[-1]))
