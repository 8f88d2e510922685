"""Where a fit's primitives start: the paper's uniform draws (method.md §2), or positions drawn from a map
of the targets: the energy of the field they imply on the SLM plane, or their edges (docs/beyond.md)."""

from __future__ import annotations

import torch
from torch import Tensor

from .config import FitConfig
from .errors import ConfigError
from .ops.propagation.reference import propagate
from .primitives import Gaussians, init_gaussians, raw_positions
from .targets import Scene

SEED_OFFSET = 0x1417  # the position draws have their own generator: the paper's draws stay as they are
# The share of `edges`' draws spread evenly: flat and dark parts need primitives too (docs/beyond.md).
EDGES_UNIFORM_SHARE = 0.3


def implied_slm_field(scene: Scene, config: FitConfig) -> Tensor:
    """The field [C, H, W] that the targets imply on the SLM plane: each plane's target amplitude √I with
    a flat phase, propagated back by its distance (BLASM, −d m), averaged over the planes."""
    amplitude = scene.targets.clamp(min=0).sqrt().to(torch.complex64)
    fields = [propagate(amplitude[plane], [-distance], config.wavelengths, config.optics.pixel_pitch)[0]
              for plane, distance in enumerate(config.plane_distances)]
    return torch.stack(fields).mean(dim=0)


def edge_density(targets: Tensor, uniform_share: float = EDGES_UNIFORM_SHARE) -> Tensor:
    """A probability per pixel [H, W] of the targets [M, C, H, W]: `uniform_share` spread evenly, the rest in
    proportion to the magnitude of the planes' and channels' mean intensity's gradient (forward differences,
    1/px). Where the targets have no edges (a flat or black image), every pixel is as likely."""
    mean = targets.double().mean(dim=(0, 1))
    dx = torch.nn.functional.pad(mean[:, 1:] - mean[:, :-1], (0, 1))
    dy = torch.nn.functional.pad(mean[1:] - mean[:-1], (0, 0, 0, 1))
    magnitude = torch.nan_to_num((dx.square() + dy.square()).sqrt(), nan=0.0, posinf=0.0)
    total = magnitude.sum()
    edges = magnitude / total if total > 0 else torch.full_like(magnitude, 1 / magnitude.numel())
    return (1 - uniform_share) * edges + uniform_share / magnitude.numel()


def positions_from_energy(energy: Tensor, count: int, generator: torch.Generator) -> Tensor:
    """`count` positions [count, 2] (x, y) px drawn with a probability proportional to `energy` [H, W] per
    pixel, uniformly within the pixel. Non-finite entries count as none; where nothing is left (black
    targets), every pixel is as likely."""
    height, width = energy.shape
    weights = torch.nan_to_num(energy.double(), nan=0.0, posinf=0.0, neginf=0.0).clamp(min=0).flatten()
    if not weights.sum() > 0:
        weights = torch.ones_like(weights)
    # Inverse-CDF draws: torch.multinomial refuses more than 2^24 categories (pixels beyond 8K).
    cumulative = weights.cumsum(dim=0)
    index = torch.searchsorted(cumulative, torch.rand(count, generator=generator, dtype=torch.float64) * cumulative[-1],
                               right=True).clamp(max=weights.numel() - 1)
    pixel = torch.stack((index % width, index // width), dim=1).float()
    return pixel + torch.rand(count, 2, generator=generator) - 0.5


def initial_gaussians(config: FitConfig, scene: Scene | None = None, device: str = "cpu") -> Gaussians:
    """The raw parameters a fit starts from (`optimisation.init`), on `device`: the paper's uniform draws, or the
    same draws with positions moved, which needs the `scene`: with `targets` to where the implied SLM field
    (`implied_slm_field`) carries its energy, with `edges` mostly to the targets' edges (`edge_density`)."""
    width, height, seed = config.targets.width, config.targets.height, config.optimisation.seed
    gaussians = init_gaussians(config.primitive_count, config.channels, width, height, seed, "cpu",
                               config.primitives.curvature == "per-channel",
                               tuple(term.name for term in config.phase.extra_terms))
    init = config.optimisation.init
    if init != "uniform":
        if scene is None:
            raise ConfigError(f"`init` {init} draws from the targets and needs the scene; pass it, or set `init` "
                              "to uniform")
        with torch.no_grad():
            scene = scene.to("cpu")
            if init == "targets":
                energy = implied_slm_field(scene, config).abs().square().sum(dim=0)
            else:
                energy = edge_density(scene.targets)
            generator = torch.Generator().manual_seed(seed + SEED_OFFSET)
            position = positions_from_energy(energy, config.primitive_count, generator)
            gaussians.position.copy_(raw_positions(position, width, height))
    return gaussians.to(device)
