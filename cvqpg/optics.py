"""What a hologram shows at its depth planes (method.md §3, §8): the SLM field, shown on the configuration's
display (`display.Display`), propagated by BLASM (odak 0.2.7's convention), as clamped intensities; each an op of
`cvqpg.ops`, on the caller's backend."""

from __future__ import annotations

from typing import Sequence

from torch import Tensor

from .config import FitConfig, padded_size
from .ops.display import shown_field
from .ops.field import Grid, clamped_intensity, guarded_field
from .ops.propagation import propagate_planes


def reconstruct(hologram: Tensor, config: FitConfig, distances_m: Sequence[float] | None = None,
                backend: str = "auto") -> Tensor:
    """Hologram [C, H, W] → the intensity [M, C, H, W], clamped to [0, 1], that `config.display` shows at
    `config`'s planes or at `distances_m` (m), with the kernels of `backend` (`config.resolve_backend`).

    The default display, the ideal complex SLM, is method.md §3's: the hologram with its guard band. Any other
    shows its canvas (`ops.display.shown_field`) in a dark zero-padded array, behind the 4f aperture, which the
    propagation's transfer functions carry (method.md §8). Differentiable either way: the
    fit's loss sees what the display shows.
    """
    display = config.display
    distances = config.plane_distances if distances_m is None else tuple(distances_m)
    if display.ideal:
        grid = Grid.for_config(config)
        field = guarded_field(hologram, grid, backend)
    else:
        grid = display_grid(config)
        field = shown_field(hologram, grid, display, backend)
    planes = propagate_planes(field, grid, distances, config.wavelengths, config.optics.pixel_pitch, backend,
                              display.aperture)
    return clamped_intensity(planes, backend)


def display_grid(config: FitConfig) -> Grid:
    """The hologram's H×W inside the zero-padded array of its display's canvas: the guard band (`optics`) around
    the canvas, not the hologram, since no light comes from beyond the SLM."""
    height, width = config.display.canvas_for(config.targets.height, config.targets.width)
    optics = config.optics
    return Grid(config.targets.height, config.targets.width,
                padded_size(height, optics.guard_band_px, optics.pad_multiple_px),
                padded_size(width, optics.guard_band_px, optics.pad_multiple_px))
