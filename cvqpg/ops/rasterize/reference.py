"""The rasterizer's PyTorch reference: the complex hologram `H_c(p) = Σ_n G_{n,c}(p)` on the W×H SLM grid (method.md §2).

`splats` reduces each primitive to the quantities every backend sums (centre, inverse covariance,
footprint, chirp) in plain differentiable PyTorch. `sum_patches` evaluates each primitive on a
square patch covering its 3σ_major footprint (primitives grouped by patch size), recomputing chunks
in the backward pass instead of storing them, so memory stays bounded by the chunk size whatever N
is. The kernels (`cpu`, `gpu`) are held against these functions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from ...phase import phase_form
from ...primitives import Primitives, inverse_covariance, major_sigma_px

Qpf = Literal["mahalanobis", "standard"]

FOOTPRINT_SIGMAS = 3.0
EXPONENT_FLOOR = -50.0
CHUNK_ELEMENTS = 1 << 20
MIN_PATCH_RADIUS_PX = 2


@dataclass
class Splats:
    """What a backend needs per primitive; the phase is `φ_c + k_c·(chirp·(D² or |p−x|²) + ψ_form)`, with
    ψ_form = P_a dx² + 2P_b dx dy + P_c dy² + L_x dx + L_y dy the phase terms beyond the curvature (`phase.phase_form`),
    absent (None) without them."""

    position_px: Tensor  # [N, 2]
    conic: Tensor  # [N, 3]: Σ⁻¹ entries (a, b, c) in 1/px²
    reach_px: Tensor  # [N]: footprint radius 3σ_major (no gradient)
    chirp: Tensor  # [N, 1] shared or [N, C] per channel: m per unit of the squared distance the QPF uses
    amplitude: Tensor  # [N, C]
    phase_rad: Tensor  # [N, C]
    opacity: Tensor  # [N]
    mahalanobis: bool  # QPF over D² (True) or over |p − x|² in px² (False)
    form: Tensor | None = None  # [N, 5]: (P_a, P_b, P_c) in m/px², (L_x, L_y) in m/px, shared by the channels

    def tensors(self) -> tuple[Tensor, ...]:
        own = (self.position_px, self.conic, self.reach_px, self.chirp, self.amplitude, self.phase_rad, self.opacity)
        return own if self.form is None else (*own, self.form)

    @staticmethod
    def of(tensors: tuple[Tensor, ...], mahalanobis: bool) -> "Splats":
        """The splats of `tensors()`'s tuple."""
        return Splats(*tensors[:7], mahalanobis, *tensors[7:])

    def select(self, index: Tensor) -> "Splats":
        return Splats.of(tuple(t[index] for t in self.tensors()), self.mahalanobis)


def curvature_columns(curvature_per_m: Tensor) -> Tensor:
    """Curvatures (1/m) as [N, S]: one shared column (S = 1) or one per channel (S = C)."""
    return curvature_per_m if curvature_per_m.dim() == 2 else curvature_per_m[:, None]


def splats(prims: Primitives, pixel_pitch: float, qpf: Qpf) -> Splats:
    """Per-primitive quantities of method.md §2 (differentiable, except the footprint radius)."""
    a, b, c = inverse_covariance(prims.scale_px, prims.rotation_rad)
    with torch.no_grad():
        reach = FOOTPRINT_SIGMAS * major_sigma_px(prims.scale_px)
    half_curvature = 0.5 * pixel_pitch**2 * curvature_columns(prims.curvature_per_m)
    mahalanobis = qpf == "mahalanobis"
    chirp = half_curvature * prims.scale_px.prod(dim=1, keepdim=True) if mahalanobis else half_curvature
    return Splats(prims.position_px, torch.stack([a, b, c], dim=1), reach, chirp, prims.amplitude,
                  prims.phase_rad, prims.opacity, mahalanobis, phase_form(prims.terms, prims.rotation_rad, pixel_pitch))


def contributions(s: Splats, px: Tensor, py: Tensor, wavenumbers: Tensor) -> tuple[Tensor, Tensor]:
    """Real and imaginary parts [C, K, P] of G_{k,c} at pixel coordinates px, py [K, P] (px).

    Pixels outside a primitive's 3σ_major circle contribute zero.
    """
    a, b, c = (s.conic[:, i:i + 1] for i in range(3))
    dx = px - s.position_px[:, 0:1]
    dy = py - s.position_px[:, 1:2]
    mahalanobis2 = a * dx * dx + 2 * b * dx * dy + c * dy * dy
    radius2 = dx * dx + dy * dy
    envelope = torch.exp(torch.clamp(-0.5 * mahalanobis2, min=EXPONENT_FLOOR))
    envelope = envelope * (radius2 <= (s.reach_px * s.reach_px)[:, None])
    path_m = s.chirp.T[:, :, None] * (mahalanobis2 if s.mahalanobis else radius2)[None]  # [1 or C, K, P]
    if s.form is not None:
        pa, pb, pc, lx, ly = (s.form[:, i:i + 1] for i in range(5))
        path_m = path_m + (pa * dx * dx + 2 * pb * dx * dy + pc * dy * dy + lx * dx + ly * dy)[None]
    amplitude = s.amplitude.T[:, :, None] * (s.opacity[:, None] * envelope)[None]  # [C, K, P]
    phase = s.phase_rad.T[:, :, None] + wavenumbers[:, None, None] * path_m
    return amplitude * torch.cos(phase), amplitude * torch.sin(phase)


def _pixel_sets(centers: Tensor, radius: int, width: int, height: int
                ) -> tuple[Tensor, Tensor, Tensor]:
    """Integer pixel coordinates [K, P] of each primitive's patch (or the whole image), and validity."""
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


def sum_patches(s: Splats, width: int, height: int, wavenumbers: Tensor) -> Tensor:
    """The splats summed on patches in plain PyTorch: complex hologram [C, H, W] (dtype follows the splats)."""
    channels = s.amplitude.shape[1]
    real_dtype = s.position_px.dtype
    wavenumbers = wavenumbers.to(device=s.position_px.device, dtype=real_dtype)
    accumulated = s.position_px.new_zeros(2, channels, height * width)
    radius = torch.ceil(s.reach_px).clamp(min=MIN_PATCH_RADIUS_PX)
    bucket = torch.ceil(2 * torch.log2(radius)).long()  # patch radii grow by √2 per bucket
    for level in torch.unique(bucket).tolist():
        members = torch.nonzero(bucket == level).flatten()
        patch_radius = math.ceil(2 ** (level / 2))
        patch_pixels = min((2 * patch_radius + 1) ** 2, width * height)
        chunk = max(1, CHUNK_ELEMENTS // (patch_pixels * channels))
        for start in range(0, members.numel(), chunk):
            group = s.select(members[start:start + chunk])
            px, py, valid = _pixel_sets(group.position_px.detach(), patch_radius, width, height)
            pixel_index = torch.where(valid, py * width + px, 0).flatten()

            def evaluate(*tensors: Tensor, px=px, py=py, valid=valid, qpf=group.mahalanobis) -> Tensor:
                real, imag = contributions(Splats.of(tensors, qpf), px.to(real_dtype), py.to(real_dtype),
                                           wavenumbers)
                return torch.stack([real, imag]).mul(valid).flatten(2)

            values = checkpoint(evaluate, *group.tensors(), use_reentrant=False)
            accumulated = accumulated.index_add(2, pixel_index, values)
    return torch.complex(accumulated[0], accumulated[1]).reshape(channels, height, width)


def splat_reference(prims: Primitives, width: int, height: int, wavenumbers: Tensor, pixel_pitch: float,
                    qpf: Qpf) -> Tensor:
    """Pure-PyTorch backend: complex hologram [C, H, W] (dtype follows the primitives), pitch in m."""
    return sum_patches(splats(prims, pixel_pitch, qpf), width, height, wavenumbers)
