"""Fitting: the optimisation loop of SPEC §6 and rendering of a fitted model."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch
from PIL import Image
from pytorch_optimizer import Adan
from torch import Tensor
from tqdm.auto import tqdm

from .config import FitConfig
from .losses import multiplane_loss, noisy_targets
from .metrics import MetricReport, evaluate
from .optics import reconstruct
from .primitives import Gaussians, activate, init_gaussians
from .rasterization import rasterize
from .targets import Scene, load_scene

LEARNING_RATE_GROUPS = ("position", "scale", "rotation", "color", "phase", "opacity", "curvature")


@dataclass
class FitResult:
    """A fitted model with its settings, final metrics and per-step history."""

    gaussians: Gaussians
    config: FitConfig
    metrics: MetricReport
    history: dict[str, list[float]] = field(default_factory=dict)
    seconds: float = 0.0


def render_hologram(gaussians: Gaussians, config: FitConfig) -> Tensor:
    """Complex hologram [C, H, W] of raw parameters under `config`."""
    return rasterize(activate(gaussians, config), config.width, config.height, config.wavelengths,
                     config.pixel_pitch, config.qpf, config.backend)


def render(gaussians: Gaussians, config: FitConfig) -> tuple[Tensor, Tensor]:
    """Hologram [C, H, W] and clamped reconstructions [M, C, H, W], without gradients."""
    with torch.no_grad():
        hologram = render_hologram(gaussians, config)
        return hologram, reconstruct(hologram, config)


def trainable_groups(config: FitConfig) -> tuple[str, ...]:
    """Parameter groups the optimiser owns: the flat primitive has no curvature."""
    if config.primitive == "flat":
        return tuple(g for g in LEARNING_RATE_GROUPS if g != "curvature")
    return LEARNING_RATE_GROUPS


def make_optimizer(gaussians: Gaussians, config: FitConfig) -> Adan:
    """Adan (pytorch-optimizer) with one group per parameter kind and SPEC §6 learning rates."""
    groups = [{"params": [getattr(gaussians, name)], "lr": getattr(config.lr, name), "name": name}
              for name in trainable_groups(config)]
    return Adan(groups, betas=config.betas, eps=config.adan_eps, weight_decay=0.0, max_grad_norm=0.0)


def position_learning_rate(step: int, config: FitConfig) -> float:
    """Cosine annealing from `lr.position` to `lr.position_final` over the run's `steps + 1` updates."""
    progress = step / (config.steps + 1)
    return config.lr.position_final + (config.lr.position - config.lr.position_final) * (
        1 + math.cos(math.pi * progress)) / 2


def psnr_from_mse(mse: Tensor) -> float:
    """Mean over planes of −10·log10(MSE) (dB), data range 1."""
    return float((-10 * torch.log10(mse.clamp(min=1e-12))).mean())


def optimisation_step(gaussians: Gaussians, optimizer: Adan, scene: Scene, config: FitConfig,
                      step: int, generator: torch.Generator) -> tuple[float, float]:
    """One update: render, propagate, loss, sanitise and clip gradients, Adan. Returns loss, PSNR."""
    if config.primitive == "cvqpg" and step == config.warmup:
        gaussians.curvature.requires_grad_(True)
    recon = reconstruct(render_hologram(gaussians, config), config)
    noise = torch.randn(scene.targets.shape, generator=generator, device=scene.targets.device)
    loss, mse = multiplane_loss(recon, scene.targets, scene.masks,
                                noisy_targets(scene.targets, noise, config.target_noise),
                                config.ssim_weight)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    apply_gradients(optimizer, config, step)
    return float(loss.detach()), psnr_from_mse(mse)


def apply_gradients(optimizer: Adan, config: FitConfig, step: int) -> None:
    """Non-finite gradient entries → 0, clip to the global norm, anneal position, Adan step."""
    params = [p for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
    for p in params:
        torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
    torch.nn.utils.clip_grad_norm_(params, config.grad_clip_norm)
    for group in optimizer.param_groups:
        if group["name"] == "position":
            group["lr"] = position_learning_rate(step, config)
    optimizer.step()


def fit(image: str | Path | Image.Image | Tensor, depth: str | Path | Image.Image | Tensor | None = None,
        config: FitConfig = FitConfig(), progress: bool = True,
        on_step: Callable[[int, float, float], None] | None = None) -> FitResult:
    """Fit an image (file, PIL image or [C, H, W] tensor) and its depth map; see `fit_scene`."""
    return fit_scene(load_scene(image, depth, config), config, progress, on_step)


def fit_scene(scene: Scene, config: FitConfig = FitConfig(), progress: bool = True,
              on_step: Callable[[int, float, float], None] | None = None) -> FitResult:
    """Fit N primitives to a scene's targets; returns the fitted model and its final metrics.

    Runs the reference loop's `config.steps + 1` updates (indices 0..steps); curvature is frozen at
    γ = 0 for the first `config.warmup` of them.
    """
    device = torch.device(config.device)
    scene = Scene(*(t.to(device) for t in (scene.image, scene.masks, scene.targets)))
    gaussians = init_gaussians(config.primitive_count, config.channels, config.width, config.height,
                               config.seed, device)
    for name in trainable_groups(config):
        getattr(gaussians, name).requires_grad_(name != "curvature" or config.warmup <= 0)
    optimizer = make_optimizer(gaussians, config)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    history: dict[str, list[float]] = {"loss": [], "psnr": []}
    started = time.perf_counter()
    bar = tqdm(range(config.steps + 1), disable=not progress, desc=f"fit {config.primitive}",
               unit="step", dynamic_ncols=True)
    for step in bar:
        loss, psnr = optimisation_step(gaussians, optimizer, scene, config, step, generator)
        history["loss"].append(loss)
        history["psnr"].append(psnr)
        bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{psnr:.2f}dB", refresh=False)
        if on_step is not None:
            on_step(step, loss, psnr)
    seconds = time.perf_counter() - started
    fitted = gaussians.detached()
    _, recon = render(fitted, config)
    return FitResult(fitted, config, evaluate(recon, scene.targets), history, seconds)
