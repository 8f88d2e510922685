"""The multi-plane training loss (SPEC §6)."""

from __future__ import annotations

import torch
from pytorch_msssim import ssim
from torch import Tensor

SSIM_WINDOW_PX = 11
SSIM_SIGMA_PX = 1.5


def noisy_targets(targets: Tensor, standard_normal: Tensor, level: float) -> Tensor:
    """`T̃ = T + level·(max T − min T)·N(0,1)`, range taken per plane over [C, H, W]."""
    flat = targets.flatten(1)
    spread = (flat.max(dim=1).values - flat.min(dim=1).values).view(-1, 1, 1, 1)
    return targets + level * spread * standard_normal


def ssim_per_plane(recon: Tensor, targets: Tensor) -> Tensor:
    """SSIM [M] of [M, C, H, W] images, Gaussian window 11 px, σ 1.5 px, data range 1.

    oneDNN is bypassed: its depthwise 1×11 convolutions cost 3× PyTorch's own on one channel (a
    grayscale step spent 40% of its time there) and are no faster on three.
    """
    with torch.backends.mkldnn.flags(enabled=False, allow_tf32=None):
        return ssim(recon, targets, data_range=1.0, size_average=False, win_size=SSIM_WINDOW_PX,
                    win_sigma=SSIM_SIGMA_PX)


def multiplane_loss(recon: Tensor, targets: Tensor, masks: Tensor, noisy: Tensor,
                    ssim_weight: float = 0.005) -> tuple[Tensor, Tensor]:
    """Σ_m [MSE(Î,T) + MSE(Î·Mask, T̃·Mask) + MSE(Î·T̃, T̃·T̃) + w·(1 − SSIM(Î,T))].

    recon, targets, noisy: [M, C, H, W]; masks: [M, H, W]. Returns the loss and the plain
    per-plane MSE(Î, T) [M] (detached), from which progress PSNR is read at no extra cost.
    """
    dims = (1, 2, 3)
    mask = masks[:, None]
    mse = ((recon - targets) ** 2).mean(dim=dims)
    masked = ((recon * mask - noisy * mask) ** 2).mean(dim=dims)
    correlation = ((recon * noisy - noisy * noisy) ** 2).mean(dim=dims)
    structure = ssim_weight * (1 - ssim_per_plane(recon, targets))
    return (mse + masked + correlation + structure).sum(), mse.detach()
