"""The per-pixel hologram: the W×H SLM field itself optimised by gradient descent, pixel by pixel (the
gradient-descent computer-generated hologram that holography compares against), as a complex hologram or as a
phase-only pattern (docs/method.md, "The per-pixel hologram")."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .config import FitConfig
from .errors import ConfigError, ModelFileError
from .primitives import REWRITE_MODEL, TensorFields
from .targets import Scene

# `init uniform`: every pixel's phase drawn from U(−half, +half) rad, a small random phase that breaks the
# symmetry of a flat start without scattering the light (docs/beyond.md, "The per-pixel hologram").
SMALL_PHASE_HALF_RANGE_RAD = 0.5
PIXEL_INITS = ("uniform", "zero", "targets")
TWO_PI = 2 * math.pi


class PixelFields(TensorFields):
    """Tensors of one shape [C, H, W]: a pixel of every channel is one of `count` = H·W pixels."""

    @property
    def count(self) -> int:
        shape = self.phase_rad.shape
        return shape[-1] * shape[-2] if len(shape) == 3 else 0

    @property
    def channels(self) -> int:
        return self.phase_rad.shape[0]


@dataclass
class PixelHologram(PixelFields):
    """A complex hologram of one value per SLM pixel and channel; what the fit optimises is what the file stores
    (the phase wrapped into [0, 2π) there)."""

    amplitude: Tensor  # [C, H, W], unitless; the SLM field clamps |H| at 1 (method.md §3)
    phase_rad: Tensor  # [C, H, W] rad

    def field(self) -> Tensor:
        """The hologram [C, H, W] complex: amplitude·e^{iφ}."""
        return torch.polar(self.amplitude, self.phase_rad)


@dataclass
class PixelPhase(PixelFields):
    """A phase-only pattern: one phase per SLM pixel and channel, unit amplitude."""

    phase_rad: Tensor  # [C, H, W] rad

    def field(self) -> Tensor:
        """The hologram [C, H, W] complex: e^{iφ}."""
        return torch.polar(torch.ones_like(self.phase_rad), self.phase_rad)


PIXEL_UNITS = {"amplitude": "per channel and SLM pixel [C, H, W], unitless (|H| clamped at 1 on the SLM)",
               "phase_rad": "rad in [0, 2π), per channel and SLM pixel [C, H, W]"}


def pixel_class(config: FitConfig) -> type[PixelFields]:
    """The per-pixel hologram `config` fits: a phase pattern for a phase-only display, else a complex one."""
    return PixelPhase if config.phase_only_pixels else PixelHologram


def pixel_shapes(config: FitConfig) -> dict[str, tuple[int, ...]]:
    """The shape of each tensor of `config`'s per-pixel hologram."""
    shape = (config.channels, config.targets.height, config.targets.width)
    names = ("phase_rad",) if config.phase_only_pixels else ("amplitude", "phase_rad")
    return {name: shape for name in names}


def wrapped(pixels: PixelFields) -> PixelFields:
    """The same hologram with its phase in [0, 2π) (what a model file stores)."""
    tensors = pixels.tensors()
    tensors["phase_rad"] = torch.remainder(tensors["phase_rad"], TWO_PI)
    return type(pixels).from_tensors(tensors)


def initial_pixels(config: FitConfig, scene: Scene | None = None, device: torch.device | str = "cpu"
                   ) -> PixelFields:
    """The hologram a per-pixel fit starts from (`optimisation.init`), on `device`: `uniform` a small random phase
    (U(±`SMALL_PHASE_HALF_RANGE_RAD`) from a CPU generator seeded with the seed), `zero` a flat phase, `targets`
    the phase of the field the targets imply on the SLM (`initialisation.implied_slm_field`). A complex hologram's
    amplitude starts at that field's amplitude with `targets`, else at √(mean target intensity) on every pixel (0.5
    without a scene), so that the light reaching the planes is about what the targets hold."""
    from .initialisation import implied_slm_field

    init = config.optimisation.init
    if init not in PIXEL_INITS:
        raise ConfigError(f"`init` {init!r} places Gaussians; a per-pixel hologram starts from "
                          f"{', '.join(map(repr, PIXEL_INITS))}")
    if scene is None and init == "targets":
        raise ConfigError("`init` targets draws from the targets and needs the scene; pass it, or set `init` to "
                          "uniform")
    shape = (config.channels, config.targets.height, config.targets.width)
    implied = None
    if init == "uniform":
        generator = torch.Generator().manual_seed(config.optimisation.seed)
        phase = (2 * torch.rand(shape, generator=generator) - 1) * SMALL_PHASE_HALF_RANGE_RAD
    elif init == "zero":
        phase = torch.zeros(shape)
    else:
        with torch.no_grad():
            implied = implied_slm_field(scene.to("cpu"), config)
        phase = torch.remainder(implied.angle(), TWO_PI).float()
    if config.phase_only_pixels:
        return PixelPhase(phase.contiguous()).to(device)
    if implied is not None:
        amplitude = implied.abs().float()
    else:
        level = 0.5 if scene is None else float(scene.targets.clamp(min=0).mean().sqrt())
        amplitude = torch.full(shape, level)
    return PixelHologram(amplitude.contiguous(), phase.contiguous()).to(device)


def check_pixel_tensors(pixels: PixelFields, config: FitConfig, name: str) -> None:
    """Raise `ModelFileError` naming the model file `name` unless every tensor has the shape `config` gives it and
    finite values."""
    tensors = pixels.tensors()
    for tensor_name, shape in pixel_shapes(config).items():
        if tensor_name not in tensors or tuple(tensors[tensor_name].shape) != shape:
            found = tuple(tensors[tensor_name].shape) if tensor_name in tensors else None
            raise ModelFileError(f"{name}: tensor {tensor_name!r} has shape {found}, expected {shape}; "
                                 f"{REWRITE_MODEL}")
        if not bool(torch.isfinite(tensors[tensor_name]).all()):
            raise ModelFileError(f"{name}: tensor {tensor_name!r} holds values that are not finite; {REWRITE_MODEL}")
