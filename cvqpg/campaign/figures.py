"""Figures of a bench folder: reconstructions side by side, the paper's QPF comparison (Fig. 2) and
the frequency-resolved ΔMSE. Matplotlib (Agg) is imported only when a figure is drawn."""

from __future__ import annotations

import io
import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..runs import write_atomic
from ..config import FitConfig
from ..fitting import render_hologram
from ..primitives import Gaussians

CROP_FRACTION = 4  # crops are 1/4 of each side
CROP_COLOR = "#ffd400"
QPF_CANVAS_PX = 96
QPF_SCALES_PX = (14.0, 5.0)
QPF_ROTATION_RAD = math.pi / 6
QPF_CURVATURE_SHARE = 0.5  # γ as a share of the primitive's adaptive bound γ_max: a few readable fringes
QPF_SHOWN_SIGMAS = 3.0  # phase is shown inside the envelope's 3σ ellipse, where the amplitude matters
SATURATED_RAW = 20.0


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(figure, path: Path) -> None:
    """PNG, written atomically; the figure is closed."""
    plt = _pyplot()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    plt.close(figure)
    write_atomic(path, buffer.getvalue())


def detailed_window(image: np.ndarray, height: int, width: int) -> tuple[int, int]:
    """Top-left corner (row, col) of the `height`×`width` window with the most gradient energy in
    `image` [H, W, C]: where fine detail, and so any difference between methods, is."""
    gray = image.astype(np.float64).mean(axis=2)
    energy = np.zeros_like(gray)
    energy[:, 1:] += np.diff(gray, axis=1) ** 2
    energy[1:, :] += np.diff(gray, axis=0) ** 2
    integral = np.pad(energy.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    sums = (integral[height:, width:] - integral[:-height, width:] - integral[height:, :-width]
            + integral[:-height, :-width])
    row, col = np.unravel_index(np.argmax(sums), sums.shape)
    return int(row), int(col)


def _load(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def comparison_figure(runs: dict[str, Path], plane_distances_m: Sequence[float], title: str, path: Path) -> None:
    """Targets and reconstructions side by side: one column for the target and one per run (label →
    run folder; the first run's targets are shown), two rows per plane (full image with the crop
    outlined, then the zoomed crop). Each panel title carries that plane's PSNR from `metrics.json`."""
    plt = _pyplot()
    from matplotlib.patches import Rectangle

    first = next(iter(runs.values()))
    psnr = {label: json.loads((folder / "metrics.json").read_text())["per_plane"]["psnr"]
            for label, folder in runs.items()}
    columns = 1 + len(runs)
    planes = len(plane_distances_m)
    figure, axes = plt.subplots(2 * planes, columns, figsize=(3.2 * columns, 5.0 * planes), dpi=110,
                                squeeze=False)
    for plane, distance in enumerate(plane_distances_m):
        target = _load(first / f"target_plane{plane}.png")
        height, width = target.shape[0] // CROP_FRACTION, target.shape[1] // CROP_FRACTION
        row, col = detailed_window(target, height, width)
        panels = [(f"target, {distance * 1e3:g} mm", target)]
        panels += [(f"{label}, {psnr[label][plane]:.2f} dB", _load(folder / f"recon_plane{plane}.png"))
                   for label, folder in runs.items()]
        for column, (label, image) in enumerate(panels):
            full, crop = axes[2 * plane, column], axes[2 * plane + 1, column]
            full.imshow(image)
            full.add_patch(Rectangle((col - 0.5, row - 0.5), width, height, fill=False, edgecolor=CROP_COLOR,
                                     linewidth=1.2))
            full.set_title(label, fontsize=9)
            crop.imshow(image[row:row + height, col:col + width], interpolation="nearest")
            for axis in (full, crop):
                axis.set_xticks([])
                axis.set_yticks([])
    figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    save_figure(figure, path)


def qpf_fields(canvas_px: int = QPF_CANVAS_PX) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Amplitude [H, W] of one anisotropic primitive, and its wrapped phase (rad, NaN outside the
    envelope's 3σ ellipse) under each QPF, rendered by the project's own rasterizer at γ = 0.5·γ_max."""
    centre = torch.zeros(1, 2)  # tanh(0) puts the primitive at the canvas centre
    raw = Gaussians(position=centre, scale=torch.log(torch.tensor([QPF_SCALES_PX]) - 0.1),
                    rotation=torch.tensor([QPF_ROTATION_RAD]), amplitude=torch.ones(1, 1), phase=torch.zeros(1, 1),
                    opacity=torch.tensor([SATURATED_RAW]),
                    curvature=torch.atanh(torch.tensor([QPF_CURVATURE_SHARE])))
    phases, amplitude = {}, None
    for qpf in ("standard", "mahalanobis"):
        config = FitConfig.create(width=canvas_px, height=canvas_px, color="gray", primitive="cvqpg", qpf=qpf)
        with torch.no_grad():
            field = render_hologram(raw, config, "torch")[0].to(torch.complex128).numpy()
        amplitude = np.abs(field)
        inside = amplitude >= amplitude.max() * math.exp(-QPF_SHOWN_SIGMAS**2 / 2)
        phases[qpf] = np.where(inside, np.mod(np.angle(field), 2 * math.pi), np.nan)
    return amplitude, phases


def qpf_figure(path: Path) -> None:
    """The paper's Fig. 2: (a) amplitude envelope, (b) standard-QPF and (c) Mahalanobis-QPF wrapped phase."""
    plt = _pyplot()
    amplitude, phases = qpf_fields()
    figure, axes = plt.subplots(1, 3, figsize=(9.6, 3.6), dpi=110)
    shown = axes[0].imshow(amplitude, cmap="viridis")
    figure.colorbar(shown, ax=axes[0], orientation="horizontal", fraction=0.05, label="amplitude")
    for axis, (name, title) in zip(axes[1:], (("standard", "(b) standard QPF"),
                                              ("mahalanobis", "(c) Mahalanobis QPF"))):
        shown = axis.imshow(phases[name], cmap="twilight", vmin=0, vmax=2 * math.pi)
        axis.set_title(title, fontsize=10)
        figure.colorbar(shown, ax=axis, orientation="horizontal", fraction=0.05, label="wrapped phase (rad)")
    axes[0].set_title("(a) amplitude envelope", fontsize=10)
    for axis in axes:
        axis.set_xticks([])
        axis.set_yticks([])
    figure.suptitle(f"one primitive, σ = {QPF_SCALES_PX[0]:g}×{QPF_SCALES_PX[1]:g} px at "
                    f"{math.degrees(QPF_ROTATION_RAD):.0f}°, γ = {QPF_CURVATURE_SHARE:g}·γ_max, 639 nm", fontsize=9)
    figure.tight_layout()
    save_figure(figure, path)


def frequency_figure(curves: dict[str, tuple[np.ndarray, np.ndarray]], path: Path,
                     ylabel: str = "ΔMSE of CVQPG over baseline (%)") -> None:
    """ΔMSE% against normalised spatial frequency, one curve per label (label → (bin centres ρ, ΔMSE %))."""
    plt = _pyplot()
    figure, axis = plt.subplots(figsize=(6.4, 3.8), dpi=110)
    for label, (centres, delta) in curves.items():
        axis.plot(centres, delta, marker="o", markersize=3, label=label)
    axis.axhline(0.0, color="0.5", linewidth=0.8)
    axis.set_xlim(0, 1)
    axis.set_xlabel("normalised spatial frequency |f| / f_Nyquist")
    axis.set_ylabel(ylabel)
    if curves:
        axis.legend()
    figure.tight_layout()
    save_figure(figure, path)


RD_MARKERS = {"cvqpg": "o", "cvqpg encode": "D", "JPEG 2000": "s", "JPEG XL": "^", "model float32": "*",
              "model float16": "P"}


def rate_distortion_figure(panels: dict[str, tuple[float, dict[str, tuple[list[float], list[float]]]]],
                           path: Path, shaded_db: tuple[float, float] = (1.0, 0.0)) -> None:
    """One panel per title (title → (the fit's PSNR in dB, codec → (bpp, PSNR) of its Pareto front)):
    PSNR against bpp (log scale), the BD-rate range (from `shaded_db[0]` to `shaded_db[1]` dB below the fit's
    PSNR) shaded, and 1 dB more below it shown."""
    deepest, shallowest = shaded_db
    plt = _pyplot()
    columns = min(len(panels), 3) or 1
    rows = max(math.ceil(len(panels) / columns), 1)
    figure, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.4 * rows), dpi=110, squeeze=False)
    for axis in axes.ravel()[len(panels):]:
        axis.set_visible(False)
    for axis, (title, (top, curves)) in zip(axes.ravel(), panels.items()):
        axis.axhspan(top - deepest, top - shallowest, color="0.92")
        for codec, (bpp, psnr) in curves.items():
            axis.plot(bpp, psnr, marker=RD_MARKERS.get(codec, "."), markersize=4, linewidth=1, label=codec)
        axis.set_xscale("log")
        axis.set_ylim(top - deepest - 1, top + 0.3)
        axis.set_title(title, fontsize=10)
        axis.set_xlabel("bits per hologram pixel")
        axis.set_ylabel("mean PSNR over planes (dB)")
    axes.ravel()[0].legend(fontsize=8, loc="lower right")
    figure.tight_layout()
    save_figure(figure, path)


def psnr_seconds_figure(curves: dict[str, tuple[np.ndarray, np.ndarray]], title: str, path: Path) -> None:
    """The progress PSNR (dB, mean over the planes, before clamping) against the fit's minutes, one curve per
    label (label → (seconds, PSNR)), each ending in a dot."""
    plt = _pyplot()
    figure, axis = plt.subplots(figsize=(6.4, 3.8), dpi=110)
    for label, (seconds, psnr) in curves.items():
        line, = axis.plot(seconds / 60, psnr, linewidth=1, label=label)
        axis.plot(seconds[-1:] / 60, psnr[-1:], marker="o", markersize=4, color=line.get_color())
    ends = [psnr[-1] for _, psnr in curves.values()]
    if ends:
        axis.set_ylim(min(ends) - 6, max(ends) + 0.5)
        axis.legend(fontsize=8, loc="lower right")
    axis.set_xlabel("minutes of the fit's loop")
    axis.set_ylabel("PSNR during the fit (dB)")
    axis.set_title(title, fontsize=10)
    axis.grid(alpha=0.3)
    figure.tight_layout()
    save_figure(figure, path)
