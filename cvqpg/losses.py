"""The multi-plane training loss (SPEC §6)."""

from __future__ import annotations

import torch
from pytorch_msssim import ssim
from torch import Tensor

from cvqpg.blur import gaussian_blur_valid
from cvqpg.rasterization import resolve_backend

SSIM_WINDOW_PX = 11
SSIM_SIGMA_PX = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03  # stabilisers, as fractions of the data range (1)


def noisy_targets(targets: Tensor, standard_normal: Tensor, level: float) -> Tensor:
    """`T̃ = T + level·(max T − min T)·N(0,1)`, range taken per plane over [C, H, W]."""
    flat = targets.flatten(1)
    spread = (flat.max(dim=1).values - flat.min(dim=1).values).view(-1, 1, 1, 1)
    return targets + level * spread * standard_normal


def ssim_per_plane(recon: Tensor, targets: Tensor, backend: str = "auto") -> Tensor:
    """SSIM [M] of [M, C, H, W] images, Gaussian window 11 px, σ 1.5 px, data range 1.

    Backend `torch` is pytorch-msssim, the reference. On the CPU (`auto`, `numba`) the same formula
    runs on `blur.gaussian_blur_valid`: PyTorch's CPU convolutions made SSIM half of a grayscale
    step. Images smaller than the window go to the reference, which then blurs only the long axis.
    """
    if resolve_backend(backend, recon.device) == "torch" or min(recon.shape[-2:]) < SSIM_WINDOW_PX:
        # oneDNN's depthwise 1×11 convolutions cost 3× PyTorch's own on one channel.
        with torch.backends.mkldnn.flags(enabled=False, allow_tf32=None):
            return ssim(recon, targets, data_range=1.0, size_average=False,
                        win_size=SSIM_WINDOW_PX, win_sigma=SSIM_SIGMA_PX)
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    mean_x, mean_xx, mean_xy = gaussian_blur_valid(
        torch.stack((recon, recon * recon, recon * targets)), SSIM_WINDOW_PX, SSIM_SIGMA_PX)
    mean_y, mean_yy = gaussian_blur_valid(
        torch.stack((targets, targets * targets)), SSIM_WINDOW_PX, SSIM_SIGMA_PX)
    mean_x_mean_y = mean_x * mean_y
    mean_x2, mean_y2 = mean_x * mean_x, mean_y * mean_y
    contrast_structure = (2 * (mean_xy - mean_x_mean_y) + c2) / (
        (mean_xx - mean_x2) + (mean_yy - mean_y2) + c2)
    luminance = (2 * mean_x_mean_y + c1) / (mean_x2 + mean_y2 + c1)
    return (luminance * contrast_structure).flatten(1).mean(dim=1)


def multiplane_loss(recon: Tensor, targets: Tensor, masks: Tensor, noisy: Tensor,
                    ssim_weight: float = 0.005, backend: str = "auto") -> tuple[Tensor, Tensor]:
    """Σ_m [MSE(Î,T) + MSE(Î·Mask, T̃·Mask) + MSE(Î·T̃, T̃·T̃) + w·(1 − SSIM(Î,T))].

    recon, targets, noisy: [M, C, H, W]; masks: [M, H, W]. Returns the loss and the plain
    per-plane MSE(Î, T) [M] (detached), from which progress PSNR is read at no extra cost. `backend`
    picks the SSIM implementation, as it picks the rasterizer.
    """
    dims = (1, 2, 3)
    mask = masks[:, None]
    mse = ((recon - targets) ** 2).mean(dim=dims)
    masked = ((recon * mask - noisy * mask) ** 2).mean(dim=dims)
    correlation = ((recon * noisy - noisy * noisy) ** 2).mean(dim=dims)
    structure = ssim_weight * (1 - ssim_per_plane(recon, targets, backend))
    return (mse + masked + correlation + structure).sum(), mse.detach()
