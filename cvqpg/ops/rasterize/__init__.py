"""The rasterizer: `rasterize`, its backends and their autograd boundaries.

Every backend sums the primitives' `reference.Splats` into the complex hologram [C, H, W]:

| backend  | where             | the sum                                    | its geometry (`splats`)      |
|----------|-------------------|--------------------------------------------|------------------------------|
| `torch`  | any device        | `reference.sum_patches` (autograd)         | PyTorch (autograd)           |
| `numba`  | CPU               | `cpu.splat_forward` / `cpu.splat_backward` | inside the kernels           |
| `triton` | CUDA              | `gpu.splat_forward` / `gpu.splat_backward` | PyTorch (autograd)           |

`auto` picks `numba` on the CPU and `triton` on CUDA when Triton imports (else `torch`). The Triton
kernels also run on the CPU under Triton's interpreter (`TRITON_INTERPRET=1`), which the tests use.
"""

from __future__ import annotations

import math
import threading
from typing import Callable, Sequence

import numba
import numpy as np
import torch
from torch import Tensor

from ...phase import FORM_COLUMNS, phase_form
from ...primitives import COVARIANCE_REGULARISER_PX2, Primitives, device_constants
from .. import resolve_backend
from . import cpu
from .reference import FOOTPRINT_SIGMAS, Qpf, curvature_columns, splat_reference, splats

PARTIAL_BUFFER_BYTES = 1 << 30
# The lane images that the calling thread keeps between calls (`_reused_lanes`), by use: they live as long as the
# thread, or until `release_buffers`.
_kept = threading.local()


def _reused_lanes(use: str, shape: tuple[int, ...]) -> np.ndarray:
    """A zero-initialised float32 array kept between calls, one per calling thread and `use` (the forward pass's
    partial images, the backward pass's lanes): allocating and zeroing tens of MB per step costs more than the
    kernels' own passes over them. A call with another shape replaces it, so a thread keeps at most one array per
    use. Its users keep the parts they rely on zero."""
    array = getattr(_kept, use, None)
    if array is None or array.shape != shape:
        setattr(_kept, use, None)  # the former array goes before the new one is made
        array = np.zeros(shape, np.float32)
        setattr(_kept, use, array)
    return array


def release_buffers() -> None:
    """Free the lane images that the calling thread keeps (`_reused_lanes`); for callers done rasterizing on the
    CPU, such as a program that goes on after its fits."""
    _kept.__dict__.clear()


def _float32_arrays(*tensors: Tensor) -> tuple[np.ndarray, ...]:
    """Contiguous float32 copies of the tensors on the CPU, which the kernels read (and keep for the backward pass)."""
    return tuple(t.detach().to("cpu", torch.float32, copy=True).contiguous().numpy() for t in tensors)


class _FusedSplat(torch.autograd.Function):
    """The Numba kernels behind one autograd boundary: the complex hologram [C, H, W] of the primitives.

    `cpu.splat_geometry` reduces the primitives to Σ⁻¹, footprints and chirps (`splats`' reduction), and
    `cpu.geometry_gradients` carries their gradients back to scales, rotations and curvatures.
    The kernels take the primitives in `cpu.locality_order` (each thread every T-th of them).
    They work on float32 lane images [2, H, (W + STRIP)·C] (`cpu`); the forward pass sums its
    threads' images into the complex hologram and clears them in one pass, and the backward pass
    turns the incoming complex gradient into a lane image in one.
    """

    @staticmethod
    def forward(ctx, position, scale, rotation, curvature, form, color, phase, opacity, wavenumbers, pixel_pitch,
                mahalanobis, width, height):
        position_a, scale_a, rotation_a, curvature_a, color_a, phase_a, opacity_a = _float32_arrays(
            position, scale, rotation, curvature_columns(curvature), color, phase, opacity)
        form_a = np.zeros((0, FORM_COLUMNS), np.float32) if form is None else _float32_arrays(form)[0]
        count = scale_a.shape[0]
        terms, conic, reach = np.empty((4, count)), np.empty((count, 3), np.float32), np.empty(count, np.float32)
        chirp = np.empty(curvature_a.shape, np.float32)
        half_pitch2 = 0.5 * pixel_pitch**2
        cpu.splat_geometry(scale_a, rotation_a, curvature_a, COVARIANCE_REGULARISER_PX2, FOOTPRINT_SIGMAS,
                               half_pitch2, mahalanobis, terms, conic, reach, chirp)
        arrays = (position_a, conic, reach, chirp, form_a, color_a, phase_a, opacity_a)
        order = cpu.locality_order(position_a, height, width)
        k = wavenumbers.detach().to("cpu", torch.float64).numpy()
        channels = color.shape[1]
        lane_width = cpu.lane_image_width(width, channels)
        threads = max(1, min(numba.get_num_threads(), PARTIAL_BUFFER_BYTES // (height * lane_width * 8)))
        partial = _reused_lanes("partial", (threads, 2, height, lane_width))
        out = torch.empty(channels, height, width, dtype=torch.complex64)
        try:
            cpu.splat_forward(order, *arrays, k, mahalanobis, partial)
            cpu.gather_partials(partial, out.numpy())  # leaves `partial` zero for the next call
        except BaseException:
            partial.fill(0.0)
            raise
        ctx.arrays, ctx.order, ctx.wavenumbers, ctx.mahalanobis = arrays, order, k, mahalanobis
        ctx.geometry = scale_a, curvature_a, half_pitch2, terms, curvature.shape
        ctx.dtype, ctx.device = position.dtype, position.device
        return out.to(device=position.device, dtype=torch.promote_types(position.dtype, torch.complex64))

    @staticmethod
    def backward(ctx, grad):
        position, conic, _, chirp, form, color, phase, opacity = ctx.arrays
        grads = tuple(np.zeros(a.shape, np.float64) for a in (position, conic, chirp, form, color, phase, opacity))
        channels, height, width = grad.shape
        lanes = _reused_lanes("lanes", (2, height, cpu.lane_image_width(width, channels)))
        cpu.split_lanes(grad.detach().to("cpu", torch.complex64).contiguous().numpy(), lanes)  # padding stays 0
        cpu.splat_backward(ctx.order, *ctx.arrays, ctx.wavenumbers, ctx.mahalanobis, lanes, *grads,
                               numba.get_num_threads())
        g_position, g_conic, g_chirp, g_form, g_color, g_phase, g_opacity = grads
        scale, curvature, half_pitch2, terms, curvature_shape = ctx.geometry
        g_scale, g_rotation, g_curvature = np.empty(scale.shape), np.empty(scale.shape[0]), np.empty(curvature.shape)
        cpu.geometry_gradients(scale, curvature, half_pitch2, ctx.mahalanobis, terms, g_conic, g_chirp, g_scale,
                                   g_rotation, g_curvature)
        results = (g_position, g_scale, g_rotation, g_curvature.reshape(curvature_shape), g_form, g_color, g_phase,
                   g_opacity)
        gradients = [torch.from_numpy(g).to(device=ctx.device, dtype=ctx.dtype) for g in results]
        if not form.shape[0]:
            gradients[4] = None
        return (*gradients, None, None, None, None, None)


# The argument types that `_FusedSplat` passes to its kernels, the same for every fit (tests/
# test_compilation.py checks them against the fits' calls). A cold fit compiles its kernels from
# these, in two processes at once, neither waiting for the kernels that come before in a pass
# (`compilation`). Types, not signature strings: Numba's cache files a compile under what `compile`
# was given, and a call looks up types.
_F32, _F64, _C64, _I64, _BOOL = numba.float32, numba.float64, numba.complex64, numba.int64, numba.boolean
_SPLATS = (_I64[::1], _F32[:, ::1], _F32[:, ::1], _F32[::1], _F32[:, ::1], _F32[:, ::1], _F32[:, ::1], _F32[:, ::1],
           _F32[::1], _F64[::1], _BOOL)  # order, position, conic, reach, chirp, form, color ... wavenumbers, mahalanobis
KERNEL_TYPES = {
    cpu.splat_geometry: (_F32[:, ::1], _F32[::1], _F32[:, ::1], _F64, _F64, _F64, _BOOL,  # scale ... mahalanobis
                         _F64[:, ::1], _F32[:, ::1], _F32[::1], _F32[:, ::1]),  # terms, conic, reach, chirp
    cpu.locality_order: (_F32[:, ::1], _I64, _I64),
    cpu.splat_forward: (*_SPLATS, _F32[:, :, :, ::1]),
    cpu.gather_partials: (_F32[:, :, :, ::1], _C64[:, :, ::1]),
    cpu.split_lanes: (_C64[:, :, ::1], _F32[:, :, ::1]),
    cpu.splat_backward: (*_SPLATS, _F32[:, :, ::1], _F64[:, ::1], _F64[:, ::1], _F64[:, ::1], _F64[:, ::1],
                         _F64[:, ::1], _F64[:, ::1], _F64[::1], _I64),  # grad, g_position ... g_opacity, threads
    cpu.geometry_gradients: (_F32[:, ::1], _F32[:, ::1], _F64, _BOOL, _F64[:, ::1],  # scale ... terms
                             _F64[:, ::1], _F64[:, ::1], _F64[:, ::1], _F64[::1],  # g_conic ... g_rotation
                             _F64[:, ::1]),  # g_curvature
}
# The two loops over the primitives: 24 of the demo fit's 45 CPU s of kernel compilation.
PER_PRIMITIVE_KERNELS = (cpu.splat_forward, cpu.splat_backward)


def splat_fused(prims: Primitives, width: int, height: int, wavenumbers: Tensor, pixel_pitch: float,
                qpf: Qpf) -> Tensor:
    """Fused CPU backend (Numba): complex hologram [C, H, W], float32 inside, pitch in m. The phase terms beyond
    the curvature enter as their form (`phase.phase_form`, differentiated by autograd)."""
    return _FusedSplat.apply(prims.position_px, prims.scale_px, prims.rotation_rad, prims.curvature_per_m,
                             phase_form(prims.terms, prims.rotation_rad, pixel_pitch), prims.amplitude,
                             prims.phase_rad, prims.opacity, wavenumbers, pixel_pitch, qpf == "mahalanobis", width,
                             height)


class _TritonSplat(torch.autograd.Function):
    """The Triton kernels behind one autograd boundary: the complex hologram [C, H, W] of the splats'
    centres, conics and reaches, weights `w = amplitude·opacity`, phases and phase rates `κ = k·chirp`
    ([N, C] each), and the phase terms' form [N, 5] or None with the wavenumbers [C] (`splat_triton` forms them
    with autograd). Float32 inside; the gradients come back in each input's dtype, the reach's as None (the
    footprint carries none)."""

    @staticmethod
    def forward(ctx, position, conic, reach, weight, phase, rate, form, wavenumbers, width, height, mahalanobis):
        # Imported here: Triton takes seconds to import and only this backend needs it.
        from . import gpu

        has_form = form is not None
        form = form if has_form else position  # a placeholder the kernels do not read
        arrays = tuple(t.detach().to(torch.float32).contiguous()
                       for t in (position, conic, reach, weight, phase, rate, form, wavenumbers))
        channels = weight.shape[1]
        out = arrays[0].new_zeros(channels, height, width, 2)
        gpu.launch(gpu.splat_forward, *arrays, out, height=height, width=width, mahalanobis=mahalanobis,
                   has_form=has_form)
        ctx.save_for_backward(*arrays)
        ctx.mahalanobis, ctx.has_form = mahalanobis, has_form
        ctx.dtypes = tuple(t.dtype for t in (position, conic, weight, phase, rate, form))
        return torch.view_as_complex(out).to(torch.promote_types(position.dtype, torch.complex64))

    @staticmethod
    def backward(ctx, grad):
        from . import gpu

        arrays = ctx.saved_tensors
        position, conic, _, weight, phase, rate, form, _ = arrays
        _, height, width = grad.shape
        incoming = torch.view_as_real(grad.to(torch.complex64).resolve_conj().contiguous())
        grads = tuple(torch.zeros_like(t) for t in (position, conic, weight, phase, rate, form))
        gpu.launch(gpu.splat_backward, *arrays, incoming, *grads, height=height, width=width,
                   mahalanobis=ctx.mahalanobis, has_form=ctx.has_form)
        g_position, g_conic, g_weight, g_phase, g_rate, g_form = (g.to(dtype) for g, dtype in zip(grads, ctx.dtypes))
        return (g_position, g_conic, None, g_weight, g_phase, g_rate, g_form if ctx.has_form else None, None, None,
                None, None)


def splat_triton(prims: Primitives, width: int, height: int, wavenumbers: Tensor, pixel_pitch: float,
                 qpf: Qpf) -> Tensor:
    """GPU backend (Triton): complex hologram [C, H, W], float32 inside, pitch in m. The geometry is
    the reference's `splats`, differentiated by autograd."""
    s = splats(prims, pixel_pitch, qpf)
    k = wavenumbers.to(device=s.chirp.device, dtype=s.chirp.dtype)
    rate = s.chirp * k  # [N, 1 or C] · [C]
    weight = s.amplitude * s.opacity[:, None]
    return _TritonSplat.apply(s.position_px, s.conic, s.reach_px, weight, s.phase_rad, rate.expand_as(weight), s.form,
                              k, width, height, s.mahalanobis)


Backend = Callable[[Primitives, int, int, Tensor, float, Qpf], Tensor]
BACKENDS: dict[str, Backend] = {"torch": splat_reference, "numba": splat_fused, "triton": splat_triton}


def wavenumbers_for(wavelengths_m: Sequence[float], device: torch.device | str = "cpu") -> Tensor:
    """k_c = 2π/λ_c (1/m) as a float64 tensor on `device` (made once per device; read-only)."""
    return device_constants(tuple(2 * math.pi / w for w in wavelengths_m), torch.float64, torch.device(device))


def rasterize(prims: Primitives, width: int, height: int, wavelengths_m: Sequence[float],
              pixel_pitch: float, qpf: Qpf = "mahalanobis", backend: str = "auto") -> Tensor:
    """Complex hologram [C, H, W] of the activated primitives on the W×H grid (px), pitch in m."""
    backend = resolve_backend(backend, prims.position_px.device)
    wavenumbers = wavenumbers_for(wavelengths_m, prims.position_px.device)
    return BACKENDS[backend](prims, width, height, wavenumbers, pixel_pitch, qpf)
