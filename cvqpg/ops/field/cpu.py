"""Fused CPU kernels (Numba) for the SLM field, the propagation's transposes and the reconstructed
intensity (SPEC §3).

PyTorch builds the guard-banded, windowed, amplitude-clamped field in about eight full passes over
the padded array (gather, content copy, window product, magnitude, clamp, quotient) and the clamped
intensity |u|² and its gradient in about ten. Each kernel here is one pass, with each thread owning
whole rows. `optics` holds the PyTorch formulas, which serve CUDA and `--backend torch`; the tests
hold these kernels against them. The transpose moves the propagation's arrays between row and
column layout (PyTorch's strided copies take about twice as long), and the products apply
transfer functions kept as half of their rows.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _unit_clamped(value):
    """u(v) = v / max(|v|, 1), as a product with a reciprocal square root that LLVM vectorises (the
    `abs` of a complex number is a `hypot` call, which it does not)."""
    one = np.float32(1.0)
    return value * (one / math.sqrt(max(value.real * value.real + value.imag * value.imag, one)))


@nb.njit(inline="always", fastmath=True)
def _windowed_clamped(source, weight_y, column_window, target):
    """target[x] = u(source[x] · w_y · w_x) over a row segment. Zero-based over slices, the loop
    vectorises (a start offset that may be negative costs every index a wrap-around check)."""
    for x in range(target.shape[0]):
        target[x] = _unit_clamped(source[x] * (weight_y * column_window[x]))


@nb.njit(inline="always", fastmath=True)
def _windowed_clamped_edge(edge, weight_y, column_window, target):
    """target[x] = u(edge · w_y · w_x): a guard band beside the content, replicating its edge value."""
    for x in range(target.shape[0]):
        target[x] = _unit_clamped(edge * (weight_y * column_window[x]))


@nb.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def guarded_field(hologram, row_window, column_window, top, left, out):
    """out [C, P_H, P_W] = u(h[c, clamp(y − top), clamp(x − left)] · w_y · w_x), u(v) = v / max(|v|, 1).

    The clamped indices replicate the content's edges into the guard band; each row is written as
    its left band, content and right band.
    """
    channels, height, width = hologram.shape
    padded_height, padded_width = out.shape[1], out.shape[2]
    for row in nb.prange(channels * padded_height):
        channel, y = row // padded_height, row % padded_height
        source = hologram[channel, min(max(y - top, 0), height - 1)]
        weight_y = row_window[y]
        _windowed_clamped_edge(source[0], weight_y, column_window[:left], out[channel, y, :left])
        _windowed_clamped(source, weight_y, column_window[left:left + width], out[channel, y, left:left + width])
        _windowed_clamped_edge(source[width - 1], weight_y, column_window[left + width:],
                               out[channel, y, left + width:])


@nb.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def guarded_field_backward(hologram, grad, top, left, out):
    """Gradient [C, H, W] for the content from the padded field's gradient [C, P_H, P_W]: the identity
    where |h| < 1, and where the amplitude saturates its projection onto the phase direction,
    `i·h·Im(h̄·g)/|h|³`."""
    channels, height, width = hologram.shape
    for row in nb.prange(channels * height):
        channel, y = row // height, row % height
        source, incoming, target = hologram[channel, y], grad[channel, y + top, left:left + width], out[channel, y]
        for x in range(width):
            h, g = source[x], incoming[x]
            magnitude2 = h.real * h.real + h.imag * h.imag
            bounded = max(magnitude2, 1.0)  # the quotient is used only where magnitude2 ≥ 1
            normal = (h.real * g.imag - h.imag * g.real) / (bounded * math.sqrt(bounded))
            target[x] = complex(-h.imag * normal, h.real * normal) if magnitude2 >= 1.0 else g


@nb.njit(parallel=True, cache=True, fastmath=True)
def clamped_intensity(field, out):
    """out = min(|u|², 1) over [..., H, W] arrays viewed as [R, W] rows."""
    for row in nb.prange(field.shape[0]):
        for x in range(field.shape[1]):
            u = field[row, x]
            out[row, x] = min(u.real * u.real + u.imag * u.imag, 1.0)


@nb.njit(parallel=True, cache=True, fastmath=True)
def clamped_intensity_backward(field, grad, out):
    """out = 2·u·g where |u|² ≤ 1 (the clamp passes its bound's gradient, as PyTorch's does), else 0;
    in float32 and without a branch, so that the loop vectorises."""
    for row in nb.prange(field.shape[0]):
        for x in range(field.shape[1]):
            u = field[row, x]
            passes = np.float32(u.real * u.real + u.imag * u.imag <= np.float32(1.0))
            out[row, x] = u * (np.float32(2.0) * grad[row, x] * passes)


@nb.njit(parallel=True, cache=True)
def copy_rows(source, out, conjugate):
    """out = source, or its complex conjugate, for [R, N] arrays either of which may be a view into a
    wider array; threads take whole rows."""
    for r in nb.prange(source.shape[0]):
        row, target = source[r], out[r]
        if conjugate:
            for j in range(row.shape[0]):
                target[j] = row[j].conjugate()
        else:
            for j in range(row.shape[0]):
                target[j] = row[j]


TRANSPOSE_TILE = 16  # a 16×16 tile of complex64 is 2 KiB: source and target tiles stay in L1


@nb.njit(parallel=True, cache=True)
def transpose(source, out):
    """out[j, i] = source[i, j] for a source [R, N] and out [N, R], either of them a view into a wider
    array. Each task takes a band of 16 target rows and moves it tile by tile; the tiles are
    zero-based slices, so no index needs a wrap-around check."""
    rows, columns = source.shape
    for band in nb.prange((columns + TRANSPOSE_TILE - 1) // TRANSPOSE_TILE):
        first = band * TRANSPOSE_TILE
        stop = min(columns, first + TRANSPOSE_TILE)
        for top in range(0, rows, TRANSPOSE_TILE):
            bottom = min(rows, top + TRANSPOSE_TILE)
            tile, target = source[top:bottom, first:stop], out[first:stop, top:bottom]
            for j in range(stop - first):
                target_row = target[j]
                for i in range(bottom - top):
                    target_row[i] = tile[i, j]


@nb.njit(inline="always")
def _mirrored_row(row, length):
    """The row of a first half [length / 2, N] that holds row `row` of a function [length, N] even
    about the middle of its first axis."""
    return min(row, length - 1 - row)


@nb.njit(parallel=True, cache=True, fastmath=True)
def mirrored_products(spectrum, halves, first_row, out):
    """out[p, r] = spectrum[r] · T_p[first_row + r] for every plane p, for transfer functions T_p [2K, N]
    even about the middle of their first axis (T[k] = T[2K − 1 − k]), given as their first halves
    (a tuple of [K, N]). Each spectrum row is read once for all planes."""
    length = 2 * halves[0].shape[0]
    for r in nb.prange(spectrum.shape[0]):
        mirrored, source = _mirrored_row(first_row + r, length), spectrum[r]
        for plane in range(len(halves)):
            transfer, target = halves[plane][mirrored], out[plane, r]
            for j in range(source.shape[0]):
                target[j] = source[j] * transfer[j]


@nb.njit(parallel=True, cache=True, fastmath=True)
def mirrored_sum(spectra, halves, first_row):
    """spectra[0][r] = Σ_p spectra[p][r] · T_p[first_row + r], in place, for transfer functions given as
    in `mirrored_products`; one pass over the planes' rows."""
    length = 2 * halves[0].shape[0]
    for r in nb.prange(spectra[0].shape[0]):
        mirrored = _mirrored_row(first_row + r, length)
        target, transfer = spectra[0][r], halves[0][mirrored]
        for j in range(target.shape[0]):
            target[j] = target[j] * transfer[j]
        for plane in range(1, len(spectra)):
            source, transfer = spectra[plane][r], halves[plane][mirrored]
            for j in range(target.shape[0]):
                target[j] += source[j] * transfer[j]
