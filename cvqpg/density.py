"""Density control at a fixed N (docs/beyond.md): primitives that carry the least field energy are moved
onto splits of primitives that sit where the reconstruction's error is largest.

A split halves a primitive's amplitude and gives the same half to the moved one, placed on it: the
hologram, a sum that is linear in the amplitudes, is unchanged by the split, and a jitter of half the
primitive's scale lets the two separate. The moved primitives' optimiser moments restart at zero. The
final model has exactly N primitives with the same parameters each, so "equal N" keeps its meaning.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .config import DensityControl, FitConfig
from .optics import reconstruct
from .primitives import Gaussians, Primitives, activate, field_energy, raw_positions
from .targets import Scene

if TYPE_CHECKING:
    from pytorch_optimizer import Adan

ERROR_WINDOW_PX = 9  # the error map is averaged over this square: a primitive's error is its neighbourhood's
JITTER_SCALES = 0.5  # a moved primitive lands this many of its source's scales away from it
SEED_OFFSET = 0x5EED  # the relocation draws come from their own generator, apart from the targets' noise


def error_map(scene: Scene, config: FitConfig, hologram: Tensor) -> Tensor:
    """Squared error of the reconstruction summed over planes and channels, averaged over
    `ERROR_WINDOW_PX`² px [H, W]."""
    error = (reconstruct(hologram, config) - scene.targets).square().sum(dim=(0, 1))
    return torch.nn.functional.avg_pool2d(error[None, None], ERROR_WINDOW_PX, 1, ERROR_WINDOW_PX // 2,
                                          count_include_pad=False)[0, 0]


def relocation(primitives: Primitives, error: Tensor, fraction: float, generator: torch.Generator
               ) -> tuple[Tensor, Tensor, Tensor]:
    """Which primitives move and where: (moved [k], sources [k], new positions [k, 2] px). The k =
    `fraction`·N with the least field energy move; each onto a distinct other primitive drawn with a
    probability proportional to the error map at its position."""
    count = primitives.opacity.shape[0]
    moves = min(int(fraction * count), count // 2)
    if moves == 0:
        return (torch.empty(0, dtype=torch.long, device=error.device),) * 2 + (error.new_empty(0, 2),)
    energy = field_energy(primitives)
    order = torch.argsort(energy, stable=True)
    moved, kept = order[:moves], order[moves:]
    height, width = error.shape
    column = primitives.position_px[kept, 0].round().long().clamp(0, width - 1)
    row = primitives.position_px[kept, 1].round().long().clamp(0, height - 1)
    weights = error[row, column].double().cpu() + torch.finfo(torch.float64).tiny
    sources = kept[torch.multinomial(weights, moves, replacement=False, generator=generator).to(kept.device)]
    jitter = torch.randn(moves, 2, generator=generator).to(error.device)
    destination = primitives.position_px[sources] + JITTER_SCALES * primitives.scale_px[sources] * jitter
    return moved, sources, destination


@dataclass
class Relocator:
    """Density control's state beside the optimiser: its settings, its own random generator (a
    checkpoint stores its state) and how many primitives it has moved so far."""

    settings: DensityControl
    generator: torch.Generator
    moved_count: int = 0

    @classmethod
    def for_config(cls, config: FitConfig) -> Relocator | None:
        if config.density is None:
            return None
        return cls(config.density, torch.Generator().manual_seed(config.seed + SEED_OFFSET))

    def due(self, step: int, steps: int) -> bool:
        return step in self.settings.event_steps(steps)

    def relocate(self, gaussians: Gaussians, optimizer: Adan, scene: Scene, config: FitConfig,
                 hologram: Tensor) -> None:
        """Move primitives in place (`relocation`), and zero the optimiser moments of the moved ones.
        `hologram` is the current model's [C, H, W] field."""
        with torch.no_grad():
            primitives = activate(gaussians, config)
            moved, sources, destination = relocation(primitives, error_map(scene, config, hologram),
                                                     self.settings.fraction, self.generator)
            if moved.numel() == 0:
                return
            gaussians.amplitude[sources] *= 0.5
            for tensor in gaussians.tensors().values():
                tensor[moved] = tensor[sources]
            gaussians.position[moved] = raw_positions(destination, config.width, config.height)
            count = gaussians.position.shape[0]
            for parameter in gaussians.tensors().values():
                for moment in optimizer.state.get(parameter, {}).values():
                    if isinstance(moment, Tensor) and moment.dim() > 0 and moment.shape[0] == count:
                        moment[moved] = 0
            self.moved_count += moved.numel()

    def to_payload(self) -> dict:
        return {"generator": self.generator.get_state(), "moved_count": self.moved_count}

    def load_payload(self, payload: dict) -> None:
        self.generator.set_state(payload["generator"])
        self.moved_count = payload["moved_count"]
