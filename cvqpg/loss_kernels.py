"""Fused CPU kernels (Numba) for the training loss (SPEC §6).

PyTorch evaluates the loss's three MSE terms and the SSIM formula as some forty full-size
element-wise passes, forward and backward, and runs SSIM's 11-tap depthwise blurs at well under
1 GMAC/s on the CPU. Here:

- `pixel_terms` makes one pass for the three MSE terms and their gradient;
- `blur_valid` blurs with each thread owning whole output rows: it sums the K input rows under the
  window into one row buffer, then filters that buffer along x, so nothing larger than one row is
  stored between the passes; `blur_valid_adjoint` scatters the same taps back;
- `ssim_maps` makes one pass for the SSIM map and its partial derivatives.

Each thread owns whole rows and rows are summed in a fixed order, so results do not depend on
scheduling.
"""

from __future__ import annotations

import numba as nb
import numpy as np


def gaussian_taps(size_px: int, sigma_px: float) -> np.ndarray:
    """The normalised 1D Gaussian window [size_px] centred on its middle tap (σ in px)."""
    offsets = np.arange(size_px, dtype=np.float64) - size_px // 2
    taps = np.exp(-offsets**2 / (2 * sigma_px**2))
    return taps / taps.sum()


@nb.njit(parallel=True, cache=True, fastmath=True)
def blur_valid(images, taps):
    """[B, H, W] → [B, H − K + 1, W − K + 1]: the separable blur with the K taps, valid pixels only."""
    count, height, width = images.shape
    size = taps.size
    out_height, out_width = height - size + 1, width - size + 1
    out = np.empty((count, out_height, out_width), images.dtype)
    for row in nb.prange(count * out_height):
        b, i = row // out_height, row % out_height
        column_sums = np.zeros(width, images.dtype)
        for k in range(size):
            tap = taps[k]
            source = images[b, i + k]
            for j in range(width):
                column_sums[j] += tap * source[j]
        target = out[b, i]
        target[:] = 0.0
        for k in range(size):
            tap = taps[k]
            for j in range(out_width):
                target[j] += tap * column_sums[j + k]
    return out


@nb.njit(parallel=True, cache=True, fastmath=True)
def blur_valid_adjoint(grad, taps, height, width):
    """The adjoint of `blur_valid`: [B, h, w] → [B, height, width]."""
    count, out_height, out_width = grad.shape
    size = taps.size
    out = np.zeros((count, height, width), grad.dtype)
    for row in nb.prange(count * height):
        b, i = row // height, row % height
        column_sums = np.zeros(out_width, grad.dtype)
        for k in range(max(0, i - out_height + 1), min(size, i + 1)):
            tap = taps[k]
            source = grad[b, i - k]
            for j in range(out_width):
                column_sums[j] += tap * source[j]
        target = out[b, i]
        for k in range(size):
            tap = taps[k]
            for j in range(out_width):
                target[j + k] += tap * column_sums[j]
    return out


@nb.njit(parallel=True, cache=True, fastmath=True)
def pixel_terms(recon, targets, noisy, masks, gradient):
    """Per-plane sums over [C, H, W] of `(x − t)²` and of `(m² + ñ²)(x − ñ)²` ([M, 2], float64).

    With x the reconstruction, t the target, ñ the noisy target and m the plane's mask, the second
    sum is the masked and the correlation MSE terms together: (x·m − ñ·m)² + (x·ñ − ñ·ñ)². Writes
    the derivative of both sums with respect to x, `2(x − t) + 2(m² + ñ²)(x − ñ)`, into `gradient`.
    """
    planes, channels, height, width = recon.shape
    rows = np.zeros((planes * height, 2))
    for row in nb.prange(planes * height):
        m, i = row // height, row % height
        plain = weighted = 0.0
        for c in range(channels):
            for j in range(width):
                x, n = recon[m, c, i, j], noisy[m, c, i, j]
                weight = masks[m, i, j] * masks[m, i, j] + n * n
                error, noisy_error = x - targets[m, c, i, j], x - n
                plain += error * error
                weighted += weight * noisy_error * noisy_error
                gradient[m, c, i, j] = 2.0 * (error + weight * noisy_error)
        rows[row, 0], rows[row, 1] = plain, weighted
    return rows.reshape(planes, height, 2).sum(axis=1)


@nb.njit(parallel=True, cache=True, fastmath=True)
def ssim_maps(mean_x, mean_y, mean_xx, mean_yy, mean_xy, c1, c2, d_mean_x, d_mean_xx, d_mean_xy):
    """Sum of the SSIM map per image ([B], float64) from the blurred moments [B, h, w].

    SSIM = a1·a2 / (b1·b2) with a1 = 2μxμy + c1, b1 = μx² + μy² + c1, a2 = 2σxy + c2,
    b2 = σx² + σy² + c2. Writes its partial derivatives with respect to μx, E[x²] and E[xy] into
    `d_mean_x`, `d_mean_xx`, `d_mean_xy`; they are written without dividing by a1 or a2, which may
    vanish (b1, b2 ≥ c1, c2 > 0).
    """
    images, height, width = mean_x.shape
    rows = np.zeros(images * height)
    for row in nb.prange(images * height):
        b, i = row // height, row % height
        total = 0.0
        for j in range(width):
            mx, my = np.float64(mean_x[b, i, j]), np.float64(mean_y[b, i, j])
            mxy = mx * my
            a1, b1 = 2.0 * mxy + c1, mx * mx + my * my + c1
            a2 = 2.0 * (mean_xy[b, i, j] - mxy) + c2
            b2 = (mean_xx[b, i, j] - mx * mx) + (mean_yy[b, i, j] - my * my) + c2
            denominator = b1 * b2
            value = a1 * a2 / denominator
            total += value
            d_mean_x[b, i, j] = 2.0 * my * (a2 - a1) / denominator - 2.0 * mx * value * (1.0 / b1 - 1.0 / b2)
            d_mean_xx[b, i, j] = -value / b2
            d_mean_xy[b, i, j] = 2.0 * a1 / denominator
        rows[row] = total
    return rows.reshape(images, height).sum(axis=1)
