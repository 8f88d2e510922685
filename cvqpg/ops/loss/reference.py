"""The training loss's PyTorch reference (SPEC §6): the pixel-wise terms and pytorch-msssim's SSIM,
differentiated by autograd."""

from __future__ import annotations

import functools
import inspect
from typing import ContextManager

import torch
from pytorch_msssim import ssim
from pytorch_msssim.ssim import _fspecial_gauss_1d
from torch import Tensor

from .cpu import SSIM_TAPS

SSIM_WINDOW_PX = SSIM_TAPS  # 11, the CPU kernels' constant window
SSIM_SIGMA_PX = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03  # stabilisers, as fractions of the data range (1)


def pixel_terms(recon: Tensor, targets: Tensor, noisy: Tensor, masks: Tensor) -> tuple[Tensor, Tensor]:
    """Per plane [M]: MSE(Î,T) + MSE(Î·Mask, T̃·Mask) + MSE(Î·T̃, T̃·T̃), and MSE(Î,T) alone (detached).
    recon, targets, noisy: [M, C, H, W]; masks: [M, H, W]."""
    dims = (1, 2, 3)
    mask = masks[:, None]
    mse = ((recon - targets) ** 2).mean(dim=dims)
    masked = ((recon * mask - noisy * mask) ** 2).mean(dim=dims)
    correlation = ((recon * noisy - noisy * noisy) ** 2).mean(dim=dims)
    return mse + masked + correlation, mse.detach()


# Newer torch's oneDNN flags take `allow_tf32`; torch 2.4's take only `enabled`.
ONEDNN_FLAGS_TAKE_TF32 = "allow_tf32" in inspect.signature(torch.backends.mkldnn.flags).parameters


def _without_onednn() -> ContextManager:
    """oneDNN off inside the block. Where the flags take `allow_tf32`, None leaves it as it is:
    setting it warns on CPUs."""
    if ONEDNN_FLAGS_TAKE_TF32:
        return torch.backends.mkldnn.flags(enabled=False, allow_tf32=None)
    return torch.backends.mkldnn.flags(enabled=False)


@functools.lru_cache(maxsize=8)
def ssim_window(channels: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """pytorch-msssim's own Gaussian window [C, 1, 1, 11] on `device`, made once: left to pytorch-msssim
    it is built on the host and copied to the device at every call, which on CUDA waits for the GPU."""
    return _fspecial_gauss_1d(SSIM_WINDOW_PX, SSIM_SIGMA_PX).repeat(channels, 1, 1, 1).to(device, dtype)


def ssim_per_plane(recon: Tensor, targets: Tensor) -> Tensor:
    """SSIM [M] of [M, C, H, W] images (pytorch-msssim), Gaussian window 11 px, σ 1.5 px, data range 1."""
    # oneDNN's depthwise 1×11 convolutions cost 3× PyTorch's own on one channel.
    with _without_onednn():
        return ssim(recon, targets, data_range=1.0, size_average=False,
                    win=ssim_window(recon.shape[1], recon.dtype, recon.device))
