"""The shown field's CPU kernels (Numba), with its gradient (method.md §8).

PyTorch shows a hologram on a phase-only display in some twenty passes over the hologram (the clamped field,
its magnitude and angle, the offset, the checkerboard, the wrap, the quantiser, the table look-up, the polar
form, the copy into the padded array) and as many again for the gradient, many of them complex; each kernel
here is one pass, each thread owning whole rows, recomputing in the backward pass what the forward one found.
`reference` holds the PyTorch formulas, which serve CUDA and `--backend torch`; the tests hold these kernels
against them.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..cpu import CALLED_BY_KERNELS_ONLY

TWO_PI = 2 * math.pi


@nb.njit(inline="always", error_model="numpy", **CALLED_BY_KERNELS_ONLY)
def _level(theta, levels, uniform, ordered, order):
    """The gray level of a phase θ ∈ [0, 2π) (rad): round(θ·L/2π) mod L, or the lookup table's phase nearest on
    the circle (`ordered`, its phases modulo 2π in float64, sorted; `order`, their gray levels)."""
    if uniform:
        return int(np.rint(theta / np.float32(TWO_PI) * np.float32(levels))) % levels
    wrapped = float(theta) % TWO_PI
    count = ordered.shape[0]
    above = np.searchsorted(ordered, wrapped) % count
    below = (above - 1) % count
    gap_below = (wrapped - ordered[below]) % TWO_PI
    gap_above = (wrapped - ordered[above]) % TWO_PI
    if min(gap_below, TWO_PI - gap_below) <= min(gap_above, TWO_PI - gap_above):
        return order[below]
    return order[above]


@nb.njit(inline="always", error_model="numpy", **CALLED_BY_KERNELS_ONLY)
def _shown_phase(h, plus, dpac, levels, uniform, phases, ordered, order):
    """The phase (rad) shown for a hologram value h: the clamped field's angle φ, ± arccos(A) for DPAC (+ on
    `plus` pixels), wrapped to [0, 2π), at its gray level's phase (`phases`); and its amplitude |h|."""
    magnitude = math.sqrt(h.real * h.real + h.imag * h.imag)
    theta = math.atan2(h.imag, h.real)
    if dpac:
        offset = math.acos(min(magnitude, np.float32(1.0)))
        theta = theta + offset if plus else theta - offset
    theta = theta % np.float32(TWO_PI)
    return phases[_level(np.float32(theta), levels, uniform, ordered, order)], magnitude


@nb.njit(parallel=True, cache=True, error_model="numpy")
def shown_field(hologram, dpac, levels, uniform, phases, ordered, order, top, left, out):
    """out[c, top + y, left + x] = e^{iθ} of the phase a phase-only display shows for h[c, y, x] (`_shown_phase`;
    DPAC's + on pixels where y + x is odd); the rest of `out` is left as it is."""
    channels, height, width = hologram.shape
    for row in nb.prange(channels * height):
        channel, y = row // height, row % height
        source, target = hologram[channel, y], out[channel, top + y, left:left + width]
        for x in range(width):
            theta, _ = _shown_phase(source[x], (y + x) % 2 == 1, dpac, levels, uniform, phases, ordered, order)
            target[x] = complex(math.cos(theta), math.sin(theta))


@nb.njit(parallel=True, cache=True, error_model="numpy")
def shown_field_backward(hologram, grad, dpac, levels, uniform, phases, ordered, order, slope_amplitude, top, left,
                         out):
    """Gradient [C, H, W] for the hologram from the shown field's [C, P_H, P_W]: the phase's gradient
    g_θ = Im(ū·g) passed straight through the quantiser; to the angle φ as it is, and for DPAC to the amplitude
    as ∓g_θ/√(1 − A²) (A held at `slope_amplitude` above it; none where |h| ≥ 1, where the field is clamped);
    to h as (g_A·|h| + i·g_θ)·h/|h|² (0 at h = 0)."""
    channels, height, width = hologram.shape
    for row in nb.prange(channels * height):
        channel, y = row // height, row % height
        source, incoming, target = hologram[channel, y], grad[channel, top + y, left:left + width], out[channel, y]
        for x in range(width):
            h, g = source[x], incoming[x]
            plus = (y + x) % 2 == 1
            theta, magnitude = _shown_phase(h, plus, dpac, levels, uniform, phases, ordered, order)
            cosine, sine = math.cos(theta), math.sin(theta)
            grad_theta = cosine * g.imag - sine * g.real
            grad_amplitude = 0.0
            if dpac and magnitude < 1.0:
                held = min(magnitude, slope_amplitude)
                grad_amplitude = grad_theta / math.sqrt(1.0 - held * held)
                grad_amplitude = -grad_amplitude if plus else grad_amplitude
            magnitude2 = magnitude * magnitude
            if magnitude2 > 0.0:
                scale_real, scale_imag = grad_amplitude * magnitude / magnitude2, grad_theta / magnitude2
                target[x] = complex(scale_real * h.real - scale_imag * h.imag, scale_real * h.imag + scale_imag * h.real)
            else:
                target[x] = 0j
