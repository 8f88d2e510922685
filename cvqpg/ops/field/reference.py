"""The SLM field's and the clamped intensity's PyTorch reference (method.md §3): the guard band, its
window, the clamped amplitude, and the intensity of a propagated field."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ...config import FitConfig, padded_size


@dataclass(frozen=True)
class Grid:
    """Geometry of the SLM content (H×W px) inside its guard-banded array (P_H×P_W px)."""

    height: int
    width: int
    padded_height: int
    padded_width: int

    @classmethod
    def for_config(cls, config: FitConfig) -> "Grid":
        return cls(config.targets.height, config.targets.width,
                   padded_size(config.targets.height, config.optics.guard_band_px, config.optics.pad_multiple_px),
                   padded_size(config.targets.width, config.optics.guard_band_px, config.optics.pad_multiple_px))

    @property
    def top(self) -> int:
        return (self.padded_height - self.height) // 2

    @property
    def left(self) -> int:
        return (self.padded_width - self.width) // 2

    def crop(self, padded: Tensor) -> Tensor:
        """Centre H×W content of a [..., P_H, P_W] array."""
        return padded[..., self.top:self.top + self.height, self.left:self.left + self.width]


def _taper(length: int, start: int, stop: int, device: torch.device) -> Tensor:
    """1 on [start, stop), raised cosine falling to 0 at both array ends across the guard band."""
    index = torch.arange(length, device=device, dtype=torch.float32)
    left_guard, right_guard = max(start, 1), max(length - stop, 1)
    into_left = (start - index) / left_guard
    into_right = (index - stop + 1) / right_guard
    into_guard = torch.clamp(torch.maximum(into_left, into_right), min=0.0)
    return 0.5 * (1 + torch.cos(math.pi * into_guard))


@functools.lru_cache(maxsize=16)
def guard_tapers(grid: Grid, device: torch.device) -> tuple[Tensor, Tensor]:
    """The window's two factors: [P_H] over rows and [P_W] over columns."""
    return (_taper(grid.padded_height, grid.top, grid.top + grid.height, device),
            _taper(grid.padded_width, grid.left, grid.left + grid.width, device))


@functools.lru_cache(maxsize=16)
def guard_window(grid: Grid, device: torch.device) -> Tensor:
    """Separable raised-cosine window [P_H, P_W]: 1 on the content, 0 at the array edge."""
    rows, cols = guard_tapers(grid, device)
    return rows[:, None] * cols[None, :]


def pad_with_guard_band(hologram: Tensor, grid: Grid) -> Tensor:
    """[C, H, W] → [C, P_H, P_W]: edge-replicated guard band (no gradient through it), windowed."""
    device = hologram.device
    rows = torch.clamp(torch.arange(grid.padded_height, device=device) - grid.top, 0, grid.height - 1)
    cols = torch.clamp(torch.arange(grid.padded_width, device=device) - grid.left, 0, grid.width - 1)
    padded = hologram.detach()[:, rows[:, None], cols[None, :]]
    padded[:, grid.top:grid.top + grid.height, grid.left:grid.left + grid.width] = hologram
    return padded * guard_window(grid, device)


def slm_field(padded: Tensor) -> Tensor:
    """`A·e^{iφ}` with `A = clamp(|H|, 0, 1)`, `φ = angle(H)`: written as `H / max(|H|, 1)`.

    The quotient is the same number without atan2/exp and keeps a finite gradient where H = 0.
    """
    return padded / torch.clamp(padded.abs(), min=1.0)


def guarded_field(hologram: Tensor, grid: Grid) -> Tensor:
    """SLM field [C, P_H, P_W] of a hologram [C, H, W]: `slm_field(pad_with_guard_band(hologram, grid))`."""
    return slm_field(pad_with_guard_band(hologram, grid))


def guarded_field_backward(hologram: Tensor, grad: Tensor, grid: Grid) -> Tensor:
    """`guarded_field`'s gradient [C, H, W] from the incoming one [C, P_H, P_W]: the content's alone
    (the guard band carries none, the window is 1 on the content), the identity where |h| < 1 and
    the projection onto the phase direction, `i·h·Im(h̄·g)/|h|³`, where the amplitude saturates."""
    incoming = grid.crop(grad)
    magnitude = hologram.abs()
    normal = (hologram.real * incoming.imag - hologram.imag * incoming.real) / magnitude**3
    projected = torch.complex(-hologram.imag * normal, hologram.real * normal)
    return torch.where(magnitude >= 1.0, projected, incoming)


def clamped_intensity(field: Tensor) -> Tensor:
    """Intensity `clamp(|u|², 0, 1)` of a complex field, as re² + im² (the CPU kernel's sum): the gradient
    of `|u|` is u/|u|, not a number where |u| underflows to 0 but u does not."""
    return torch.clamp(torch.view_as_real(field).square().sum(-1), 0.0, 1.0)
