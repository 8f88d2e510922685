"""The paper's image metrics (method.md §7): PSNR, SSIM, FLIP always; LPIPS and ColorVideoVDP when present.

Nothing is downloaded: LPIPS needs `lpips` (and torchvision) plus the VGG16 weights already in the
torch hub cache; ColorVideoVDP needs `cvvdp`. When either is missing its value is None and
`unavailable` says why.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

METRIC_NAMES = ("psnr", "ssim", "flip", "lpips", "cvvdp")
VGG16_WEIGHTS = "vgg16-397923af.pth"
CVVDP_DISPLAY = "standard_4k"


class MetricUnavailable(RuntimeError):
    """A metric cannot run on this machine; the message says what is missing."""


@dataclass
class MetricReport:
    """Per-plane values, their means, and why any metric is missing."""

    per_plane: dict[str, list[float | None]]
    unavailable: dict[str, str] = field(default_factory=dict)

    @property
    def mean(self) -> dict[str, float | None]:
        return {name: (None if any(v is None for v in values) else float(np.mean(values)))
                for name, values in self.per_plane.items()}

    def to_dict(self) -> dict:
        return {"mean": self.mean, "per_plane": self.per_plane, "unavailable": self.unavailable}


def _hwc(image: Tensor) -> np.ndarray:
    return image.detach().to("cpu", torch.float32).clamp(0, 1).permute(1, 2, 0).numpy()


def _rgb(image: np.ndarray) -> np.ndarray:
    return np.repeat(image, 3, axis=2) if image.shape[2] == 1 else image


def psnr(recon: np.ndarray, target: np.ndarray) -> float:
    """PSNR (dB), data range 1, over all channels."""
    from skimage.metrics import peak_signal_noise_ratio  # imports SciPy: a second that a fit's start need not wait for

    return float(peak_signal_noise_ratio(target, recon, data_range=1.0))


def mean_psnr(recon: Tensor, targets: Tensor) -> float:
    """PSNR (dB) of reconstructions [M, C, H, W] against targets, averaged over planes (method.md §7)."""
    return float(np.mean([psnr(_hwc(r), _hwc(t)) for r, t in zip(recon, targets)]))


def mean_ssim(recon: Tensor, targets: Tensor) -> float:
    """SSIM of reconstructions [M, C, H, W] against targets, averaged over planes."""
    return float(np.mean([ssim(_hwc(r), _hwc(t)) for r, t in zip(recon, targets)]))


def ssim(recon: np.ndarray, target: np.ndarray) -> float:
    """scikit-image SSIM with its defaults (7×7 uniform window), data range 1."""
    from skimage.metrics import structural_similarity

    if recon.shape[2] == 1:
        return float(structural_similarity(target[..., 0], recon[..., 0], data_range=1.0))
    return float(structural_similarity(target, recon, data_range=1.0, channel_axis=-1))


def flip(recon: np.ndarray, target: np.ndarray) -> float:
    """Mean LDR-FLIP error, reference = target."""
    import flip_evaluator

    return float(flip_evaluator.evaluate(np.ascontiguousarray(_rgb(target)),
                                         np.ascontiguousarray(_rgb(recon)), "LDR")[1])


@functools.lru_cache(maxsize=1)
def _lpips_model():
    try:
        import lpips
    except Exception as error:  # lpips imports torchvision, which may be absent or broken
        raise MetricUnavailable(f"package 'lpips' does not import ({type(error).__name__}: {error})")
    weights = Path(torch.hub.get_dir()) / "checkpoints" / VGG16_WEIGHTS
    if not weights.is_file():
        raise MetricUnavailable(f"VGG16 weights not found at {weights}; copy {VGG16_WEIGHTS} there "
                                "(nothing is downloaded at run time)")
    return lpips.LPIPS(net="vgg", verbose=False).eval()


def lpips_vgg(recon: np.ndarray, target: np.ndarray) -> float:
    """LPIPS (VGG), inputs mapped to [−1, 1]."""
    model = _lpips_model()
    to_input = lambda a: torch.from_numpy(_rgb(a)).permute(2, 0, 1)[None] * 2 - 1  # noqa: E731
    with torch.no_grad():
        return float(model(to_input(recon), to_input(target)).item())


@functools.lru_cache(maxsize=1)
def _cvvdp_model():
    try:
        import pycvvdp
    except Exception as error:
        raise MetricUnavailable(f"package 'cvvdp' does not import ({type(error).__name__}: {error})")
    return pycvvdp.cvvdp(display_name=CVVDP_DISPLAY)


def cvvdp(recon: np.ndarray, target: np.ndarray) -> float:
    """ColorVideoVDP JOD on display model `standard_4k`, single image."""
    model = _cvvdp_model()
    jod, _ = model.predict(torch.from_numpy(_rgb(recon)), torch.from_numpy(_rgb(target)), dim_order="HWC")
    return float(jod)


METRICS: dict[str, Callable[[np.ndarray, np.ndarray], float]] = {
    "psnr": psnr, "ssim": ssim, "flip": flip, "lpips": lpips_vgg, "cvvdp": cvvdp}


def evaluate(recon: Tensor, targets: Tensor) -> MetricReport:
    """Metrics of reconstructions [M, C, H, W] against noise-free targets [M, C, H, W], per plane."""
    report = MetricReport(per_plane={name: [] for name in METRIC_NAMES})
    for plane_recon, plane_target in zip(recon, targets):
        r, t = _hwc(plane_recon), _hwc(plane_target)
        for name, metric in METRICS.items():
            value = None
            if name not in report.unavailable:
                try:
                    value = metric(r, t)
                except MetricUnavailable as reason:
                    report.unavailable[name] = str(reason)
            report.per_plane[name].append(value)
    return report


def radial_error_spectrum(recon: Tensor, target: Tensor, bins: int = 32
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Squared error per spatial frequency, averaged in radial bins (method.md §7's frequency analysis).

    `recon` and `target` are [..., H, W]; leading axes (planes, channels) are averaged. The error
    spectrum `|FFT2(recon − target)|² / (H·W)` is normalised so that its mean over all frequencies
    equals the pixel MSE (Parseval). Radial frequency is `ρ = |f| / 0.5` with f in cycles/px from
    `fftfreq` on each axis, so ρ = 1 is Nyquist along an axis. Bins 0..bins−1 split [0, 1] evenly
    (intervals closed on the right, the first also on the left, so DC and Nyquist are in band);
    one extra last bin [1, √2] holds the corner frequencies beyond Nyquist that only diagonals
    reach, so that `Σ power·counts / Σ counts` is still the pixel MSE.

    Returns `edges` [bins + 2] (ρ), `power` [bins + 1] (mean error power per frequency in the bin,
    NaN where a bin holds no frequency) and `counts` [bins + 1] (frequencies per bin).
    """
    height, width = recon.shape[-2:]
    error = (recon.detach().double() - target.detach().double()).reshape(-1, height, width).cpu()
    power = (torch.fft.fft2(error).abs() ** 2).mean(dim=0) / (height * width)
    fy = torch.fft.fftfreq(height, dtype=torch.float64)[:, None]
    fx = torch.fft.fftfreq(width, dtype=torch.float64)[None, :]
    rho = torch.sqrt(fx**2 + fy**2) / 0.5
    index = torch.clamp(torch.ceil(rho * bins).long() - 1, 0, bins).flatten()
    counts = torch.bincount(index, minlength=bins + 1).numpy()
    sums = torch.bincount(index, weights=power.flatten(), minlength=bins + 1).numpy()
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_power = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    edges = np.append(np.linspace(0.0, 1.0, bins + 1), np.sqrt(2.0))
    return edges, mean_power, counts
