"""The shown field's CPU kernels (Numba), with its gradient (method.md §8).

PyTorch shows a hologram on a phase-only display in some twenty passes over the hologram (the clamped field,
its magnitude and angle, the offset, the checkerboard, the wrap, the quantiser, the table look-up, the polar
form, the copy into the padded array) and as many again for the gradient, many of them complex; each kernel
here is one pass, each thread owning whole rows. The forward pass guesses a row's uniform gray levels in a
vectorised loop and takes the libm path (`_shown_level`) only where a phase lies near a boundary between two
levels, so that its levels are that path's; it keeps each pixel's level, so that the backward pass needs no
arctangent, arccosine or level search of its own, and both look up each level's field e^{iθ} in a table rather
than take a cosine and a sine per pixel.
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


# atan(t) ≈ t·P(t²) on [0, 1], P of degree 8: least squares on Chebyshev nodes, within 7e-9 rad (the tests check it).
ARCTANGENT_COEFFICIENTS = (0.9999999055457105, -0.333326578525958, 0.19986537489138684, -0.1416433337508705,
                           0.10507319786920057, -0.07247950662104494, 0.03989956003880088, -0.014458697067324444,
                           0.002468246624679835)
# How near a phase may come to the boundary between two gray levels (in levels, per level of the display) before
# the exact path decides its level. The exact path's float32 phase is off the true one by its libm calls (an
# arctangent and an arccosine, a few ulp each) and four roundings: by at most 4e-7 of a level per level (1e-4 at 256
# levels). The guess, in float64 (`_arctangent`), is off by less than 3e-9 per level. 2e-5 is 50 times their sum;
# 1% of the phases take the exact path at 256 levels, all of them from 25 000 levels on.
LEVEL_MARGIN = 2e-5


@nb.njit(inline="always", error_model="numpy", **CALLED_BY_KERNELS_ONLY)
def _arctangent(y, x):
    """atan2(y, x) (rad, float64) to within 7e-9 rad, as a polynomial and selects that LLVM vectorises; NaN where
    x = y = 0 or both are infinite."""
    c0, c1, c2, c3, c4, c5, c6, c7, c8 = ARCTANGENT_COEFFICIENTS
    along, across = abs(x), abs(y)
    t = min(along, across) / max(along, across)
    z = t * t
    angle = t * (c0 + z * (c1 + z * (c2 + z * (c3 + z * (c4 + z * (c5 + z * (c6 + z * (c7 + z * c8))))))))
    angle = 0.5 * math.pi - angle if across > along else angle
    angle = math.pi - angle if x < 0 else angle
    return -angle if y < 0 else angle


@nb.njit(inline="always", error_model="numpy", **CALLED_BY_KERNELS_ONLY)
def _guessed_levels(source, plus_first, dpac, levels, margin, out):
    """out[x] = the uniform gray level that `_shown_level` gives source[x], or −1 where the phase, computed in
    float64 without libm (`_arctangent`; arccos(A) as atan2(√(1 − A²), A)), lies within `margin` levels of a
    boundary between two levels, where only the exact path can tell (or is not finite). DPAC's + on odd x when
    `plus_first` is false, on even x when true."""
    scale = levels / float(np.float32(TWO_PI))  # the exact path divides by 2π in float32
    for x in range(source.shape[0]):
        h = source[x]
        magnitude = math.sqrt(h.real * h.real + h.imag * h.imag)
        theta = _arctangent(float(h.imag), float(h.real))
        if dpac:
            amplitude = min(float(magnitude), 1.0)
            offset = _arctangent(math.sqrt((1.0 - amplitude) * (1.0 + amplitude)), amplitude)
            theta = theta + offset if (x % 2 == 1) != plus_first else theta - offset
        position = theta * scale
        nearest = np.rint(position)
        sure = abs(position - nearest) < 0.5 - margin and magnitude < np.inf
        out[x] = int(nearest - levels * np.floor(nearest / levels)) if sure else -1


@nb.njit(cache=True, error_model="numpy")
def level_fields(phases, out):
    """out[g] = e^{iφ_g} (complex64) of each gray level's phase φ_g (rad, float32): the field a pixel at that
    level shows, looked up by the kernels instead of a cosine and a sine per pixel."""
    for gray in range(phases.shape[0]):
        out[gray] = complex(math.cos(phases[gray]), math.sin(phases[gray]))


@nb.njit(parallel=True, cache=True, error_model="numpy")
def shown_field(hologram, dpac, levels, uniform, margin, fields, ordered, order, top, left, canvas, background, out,
                grays):
    """out [C, P_H, P_W] = `fields`[g] (`level_fields`) at the gray level g that a phase-only display shows for
    h[c, y, x] at out[c, top + y, left + x] (`_shown_level`; DPAC's + on pixels where y + x is odd), `background`
    on the rest of the `canvas` (its top, left, height and width in `out`), 0 beyond; grays[c, y, x] = g for the
    backward pass. Each row is written whole, so `out` need not be zeroed first. With uniform levels, a row's levels
    are guessed first (`_guessed_levels`, vectorised), and only the phases within `margin` levels of a boundary
    (`LEVEL_MARGIN` per level; 0.5 or more: all of them) take `_shown_level`'s libm path: the same levels either
    way."""
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
        guessed = np.empty(width, dtype=np.int32)
        if uniform and margin < 0.5:
            _guessed_levels(source, (y - top) % 2 == 1, dpac, levels, margin, guessed)
        else:
            guessed[:] = -1
        for x in range(width):
            level = guessed[x]
            if level < 0:
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
