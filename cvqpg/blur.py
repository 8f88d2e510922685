"""Separable Gaussian blur without padding ("valid"), and its adjoint, as CPU kernels (Numba).

The loss's SSIM blurs five maps per plane and channel with an 11-tap window. PyTorch's CPU
convolution runs those 1×11 and 11×1 depthwise filters at well under 1 GMAC/s, which made SSIM half
of a grayscale step. Here each thread owns whole output rows: it sums the K input rows under the
window into one row buffer, then filters that buffer along x, so nothing larger than one row is
stored between the passes. The adjoint (the backward pass) scatters the same taps back. Results do
not depend on scheduling, since every output row is summed by one thread in a fixed order.
"""

from __future__ import annotations

import numba as nb
import numpy as np
import torch
from torch import Tensor


def gaussian_taps(size_px: int, sigma_px: float) -> np.ndarray:
    """The normalised 1D Gaussian window [size_px] centred on its middle tap (σ in px)."""
    offsets = np.arange(size_px, dtype=np.float64) - size_px // 2
    taps = np.exp(-offsets**2 / (2 * sigma_px**2))
    return taps / taps.sum()


@nb.njit(parallel=True, cache=True, fastmath=True)
def _blur_valid(images, taps):
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
def _blur_valid_adjoint(grad, taps, height, width):
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


class _GaussianBlur(torch.autograd.Function):
    @staticmethod
    def forward(ctx, images: Tensor, taps: np.ndarray) -> Tensor:
        ctx.taps, ctx.shape, ctx.device = taps, images.shape, images.device
        flat = images.detach().reshape(-1, *images.shape[-2:]).cpu().contiguous().numpy()
        out = _blur_valid(flat, taps.astype(flat.dtype))
        return torch.from_numpy(out).reshape(*images.shape[:-2], *out.shape[-2:]).to(ctx.device)

    @staticmethod
    def backward(ctx, grad: Tensor):
        height, width = ctx.shape[-2:]
        flat = grad.detach().reshape(-1, *grad.shape[-2:]).cpu().contiguous().numpy()
        out = _blur_valid_adjoint(flat, ctx.taps.astype(flat.dtype), height, width)
        return torch.from_numpy(out).reshape(ctx.shape).to(ctx.device), None


def gaussian_blur_valid(images: Tensor, size_px: int, sigma_px: float) -> Tensor:
    """Blur [..., H, W] with the separable Gaussian window, keeping only the pixels whose window
    lies inside: [..., H − size + 1, W − size + 1]. Differentiable; runs on the CPU."""
    if min(images.shape[-2:]) < size_px:
        raise ValueError(f"images of {tuple(images.shape[-2:])} px are smaller than the "
                         f"{size_px}-px blur window")
    return _GaussianBlur.apply(images, gaussian_taps(size_px, sigma_px))

