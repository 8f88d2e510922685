"""Hologram field and band-limited angular spectrum propagation (SPEC §3, odak 0.2.7's convention)."""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from .config import FitConfig
from .ops.field import Grid, clamped_intensity, guarded_field
from .ops.propagation import cpu as propagation_kernels


SpectralTerms = tuple[Tensor, Tensor, Tensor]


def spectral_terms(rows: int, cols: int, pixel_pitch: float, wavelength: float, device: torch.device,
                   centred: bool = True) -> SpectralTerms:
    """The distance-independent parts of `transfer_function`, most of its time: 2π·sqrt(1/λ² − f²)
    [rows, cols] (rad/m), and |f| along the rows [rows, 1] and the columns [1, cols] (1/m)."""
    length_rows, length_cols = pixel_pitch * rows, pixel_pitch * cols
    f_rows = torch.linspace(-1 / (2 * pixel_pitch) + 0.5 / (2 * length_rows),
                            1 / (2 * pixel_pitch) - 0.5 / (2 * length_rows), rows,
                            dtype=torch.float32, device=device)
    f_cols = torch.linspace(-1 / (2 * pixel_pitch) + 0.5 / (2 * length_cols),
                            1 / (2 * pixel_pitch) - 0.5 / (2 * length_cols), cols,
                            dtype=torch.float32, device=device)
    if not centred:
        f_rows, f_cols = torch.fft.ifftshift(f_rows), torch.fft.ifftshift(f_cols)
    fr, fc = torch.meshgrid(f_rows, f_cols, indexing="ij")
    return 2 * math.pi * torch.sqrt(1 / wavelength**2 - (fc**2 + fr**2)), f_rows.abs()[:, None], f_cols.abs()[None, :]


def transfer_function(rows: int, cols: int, pixel_pitch: float, wavelength: float, distance: float,
                      device: torch.device, centred: bool = True,
                      part: tuple[slice, slice] = (slice(None), slice(None)),
                      terms: SpectralTerms | None = None) -> Tensor:
    """BLASM transfer function [rows, cols] (complex64), exactly as odak 0.2.7 builds it.

    Computed in float32 like odak, whose numbers the paper reports. As in odak, the band limit of
    each axis' frequency is taken with the other axis' length (identical on square grids).
    `centred=False` gives it ifftshift-ed (zero frequency first, FFT order): the shift is applied to
    the 1D frequency axes, so no second full-size array is ever made. `part` (rows, columns) computes
    only that block of it; `terms`, this grid's and wavelength's `spectral_terms`, are shared by every distance.
    """
    length_rows, length_cols = pixel_pitch * rows, pixel_pitch * cols
    terms = terms or spectral_terms(rows, cols, pixel_pitch, wavelength, device, centred)
    wavenumbers, abs_rows, abs_cols = terms
    wavenumbers, abs_rows, abs_cols = wavenumbers[part], abs_rows[part[0]], abs_cols[:, part[1]]
    z = torch.tensor([distance], dtype=torch.float32, device=device)
    phase = wavenumbers * z
    limit_cols = 1 / torch.sqrt((2 * z * (1 / length_rows)) ** 2 + 1) / wavelength
    limit_rows = 1 / torch.sqrt((2 * z * (1 / length_cols)) ** 2 + 1) / wavelength
    passband = (abs_cols < limit_cols) & (abs_rows < limit_rows)
    return torch.polar(passband.float(), phase)


TRANSFER_CACHE_BYTES = 2**30


@dataclass(frozen=True)
class TransferBank:
    """BLASM transfer functions of every (plane, channel) on one doubled grid, in FFT order.

    In FFT order each function is even about the middle of both axes (odak's frequencies are
    symmetric about zero, exactly so in float32), so its first axis' first half holds all of it:
    the bank keeps those halves, half the memory. They are built once and kept while all of them
    fit in `TRANSFER_CACHE_BYTES` (1 GiB: 640×480 RGB needs 0.07 GiB, 3840×2160 RGB 0.93 GiB); past
    that each is rebuilt when asked, which its users do once per pass. `transposed` banks hold each
    function as [cols, rows] (frequency f_x first), the layout of `propagate_content`'s spectra.
    """

    rows: int
    cols: int
    pixel_pitch: float
    wavelengths: tuple[float, ...]
    distances: tuple[float, ...]
    device: torch.device
    transposed: bool = False

    @property
    def nbytes(self) -> int:
        """Bytes of all the kept halves."""
        return len(self.distances) * len(self.wavelengths) * self.rows * self.cols * 4

    def half(self, plane: int, channel: int) -> Tensor:
        """First half (along the first axis) of the complex64 transfer function to `distances[plane]`
        at `wavelengths[channel]`; row k of the whole function is row min(k, length − 1 − k) of it."""
        if self.nbytes <= TRANSFER_CACHE_BYTES:
            return _transfer_halves(self)[plane][channel]
        return self.build_half(plane, channel)

    def __call__(self, plane: int, channel: int) -> Tensor:
        """The whole complex64 transfer function to `distances[plane]` at `wavelengths[channel]`."""
        half = self.half(plane, channel)
        return torch.cat([half, half.flip(0)])

    def spectral_terms(self, channel: int) -> SpectralTerms:
        return spectral_terms(self.rows, self.cols, self.pixel_pitch, self.wavelengths[channel], self.device,
                              centred=False)

    def build_half(self, plane: int, channel: int, terms: SpectralTerms | None = None) -> Tensor:
        part = (slice(None), slice(self.cols // 2)) if self.transposed else (slice(self.rows // 2), slice(None))
        transfer = transfer_function(self.rows, self.cols, self.pixel_pitch, self.wavelengths[channel],
                                     self.distances[plane], self.device, centred=False, part=part,
                                     terms=terms or self.spectral_terms(channel))
        return transfer.T.contiguous() if self.transposed else transfer


@functools.lru_cache(maxsize=4)
def _transfer_halves(bank: TransferBank) -> tuple[tuple[Tensor, ...], ...]:
    """Every half, by plane then channel (not stacked: a copy of all of them would cost as much as a sweep's
    propagation). Each channel's spectral terms serve all its planes."""
    by_channel = []
    for channel in range(len(bank.wavelengths)):
        terms = bank.spectral_terms(channel)
        by_channel.append([bank.build_half(plane, channel, terms) for plane in range(len(bank.distances))])
    return tuple(zip(*by_channel))


def release_transfer_functions() -> None:
    """Free the kept transfer functions; for callers that propagate to many distances once each (a focal
    sweep), whose banks would otherwise stay in memory."""
    _transfer_halves.cache_clear()


def transfer_bank(field: Tensor, distances_m: Sequence[float], wavelengths_m: Sequence[float],
                  pixel_pitch: float, transposed: bool = False) -> TransferBank:
    """The transfer functions that propagate a [C, P_H, P_W] field (zero-padded to 2P_H×2P_W)."""
    channels, rows, cols = field.shape
    if len(wavelengths_m) != channels:
        raise ValueError(f"{len(wavelengths_m)} wavelengths for a field of {channels} channels")
    return TransferBank(2 * rows, 2 * cols, float(pixel_pitch), tuple(map(float, wavelengths_m)),
                        tuple(map(float, distances_m)), field.device, transposed)


def propagate(field: Tensor, distances_m: Sequence[float], wavelengths_m: Sequence[float],
              pixel_pitch: float) -> Tensor:
    """Propagate a [C, P_H, P_W] field to every distance: complex [M, C, P_H, P_W].

    odak's recipe: zero-pad to 2P_H×2P_W, centred FFT, BLASM transfer function, inverse, centre
    crop. Because fftshift/ifftshift cancel around a pointwise product on even grids, the shifts are
    folded into the transfer functions; one forward FFT per channel serves every plane.
    """
    bank = transfer_bank(field, distances_m, wavelengths_m, pixel_pitch)
    channels, rows, cols = field.shape
    top, left = rows // 2, cols // 2
    padded = field.new_zeros(channels, 2 * rows, 2 * cols)
    padded[:, top:top + rows, left:left + cols] = field
    spectrum = torch.fft.fft2(padded)
    transfer = torch.stack([torch.stack([bank(m, c) for c in range(channels)]) for m in range(len(distances_m))])
    output = torch.fft.ifft2(spectrum[None] * transfer)
    return output[..., top:top + rows, left:left + cols]


@functools.lru_cache(maxsize=8)
def _zero_margined(rows: int, cols: int, start: int, stop: int, dtype: torch.dtype, device: torch.device,
                   thread: int) -> Tensor:
    """A reusable zero array [rows, cols] whose columns start..stop its users overwrite: the margins
    stay zero without being written again (one per thread, as users write into it)."""
    return torch.zeros(rows, cols, dtype=dtype, device=device)


def _placed(values: Tensor, length: int, offset: int, conjugate: bool = False) -> Tensor:
    """Rows [R, n] (or their conjugates) at columns offset..offset+n of zero rows [R, length] (a reused
    array: read it before the next call)."""
    rows, count = values.shape
    out = _zero_margined(rows, length, offset, offset + count, values.dtype, values.device, threading.get_ident())
    _copy(values, out[:, offset:offset + count], conjugate)
    return out


def _uses_cpu_kernels(tensor: Tensor) -> bool:
    """Whether the propagation's copies, transposes and transfer products run as the CPU kernels (else
    as PyTorch operations, on any device)."""
    return tensor.device.type == "cpu"


def _copy(values: Tensor, out: Tensor, conjugate: bool = False) -> None:
    """out = values, or their conjugates, for [R, N] arrays either of which may be a view into a wider
    array (PyTorch copies such views on one thread: 1 ms for a 768×960 field here)."""
    if _uses_cpu_kernels(values):
        propagation_kernels.copy_rows(values.numpy(), out.numpy(), conjugate)
    else:
        out.copy_(values.conj() if conjugate else values)


def _placed_transposed(values: Tensor, length: int, offset: int) -> Tensor:
    """[R, N] → [N, length]: `values.T` at columns offset..offset+R, zero elsewhere (a reused array)."""
    rows, count = values.shape
    out = _zero_margined(count, length, offset, offset + rows, values.dtype, values.device, threading.get_ident())
    _transpose(values, out[:, offset:offset + rows])
    return out


def _transpose(values: Tensor, out: Tensor) -> None:
    """out [N, R] = values [R, N] transposed; either may be a view into a wider array."""
    if _uses_cpu_kernels(values):
        propagation_kernels.transpose(values.numpy(), out.numpy())
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


def _filtered(spectrum: Tensor, halves: Sequence[Tensor], rows: slice) -> Tensor:
    """spectrum · T_p[rows] for every plane p [P, R, N] (a reused array: read it before the next call),
    for transfer functions T_p given as halves (`TransferBank.half`). One pass reads the spectrum for
    all planes."""
    out = _planes_buffer(len(halves), *spectrum.shape, spectrum.dtype, spectrum.device, threading.get_ident())
    if _uses_cpu_kernels(spectrum):
        propagation_kernels.mirrored_products(spectrum.numpy(), tuple(half.numpy() for half in halves), rows.start,
                                         out.numpy())
    else:
        for plane, half in enumerate(halves):
            torch.mul(spectrum, _transfer_rows(half, rows), out=out[plane])
    return out


def _filtered_sum(spectra: Sequence[Tensor], halves: Sequence[Tensor], rows: slice) -> Tensor:
    """Σ_p spectra[p] · T_p[rows], written into spectra[0], in one pass over the planes' spectra."""
    total = spectra[0]
    if _uses_cpu_kernels(total):
        propagation_kernels.mirrored_sum(tuple(spectrum.numpy() for spectrum in spectra),
                                    tuple(half.numpy() for half in halves), rows.start)
        return total
    total.mul_(_transfer_rows(halves[0], rows))
    for spectrum, half in zip(spectra[1:], halves[1:]):
        total.addcmul_(spectrum, _transfer_rows(half, rows))
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
    That is about 0.4 of the 2D transforms' arithmetic (0.6 of their time on the development machine,
    docs/performance.md), and the result is the same to float32 rounding.

    Between the two x passes everything works on blocks of `SPECTRUM_BLOCK_ROWS` spectrum rows (f_x):
    transpose in, y transform, transfer product, inverse y transform, transpose out, while the block
    is in cache; whole-array passes would stream each array through memory several times.

    The forward keeps only the H×W content of each plane. The adjoint of the propagation is
    `ifft2(conj(T)·fft2(g))` summed over planes; it is computed as `conj(fft2(Σ_m T_m·ifft2(conj g_m)))`,
    the same number, so the transfer functions are never conjugated (a conjugate would be
    materialised, a full array per plane and channel) and the planes share one inverse transform
    per channel. Zero-padded inputs are written into reused arrays whose margins stay zero.
    """

    @staticmethod
    def forward(ctx, field: Tensor, grid: Grid, bank: TransferBank) -> Tensor:
        channels, rows, cols = field.shape
        planes = len(bank.distances)
        top, left = rows // 2 + grid.top, cols // 2 + grid.left
        content = field.new_empty(planes, channels, grid.height, grid.width)
        along_y = field.new_empty(planes, grid.height, 2 * cols)
        for channel in range(channels):
            halves = [bank.half(plane, channel) for plane in range(planes)]  # once: they may be rebuilt
            along_x = torch.fft.fft(_placed(field[channel], 2 * cols, cols // 2))
            for block in _blocks(2 * cols):
                spectrum = torch.fft.fft(_placed_transposed(along_x[:, block], 2 * rows, rows // 2))
                filtered = _filtered(spectrum, halves, block)
                for plane in range(planes):
                    _transpose(torch.fft.ifft(filtered[plane])[:, top:top + grid.height], along_y[plane, :, block])
            for plane in range(planes):  # one 2D batch each: MKL runs a 3D batch several times slower
                _copy(torch.fft.ifft(along_y[plane])[:, left:left + grid.width], content[plane, channel])
        ctx.grid, ctx.bank, ctx.field_shape = grid, bank, field.shape
        return content

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None]:
        grid, bank = ctx.grid, ctx.bank
        channels, rows, cols = ctx.field_shape
        planes = len(bank.distances)
        top, left = rows // 2 + grid.top, cols // 2 + grid.left
        grad_field = grad.new_empty(channels, rows, cols)
        along_y = grad.new_empty(rows, 2 * cols)
        for channel in range(channels):
            halves = [bank.half(plane, channel) for plane in range(planes)]
            along_x = [torch.fft.ifft(_placed(grad[plane, channel], 2 * cols, left, conjugate=True))
                       for plane in range(planes)]
            for block in _blocks(2 * cols):
                spectra = [torch.fft.ifft(_placed_transposed(along_x[plane][:, block], 2 * rows, top))
                           for plane in range(planes)]
                accumulated = _filtered_sum(spectra, halves, block)
                _transpose(torch.fft.fft(accumulated)[:, rows // 2:rows // 2 + rows], along_y[:, block])
            _copy(torch.fft.fft(along_y)[:, cols // 2:cols // 2 + cols], grad_field[channel], conjugate=True)
        return grad_field, None, None


def propagate_content(field: Tensor, grid: Grid, distances_m: Sequence[float], wavelengths_m: Sequence[float],
                      pixel_pitch: float) -> Tensor:
    """The H×W content [M, C, H, W] of `propagate(field, ...)` for a [C, P_H, P_W] field, lean in memory
    and time."""
    bank = transfer_bank(field, distances_m, wavelengths_m, pixel_pitch, transposed=True)
    return _ContentPropagation.apply(field, grid, bank)


def reconstruct(hologram: Tensor, config: FitConfig, distances_m: Sequence[float] | None = None) -> Tensor:
    """Hologram [C, H, W] → reconstructed intensity [M, C, H, W] clamped to [0, 1] (SPEC §3), at
    `config`'s planes or at `distances_m` (m)."""
    grid = Grid.for_config(config)
    field = guarded_field(hologram, grid, config.backend)
    distances = config.plane_distances if distances_m is None else tuple(distances_m)
    if resolve_propagation("auto", field.device) == "full":
        planes = grid.crop(propagate(field, distances, config.wavelengths, config.pixel_pitch))
    else:
        planes = propagate_content(field, grid, distances, config.wavelengths, config.pixel_pitch)
    return clamped_intensity(planes, config.backend)


def resolve_propagation(propagation: str, device: torch.device | str) -> str:
    """`auto` → the pruned transforms (`propagate_content`) on the CPU, where they were measured faster,
    and the full-grid transforms (`propagate`, one batched cuFFT call each way) elsewhere; which is
    faster on a GPU has not been measured (docs/performance.md)."""
    if propagation == "auto":
        return "pruned" if torch.device(device).type == "cpu" else "full"
    return propagation
