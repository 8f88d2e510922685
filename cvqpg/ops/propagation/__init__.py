"""BLASM propagation (method.md §3): the public op and the autograd boundary of the pruned transforms.

`propagate_planes` is the op: the H×W content of an SLM field propagated to every plane, through the
backend's transforms (`cvqpg.ops.resolve_backend`). With `numba`, the CPU's default, they are the
pruned transforms of `propagate_content`, whose copies, transposes and transfer products run as the
CPU kernels (`cpu`); with `torch` the full-grid reference (`reference.propagate`), on any device;
with `triton` the same full-grid transforms on CUDA, one batched cuFFT call each way. With `fused`
off, `propagate_content` runs on any device through PyTorch's operations, so that a benchmark can
set the pruned transforms against the full-grid ones on a GPU (`benchmarks/step.py --device cuda`);
which of them is faster there has not been measured.
"""

from __future__ import annotations

import functools
import threading
from typing import Sequence

import torch
from torch import Tensor

from .. import resolve_backend
from ..field import Grid
from . import cpu
from .reference import TransferBank, propagate, release_transfer_functions, transfer_bank, transfer_function

__all__ = ["SPECTRUM_BLOCK_ROWS", "TransferBank", "plane_groups", "propagate", "propagate_content",
           "propagate_planes", "release_transfer_functions", "transfer_function"]


@functools.lru_cache(maxsize=8)
def _zero_margined(rows: int, cols: int, start: int, stop: int, dtype: torch.dtype, device: torch.device,
                   thread: int) -> Tensor:
    """A reusable zero array [rows, cols] whose columns start..stop its users overwrite: the margins
    stay zero without being written again (one per thread, as users write into it)."""
    return torch.zeros(rows, cols, dtype=dtype, device=device)


def _placed(values: Tensor, length: int, offset: int, fused: bool, conjugate: bool = False) -> Tensor:
    """Rows [R, n] (or their conjugates) at columns offset..offset+n of zero rows [R, length] (a reused
    array: read it before the next call)."""
    rows, count = values.shape
    out = _zero_margined(rows, length, offset, offset + count, values.dtype, values.device, threading.get_ident())
    _copy(values, out[:, offset:offset + count], fused, conjugate)
    return out


def _copy(values: Tensor, out: Tensor, fused: bool, conjugate: bool = False) -> None:
    """out = values, or their conjugates, for [R, N] arrays either of which may be a view into a wider
    array (PyTorch copies such views on one thread; docs/performance.md, "Measured choices")."""
    if fused:
        cpu.copy_rows(values.numpy(), out.numpy(), conjugate)
    else:
        out.copy_(values.conj() if conjugate else values)


def _placed_transposed(values: Tensor, length: int, offset: int, fused: bool) -> Tensor:
    """[R, N] → [N, length]: `values.T` at columns offset..offset+R, zero elsewhere (a reused array)."""
    rows, count = values.shape
    out = _zero_margined(count, length, offset, offset + rows, values.dtype, values.device, threading.get_ident())
    _transpose(values, out[:, offset:offset + rows], fused)
    return out


def _transpose(values: Tensor, out: Tensor, fused: bool) -> None:
    """out [N, R] = values [R, N] transposed; either may be a view into a wider array."""
    if fused:
        cpu.transpose(values.numpy(), out.numpy())
    else:
        out.copy_(values.T)


def _transfer_rows(half: Tensor, rows: slice) -> Tensor:
    """Rows `rows` of a transfer function given as the first half of its first axis (`TransferBank.half`)."""
    index = torch.arange(rows.start, rows.stop, device=half.device)
    return half[torch.minimum(index, 2 * half.shape[0] - 1 - index)]


@functools.lru_cache(maxsize=8)
def _planes_buffer(planes: int, rows: int, cols: int, dtype: torch.dtype, device: torch.device,
                   thread: int) -> Tensor:
    """A reusable array [planes, rows, cols] for one spectrum block's filtered copies (one per thread)."""
    return torch.empty(planes, rows, cols, dtype=dtype, device=device)


def _filtered(spectrum: Tensor, halves: Sequence[Tensor], rows: slice, fused: bool) -> Tensor:
    """spectrum · T_p[rows] for every plane p [P, R, N] (a reused array: read it before the next call),
    for transfer functions T_p given as halves (`TransferBank.half`). One pass reads the spectrum for
    a group of planes (`plane_groups`)."""
    out = _planes_buffer(len(halves), *spectrum.shape, spectrum.dtype, spectrum.device, threading.get_ident())
    if not fused:
        for plane, half in enumerate(halves):
            torch.mul(spectrum, _transfer_rows(half, rows), out=out[plane])
        return out
    for group in plane_groups(len(halves)):
        cpu.mirrored_products(spectrum.numpy(), tuple(half.numpy() for half in halves[group]), rows.start,
                              out[group].numpy())
    return out


FUSED_PLANES_AT_ONCE = 8


def plane_groups(planes: int) -> list[slice]:
    """The planes in groups of at most `FUSED_PLANES_AT_ONCE`, one fused kernel call each. The kernels take a
    group as a tuple of arrays, and Numba compiles them anew for every tuple length, the longer the longer
    the tuple (about 2 s for 8 planes, 10 s for 32, minutes for 100, the most it takes): groups keep the
    lengths few and short, whatever the plane count."""
    at_once = min(FUSED_PLANES_AT_ONCE, cpu.MAX_FUSED_PLANES)
    return [slice(start, min(start + at_once, planes)) for start in range(0, planes, at_once)]


def _filtered_sum(spectra: Sequence[Tensor], halves: Sequence[Tensor], rows: slice, fused: bool) -> Tensor:
    """Σ_p spectra[p] · T_p[rows], written into spectra[0], in one pass over each group of planes' spectra
    (`plane_groups`), whose sums add up in plane order."""
    total = spectra[0]
    if not fused:
        total.mul_(_transfer_rows(halves[0], rows))
        for spectrum, half in zip(spectra[1:], halves[1:]):
            total.addcmul_(spectrum, _transfer_rows(half, rows))
        return total
    for group in plane_groups(len(halves)):
        cpu.mirrored_sum(tuple(spectrum.numpy() for spectrum in spectra[group]),
                         tuple(half.numpy() for half in halves[group]), rows.start)
        if group.start:
            total.add_(spectra[group.start])
    return total


SPECTRUM_BLOCK_ROWS = 256  # rows of a transposed spectrum handled at once: 3 MB at 640×480, half per core in L2


def _blocks(count: int) -> list[slice]:
    return [slice(start, min(start + SPECTRUM_BLOCK_ROWS, count)) for start in range(0, count, SPECTRUM_BLOCK_ROWS)]


class _ContentPropagation(torch.autograd.Function):
    """`grid.crop(propagate(field, ...))` with pruned transforms and a hand-written adjoint.

    A 2D transform is a 1D transform along x (each row) and one along y (each column); both run here
    as batched row transforms, with a transpose in between, and the spectra stay transposed
    ([f_x, f_y], against the transposed transfer functions). Each 1D pass is pruned to the rows it
    needs: the forward transform's x pass runs over the P_H rows that hold the field (of 2P_H), each
    inverse's x pass only over the H content rows it returns, and the same holds for the adjoint,
    whose input is the content and whose output the field. The y passes run over all 2P_W columns.
    That is about 0.4 of the 2D transforms' arithmetic (their share of the time is the "pruned
    transforms alone" line of `benchmarks/step.py`, docs/performance.md), and the result is the same
    to float32 rounding.

    Between the two x passes everything works on blocks of `SPECTRUM_BLOCK_ROWS` spectrum rows (f_x):
    transpose in, y transform, transfer product, inverse y transform, transpose out, while the block
    is in cache; whole-array passes would stream each array through memory several times.

    The forward keeps only the H×W content of each plane. The adjoint of the propagation is
    `ifft2(conj(T)·fft2(g))` summed over planes; it is computed as `conj(fft2(Σ_m T_m·ifft2(conj g_m)))`,
    the same number, so the transfer functions are never conjugated (a conjugate would be
    materialised, a full array per plane and channel) and the planes share one inverse transform
    per channel. Zero-padded inputs are written into reused arrays whose margins stay zero. `fused`
    runs the copies, transposes and transfer products as the CPU kernels.
    """

    @staticmethod
    def forward(ctx, field: Tensor, grid: Grid, bank: TransferBank, fused: bool) -> Tensor:
        channels, rows, cols = field.shape
        planes = len(bank.distances)
        top, left = rows // 2 + grid.top, cols // 2 + grid.left
        content = field.new_empty(planes, channels, grid.height, grid.width)
        along_y = field.new_empty(planes, grid.height, 2 * cols)
        for channel in range(channels):
            halves = [bank.half(plane, channel) for plane in range(planes)]  # once: they may be rebuilt
            along_x = torch.fft.fft(_placed(field[channel], 2 * cols, cols // 2, fused))
            for block in _blocks(2 * cols):
                spectrum = torch.fft.fft(_placed_transposed(along_x[:, block], 2 * rows, rows // 2, fused))
                filtered = _filtered(spectrum, halves, block, fused)
                for plane in range(planes):
                    _transpose(torch.fft.ifft(filtered[plane])[:, top:top + grid.height], along_y[plane, :, block],
                               fused)
            for plane in range(planes):  # one 2D batch each: MKL runs a 3D batch slower (docs/performance.md)
                _copy(torch.fft.ifft(along_y[plane])[:, left:left + grid.width], content[plane, channel], fused)
        ctx.grid, ctx.bank, ctx.field_shape, ctx.fused = grid, bank, field.shape, fused
        return content

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None, None]:
        grid, bank, fused = ctx.grid, ctx.bank, ctx.fused
        channels, rows, cols = ctx.field_shape
        planes = len(bank.distances)
        top, left = rows // 2 + grid.top, cols // 2 + grid.left
        grad_field = grad.new_empty(channels, rows, cols)
        along_y = grad.new_empty(rows, 2 * cols)
        for channel in range(channels):
            halves = [bank.half(plane, channel) for plane in range(planes)]
            along_x = [torch.fft.ifft(_placed(grad[plane, channel], 2 * cols, left, fused, conjugate=True))
                       for plane in range(planes)]
            for block in _blocks(2 * cols):
                spectra = [torch.fft.ifft(_placed_transposed(along_x[plane][:, block], 2 * rows, top, fused))
                           for plane in range(planes)]
                accumulated = _filtered_sum(spectra, halves, block, fused)
                _transpose(torch.fft.fft(accumulated)[:, rows // 2:rows // 2 + rows], along_y[:, block], fused)
            _copy(torch.fft.fft(along_y)[:, cols // 2:cols // 2 + cols], grad_field[channel], fused, conjugate=True)
        return grad_field, None, None, None


def propagate_content(field: Tensor, grid: Grid, distances_m: Sequence[float], wavelengths_m: Sequence[float],
                      pixel_pitch: float, fused: bool, aperture: float | None = None) -> Tensor:
    """The H×W content [M, C, H, W] of `propagate(field, ..., aperture)` for a [C, P_H, P_W] field (distances,
    wavelengths and pitch in m), lean in memory and time: the pruned transforms, their copies,
    transposes and transfer products as the CPU kernels (`fused`, a CPU field) or PyTorch's
    operations (any device). The 4f `aperture` rides in the transfer functions (`TransferBank`)."""
    bank = transfer_bank(field, distances_m, wavelengths_m, pixel_pitch, transposed=True, aperture=aperture)
    return _ContentPropagation.apply(field, grid, bank, fused)


def propagate_planes(field: Tensor, grid: Grid, distances_m: Sequence[float], wavelengths_m: Sequence[float],
                     pixel_pitch: float, backend: str = "auto", aperture: float | None = None) -> Tensor:
    """The H×W content [M, C, H, W] of a [C, P_H, P_W] SLM field propagated to every distance (m) at
    each channel's wavelength (m), pitch in m (method.md §3), behind a 4f system's circular Fourier `aperture`
    (a fraction of the Nyquist frequency; None: none, method.md §8): the pruned transforms with the CPU kernels
    (`numba`), else the full-grid ones (`torch`, `triton`); the same numbers to float32 rounding."""
    if resolve_backend(backend, field.device) == "numba":
        return propagate_content(field, grid, distances_m, wavelengths_m, pixel_pitch, fused=True, aperture=aperture)
    return grid.crop(propagate(field, distances_m, wavelengths_m, pixel_pitch, aperture))
