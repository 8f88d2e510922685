"""What a fit optimises: the representation of the hologram, one definition that the fit, its checkpoints, the
model files and every command that renders a model use. Two exist: Gaussian primitives (`flat` and `cvqpg`,
method.md §2) and the per-pixel hologram (`pixel`, `cvqpg.pixels`). `representation(config)` gives the one a
configuration fits."""

from __future__ import annotations

from typing import Any, Protocol

import torch
from torch import Tensor

from .config import FitConfig, LearningRates
from .errors import ConfigError
from .initialisation import initial_gaussians
from .ops.rasterize import rasterize
from .pixels import PIXEL_UNITS, PixelFields, check_pixel_tensors, initial_pixels, pixel_class, pixel_shapes, wrapped
from .primitives import Gaussians, Primitives, TensorFields, activate, check_tensors
from .targets import Scene

GAUSSIAN_GROUPS = ("position", "scale", "rotation", "amplitude", "phase", "opacity", "curvature")
GAUSSIAN_UNITS = {"position_px": "px (x, y), pixel centres at integers", "scale_px": "px (σ along the Gaussian's axes)",
                  "rotation_rad": "rad", "amplitude": "per channel, unitless", "phase_rad": "rad in [0, 2π), per channel",
                  "opacity": "in (0, 1)", "curvature_per_m": "1/m (γ of the quadratic phase)"}


class Representation(Protocol):
    """A hologram representation: raw parameters the optimiser owns, and the physical ones a model file stores and
    the renderer turns into the W×H SLM hologram."""

    name: str

    def units(self, config: FitConfig) -> dict[str, str]:
        """The physical tensors of a model of `config` by name, with their units (a model file's `units`)."""

    def initial(self, config: FitConfig, scene: Scene | None, device: torch.device | str) -> TensorFields:
        """The raw parameters a fit of `config` starts from (`optimisation.init`), on `device`."""

    def groups(self, config: FitConfig) -> dict[str, str]:
        """The raw tensors the optimiser owns, by name, each with the name of its learning rate (`LearningRates`)."""

    def before_update(self, raw: TensorFields, config: FitConfig, step: int) -> None:
        """Whatever changes in what trains at update `step` (the curvature warm-up)."""

    def activate(self, raw: TensorFields, config: FitConfig) -> TensorFields:
        """The physical parameters of raw ones (differentiable)."""

    def field(self, physical: TensorFields, config: FitConfig, backend: str = "auto") -> Tensor:
        """The complex hologram [C, H, W] on `config`'s W×H SLM grid, with the kernels of `backend`."""

    def from_tensors(self, tensors: dict[str, Tensor], config: FitConfig) -> TensorFields:
        """The physical parameters of a model file's tensors."""

    def check(self, physical: TensorFields, config: FitConfig, name: str) -> None:
        """`ModelFileError` naming the file `name` unless the tensors have `config`'s shapes and sane values."""


class GaussianRepresentation:
    """N complex-valued 2D Gaussians (method.md §2), flat or with CVQPG's quadratic phase."""

    name = "gaussians"

    def units(self, config: FitConfig) -> dict[str, str]:
        return GAUSSIAN_UNITS

    def initial(self, config: FitConfig, scene: Scene | None, device: torch.device | str) -> Gaussians:
        return initial_gaussians(config, scene, device)

    def groups(self, config: FitConfig) -> dict[str, str]:
        # the flat primitive has no curvature, a phase without the quadratic term neither; each further phase term
        # (`cvqpg.phase`) is a group of its own
        phase = config.phase
        own = {name: name for name in GAUSSIAN_GROUPS if name != "curvature" or phase.has("quadratic")}
        return {**own, **{term.name: term.learning_rate for term in phase.extra_terms}}

    def before_update(self, raw: Gaussians, config: FitConfig, step: int) -> None:
        raw.curvature.requires_grad_(config.phase.has("quadratic") and step >= config.optimisation.curvature_warmup)
        for tensor in raw.terms.values():
            tensor.requires_grad_(step >= config.terms_warmup)

    def activate(self, raw: Gaussians, config: FitConfig) -> Primitives:
        return activate(raw, config)

    def field(self, physical: Primitives, config: FitConfig, backend: str = "auto") -> Tensor:
        return rasterize(physical, config.targets.width, config.targets.height, config.wavelengths,
                         config.optics.pixel_pitch, config.primitives.qpf, backend)

    def from_tensors(self, tensors: dict[str, Tensor], config: FitConfig) -> Primitives:
        return Primitives.from_tensors(tensors)

    def check(self, physical: Primitives, config: FitConfig, name: str) -> None:
        check_tensors(physical, config, name)


class PixelRepresentation:
    """The W×H hologram itself, one complex value (or one phase) per SLM pixel and channel (`cvqpg.pixels`)."""

    name = "pixels"

    def units(self, config: FitConfig) -> dict[str, str]:
        return {name: PIXEL_UNITS[name] for name in pixel_shapes(config)}

    def initial(self, config: FitConfig, scene: Scene | None, device: torch.device | str) -> PixelFields:
        return initial_pixels(config, scene, device)

    def groups(self, config: FitConfig) -> dict[str, str]:
        return {name: {"amplitude": "amplitude", "phase_rad": "phase"}[name]
                for name in pixel_class(config).__dataclass_fields__}

    def before_update(self, raw: PixelFields, config: FitConfig, step: int) -> None:
        pass

    def activate(self, raw: PixelFields, config: FitConfig) -> PixelFields:
        return wrapped(raw)

    def field(self, physical: PixelFields, config: FitConfig, backend: str = "auto") -> Tensor:
        return physical.field()

    def from_tensors(self, tensors: dict[str, Tensor], config: FitConfig) -> PixelFields:
        return pixel_class(config).from_tensors(tensors)

    def check(self, physical: PixelFields, config: FitConfig, name: str) -> None:
        check_pixel_tensors(physical, config, name)


GAUSSIANS = GaussianRepresentation()
PIXELS = PixelRepresentation()


def representation(config: FitConfig) -> Representation:
    """The representation `config` fits: per-pixel for `primitive` pixel, Gaussians otherwise."""
    return PIXELS if config.primitives.kind == "pixel" else GAUSSIANS


def param_groups(raw: TensorFields, config: FitConfig, lr: LearningRates | None = None) -> list[dict[str, Any]]:
    """The optimiser's groups of `raw`: one per trainable tensor, named by its learning rate in `lr` (default:
    `config.optimisation.lr`)."""
    lr = config.optimisation.lr if lr is None else lr
    return [{"params": [raw.parameter(tensor)], "lr": getattr(lr, rate), "name": rate}
            for tensor, rate in representation(config).groups(config).items()]


def require_gaussians(config: FitConfig, what: str, remedy: str) -> None:
    """`ConfigError` where `config` fits no Gaussians: `what` (the `.cvq` codec, say) works on Gaussians only;
    `remedy` says what to do instead."""
    if representation(config) is not GAUSSIANS:
        raise ConfigError(f"{what} works on Gaussian primitives, and this is a per-pixel hologram; {remedy}")
