"""The multi-plane training loss (SPEC §6).

Two implementations of one formula. The reference (`--backend torch`, and CUDA) is plain PyTorch
with pytorch-msssim's SSIM, differentiated by autograd. On the CPU the pixel-wise parts run as the
fused kernels of `loss_kernels` behind two autograd Functions whose backward passes are written
out; the tests hold them against the reference in value and gradient.
"""

from __future__ import annotations

import functools
import inspect
import math
from typing import ContextManager, Sequence

import numpy as np
import torch
from pytorch_msssim import ssim
from pytorch_msssim.ssim import _fspecial_gauss_1d
from torch import Tensor

from .loss_kernels import SSIM_TAPS, gaussian_taps, pixel_terms, ssim_backward, ssim_forward, standard_normals
from .rasterization import cpu_array, resolve_backend

SSIM_WINDOW_PX = SSIM_TAPS  # 11, the fused kernels' constant window
SSIM_SIGMA_PX = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03  # stabilisers, as fractions of the data range (1)


def standard_normal(shape: Sequence[int], generator: torch.Generator) -> Tensor:
    """Standard normal draws [shape] (float32) on the generator's device, for the targets' noise.

    On the CPU they are `loss_kernels.standard_normals` of one seed drawn from `generator`: a pure
    function of that seed, vectorised and threaded, about 3.5× faster than `torch.randn`, which
    draws from one sequential generator. Elsewhere they are `torch.randn`'s.
    """
    if generator.device.type != "cpu":
        return torch.randn(tuple(shape), generator=generator, device=generator.device)
    seed = int(torch.randint(0, 2**63 - 1, (), generator=generator))
    count = math.prod(shape)
    draws = torch.empty(count + count % 2)  # the kernel fills whole pairs
    standard_normals(seed, draws.numpy())
    return draws[:count].view(tuple(shape))


def noisy_targets(targets: Tensor, standard_normal: Tensor, level: float) -> Tensor:
    """`T̃ = T + level·(max T − min T)·N(0,1)`, range taken per plane over [C, H, W]."""
    planes = targets.flatten(1)
    spread = planes.amax(dim=1) - planes.amin(dim=1)  # 10× faster here than torch.aminmax along a dim
    return torch.addcmul(targets, (level * spread).view(-1, 1, 1, 1), standard_normal)


class _FusedSsim(torch.autograd.Function):
    """SSIM per plane [M] of [M, C, H, W] images; differentiable in the reconstruction only (the
    targets are constants of a fit). The backward pass is the chain rule through the blurred
    moments: ∂SSIM/∂x = B*(∂S/∂μx) + 2x·B*(∂S/∂E[x²]) + y·B*(∂S/∂E[xy]), B* the adjoint blur."""

    @staticmethod
    def images(recon: Tensor, targets: Tensor) -> tuple[np.ndarray, np.ndarray]:
        """[M, C, H, W] tensors as [M·C, H, W] arrays of the reconstruction's dtype."""
        x = cpu_array(recon).reshape(-1, *recon.shape[-2:])
        return x, cpu_array(targets).astype(x.dtype, copy=False).reshape(x.shape)

    @staticmethod
    def forward(ctx, recon: Tensor, targets: Tensor) -> Tensor:
        planes, channels, height, width = recon.shape
        x, y = _FusedSsim.images(recon, targets)
        taps = gaussian_taps(SSIM_WINDOW_PX, SSIM_SIGMA_PX).astype(x.dtype)
        valid = (x.shape[0], height - taps.size + 1, width - taps.size + 1)
        derivatives = tuple(np.empty(valid, x.dtype) for _ in range(3))
        sums = ssim_forward(x, y, taps, SSIM_K1**2, SSIM_K2**2, *derivatives)
        ctx.derivatives, ctx.taps, ctx.count = derivatives, taps, channels * valid[1] * valid[2]
        ctx.save_for_backward(recon, targets)
        return torch.from_numpy(sums.reshape(planes, channels).sum(axis=1) / ctx.count).to(recon.device, recon.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:
        recon, targets = ctx.saved_tensors
        x, y = _FusedSsim.images(recon, targets)
        weights = np.repeat(cpu_array(grad).astype(np.float64) / ctx.count, recon.shape[1])
        gradient = np.empty_like(x)
        ssim_backward(*ctx.derivatives, weights, x, y, ctx.taps, gradient)
        return torch.from_numpy(gradient).view(recon.shape).to(recon.device), None


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


def ssim_per_plane(recon: Tensor, targets: Tensor, backend: str = "auto") -> Tensor:
    """SSIM [M] of [M, C, H, W] images, Gaussian window 11 px, σ 1.5 px, data range 1.

    Backend `torch` is pytorch-msssim, the reference, differentiable in both arguments. On the CPU
    (`auto`, `numba`) the fused kernels compute the same numbers, differentiable in `recon`. Images
    smaller than the window go to the reference, which then blurs only the long axis.
    """
    if resolve_backend(backend, recon.device) == "torch" or min(recon.shape[-2:]) < SSIM_WINDOW_PX:
        # oneDNN's depthwise 1×11 convolutions cost 3× PyTorch's own on one channel.
        with _without_onednn():
            return ssim(recon, targets, data_range=1.0, size_average=False,
                        win=ssim_window(recon.shape[1], recon.dtype, recon.device))
    return _FusedSsim.apply(recon, targets)


class _FusedPixelTerms(torch.autograd.Function):
    """Per plane [M]: MSE(Î,T) + MSE(Î·Mask, T̃·Mask) + MSE(Î·T̃, T̃·T̃), and MSE(Î,T) alone (not
    differentiated). The gradient is formed in the same pass as the value and scaled in backward."""

    @staticmethod
    def forward(ctx, recon: Tensor, targets: Tensor, noisy: Tensor, masks: Tensor) -> tuple[Tensor, Tensor]:
        x = cpu_array(recon)
        gradient = np.empty_like(x)
        sums = pixel_terms(x, cpu_array(targets).astype(x.dtype, copy=False),
                           cpu_array(noisy).astype(x.dtype, copy=False),
                           cpu_array(masks).astype(x.dtype, copy=False), gradient)
        count = x[0].size
        ctx.gradient, ctx.count = gradient, count
        values, mse = (torch.from_numpy(v / count).to(recon.device, recon.dtype) for v in (sums.sum(axis=1), sums[:, 0]))
        ctx.mark_non_differentiable(mse)
        return values, mse

    @staticmethod
    def backward(ctx, grad: Tensor, _: Tensor) -> tuple[Tensor, None, None, None]:
        scale = (grad / ctx.count).view(-1, 1, 1, 1)
        return torch.from_numpy(ctx.gradient).to(grad.device) * scale, None, None, None


def multiplane_loss(recon: Tensor, targets: Tensor, masks: Tensor, noisy: Tensor,
                    ssim_weight: float = 0.005, backend: str = "auto") -> tuple[Tensor, Tensor]:
    """Σ_m [MSE(Î,T) + MSE(Î·Mask, T̃·Mask) + MSE(Î·T̃, T̃·T̃) + w·(1 − SSIM(Î,T))].

    recon, targets, noisy: [M, C, H, W]; masks: [M, H, W]. Returns the loss and the plain
    per-plane MSE(Î, T) [M] (detached), from which progress PSNR is read at no extra cost. `backend`
    picks the reference or the fused CPU kernels, as it picks the rasterizer.
    """
    structure = ssim_weight * (1 - ssim_per_plane(recon, targets, backend))
    if resolve_backend(backend, recon.device) != "torch":
        pixel, mse = _FusedPixelTerms.apply(recon, targets, noisy, masks)
        return (pixel + structure).sum(), mse
    dims = (1, 2, 3)
    mask = masks[:, None]
    mse = ((recon - targets) ** 2).mean(dim=dims)
    masked = ((recon * mask - noisy * mask) ** 2).mean(dim=dims)
    correlation = ((recon * noisy - noisy * noisy) ** 2).mean(dim=dims)
    return (mse + masked + correlation + structure).sum(), mse.detach()
