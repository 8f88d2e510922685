"""BLASM propagation's PyTorch reference (method.md §3, odak 0.2.7's convention): the transfer function,
its distance-independent spectral terms, the bank of transfer functions a propagation uses (with a display's 4f
aperture folded in, method.md §8), and the full-grid propagation."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor


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
                      terms: SpectralTerms | None = None, aperture: float | None = None) -> Tensor:
    """BLASM transfer function [rows, cols] (complex64), exactly as odak 0.2.7 builds it.

    Computed in float32 like odak, whose numbers the paper reports. As in odak, the band limit of
    each axis' frequency is taken with the other axis' length (identical on square grids).
    `centred=False` gives it ifftshift-ed (zero frequency first, FFT order): the shift is applied to
    the 1D frequency axes, so no second full-size array is ever made. `part` (rows, columns) computes
    only that block of it; `terms`, this grid's and wavelength's `spectral_terms`, are shared by every distance.
    `aperture` multiplies it by a 4f system's circular Fourier aperture, which passes spatial frequencies up to
    `aperture` × the Nyquist frequency 1/(2·pixel_pitch) (None: no aperture); on these frequencies, symmetric about
    zero, the aperture is even like the transfer function.
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
    if aperture is not None:
        passband &= abs_cols**2 + abs_rows**2 <= (aperture / (2 * pixel_pitch)) ** 2
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
    function as [cols, rows] (frequency f_x first), the layout of `propagate_content`'s spectra. A bank with an
    `aperture` (a fraction of the Nyquist frequency) holds each function times a display's 4f aperture
    (`transfer_function`): the filter costs the propagation no transform and no product of its own.
    """

    rows: int
    cols: int
    pixel_pitch: float
    wavelengths: tuple[float, ...]
    distances: tuple[float, ...]
    device: torch.device
    transposed: bool = False
    aperture: float | None = None

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
                                     terms=terms or self.spectral_terms(channel), aperture=self.aperture)
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
                  pixel_pitch: float, transposed: bool = False, aperture: float | None = None) -> TransferBank:
    """The transfer functions that propagate a [C, P_H, P_W] field (zero-padded to 2P_H×2P_W), times the 4f
    `aperture` (a fraction of the Nyquist frequency; None: none)."""
    channels, rows, cols = field.shape
    if len(wavelengths_m) != channels:
        raise ValueError(f"{len(wavelengths_m)} wavelengths for a field of {channels} channels")
    return TransferBank(2 * rows, 2 * cols, float(pixel_pitch), tuple(map(float, wavelengths_m)),
                        tuple(map(float, distances_m)), field.device, transposed,
                    None if aperture is None else float(aperture))


def propagate(field: Tensor, distances_m: Sequence[float], wavelengths_m: Sequence[float],
              pixel_pitch: float, aperture: float | None = None) -> Tensor:
    """Propagate a [C, P_H, P_W] field to every distance: complex [M, C, P_H, P_W], through a 4f system's
    circular Fourier `aperture` first (a fraction of the Nyquist frequency; None: none).

    odak's recipe: zero-pad to 2P_H×2P_W, centred FFT, BLASM transfer function, inverse, centre
    crop. Because fftshift/ifftshift cancel around a pointwise product on even grids, the shifts are
    folded into the transfer functions; one forward FFT per channel serves every plane. The aperture
    filters the same spectrum: it is one more factor of the transfer functions.
    """
    bank = transfer_bank(field, distances_m, wavelengths_m, pixel_pitch, aperture=aperture)
    channels, rows, cols = field.shape
    top, left = rows // 2, cols // 2
    padded = field.new_zeros(channels, 2 * rows, 2 * cols)
    padded[:, top:top + rows, left:left + cols] = field
    spectrum = torch.fft.fft2(padded)
    transfer = torch.stack([torch.stack([bank(m, c) for c in range(channels)]) for m in range(len(distances_m))])
    output = torch.fft.ifft2(spectrum[None] * transfer)
    return output[..., top:top + rows, left:left + cols]
