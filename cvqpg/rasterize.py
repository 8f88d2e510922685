"""Rasterization: the complex hologram `H_c(p) = Σ_n G_{n,c}(p)` on the W×H SLM grid (SPEC §2).

`rasterize` is the one entry point; backends register in `BACKENDS`. The reference backend is plain
PyTorch: each primitive is evaluated only on a square patch that covers its 3σ_major footprint
(primitives are grouped by patch size), chunks are recomputed in the backward pass instead of stored,
so memory stays bounded by the chunk size whatever N is.
"""

from __future__ import annotations

import math
from typing import Callable, Literal, Sequence

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from .primitives import Primitives, inverse_covariance, major_sigma_px

Qpf = Literal["mahalanobis", "standard"]

FOOTPRINT_SIGMAS = 3.0
EXPONENT_FLOOR = -50.0
CHUNK_ELEMENTS = 1 << 20
MIN_PATCH_RADIUS_PX = 2


def contributions(prims: Primitives, px: Tensor, py: Tensor, wavenumbers: Tensor,
                  pixel_pitch: float, qpf: Qpf) -> tuple[Tensor, Tensor]:
    """Real and imaginary parts [C, K, P] of G_{k,c} at pixel coordinates px, py [K, P] (px).

    Pixels outside a primitive's 3σ_major circle contribute zero.
    """
    a, b, c = inverse_covariance(prims.scale_px, prims.rotation_rad)
    dx = px - prims.position_px[:, 0:1]
    dy = py - prims.position_px[:, 1:2]
    mahalanobis2 = a[:, None] * dx * dx + 2 * b[:, None] * dx * dy + c[:, None] * dy * dy
    radius2 = dx * dx + dy * dy
    reach = FOOTPRINT_SIGMAS * major_sigma_px(prims.scale_px, prims.rotation_rad)
    envelope = torch.exp(torch.clamp(-0.5 * mahalanobis2, min=EXPONENT_FLOOR))
    envelope = envelope * (radius2 <= (reach * reach)[:, None])
    if qpf == "mahalanobis":
        path_scale = 0.5 * prims.curvature_per_m * prims.scale_px.prod(dim=1) * pixel_pitch**2
        path_m = path_scale[:, None] * mahalanobis2
    else:
        path_m = (0.5 * prims.curvature_per_m * pixel_pitch**2)[:, None] * radius2
    weight = (prims.opacity[:, None] * envelope)[None]  # [1, K, P]
    amplitude = prims.color.T[:, :, None] * weight  # [C, K, P]
    phase = prims.phase_rad.T[:, :, None] + wavenumbers[:, None, None] * path_m[None]
    return amplitude * torch.cos(phase), amplitude * torch.sin(phase)


def _patch_radius_px(prims: Primitives) -> Tensor:
    with torch.no_grad():
        reach = FOOTPRINT_SIGMAS * major_sigma_px(prims.scale_px, prims.rotation_rad)
        return torch.ceil(reach).clamp(min=MIN_PATCH_RADIUS_PX)


def _select(prims: Primitives, index: Tensor) -> Primitives:
    return Primitives(**{name: value[index] for name, value in vars(prims).items()})


def _pixel_sets(centers: Tensor, radius: int, width: int, height: int
                ) -> tuple[Tensor, Tensor, Tensor]:
    """Integer pixel coordinates [K, P] of each primitive's patch, and their validity."""
    device = centers.device
    if (2 * radius + 1) ** 2 >= width * height:
        ys, xs = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device),
                                indexing="ij")
        px = xs.reshape(1, -1).expand(centers.shape[0], -1)
        py = ys.reshape(1, -1).expand(centers.shape[0], -1)
        return px, py, torch.ones_like(px, dtype=torch.bool)
    offsets = torch.arange(-radius, radius + 1, device=device)
    oy, ox = torch.meshgrid(offsets, offsets, indexing="ij")
    rounded = torch.round(centers).long()
    px = rounded[:, 0:1] + ox.reshape(1, -1)
    py = rounded[:, 1:2] + oy.reshape(1, -1)
    valid = (px >= 0) & (px < width) & (py >= 0) & (py < height)
    return px, py, valid


def rasterize_reference(prims: Primitives, width: int, height: int, wavenumbers: Tensor,
                        pixel_pitch: float, qpf: Qpf = "mahalanobis") -> Tensor:
    """Pure-PyTorch rasterizer: complex hologram [C, H, W] (dtype follows the parameters)."""
    channels = prims.color.shape[1]
    real_dtype = prims.position_px.dtype
    wavenumbers = wavenumbers.to(device=prims.position_px.device, dtype=real_dtype)
    accumulated = prims.position_px.new_zeros(2, channels, height * width)
    radius = _patch_radius_px(prims)
    bucket = torch.clamp(torch.ceil(torch.log2(radius)), min=0).long()
    for level in torch.unique(bucket).tolist():
        members = torch.nonzero(bucket == level).flatten()
        patch_radius = 2 ** level
        patch_pixels = min((2 * patch_radius + 1) ** 2, width * height)
        chunk = max(1, CHUNK_ELEMENTS // (patch_pixels * channels))
        for start in range(0, members.numel(), chunk):
            group = _select(prims, members[start:start + chunk])
            px, py, valid = _pixel_sets(group.position_px.detach(), patch_radius, width, height)
            pixel_index = torch.where(valid, py * width + px, 0).flatten()

            def evaluate(*leaves: Tensor, px=px, py=py, valid=valid) -> Tensor:
                chunk_prims = Primitives(*leaves)
                real, imag = contributions(chunk_prims, px.to(real_dtype), py.to(real_dtype),
                                           wavenumbers, pixel_pitch, qpf)
                return torch.stack([real, imag]).mul(valid).flatten(2)

            values = checkpoint(evaluate, *vars(group).values(), use_reentrant=False)
            accumulated = accumulated.index_add(2, pixel_index, values)
    field = torch.complex(accumulated[0], accumulated[1])
    return field.reshape(channels, height, width)


Rasterizer = Callable[..., Tensor]
BACKENDS: dict[str, Rasterizer] = {"torch": rasterize_reference}


def wavenumbers_for(wavelengths_m: Sequence[float]) -> Tensor:
    """k_c = 2π/λ_c (1/m) as a float64 tensor."""
    return torch.tensor([2 * math.pi / w for w in wavelengths_m], dtype=torch.float64)


def rasterize(prims: Primitives, width: int, height: int, wavelengths_m: Sequence[float],
              pixel_pitch: float, qpf: Qpf = "mahalanobis", backend: str = "torch") -> Tensor:
    """Complex hologram [C, H, W] of the activated primitives on the W×H grid (px), pitch in m."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {backend!r}; choose one of {sorted(BACKENDS)}")
    return BACKENDS[backend](prims, width, height, wavenumbers_for(wavelengths_m), pixel_pitch, qpf)
