"""Run folders: everything a fit leaves behind, and re-evaluation of a saved run."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from torch import Tensor

from . import __version__
from .config import FitConfig
from .fitting import FitResult, render
from .metrics import MetricReport, evaluate
from .scenes import builtin_scene
from .storage import load_model, save_model
from .targets import Scene, load_scene

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.json"
MODEL_FILE = "model.safetensors"
CHECKPOINT_FILE = "checkpoint.pt"
PLANE_IMAGES = ("target_plane*.png", "recon_plane*.png")


def write_json(path: Path, data: Any) -> None:
    """Write JSON atomically: a reader never sees a half-written file."""
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(partial, path)


def to_8bit(image: Tensor) -> Image.Image:
    """[C, H, W] in [0, 1] → 8-bit RGB or L image."""
    array = np.clip(np.round(image.detach().cpu().float().numpy() * 255), 0, 255).astype(np.uint8)
    return Image.fromarray(array[0], "L") if array.shape[0] == 1 else Image.fromarray(
        array.transpose(1, 2, 0), "RGB")


def colormapped(values: np.ndarray, cmap: str, low: float, high: float) -> Image.Image:
    """Channels [C, H, W] side by side through a matplotlib colour map."""
    import matplotlib

    tiled = np.concatenate(list(values), axis=1)
    rgba = matplotlib.colormaps[cmap]((tiled - low) / (high - low))
    return Image.fromarray((rgba[..., :3] * 255).astype(np.uint8), "RGB")


def save_hologram_images(hologram: Tensor, folder: Path) -> None:
    """`amplitude.png` (viridis, 0..max) and `phase.png` (twilight, 0..2π), one panel per channel."""
    amplitude = hologram.abs().cpu().numpy()
    phase = np.mod(hologram.angle().cpu().numpy(), 2 * math.pi)
    colormapped(amplitude, "viridis", 0.0, max(float(amplitude.max()), 1e-12)).save(folder / "amplitude.png")
    colormapped(phase, "twilight", 0.0, 2 * math.pi).save(folder / "phase.png")


def save_curve(history: dict[str, list[float]], path: Path) -> None:
    """Loss (log scale) and PSNR per step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, loss_axis = plt.subplots(figsize=(7, 3.5), dpi=110)
    steps = np.arange(len(history["loss"]))
    loss_axis.semilogy(steps, history["loss"], color="tab:blue")
    loss_axis.set_xlabel("step")
    loss_axis.set_ylabel("loss", color="tab:blue")
    psnr_axis = loss_axis.twinx()
    psnr_axis.plot(steps, history["psnr"], color="tab:orange")
    psnr_axis.set_ylabel("PSNR vs targets (dB)", color="tab:orange")
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def metrics_record(report: MetricReport, config: FitConfig, seconds: float,
                   extra: dict[str, Any] | None = None) -> dict[str, Any]:
    return {**report.to_dict(), "steps": config.steps, "num_gaussians": config.primitive_count,
            "num_params": config.primitive_count * config.params_per_primitive,
            "seconds": seconds, **(extra or {})}


def start_run(folder: str | Path, config: FitConfig, source: dict[str, Any]) -> Path:
    """Create the run folder with its `config.json` (enough to resume); clear a previous run's outputs."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for pattern in (METRICS_FILE, CHECKPOINT_FILE, MODEL_FILE, *PLANE_IMAGES):
        for stale in folder.glob(pattern):
            stale.unlink()
    write_json(folder / CONFIG_FILE, {"cvqpg_version": __version__, "source": source, **config.to_dict()})
    return folder


def read_run(folder: str | Path) -> tuple[FitConfig, dict[str, Any]]:
    """The configuration and input description of a run folder."""
    recorded = json.loads((Path(folder) / CONFIG_FILE).read_text())
    return FitConfig.from_dict(recorded), recorded["source"]


def write_run(folder: str | Path, result: FitResult, scene: Scene, source: dict[str, Any]) -> Path:
    """Save config, metrics, model, per-plane targets and reconstructions, hologram and curve."""
    folder = start_run(folder, result.config, source)
    config = result.config
    save_model(folder / MODEL_FILE, result.gaussians, config)
    hologram, recon = render(result.gaussians, config)
    for plane, (target, image) in enumerate(zip(scene.targets, recon)):
        to_8bit(target).save(folder / f"target_plane{plane}.png")
        to_8bit(image).save(folder / f"recon_plane{plane}.png")
    save_hologram_images(hologram, folder)
    save_curve(result.history, folder / "curve.png")
    history = result.history["psnr"]
    write_json(folder / METRICS_FILE, metrics_record(
        result.metrics, config, result.seconds,
        {"updates": len(history), "initial_psnr": history[0] if history else None,
         "skipped_steps": result.skipped_steps, "sanitised_steps": result.sanitised_steps}))
    return folder


def scene_from_source(source: dict[str, Any], config: FitConfig) -> Scene:
    """Rebuild a run's scene from what `config.json` recorded about its inputs."""
    if "scene" in source:
        builtin = builtin_scene(source["scene"], config.width, config.height)
        return load_scene(builtin.image, builtin.depth, config)
    return load_scene(source["image"], source.get("depth"), config, source.get("resize_depth", False))


def evaluate_run(folder: str | Path) -> dict[str, Any]:
    """Recompute a saved run's metrics from its model and inputs; rewrites `metrics.json`."""
    folder = Path(folder)
    _, source = read_run(folder)
    gaussians, config = load_model(folder / MODEL_FILE)
    scene = scene_from_source(source, config)
    _, recon = render(gaussians, config)
    previous = {}
    if (folder / METRICS_FILE).is_file():
        previous = json.loads((folder / METRICS_FILE).read_text())
    kept = {k: v for k, v in previous.items() if k not in ("mean", "per_plane", "unavailable")}
    record = {**metrics_record(evaluate(recon, scene.targets), config, previous.get("seconds", 0.0)), **kept}
    write_json(folder / METRICS_FILE, record)
    return record
