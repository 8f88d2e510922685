"""The shown field's CPU kernels (Numba), with its gradient (method.md §8).

PyTorch shows a hologram on a phase-only display in some twenty passes over the hologram (the clamped field,
its magnitude and angle, the offset, the checkerboard, the wrap, the quantiser, the table look-up, the polar
form, the copy into the padded array) and as many again for the gradient, many of them complex; each kernel
here is one pass, each thread owning whole rows. The forward pass keeps each pixel's gray level, so that the
backward pass needs no arctangent, arccosine or level search of its own, and both look up each level's field
e^{iθ} in a table rather than take a cosine and a sine per pixel.
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
def _wrapped(theta):
    """θ mod 2π (float32) for θ ∈ [−2π, 2π], the angle plus or minus an arccosine: the float32 remainder `%` gives
    (the same gray level; its zero may be −0), without its call to fmodf, which is exact on that interval."""
    full = np.float32(TWO_PI)
    if theta < 0:
        return theta + full
    return theta - full if theta >= full else theta


@nb.njit(inline="always", error_model="numpy", **CALLED_BY_KERNELS_ONLY)
def _shown_level(h, plus, dpac, levels, uniform, ordered, order):
    """The gray level shown for a hologram value h: that of the clamped field's angle φ, ± arccos(A) for DPAC (+ on
    `plus` pixels), wrapped to [0, 2π); and its amplitude |h|."""
    magnitude = math.sqrt(h.real * h.real + h.imag * h.imag)
    theta = math.atan2(h.imag, h.real)
    if dpac:
        offset = math.acos(min(magnitude, np.float32(1.0)))
        theta = theta + offset if plus else theta - offset
    return _level(np.float32(_wrapped(theta)), levels, uniform, ordered, order), magnitude


@nb.njit(cache=True, error_model="numpy")
def level_fields(phases, out):
    """out[g] = e^{iφ_g} (complex64) of each gray level's phase φ_g (rad, float32): the field a pixel at that
    level shows, looked up by the kernels instead of a cosine and a sine per pixel."""
    for gray in range(phases.shape[0]):
        out[gray] = complex(math.cos(phases[gray]), math.sin(phases[gray]))


@nb.njit(parallel=True, cache=True, error_model="numpy")
def shown_field(hologram, dpac, levels, uniform, fields, ordered, order, top, left, canvas, background, out, grays):
    """out [C, P_H, P_W] = `fields`[g] (`level_fields`) at the gray level g that a phase-only display shows for
    h[c, y, x] at out[c, top + y, left + x] (`_shown_level`; DPAC's + on pixels where y + x is odd), `background`
    on the rest of the `canvas` (its top, left, height and width in `out`), 0 beyond; grays[c, y, x] = g for the
    backward pass. Each row is written whole, so `out` need not be zeroed first."""
    channels, height, width = hologram.shape
    padded_height = out.shape[1]
    canvas_top, canvas_left, canvas_height, canvas_width = canvas
    canvas_right = canvas_left + canvas_width
    for row in nb.prange(channels * padded_height):
        channel, y = row // padded_height, row % padded_height
        target = out[channel, y]
        if not canvas_top <= y < canvas_top + canvas_height:
            target[:] = 0
            continue
        target[:canvas_left] = 0
        target[canvas_right:] = 0
        if not top <= y < top + height:
            target[canvas_left:canvas_right] = background
            continue
        target[canvas_left:left] = background
        target[left + width:canvas_right] = background
        source, shown, gray = hologram[channel, y - top], target[left:left + width], grays[channel, y - top]
        for x in range(width):
            level, _ = _shown_level(source[x], (y - top + x) % 2 == 1, dpac, levels, uniform, ordered, order)
            gray[x] = level
            shown[x] = fields[level]


@nb.njit(parallel=True, cache=True, error_model="numpy")
def shown_field_backward(hologram, grays, grad, dpac, fields, slope_amplitude, top, left, out):
    """Gradient [C, H, W] for the hologram from the shown field's [C, P_H, P_W], at the gray levels the forward
    pass showed (`grays`, their fields e^{iθ} in `fields`): the phase's gradient g_θ = Im(ū·g) passed straight
    through the quantiser; to the angle φ as it is, and for DPAC to the amplitude as ∓g_θ/√(1 − A²) (A held at
    `slope_amplitude` above it; none where |h| ≥ 1, where the field is clamped); to h as (g_A·|h| + i·g_θ)·h/|h|²
    (0 at h = 0)."""
    channels, height, width = hologram.shape
    for row in nb.prange(channels * height):
        channel, y = row // height, row % height
        source, incoming, target = hologram[channel, y], grad[channel, top + y, left:left + width], out[channel, y]
        gray = grays[channel, y]
        for x in range(width):
            h, g, shown = source[x], incoming[x], fields[gray[x]]
            plus = (y + x) % 2 == 1
            magnitude = math.sqrt(h.real * h.real + h.imag * h.imag)
            cosine, sine = shown.real, shown.imag
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
