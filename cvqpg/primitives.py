"""Complex-valued Gaussian primitives: raw parameters, initialisation and activations (SPEC §2, §4)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from .config import FitConfig

COVARIANCE_REGULARISER_PX2 = 0.1
MIN_SCALE_PX = 0.1
MAX_LOG_SCALE = math.log(1e4)
DET_FLOOR = 1e-10
POSITION_CLAMP = 0.999
INIT_SCALE_RANGE_PX = (1.5, 5.0)
INIT_OPACITY_RAW = -0.5


class TensorFields:
    """Per-primitive tensors of a dataclass, handled as one dict (checkpoints, files, devices)."""

    @property
    def count(self) -> int:
        return getattr(self, fields(self)[0].name).shape[0]

    def tensors(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_tensors(cls, tensors: dict[str, Tensor]):
        return cls(**{f.name: tensors[f.name] for f in fields(cls)})

    def to(self, device: torch.device | str, dtype: torch.dtype | None = None):
        return self.from_tensors({k: v.to(device, dtype) for k, v in self.tensors().items()})

    def detached(self):
        return self.from_tensors({k: v.detach().clone() for k, v in self.tensors().items()})


@dataclass
class Gaussians(TensorFields):
    """Raw (pre-activation) parameters of N primitives; each tensor is an optimisable leaf."""

    position: Tensor  # [N, 2] → px via (tanh+1)/2·(W, H)
    scale: Tensor  # [N, 2] → px via exp + 0.1
    rotation: Tensor  # [N] rad
    color: Tensor  # [N, C] amplitude
    phase: Tensor  # [N, C] → rad via mod 2π
    opacity: Tensor  # [N] → sigmoid
    curvature: Tensor  # [N] → 1/m via γ_max·tanh

    @property
    def channels(self) -> int:
        return self.color.shape[1]


@dataclass
class Primitives(TensorFields):
    """Activated, physical parameters that the rasterizer consumes and a model file stores."""

    position_px: Tensor  # [N, 2] (x, y), pixel centres at integers
    scale_px: Tensor  # [N, 2]
    rotation_rad: Tensor  # [N]
    amplitude: Tensor  # [N, C]
    phase_rad: Tensor  # [N, C]
    opacity: Tensor  # [N]
    curvature_per_m: Tensor  # [N], γ in 1/m

    @property
    def channels(self) -> int:
        return self.amplitude.shape[1]


def init_gaussians(count: int, channels: int, width: int, height: int, seed: int,
                   device: torch.device | str = "cpu") -> Gaussians:
    """The reference initialisation: draws from a CPU generator in SPEC order, then moves to `device`."""
    generator = torch.Generator().manual_seed(seed)
    u_position = torch.rand(count, 2, generator=generator)
    u_color = torch.rand(count, channels, generator=generator)
    u_scale = torch.rand(count, 2, generator=generator)
    u_rotation = torch.rand(count, generator=generator)
    low, high = INIT_SCALE_RANGE_PX
    raw = Gaussians(
        position=torch.atanh(torch.clamp(2 * u_position - 1, -POSITION_CLAMP, POSITION_CLAMP)),
        scale=torch.log(low + (high - low) * u_scale),
        rotation=(2 * u_rotation - 1) * math.pi,
        color=u_color,
        phase=torch.zeros(count, channels),
        opacity=torch.full((count,), INIT_OPACITY_RAW),
        curvature=torch.zeros(count),
    )
    return raw.to(device)


def positions_px(raw_position: Tensor, width: int, height: int) -> Tensor:
    """Raw position → px: `(tanh(raw)+1)/2 · (W, H)`."""
    extent = torch.tensor([width, height], dtype=raw_position.dtype, device=raw_position.device)
    return (torch.tanh(raw_position) + 1) / 2 * extent


def scales_px(raw_scale: Tensor) -> Tensor:
    """Raw scale → px: `exp(raw) + 0.1`, capped at 1e4 px so Σ stays finite in float32."""
    return torch.exp(torch.clamp(raw_scale, max=MAX_LOG_SCALE)) + MIN_SCALE_PX


def curvature_bound(scale_px: Tensor, config: FitConfig) -> Tensor:
    """γ_max (1/m) per primitive: `η λ_min / (6 σ Δx²)` with σ = max scale (px), or the global bound."""
    if config.bound == "global":
        return torch.full_like(scale_px[:, 0], config.global_bound)
    sigma_px = scale_px.max(dim=1).values
    return config.eta * min(config.wavelengths) / (6 * sigma_px * config.pixel_pitch**2)


def activate(raw: Gaussians, config: FitConfig) -> Primitives:
    """Apply SPEC §2's activations; the curvature bound follows `config.bound`."""
    scale = scales_px(raw.scale)
    return Primitives(
        position_px=positions_px(raw.position, config.width, config.height),
        scale_px=scale,
        rotation_rad=raw.rotation,
        amplitude=raw.color,
        phase_rad=torch.remainder(raw.phase, 2 * math.pi),
        opacity=torch.sigmoid(raw.opacity),
        curvature_per_m=curvature_bound(scale, config) * torch.tanh(raw.curvature),
    )


def covariance(scale_px: Tensor, rotation_rad: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Entries (Σxx, Σxy, Σyy) of `Σ = R S Sᵀ Rᵀ + 0.1·I` in px²."""
    cos, sin = torch.cos(rotation_rad), torch.sin(rotation_rad)
    sx2, sy2 = scale_px[:, 0] ** 2, scale_px[:, 1] ** 2
    sxx = cos * cos * sx2 + sin * sin * sy2 + COVARIANCE_REGULARISER_PX2
    syy = sin * sin * sx2 + cos * cos * sy2 + COVARIANCE_REGULARISER_PX2
    sxy = cos * sin * (sx2 - sy2)
    return sxx, sxy, syy


def inverse_covariance(scale_px: Tensor, rotation_rad: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Entries (a, b, c) of Σ⁻¹ = [[a, b], [b, c]] in 1/px², determinant clamped at 1e-10."""
    sxx, sxy, syy = covariance(scale_px, rotation_rad)
    det = torch.clamp(sxx * syy - sxy * sxy, min=DET_FLOOR)
    return syy / det, -sxy / det, sxx / det


def major_sigma_px(scale_px: Tensor, rotation_rad: Tensor) -> Tensor:
    """σ_major (px): square root of Σ's largest eigenvalue."""
    sxx, sxy, syy = covariance(scale_px, rotation_rad)
    half_trace = (sxx + syy) / 2
    return torch.sqrt(half_trace + torch.sqrt(((sxx - syy) / 2) ** 2 + sxy**2))
