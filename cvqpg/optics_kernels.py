"""Fused CPU kernels (Numba) for the SLM field, the propagation's transposes and the reconstructed
intensity (SPEC §3).

PyTorch builds the guard-banded, windowed, amplitude-clamped field in about eight full passes over
the padded array (gather, content copy, window product, magnitude, clamp, quotient) and the clamped
intensity |u|² and its gradient in about ten. Each kernel here is one pass, with each thread owning
whole rows. `optics` holds the PyTorch formulas, which serve CUDA and `--backend torch`; the tests
hold these kernels against them. The transpose moves the propagation's arrays between row and
column layout (PyTorch's strided copies take about twice as long).
"""

from __future__ import annotations

import numba as nb


@nb.njit(parallel=True, cache=True, fastmath=True)
def guarded_field(hologram, row_window, column_window, top, left, out):
    """out [C, P_H, P_W] = u(h[c, clamp(y − top), clamp(x − left)] · w_y · w_x), u(v) = v / max(|v|, 1).

    The clamped indices replicate the content's edges into the guard band.
    """
    channels, height, width = hologram.shape
    padded_height, padded_width = out.shape[1], out.shape[2]
    for row in nb.prange(channels * padded_height):
        channel, y = row // padded_height, row % padded_height
        source = hologram[channel, min(max(y - top, 0), height - 1)]
        weight_y = row_window[y]
        for x in range(padded_width):
            value = source[min(max(x - left, 0), width - 1)] * (weight_y * column_window[x])
            magnitude = abs(value)
            out[channel, y, x] = value / magnitude if magnitude > 1.0 else value


@nb.njit(parallel=True, cache=True, fastmath=True)
def guarded_field_backward(hologram, grad, top, left, out):
    """Gradient [C, H, W] for the content from the padded field's gradient [C, P_H, P_W]: the identity
    where |h| < 1, and where the amplitude saturates its projection onto the phase direction,
    `i·h·Im(h̄·g)/|h|³`."""
    channels, height, width = hologram.shape
    for row in nb.prange(channels * height):
        channel, y = row // height, row % height
        for x in range(width):
            h = hologram[channel, y, x]
            g = grad[channel, y + top, x + left]
            magnitude = abs(h)
            if magnitude >= 1.0:
                normal = (h.real * g.imag - h.imag * g.real) / magnitude**3
                out[channel, y, x] = complex(-h.imag * normal, h.real * normal)
            else:
                out[channel, y, x] = g


@nb.njit(parallel=True, cache=True, fastmath=True)
def clamped_intensity(field, out):
    """out = min(|u|², 1) over [..., H, W] arrays viewed as [R, W] rows."""
    for row in nb.prange(field.shape[0]):
        for x in range(field.shape[1]):
            u = field[row, x]
            out[row, x] = min(u.real * u.real + u.imag * u.imag, 1.0)


@nb.njit(parallel=True, cache=True, fastmath=True)
def clamped_intensity_backward(field, grad, out):
    """out = 2·u·g where |u|² ≤ 1 (the clamp passes its bound's gradient, as PyTorch's does), else 0."""
    for row in nb.prange(field.shape[0]):
        for x in range(field.shape[1]):
            u = field[row, x]
            passes = u.real * u.real + u.imag * u.imag <= 1.0
            out[row, x] = 2.0 * grad[row, x] * u if passes else 0.0


TRANSPOSE_BAND = 8  # target rows per task: 8 complex64 values of a source row are one cache line


@nb.njit(parallel=True, cache=True)
def transpose(source, out):
    """out[j, i] = source[i, j] for a source [R, N] and out [N, R], either of them a view into a wider
    array. Each task takes a band of target rows and reads the source row by row, a cache line at a
    time, while it writes its rows in order."""
    rows, columns = source.shape
    for band in nb.prange((columns + TRANSPOSE_BAND - 1) // TRANSPOSE_BAND):
        first, stop = band * TRANSPOSE_BAND, min(columns, (band + 1) * TRANSPOSE_BAND)
        for i in range(rows):
            line = source[i]
            for j in range(first, stop):
                out[j, i] = line[j]
