"""Fused CPU kernels (Numba) for the splatting sum and its gradient.

Both passes visit only the pixels inside each primitive's 3σ_major circle and never store anything
of size N × pixels. The forward pass splits the image into bands of rows, one thread per band, each
summing the primitives that reach its rows, so no two threads write the same pixel. The backward
pass gives each thread whole primitives: a primitive's gradient is a sum over its own footprint,
read from the shared output gradient. Arithmetic is float64 inside, float32 in the arrays.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

EXPONENT_FLOOR = -50.0
BAND_ROWS = 8


@nb.njit(cache=True, nogil=True)
def _row_span(center_y: float, reach: float, height: int) -> tuple[int, int]:
    return max(0, math.ceil(center_y - reach)), min(height - 1, math.floor(center_y + reach))


@nb.njit(cache=True, nogil=True)
def _column_span(center_x: float, reach: float, dy: float, width: int) -> tuple[int, int]:
    half = math.sqrt(max(reach * reach - dy * dy, 0.0))
    return max(0, math.ceil(center_x - half)), min(width - 1, math.floor(center_x + half))


@nb.njit(cache=True)
def bin_rows(position: np.ndarray, reach: np.ndarray, width: int, height: int,
             band_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR lists of the primitives whose footprint meets each band of `band_rows` rows."""
    bands = (height + band_rows - 1) // band_rows
    starts = np.zeros(bands + 1, np.int64)
    count = position.shape[0]
    for n in range(count):
        x, y, r = position[n, 0], position[n, 1], reach[n]
        low, high = _row_span(y, r, height)
        if low > high or x + r < 0 or x - r > width - 1:
            continue
        for band in range(low // band_rows, high // band_rows + 1):
            starts[band + 1] += 1
    for band in range(bands):
        starts[band + 1] += starts[band]
    items = np.empty(starts[bands], np.int64)
    fill = starts[:-1].copy()
    for n in range(count):
        x, y, r = position[n, 0], position[n, 1], reach[n]
        low, high = _row_span(y, r, height)
        if low > high or x + r < 0 or x - r > width - 1:
            continue
        for band in range(low // band_rows, high // band_rows + 1):
            items[fill[band]] = n
            fill[band] += 1
    return starts, items


@nb.njit(cache=True, nogil=True)
def _chirp_steps(a, b, dx, dy, mahalanobis):
    """(B, ΔB, ΔΔB) of the QPF's squared distance B (D² or |p − x|²) stepping dx → dx + 1."""
    if mahalanobis:
        return a * dx * dx + 2.0 * b * dx * dy, a * (2.0 * dx + 1.0) + 2.0 * b * dy, 2.0 * a
    return dx * dx, 2.0 * dx + 1.0, 2.0


@nb.njit(cache=True, nogil=True)
def _start_row(rotors, steps, curls, phase_n, wavenumbers, k_chirp, base_y, base, step, step2):
    """Unit phasors along a row: rotor_c = e^{i(φ_c + k_c χ B)} at its first pixel, step_c its
    ratio to the next pixel, curl_c the constant ratio of successive steps (B is quadratic in x)."""
    for ch in range(rotors.shape[0]):
        scale = wavenumbers[ch] * k_chirp
        angle = phase_n[ch] + scale * (base + base_y)
        rotors[ch] = complex(math.cos(angle), math.sin(angle))
        steps[ch] = complex(math.cos(scale * step), math.sin(scale * step))
        curls[ch] = complex(math.cos(scale * step2), math.sin(scale * step2))


@nb.njit(parallel=True, cache=True)
def splat_forward(position, conic, reach, chirp, color, phase, opacity, wavenumbers, mahalanobis,
                  band_starts, band_items, band_rows, out):
    """out[0|1, c, y, x] += Re|Im G_{n,c}(x, y) for every primitive n; `out` starts at zero.

    The quadratic phase is stepped along each row by complex multiplication (exact in exact
    arithmetic; float64 keeps the drift near 1e-15 over a row); the envelope is evaluated directly
    so the −50 exponent floor holds exactly.
    """
    channels, height, width = out.shape[1], out.shape[2], out.shape[3]
    for band in nb.prange(band_starts.shape[0] - 1):
        rotors = np.empty(channels, np.complex128)
        steps = np.empty(channels, np.complex128)
        curls = np.empty(channels, np.complex128)
        band_low = band * band_rows
        band_high = min(band_low + band_rows, height) - 1
        for item in range(band_starts[band], band_starts[band + 1]):
            n = band_items[item]
            x0, y0, r = np.float64(position[n, 0]), np.float64(position[n, 1]), np.float64(reach[n])
            a, b, c = np.float64(conic[n, 0]), np.float64(conic[n, 1]), np.float64(conic[n, 2])
            alpha, k_chirp = np.float64(opacity[n]), np.float64(chirp[n])
            low, high = _row_span(y0, r, height)
            for py in range(max(low, band_low), min(high, band_high) + 1):
                dy = py - y0
                left, right = _column_span(x0, r, dy, width)
                dx = left - x0
                base, step, step2 = _chirp_steps(a, b, dx, dy, mahalanobis)
                base_y = c * dy * dy if mahalanobis else dy * dy
                _start_row(rotors, steps, curls, phase[n], wavenumbers, k_chirp, base_y, base, step, step2)
                for px in range(left, right + 1):
                    if dx * dx + dy * dy <= r * r:
                        mahalanobis2 = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
                        weight = alpha * math.exp(max(-0.5 * mahalanobis2, EXPONENT_FLOOR))
                        for ch in range(channels):
                            value = weight * color[n, ch] * rotors[ch]
                            out[0, ch, py, px] += value.real
                            out[1, ch, py, px] += value.imag
                    for ch in range(channels):
                        rotors[ch] *= steps[ch]
                        steps[ch] *= curls[ch]
                    dx += 1.0


@nb.njit(parallel=True, cache=True)
def splat_backward(position, conic, reach, chirp, color, phase, opacity, wavenumbers, mahalanobis,
                   grad, g_position, g_conic, g_chirp, g_color, g_phase, g_opacity):
    """Gradients (float64, each row written by its own primitive only) from grad[0|1, c, y, x]."""
    channels, height, width = grad.shape[1], grad.shape[2], grad.shape[3]
    for n in nb.prange(position.shape[0]):
        rotors = np.empty(channels, np.complex128)
        steps = np.empty(channels, np.complex128)
        curls = np.empty(channels, np.complex128)
        x0, y0, r = np.float64(position[n, 0]), np.float64(position[n, 1]), np.float64(reach[n])
        a, b, c = np.float64(conic[n, 0]), np.float64(conic[n, 1]), np.float64(conic[n, 2])
        alpha, k_chirp = np.float64(opacity[n]), np.float64(chirp[n])
        gx = gy = ga = gb = gc = gchirp = galpha = 0.0
        low, high = _row_span(y0, r, height)
        if x0 + r < 0 or x0 - r > width - 1:
            high = low - 1
        for py in range(low, high + 1):
            dy = py - y0
            left, right = _column_span(x0, r, dy, width)
            dx = left - x0
            base, step, step2 = _chirp_steps(a, b, dx, dy, mahalanobis)
            base_y = c * dy * dy if mahalanobis else dy * dy
            _start_row(rotors, steps, curls, phase[n], wavenumbers, k_chirp, base_y, base, step, step2)
            for px in range(left, right + 1):
                radius2 = dx * dx + dy * dy
                if radius2 <= r * r:
                    mahalanobis2 = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
                    exponent = -0.5 * mahalanobis2
                    envelope = math.exp(max(exponent, EXPONENT_FLOOR))
                    d_envelope = 0.0
                    d_path = 0.0
                    for ch in range(channels):
                        cos_a, sin_a = rotors[ch].real, rotors[ch].imag
                        g_re, g_im = grad[0, ch, py, px], grad[1, ch, py, px]
                        d_amplitude = g_re * cos_a + g_im * sin_a
                        d_angle = alpha * envelope * color[n, ch] * (g_im * cos_a - g_re * sin_a)
                        g_color[n, ch] += alpha * envelope * d_amplitude
                        g_phase[n, ch] += d_angle
                        d_envelope += color[n, ch] * d_amplitude
                        d_path += wavenumbers[ch] * d_angle
                    base = mahalanobis2 if mahalanobis else radius2
                    galpha += envelope * d_envelope
                    gchirp += d_path * base
                    d_base = d_path * k_chirp
                    d_mahalanobis2 = d_base if mahalanobis else 0.0
                    if exponent > EXPONENT_FLOOR:
                        d_mahalanobis2 -= 0.5 * envelope * alpha * d_envelope
                    d_radius2 = 0.0 if mahalanobis else d_base
                    ga += d_mahalanobis2 * dx * dx
                    gb += d_mahalanobis2 * 2.0 * dx * dy
                    gc += d_mahalanobis2 * dy * dy
                    gx -= 2.0 * (d_mahalanobis2 * (a * dx + b * dy) + d_radius2 * dx)
                    gy -= 2.0 * (d_mahalanobis2 * (b * dx + c * dy) + d_radius2 * dy)
                for ch in range(channels):
                    rotors[ch] *= steps[ch]
                    steps[ch] *= curls[ch]
                dx += 1.0
        g_position[n, 0], g_position[n, 1] = gx, gy
        g_conic[n, 0], g_conic[n, 1], g_conic[n, 2] = ga, gb, gc
        g_chirp[n], g_opacity[n] = gchirp, galpha
