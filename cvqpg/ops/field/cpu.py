"""The SLM field's and the clamped intensity's CPU kernels (Numba), with their gradients (method.md §3).

PyTorch builds the guard-banded, windowed, amplitude-clamped field in about eight full passes over
the padded array (gather, content copy, window product, magnitude, clamp, quotient) and the clamped
intensity |u|² and its gradient in about ten. Each kernel here is one pass, with each thread owning
whole rows. `reference` holds the PyTorch formulas, which serve CUDA and `--backend torch`; the
tests hold these kernels against them.
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
    padded_height = out.shape[1]
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
