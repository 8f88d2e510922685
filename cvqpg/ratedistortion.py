"""Rate–distortion points of one fitted model: the `.cvq` codec at several bit budgets, the float32 and
float16 model files, and the still-image anchors of hologram compression (JPEG 2000 and JPEG XL via
`imagecodecs`, the `compression` extra) on the real and imaginary parts of the model's float32 field.

Rate is bits per hologram pixel (8·bytes / (W·H), all channels together); distortion is the mean
multi-plane PSNR (dB) and SSIM of the reconstructions against the run's targets.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from .compression import LADDER, BitDepths, decode, encode
from .config import FitConfig
from .fitting import hologram
from .metrics import mean_psnr, mean_ssim
from .optics import reconstruct
from .primitives import Primitives
from .storage import load_model, save_model

JPEG2K_PSNRS = (35, 40, 45, 50, 55, 60, 70)  # OpenJPEG's quality layer, the planes' own PSNR in dB
JPEGXL_DISTANCES = (8.0, 4.0, 2.0, 1.5, 1.0, 0.7, 0.5, 0.25)  # butteraugli distances, smaller is finer
RANGE_BYTES = 8  # float32 low and high per plane


@dataclass
class Point:
    """One rate–distortion point; times in s (encode, and decode + render of the planes)."""

    codec: str
    setting: str
    bytes: int
    bpp: float
    psnr: float
    ssim: float
    encode_s: float
    decode_s: float


def _score(recon: Tensor, targets: Tensor) -> tuple[float, float]:
    return mean_psnr(recon, targets), mean_ssim(recon, targets)


def _point(codec: str, setting: str, size: int, config: FitConfig, recon: Tensor, targets: Tensor,
           encode_s: float, decode_s: float) -> Point:
    return Point(codec, setting, size, 8 * size / (config.width * config.height), *_score(recon, targets),
                 encode_s, decode_s)


def _render(primitives: Primitives, config: FitConfig) -> Tensor:
    with torch.no_grad():
        return reconstruct(hologram(primitives, config), config)


def codec_points(primitives: Primitives, config: FitConfig, targets: Tensor,
                 ladder: Sequence[BitDepths] = LADDER) -> list[Point]:
    """The `.cvq` codec at each budget of `ladder`."""
    points = []
    for bits in ladder:
        started = time.perf_counter()
        data = encode(primitives, config, bits)
        encoded = time.perf_counter()
        recon = _render(decode(data).primitives, config)
        points.append(_point("cvqpg", " ".join(f"{k}={v}" for k, v in asdict(bits).items()), len(data), config,
                             recon, targets, encoded - started, time.perf_counter() - encoded))
    return points


def model_file_points(primitives: Primitives, config: FitConfig, targets: Tensor) -> list[Point]:
    """The float32 and float16 `model.safetensors` files."""
    points = []
    with tempfile.TemporaryDirectory(prefix="cvqpg-rd-") as scratch:
        for dtype in ("float32", "float16"):
            path = Path(scratch) / f"model.{dtype}.safetensors"
            started = time.perf_counter()
            save_model(path, primitives, config, dtype)
            encoded = time.perf_counter()
            loaded, _ = load_model(path)
            recon = _render(loaded, config)
            points.append(_point(f"model {dtype}", "safetensors", path.stat().st_size, config, recon, targets,
                                 encoded - started, time.perf_counter() - encoded))
    return points


def _planes(field: Tensor) -> list[np.ndarray]:
    """Real and imaginary parts of each channel, float64 [H, W]."""
    array = field.detach().cpu().numpy()
    return [part.astype(np.float64) for channel in array for part in (channel.real, channel.imag)]


def _field(planes: list[np.ndarray], channels: int) -> Tensor:
    return torch.from_numpy(np.stack([planes[2 * c] + 1j * planes[2 * c + 1] for c in range(channels)])
                            .astype(np.complex64))


def anchor_points(primitives: Primitives, config: FitConfig, targets: Tensor,
                  settings: dict[str, Sequence[Any]] | None = None) -> list[Point]:
    """JPEG 2000 and JPEG XL on the model's float32 field: each real and imaginary plane mapped from
    its own [min, max] to 16 bits (the range, two float32, counted as side information)."""
    import imagecodecs

    codecs: dict[str, tuple[Callable[[np.ndarray, Any], bytes], Callable[[bytes], np.ndarray]]] = {
        "JPEG 2000": (lambda plane, psnr: imagecodecs.jpeg2k_encode(plane, level=psnr, codecformat="j2k"),
                      imagecodecs.jpeg2k_decode),
        "JPEG XL": (lambda plane, distance: imagecodecs.jpegxl_encode(plane, distance=distance),
                    imagecodecs.jpegxl_decode)}
    settings = settings or {"JPEG 2000": JPEG2K_PSNRS, "JPEG XL": JPEGXL_DISTANCES}
    with torch.no_grad():
        planes = _planes(hologram(primitives, config))
    ranges = [(plane.min(), plane.max()) for plane in planes]
    quantised = [np.rint((plane - low) / max(high - low, 1e-30) * 65535).astype(np.uint16)
                 for plane, (low, high) in zip(planes, ranges)]
    points = []
    for codec, values in settings.items():
        encoder, decoder = codecs[codec]
        for value in values:
            started = time.perf_counter()
            streams = [encoder(plane, value) for plane in quantised]
            encoded = time.perf_counter()
            decoded = [low + decoder(stream).astype(np.float64) / 65535 * (high - low)
                       for stream, (low, high) in zip(streams, ranges)]
            with torch.no_grad():
                recon = reconstruct(_field(decoded, config.channels), config)
            size = sum(len(s) for s in streams) + RANGE_BYTES * len(streams)
            points.append(_point(codec, str(value), size, config, recon, targets, encoded - started,
                                 time.perf_counter() - encoded))
    return points


def rd_points(primitives: Primitives, config: FitConfig, targets: Tensor, ladder: Sequence[BitDepths] = LADDER,
              anchors: bool = True) -> list[dict[str, Any]]:
    """All R-D points of one model against `targets` [M, C, H, W], as plain dicts (for JSON and tables)."""
    points = [*model_file_points(primitives, config, targets), *codec_points(primitives, config, targets, ladder)]
    if anchors:
        points += anchor_points(primitives, config, targets)
    return [asdict(p) for p in points]


def bd_rate(anchor: Sequence[dict[str, Any]], test: Sequence[dict[str, Any]], top_psnr: float,
            span_db: float = 1.0) -> float:
    """BD-rate (%) of `test` against `anchor` (points as `rd_points` gives them) over PSNR from
    `top_psnr` − `span_db` to `top_psnr`, with `bjontegaard`'s PCHIP interpolation; each curve keeps
    its points in that range plus the nearest point on either side, so that the range is bracketed."""
    import bjontegaard

    def bracketed(points: Sequence[dict[str, Any]]) -> tuple[list[float], list[float]]:
        ordered = sorted(points, key=lambda p: p["psnr"])
        psnrs = [p["psnr"] for p in ordered]
        low = max(np.searchsorted(psnrs, top_psnr - span_db) - 1, 0)
        high = min(np.searchsorted(psnrs, top_psnr) + 1, len(ordered))
        kept = ordered[low:high]
        return [p["bpp"] for p in kept], [p["psnr"] for p in kept]

    rate_a, psnr_a = bracketed(anchor)
    rate_t, psnr_t = bracketed(test)
    return float(bjontegaard.bd_rate(rate_a, psnr_a, rate_t, psnr_t, method="pchip", require_matching_points=False))
