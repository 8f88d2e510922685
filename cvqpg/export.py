"""Phase-only patterns for real SLMs (method.md §8): double-phase amplitude coding, quantisation, the
SLM canvas, and a simulated 4f display that reconstructs the quantised pattern."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from .config import FitConfig, padded_size
from .defaults import DEFAULT_APERTURE, DEFAULT_LEVELS, ENCODINGS
from .errors import ConfigError, choices_error
from .ops.field import Grid, slm_field
from .ops.propagation import propagate_planes

Encoding = Literal["dpac", "phase"]
MAX_LEVELS = 2**16
TWO_PI = 2 * math.pi


def checkerboard(height: int, width: int, device: torch.device | str = "cpu") -> Tensor:
    """Bool [H, W], true where row + column is odd."""
    rows = torch.arange(height, device=device)[:, None]
    cols = torch.arange(width, device=device)[None, :]
    return (rows + cols) % 2 == 1


def double_phase(field: Tensor) -> Tensor:
    """DPAC of a field [C, H, W] with |field| ≤ 1: phase φ ± arccos(A) on the two checkerboard
    halves (rad, in [0, 2π)). Each pair of neighbours averages to A·e^{iφ}."""
    offset = torch.arccos(field.abs().clamp(max=1.0))
    phase = field.angle()
    odd = checkerboard(field.shape[-2], field.shape[-1], field.device)
    return torch.remainder(torch.where(odd, phase + offset, phase - offset), TWO_PI)


def encode(field: Tensor, encoding: Encoding) -> Tensor:
    """Phase-only pattern (rad, [0, 2π)) of a field [C, H, W]: DPAC, or its bare phase (amplitude dropped)."""
    if encoding == "dpac":
        return double_phase(field)
    if encoding == "phase":
        return torch.remainder(field.angle(), TWO_PI)
    raise choices_error("encoding", encoding, ENCODINGS)


def quantise(phase: Tensor, levels: int = DEFAULT_LEVELS) -> Tensor:
    """Gray levels g ∈ {0, …, levels−1} (int64) with g ↔ phase 2πg/levels, nearest level, wrapping at 2π."""
    if not 2 <= levels <= MAX_LEVELS:
        raise ConfigError(f"`levels` {levels}: an SLM has between 2 and {MAX_LEVELS} phase levels")
    return torch.remainder(torch.round(phase / TWO_PI * levels), levels).to(torch.int64)


def dequantise(gray: Tensor, levels: int = DEFAULT_LEVELS) -> Tensor:
    """Phase (rad) of gray levels: 2πg/levels."""
    return gray.to(torch.float32) * (TWO_PI / levels)


def canvas_offset(canvas: tuple[int, int], pattern: tuple[int, int]) -> tuple[int, int]:
    """(top, left) px of a (H, W) pattern centred on a (H, W) canvas."""
    return (canvas[0] - pattern[0]) // 2, (canvas[1] - pattern[1]) // 2


def place_on_canvas(pattern: Tensor, canvas_width: int, canvas_height: int) -> Tensor:
    """[C, H, W] → [C, canvas_height, canvas_width]: centred, the rest of the canvas at 0."""
    channels, height, width = pattern.shape
    if canvas_width < width or canvas_height < height:
        raise ConfigError(f"`slm` {canvas_width}×{canvas_height} is smaller than the {width}×{height} hologram; "
                          "give an SLM at least that large")
    top, left = canvas_offset((canvas_height, canvas_width), (height, width))
    canvas = pattern.new_zeros(channels, canvas_height, canvas_width)
    canvas[:, top:top + height, left:left + width] = pattern
    return canvas


def fourier_aperture(rows: int, cols: int, radius: float, device: torch.device | str = "cpu") -> Tensor:
    """Circular pass band [rows, cols] in FFT order: spatial frequency ≤ radius × Nyquist (0.5 cycles/px)."""
    fy = torch.fft.fftfreq(rows, device=device)[:, None]
    fx = torch.fft.fftfreq(cols, device=device)[None, :]
    return (fx**2 + fy**2 <= (0.5 * radius) ** 2).to(torch.complex64)


@dataclass(frozen=True)
class Display:
    """A simulated SLM: a canvas of `canvas` (H, W) px lit only on itself, behind a 4f system whose
    circular Fourier aperture passes `aperture` × Nyquist (None: no filter)."""

    canvas: tuple[int, int]
    aperture: float | None = DEFAULT_APERTURE


def simulate_display(canvas_field: Tensor, display: Display, config: FitConfig, backend: str = "auto") -> Tensor:
    """Intensity [M, C, H, W] at `config`'s planes of a field [C, canvas H, canvas W] shown on `display`.

    The canvas sits in a zero-padded array (no light beyond the SLM), the 4f aperture filters its
    spectrum, and the hologram's W×H region of each propagated plane is returned, clamped to [0, 1], propagated
    with the kernels of `backend`.
    """
    canvas_h, canvas_w = display.canvas
    grid = Grid(config.targets.height, config.targets.width,
                padded_size(canvas_h, config.optics.guard_band_px, config.optics.pad_multiple_px),
                padded_size(canvas_w, config.optics.guard_band_px, config.optics.pad_multiple_px))
    inner_top, inner_left = canvas_offset(display.canvas, (config.targets.height, config.targets.width))
    top, left = grid.top - inner_top, grid.left - inner_left
    padded = canvas_field.new_zeros(canvas_field.shape[0], grid.padded_height, grid.padded_width)
    padded[:, top:top + canvas_h, left:left + canvas_w] = canvas_field
    if display.aperture is not None:
        aperture = fourier_aperture(grid.padded_height, grid.padded_width, display.aperture, padded.device)
        padded = torch.fft.ifft2(torch.fft.fft2(padded) * aperture)
    planes = propagate_planes(padded, grid, config.plane_distances, config.wavelengths, config.optics.pixel_pitch,
                              backend)
    return torch.clamp(planes.abs() ** 2, 0.0, 1.0)


@dataclass
class PhasePattern:
    """A quantised phase-only pattern on an SLM canvas, per colour channel."""

    gray: Tensor  # [C, canvas H, canvas W] int64 levels
    phase_rad: Tensor  # [C, canvas H, canvas W] the unquantised phase on the canvas
    levels: int

    @property
    def displayed_field(self) -> Tensor:
        """e^{i·2πg/levels}: the field of the quantised pattern under unit illumination."""
        return torch.polar(torch.ones_like(self.phase_rad), dequantise(self.gray, self.levels))


def phase_pattern(hologram: Tensor, encoding: Encoding, levels: int, canvas: tuple[int, int]) -> PhasePattern:
    """Encode a hologram [C, H, W] as a phase-only pattern on a (H, W) canvas (rest at phase 0).

    The encoded field is what the fit's propagation sees on the SLM, `clamp(|H|, 0, 1)·e^{i∠H}`.
    """
    phase = place_on_canvas(encode(slm_field(hologram), encoding), canvas[1], canvas[0])
    return PhasePattern(quantise(phase, levels), phase, levels)
