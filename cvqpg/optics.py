"""Reconstruction of a hologram at its depth planes (method.md §3): the SLM field, propagated by BLASM
(odak 0.2.7's convention), as clamped intensities; each an op of `cvqpg.ops`, on the caller's backend."""

from __future__ import annotations

from typing import Sequence

from torch import Tensor

from .config import FitConfig
from .ops.field import Grid, clamped_intensity, guarded_field
from .ops.propagation import propagate_planes


def reconstruct(hologram: Tensor, config: FitConfig, distances_m: Sequence[float] | None = None,
                backend: str = "auto") -> Tensor:
    """Hologram [C, H, W] → reconstructed intensity [M, C, H, W] clamped to [0, 1] (method.md §3), at
    `config`'s planes or at `distances_m` (m), with the kernels of `backend` (`config.resolve_backend`)."""
    grid = Grid.for_config(config)
    field = guarded_field(hologram, grid, backend)
    distances = config.plane_distances if distances_m is None else tuple(distances_m)
    planes = propagate_planes(field, grid, distances, config.wavelengths, config.optics.pixel_pitch, backend)
    return clamped_intensity(planes, backend)
