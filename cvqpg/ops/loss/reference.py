"""The training loss's PyTorch reference (method.md §6): the pixel-wise terms and pytorch-msssim's SSIM,
differentiated by autograd, and the targets' noise as counter-based draws."""

from __future__ import annotations

import functools
import inspect
import math
from typing import ContextManager

import torch
from pytorch_msssim import ssim
from pytorch_msssim.ssim import _fspecial_gauss_1d
from torch import Tensor

from .cpu import GOLDEN_GAMMA, MIX_MULTIPLIERS, MIX_SHIFTS, SSIM_TAPS, UNIFORM_BITS

SSIM_WINDOW_PX = SSIM_TAPS  # 11, the CPU kernels' constant window
SSIM_SIGMA_PX = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03  # stabilisers, as fractions of the data range (1)


def pixel_terms(recon: Tensor, targets: Tensor, noisy: Tensor, masks: Tensor, focus_weight: float = 1.0,
                product_weight: float = 1.0) -> tuple[Tensor, Tensor]:
    """Per plane [M]: MSE(Î,T) + w_f·MSE(Î·Mask, T̃·Mask) + w_p·MSE(Î·T̃, T̃·T̃), and MSE(Î,T) alone (detached).
    recon, targets, noisy: [M, C, H, W]; masks: [M, H, W]; the paper's weights are 1."""
    dims = (1, 2, 3)
    mask = masks[:, None]
    mse = ((recon - targets) ** 2).mean(dim=dims)
    masked = ((recon * mask - noisy * mask) ** 2).mean(dim=dims)
    correlation = ((recon * noisy - noisy * noisy) ** 2).mean(dim=dims)
    return mse + focus_weight * masked + product_weight * correlation, mse.detach()


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
    # oneDNN's depthwise 1×11 convolutions are slower than PyTorch's own (docs/performance.md, "Measured choices").
    with _without_onednn():
        return ssim(recon, targets, data_range=1.0, size_average=False,
                    win=ssim_window(recon.shape[1], recon.dtype, recon.device))


def _as_int64(bits: int) -> int:
    """The int64 with the same 64 bits as an unsigned value: PyTorch has no uint64 arithmetic, and its
    int64 products and sums wrap as uint64's do."""
    return bits - (1 << 64) if bits >= 1 << 63 else bits


def _shifted_right(values: Tensor, bits: int) -> Tensor:
    """values >> bits for int64 values read as unsigned: PyTorch shifts arithmetically, so the copies
    of the sign bit are masked off."""
    return (values >> bits) & ((1 << (64 - bits)) - 1)


def _mixed(states: Tensor) -> Tensor:
    """SplitMix64's output function of counter states (int64 holding uint64 bits)."""
    for shift, multiplier in zip(MIX_SHIFTS, MIX_MULTIPLIERS):
        states = (states ^ _shifted_right(states, int(shift))) * _as_int64(int(multiplier))
    return states ^ _shifted_right(states, int(MIX_SHIFTS[-1]))


def standard_normals(seed: int, count: int) -> Tensor:
    """[count] standard normal draws (float32, count even) as `cpu.standard_normals` makes them: values
    2p and 2p + 1 from the counter p, SplitMix64's 64 bits of seed + (p + 1)·γ giving two 23-bit
    uniforms u = (k + ½)·2⁻²³ (the top bits) and v (the low bits), and Box–Muller
    √(−2 ln u)·(cos 2πv, sin 2πv). With PyTorch's ln, cos and sin, which the kernel replaces with its
    vectorised own: the same numbers up to their rounding."""
    counters = torch.arange(1, count // 2 + 1, dtype=torch.int64)
    bits = _mixed(seed + counters * _as_int64(int(GOLDEN_GAMMA)))
    scale = 2.0**-UNIFORM_BITS
    uniforms = (_shifted_right(bits, 64 - UNIFORM_BITS).float() + 0.5) * scale  # exact in float32
    angles = (bits & (2**UNIFORM_BITS - 1)).double() * (2 * math.pi * scale)
    radii = torch.sqrt(-2 * torch.log(uniforms)).double()  # float32 like the kernel's, its product float64
    return torch.stack([radii * torch.cos(angles), radii * torch.sin(angles)], dim=1).flatten().float()
