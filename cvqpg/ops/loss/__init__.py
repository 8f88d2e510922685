"""The multi-plane training loss (method.md §6) and the targets' noise: the public ops and their autograd boundaries.

| op               | reference (PyTorch)         | cpu (Numba)                              |
|------------------|-----------------------------|------------------------------------------|
| `multiplane_loss`| `reference.pixel_terms`     | `cpu.pixel_terms`                        |
| `ssim_per_plane` | `reference.ssim_per_plane`  | `cpu.ssim_forward`, `cpu.ssim_backward`  |
| `standard_normal`| `reference.standard_normals`| `cpu.standard_normals`                   |

The reference (`--backend torch`, and CUDA) is plain PyTorch with pytorch-msssim's SSIM,
differentiated by autograd; on CUDA the noise is `torch.randn`'s. With `numba` the pixel-wise parts
run as the CPU kernels behind two autograd Functions whose backward passes are written out; the
tests hold them against the reference in value and gradient.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from .. import cpu_array, resolve_backend
from . import cpu, reference
from .reference import SSIM_K1, SSIM_K2, SSIM_SIGMA_PX, SSIM_WINDOW_PX


def standard_normal(shape: Sequence[int], generator: torch.Generator, backend: str = "auto") -> Tensor:
    """Standard normal draws [shape] (float32) on the generator's device, for the targets' noise.

    On the CPU they are counter-based draws from one seed drawn from `generator`, a pure function of
    that seed: with `numba` the kernel `cpu.standard_normals`, vectorised and threaded, faster than
    `torch.randn`, which draws from one sequential generator (docs/performance.md, "Measured
    choices"); otherwise its reference, the same numbers to float32 rounding. Elsewhere they are
    `torch.randn`'s.
    """
    if generator.device.type != "cpu":
        return torch.randn(tuple(shape), generator=generator, device=generator.device)
    seed = int(torch.randint(0, 2**63 - 1, (), generator=generator))
    count = math.prod(shape)
    even = count + count % 2  # the draws come in pairs
    if resolve_backend(backend, generator.device) == "numba":
        draws = torch.empty(even)
        cpu.standard_normals(seed, draws.numpy())
    else:
        draws = reference.standard_normals(seed, even)
    return draws[:count].view(tuple(shape))


def noisy_targets(targets: Tensor, standard_normal: Tensor, level: float) -> Tensor:
    """`T̃ = T + level·(max T − min T)·N(0,1)`, range taken per plane over [C, H, W]."""
    planes = targets.flatten(1)
    spread = planes.amax(dim=1) - planes.amin(dim=1)  # faster than torch.aminmax along a dim (docs/performance.md)
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
        taps = cpu.gaussian_taps(SSIM_WINDOW_PX, SSIM_SIGMA_PX).astype(x.dtype)
        valid = (x.shape[0], height - taps.size + 1, width - taps.size + 1)
        derivatives = tuple(np.empty(valid, x.dtype) for _ in range(3))
        sums = cpu.ssim_forward(x, y, taps, SSIM_K1**2, SSIM_K2**2, *derivatives)
        ctx.derivatives, ctx.taps, ctx.count = derivatives, taps, channels * valid[1] * valid[2]
        ctx.save_for_backward(recon, targets)
        return torch.from_numpy(sums.reshape(planes, channels).sum(axis=1) / ctx.count).to(recon.device, recon.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:
        recon, targets = ctx.saved_tensors
        x, y = _FusedSsim.images(recon, targets)
        weights = np.repeat(cpu_array(grad).astype(np.float64) / ctx.count, recon.shape[1])
        gradient = np.empty_like(x)
        cpu.ssim_backward(*ctx.derivatives, weights, x, y, ctx.taps, gradient)
        return torch.from_numpy(gradient).view(recon.shape).to(recon.device), None


def ssim_per_plane(recon: Tensor, targets: Tensor, backend: str = "auto") -> Tensor:
    """SSIM [M] of [M, C, H, W] images, Gaussian window 11 px, σ 1.5 px, data range 1.

    Backend `torch` is pytorch-msssim, the reference, differentiable in both arguments. On the CPU
    (`auto`, `numba`) the fused kernels compute the same numbers, differentiable in `recon`. Images
    smaller than the window go to the reference, which then blurs only the long axis.
    """
    if resolve_backend(backend, recon.device) != "numba" or min(recon.shape[-2:]) < SSIM_WINDOW_PX:
        return reference.ssim_per_plane(recon, targets)
    return _FusedSsim.apply(recon, targets)


class _FusedPixelTerms(torch.autograd.Function):
    """Per plane [M]: MSE(Î,T) + MSE(Î·a, T̃·a) + MSE(Î·b, T̃·b), and MSE(Î,T) alone (not differentiated),
    with a the focus weight [M, H, W] and b the guide [M, C, H, W] (`multiplane_loss` passes √w_f·Mask and
    √w_p·T̃). The gradient is formed in the same pass as the value and scaled in backward."""

    @staticmethod
    def forward(ctx, recon: Tensor, targets: Tensor, noisy: Tensor, focus: Tensor, guide: Tensor
                ) -> tuple[Tensor, Tensor]:
        x = cpu_array(recon)
        gradient = np.empty_like(x)
        sums = cpu.pixel_terms(x, *(cpu_array(t).astype(x.dtype, copy=False) for t in (targets, noisy, focus, guide)),
                               gradient)
        count = x[0].size
        ctx.gradient, ctx.count = gradient, count
        values, mse = (torch.from_numpy(v / count).to(recon.device, recon.dtype) for v in (sums.sum(axis=1), sums[:, 0]))
        ctx.mark_non_differentiable(mse)
        return values, mse

    @staticmethod
    def backward(ctx, grad: Tensor, _: Tensor) -> tuple[Tensor, None, None, None, None]:
        scale = (grad / ctx.count).view(-1, 1, 1, 1)
        return torch.from_numpy(ctx.gradient).to(grad.device) * scale, None, None, None, None


def _scaled(values: Tensor, weight: float) -> Tensor:
    """√weight·values; `values` itself at weight 1, so that the paper's loss keeps its arithmetic bit for bit."""
    return values if weight == 1 else values * math.sqrt(weight)


def multiplane_loss(recon: Tensor, targets: Tensor, masks: Tensor, noisy: Tensor, ssim_weight: float = 0.005,
                    backend: str = "auto", focus_weight: float = 1.0, product_weight: float = 1.0
                    ) -> tuple[Tensor, Tensor]:
    """Σ_m [MSE(Î,T) + w_f·MSE(Î·Mask, T̃·Mask) + w_p·MSE(Î·T̃, T̃·T̃) + w·(1 − SSIM(Î,T))], the paper's
    with w_f = w_p = 1 (method.md §6), weights ≥ 0.

    recon, targets, noisy: [M, C, H, W]; masks: [M, H, W]. Returns the loss and the plain
    per-plane MSE(Î, T) [M] (detached), from which progress PSNR is read at no extra cost. `backend`
    picks the reference or the fused CPU kernels, as it picks the rasterizer.
    """
    structure = ssim_weight * (1 - ssim_per_plane(recon, targets, backend))
    if resolve_backend(backend, recon.device) == "numba":
        pixel, mse = _FusedPixelTerms.apply(recon, targets, noisy, _scaled(masks, focus_weight),
                                            _scaled(noisy, product_weight))
        return (pixel + structure).sum(), mse
    pixel, mse = reference.pixel_terms(recon, targets, noisy, masks, focus_weight, product_weight)
    return (pixel + structure).sum(), mse
