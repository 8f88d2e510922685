"""Rasterization: the complex hologram `H_c(p) = Σ_n G_{n,c}(p)` on the W×H SLM grid (SPEC §2).

`rasterize` is the one entry point; it hands the activated primitives to a backend that sums them
into the hologram. Both backends reduce each primitive to the same `Splats` quantities (centre,
inverse covariance, footprint, chirp). The reference backend does it with plain differentiable
PyTorch (`splats`), then evaluates each primitive on a square patch covering its 3σ_major footprint
(primitives grouped by patch size), recomputing chunks in the backward pass instead of storing them,
so memory stays bounded by the chunk size whatever N is. The fused CPU backend does the reduction
and its chain rule inside its kernels (`kernels.splat_geometry`), where it costs a fraction of the
autograd graph's time.
"""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass
from typing import Callable, Literal, Sequence

import numba
import numpy as np
import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from . import cpu as kernels
from ...primitives import COVARIANCE_REGULARISER_PX2, Primitives, inverse_covariance, major_sigma_px

Qpf = Literal["mahalanobis", "standard"]

FOOTPRINT_SIGMAS = 3.0
EXPONENT_FLOOR = -50.0
CHUNK_ELEMENTS = 1 << 20
PARTIAL_BUFFER_BYTES = 1 << 30
MIN_PATCH_RADIUS_PX = 2


@dataclass
class Splats:
    """What a backend needs per primitive; the phase is `φ_c + k_c·chirp·(D² or |p−x|²)`."""

    position_px: Tensor  # [N, 2]
    conic: Tensor  # [N, 3]: Σ⁻¹ entries (a, b, c) in 1/px²
    reach_px: Tensor  # [N]: footprint radius 3σ_major (no gradient)
    chirp: Tensor  # [N, 1] shared or [N, C] per channel: m per unit of the squared distance the QPF uses
    amplitude: Tensor  # [N, C]
    phase_rad: Tensor  # [N, C]
    opacity: Tensor  # [N]
    mahalanobis: bool  # QPF over D² (True) or over |p − x|² in px² (False)

    def tensors(self) -> tuple[Tensor, ...]:
        return (self.position_px, self.conic, self.reach_px, self.chirp, self.amplitude, self.phase_rad,
                self.opacity)

    def select(self, index: Tensor) -> "Splats":
        return Splats(*(t[index] for t in self.tensors()), self.mahalanobis)


def curvature_columns(curvature_per_m: Tensor) -> Tensor:
    """Curvatures (1/m) as [N, S]: one shared column (S = 1) or one per channel (S = C)."""
    return curvature_per_m if curvature_per_m.dim() == 2 else curvature_per_m[:, None]


def splats(prims: Primitives, pixel_pitch: float, qpf: Qpf) -> Splats:
    """Per-primitive quantities of SPEC §2 (differentiable, except the footprint radius)."""
    a, b, c = inverse_covariance(prims.scale_px, prims.rotation_rad)
    with torch.no_grad():
        reach = FOOTPRINT_SIGMAS * major_sigma_px(prims.scale_px)
    half_curvature = 0.5 * pixel_pitch**2 * curvature_columns(prims.curvature_per_m)
    mahalanobis = qpf == "mahalanobis"
    chirp = half_curvature * prims.scale_px.prod(dim=1, keepdim=True) if mahalanobis else half_curvature
    return Splats(prims.position_px, torch.stack([a, b, c], dim=1), reach, chirp, prims.amplitude,
                  prims.phase_rad, prims.opacity, mahalanobis)


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
                real, imag = contributions(Splats(*tensors, qpf), px.to(real_dtype), py.to(real_dtype),
                                           wavenumbers)
                return torch.stack([real, imag]).mul(valid).flatten(2)

            values = checkpoint(evaluate, *group.tensors(), use_reentrant=False)
            accumulated = accumulated.index_add(2, pixel_index, values)
    return torch.complex(accumulated[0], accumulated[1]).reshape(channels, height, width)


def splat_reference(prims: Primitives, width: int, height: int, wavenumbers: Tensor, pixel_pitch: float,
                    qpf: Qpf) -> Tensor:
    """Pure-PyTorch backend: complex hologram [C, H, W] (dtype follows the primitives), pitch in m."""
    return sum_patches(splats(prims, pixel_pitch, qpf), width, height, wavenumbers)


@functools.lru_cache(maxsize=8)
def _reused_lanes(shape: tuple[int, ...], thread: int) -> np.ndarray:
    """A zero-initialised float32 array kept between calls (one per calling thread): allocating and
    zeroing tens of MB per step costs more than the kernels' own passes over them. Its users keep the
    parts they rely on zero."""
    return np.zeros(shape, np.float32)


def _float32_arrays(*tensors: Tensor) -> tuple[np.ndarray, ...]:
    """Contiguous float32 copies of the tensors on the CPU, which the kernels read (and keep for the backward pass)."""
    return tuple(t.detach().to("cpu", torch.float32, copy=True).contiguous().numpy() for t in tensors)


class _FusedSplat(torch.autograd.Function):
    """The Numba kernels behind one autograd boundary: the complex hologram [C, H, W] of the primitives.

    `kernels.splat_geometry` reduces the primitives to Σ⁻¹, footprints and chirps (`splats`' reduction), and
    `kernels.geometry_gradients` carries their gradients back to scales, rotations and curvatures.
    The kernels take the primitives in `kernels.locality_order` (each thread every T-th of them).
    They work on float32 lane images [2, H, (W + STRIP)·C] (`kernels`); the forward pass sums its
    threads' images into the complex hologram and clears them in one pass, and the backward pass
    turns the incoming complex gradient into a lane image in one.
    """

    @staticmethod
    def forward(ctx, position, scale, rotation, curvature, color, phase, opacity, wavenumbers, pixel_pitch, mahalanobis,
                width, height):
        position_a, scale_a, rotation_a, curvature_a, color_a, phase_a, opacity_a = _float32_arrays(
            position, scale, rotation, curvature_columns(curvature), color, phase, opacity)
        count = scale_a.shape[0]
        terms, conic, reach = np.empty((4, count)), np.empty((count, 3), np.float32), np.empty(count, np.float32)
        chirp = np.empty(curvature_a.shape, np.float32)
        half_pitch2 = 0.5 * pixel_pitch**2
        kernels.splat_geometry(scale_a, rotation_a, curvature_a, COVARIANCE_REGULARISER_PX2, FOOTPRINT_SIGMAS,
                               half_pitch2, mahalanobis, terms, conic, reach, chirp)
        arrays = (position_a, conic, reach, chirp, color_a, phase_a, opacity_a)
        order = kernels.locality_order(position_a, height, width)
        k = wavenumbers.detach().to("cpu", torch.float64).numpy()
        channels = color.shape[1]
        lane_width = kernels.lane_image_width(width, channels)
        threads = max(1, min(numba.get_num_threads(), PARTIAL_BUFFER_BYTES // (height * lane_width * 8)))
        partial = _reused_lanes((threads, 2, height, lane_width), threading.get_ident())
        out = torch.empty(channels, height, width, dtype=torch.complex64)
        try:
            kernels.splat_forward(order, *arrays, k, mahalanobis, partial)
            kernels.gather_partials(partial, out.numpy())  # leaves `partial` zero for the next call
        except BaseException:
            partial.fill(0.0)
            raise
        ctx.arrays, ctx.order, ctx.wavenumbers, ctx.mahalanobis = arrays, order, k, mahalanobis
        ctx.geometry = scale_a, curvature_a, half_pitch2, terms, curvature.shape
        ctx.dtype, ctx.device = position.dtype, position.device
        return out.to(device=position.device, dtype=torch.promote_types(position.dtype, torch.complex64))

    @staticmethod
    def backward(ctx, grad):
        position, conic, _, chirp, color, phase, opacity = ctx.arrays
        grads = tuple(np.zeros(a.shape, np.float64) for a in (position, conic, chirp, color, phase, opacity))
        channels, height, width = grad.shape
        lanes = _reused_lanes((2, height, kernels.lane_image_width(width, channels)), threading.get_ident())
        kernels.split_lanes(grad.detach().to("cpu", torch.complex64).contiguous().numpy(), lanes)  # padding stays 0
        kernels.splat_backward(ctx.order, *ctx.arrays, ctx.wavenumbers, ctx.mahalanobis, lanes, *grads,
                               numba.get_num_threads())
        g_position, g_conic, g_chirp, g_color, g_phase, g_opacity = grads
        scale, curvature, half_pitch2, terms, curvature_shape = ctx.geometry
        g_scale, g_rotation, g_curvature = np.empty(scale.shape), np.empty(scale.shape[0]), np.empty(curvature.shape)
        kernels.geometry_gradients(scale, curvature, half_pitch2, ctx.mahalanobis, terms, g_conic, g_chirp, g_scale,
                                   g_rotation, g_curvature)
        results = (g_position, g_scale, g_rotation, g_curvature.reshape(curvature_shape), g_color, g_phase, g_opacity)
        return (*(torch.from_numpy(g).to(device=ctx.device, dtype=ctx.dtype) for g in results),
                None, None, None, None, None)


def splat_fused(prims: Primitives, width: int, height: int, wavenumbers: Tensor, pixel_pitch: float,
                qpf: Qpf) -> Tensor:
    """Fused CPU backend (Numba): complex hologram [C, H, W], float32 inside, pitch in m."""
    return _FusedSplat.apply(prims.position_px, prims.scale_px, prims.rotation_rad, prims.curvature_per_m,
                             prims.amplitude, prims.phase_rad, prims.opacity, wavenumbers, pixel_pitch,
                             qpf == "mahalanobis", width, height)


Backend = Callable[[Primitives, int, int, Tensor, float, Qpf], Tensor]
BACKENDS: dict[str, Backend] = {"torch": splat_reference, "numba": splat_fused}


def cpu_array(tensor: Tensor) -> np.ndarray:
    """A tensor's values as a contiguous NumPy array on the CPU (no gradient), for the Numba kernels."""
    return tensor.detach().cpu().contiguous().numpy()


def resolve_backend(backend: str, device: torch.device | str) -> str:
    """`auto` → the fused kernels on CPU, the PyTorch reference elsewhere."""
    if backend == "auto":
        return "numba" if torch.device(device).type == "cpu" else "torch"
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {backend!r}; choose auto or one of "
                         f"{', '.join(sorted(BACKENDS))}")
    if backend == "numba" and torch.device(device).type != "cpu":
        raise ValueError("the numba backend runs on the CPU; use --backend torch with --device cuda")
    return backend


def wavenumbers_for(wavelengths_m: Sequence[float]) -> Tensor:
    """k_c = 2π/λ_c (1/m) as a float64 tensor."""
    return torch.tensor([2 * math.pi / w for w in wavelengths_m], dtype=torch.float64)


def rasterize(prims: Primitives, width: int, height: int, wavelengths_m: Sequence[float],
              pixel_pitch: float, qpf: Qpf = "mahalanobis", backend: str = "auto") -> Tensor:
    """Complex hologram [C, H, W] of the activated primitives on the W×H grid (px), pitch in m."""
    backend = resolve_backend(backend, prims.position_px.device)
    return BACKENDS[backend](prims, width, height, wavenumbers_for(wavelengths_m), pixel_pitch, qpf)
