"""Complex-valued Gaussian primitives: raw parameters, initialisation and activations (method.md §2, §4)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, fields

import torch
from torch import Tensor

from .config import FitConfig
from .errors import ConfigError, ModelFileError
from .phase import QUADRATIC, TERMS, activate_terms, term_limits

COVARIANCE_REGULARISER_PX2 = 0.1
MIN_SCALE_PX = 0.1
MAX_LOG_SCALE = math.log(1e4)
POSITION_CLAMP = 0.999
INIT_SCALE_RANGE_PX = (1.5, 5.0)
INIT_OPACITY_RAW = -0.5


class TensorFields:
    """Per-primitive tensors of a dataclass, handled as one dict (checkpoints, files, devices): its fields, and where
    it has a `terms` field (the phase terms beyond the curvature, by term name) those under their names
    (`_term_name`), only where a model has them: a model without them has exactly the tensors of the versions
    before them."""

    @staticmethod
    def _term_name(term: str) -> str:
        return term

    @property
    def count(self) -> int:
        return getattr(self, fields(self)[0].name).shape[0]

    def tensors(self) -> dict[str, Tensor]:
        own = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "terms"}
        return {**own, **{self._term_name(name): tensor for name, tensor in getattr(self, "terms", {}).items()}}

    @classmethod
    def from_tensors(cls, tensors: dict[str, Tensor]):
        own = {f.name: tensors[f.name] for f in fields(cls) if f.name != "terms"}
        if "terms" not in {f.name for f in fields(cls)}:
            return cls(**own)
        terms = {name: tensors[cls._term_name(name)] for name in TERMS
                 if name != QUADRATIC.name and cls._term_name(name) in tensors}
        return cls(**own, terms=terms)

    def parameter(self, name: str) -> Tensor:
        """The raw tensor of an optimiser group: a field, or a phase term."""
        terms = getattr(self, "terms", {})
        return terms[name] if name in terms else getattr(self, name)

    def to(self, device: torch.device | str, dtype: torch.dtype | None = None):
        return self.from_tensors({k: v.to(device, dtype) for k, v in self.tensors().items()})

    def detached(self):
        return self.from_tensors({k: v.detach().clone() for k, v in self.tensors().items()})


@dataclass
class Gaussians(TensorFields):
    """Raw (pre-activation) parameters of N primitives; each tensor is an optimisable leaf."""

    position: Tensor  # [N, 2] → px via (tanh+1)/2·(W, H)
    scale: Tensor  # [N, 2] → px via exp + 0.1
    rotation: Tensor  # [N] rad
    amplitude: Tensor  # [N, C], unitless (used as is)
    phase: Tensor  # [N, C] → rad via mod 2π
    opacity: Tensor  # [N] → sigmoid
    curvature: Tensor  # [N], or [N, C] per channel → 1/m via γ_max·tanh
    terms: dict[str, Tensor] = field(default_factory=dict)  # the phase terms beyond γ [N, P] (cvqpg/phase.py)

    @property
    def channels(self) -> int:
        return self.amplitude.shape[1]


@dataclass
class Primitives(TensorFields):
    """Activated, physical parameters that the rasterizer consumes and a model file stores."""

    position_px: Tensor  # [N, 2] (x, y), pixel centres at integers
    scale_px: Tensor  # [N, 2]
    rotation_rad: Tensor  # [N]
    amplitude: Tensor  # [N, C]
    phase_rad: Tensor  # [N, C]
    opacity: Tensor  # [N]
    curvature_per_m: Tensor  # [N] shared, or [N, C] one per channel: γ in 1/m
    terms: dict[str, Tensor] = field(default_factory=dict)  # the phase terms beyond γ, physical [N, P], by term name

    @staticmethod
    def _term_name(term: str) -> str:
        return TERMS[term].physical

    @property
    def channels(self) -> int:
        return self.amplitude.shape[1]


# What to do with a model file that is refused for making no physical sense.
REWRITE_MODEL = "the file was damaged or altered, or not written by cvqpg: write it again from its run"


def model_shapes(count: int, config: FitConfig) -> dict[str, tuple[int, ...]]:
    """The shape of each tensor of `count` primitives under `config`."""
    channels = config.channels
    return {"position_px": (count, 2), "scale_px": (count, 2), "rotation_rad": (count,),
            "amplitude": (count, channels), "phase_rad": (count, channels), "opacity": (count,),
            "curvature_per_m": (count,) if config.primitives.curvature == "shared" else (count, channels),
            **{term.physical: (count, term.parameters) for term in config.phase.extra_terms}}


def check_settings(config: FitConfig, count: object, name: str) -> None:
    """Raise `ModelFileError` naming the model file `name` unless it holds at least one primitive and its
    settings, with its primitive count `count`, validate."""
    if not isinstance(count, int) or isinstance(count, bool) or count < 1:
        raise ModelFileError(f"{name}: it holds {count!r} primitives, not at least 1; {REWRITE_MODEL}")
    try:
        config.replace(num_gaussians=count).validate()
    except ConfigError as error:
        raise ModelFileError(f"{name}: its settings cannot work ({error}); {REWRITE_MODEL}") from None


def check_tensors(primitives: Primitives, config: FitConfig, name: str) -> None:
    """Raise `ModelFileError` naming the model file `name` unless every tensor has the shape `config` gives
    it and finite values, and every scale (px) is positive."""
    tensors = primitives.tensors()
    count = tensors["position_px"].shape[0] if tensors["position_px"].dim() else 0
    shapes = model_shapes(count, config)
    unknown = sorted(tensors.keys() - shapes.keys())
    if unknown:
        raise ModelFileError(f"{name}: tensor {unknown[0]!r} belongs to no phase term of its settings; {REWRITE_MODEL}")
    for tensor_name, shape in shapes.items():
        if tensor_name not in tensors:
            raise ModelFileError(f"{name}: tensor {tensor_name!r} is missing; {REWRITE_MODEL}")
        if tuple(tensors[tensor_name].shape) != shape:
            raise ModelFileError(f"{name}: tensor {tensor_name!r} has shape {tuple(tensors[tensor_name].shape)}, "
                                 f"expected {shape}; {REWRITE_MODEL}")
    # the scale first: a decoded curvature follows from it, and is not finite where it is not positive
    scale = primitives.scale_px
    if not bool((torch.isfinite(scale) & (scale > 0)).all()):
        raise ModelFileError(f"{name}: some scales (px) are not finite and positive; {REWRITE_MODEL}")
    for tensor_name, tensor in tensors.items():
        if not bool(torch.isfinite(tensor).all()):
            raise ModelFileError(f"{name}: tensor {tensor_name!r} holds values that are not finite; {REWRITE_MODEL}")


def init_gaussians(count: int, channels: int, width: int, height: int, seed: int,
                   device: torch.device | str = "cpu", per_channel_curvature: bool = False,
                   terms: tuple[str, ...] = ()) -> Gaussians:
    """The reference initialisation: draws from a CPU generator in method.md's order (§2), then moves to `device`.

    Curvature starts at 0, [N] or [N, C] with `per_channel_curvature`, and so do the phase `terms` beyond it
    (names in `phase.TERMS`): the primitive starts flat. The draws depend on neither.
    """
    generator = torch.Generator().manual_seed(seed)
    u_position = torch.rand(count, 2, generator=generator)
    u_amplitude = torch.rand(count, channels, generator=generator)
    u_scale = torch.rand(count, 2, generator=generator)
    u_rotation = torch.rand(count, generator=generator)
    low, high = INIT_SCALE_RANGE_PX
    raw = Gaussians(
        position=torch.atanh(torch.clamp(2 * u_position - 1, -POSITION_CLAMP, POSITION_CLAMP)),
        scale=torch.log(low + (high - low) * u_scale),
        rotation=(2 * u_rotation - 1) * math.pi,
        amplitude=u_amplitude,
        phase=torch.zeros(count, channels),
        opacity=torch.full((count,), INIT_OPACITY_RAW),
        curvature=torch.zeros((count, channels) if per_channel_curvature else (count,)),
        terms={name: torch.zeros(count, TERMS[name].parameters) for name in terms},
    )
    return raw.to(device)


@functools.lru_cache(maxsize=32)
def device_constants(values: tuple[float, ...], dtype: torch.dtype, device: torch.device) -> Tensor:
    """A few numbers as a tensor on `device`, made once: building it every step would copy it from
    the host each time, which on CUDA waits for the GPU's queue. Read-only."""
    return torch.tensor(values, dtype=dtype, device=device)


def positions_px(raw_position: Tensor, width: int, height: int) -> Tensor:
    """Raw position → px: `(tanh(raw)+1)/2 · (W, H)`."""
    extent = device_constants((width, height), raw_position.dtype, raw_position.device)
    return (torch.tanh(raw_position) + 1) / 2 * extent


def raw_positions(position_px: Tensor, width: int, height: int) -> Tensor:
    """Inverse of `positions_px`: px → raw, clamped as the initialisation clamps."""
    extent = device_constants((width, height), position_px.dtype, position_px.device)
    return torch.atanh(torch.clamp(2 * position_px / extent - 1, -POSITION_CLAMP, POSITION_CLAMP))


def scales_px(raw_scale: Tensor) -> Tensor:
    """Raw scale → px: `exp(raw) + 0.1`, capped at 1e4 px so Σ stays finite in float32."""
    return torch.exp(torch.clamp(raw_scale, max=MAX_LOG_SCALE)) + MIN_SCALE_PX


def curvature_bound(scale_px: Tensor, config: FitConfig) -> Tensor:
    """γ_max (1/m): `η λ / (6 σ Δx²)` with σ = max scale (px), or the global bound.

    Shared curvature: [N], bounded with the shortest wavelength, whose fringes are the finest.
    `per-channel` and `channel-bound`: [N, C], each channel bounded with its own wavelength.
    """
    per_channel = config.primitives.curvature != "shared"
    if config.primitives.bound == "global":
        shape = (scale_px.shape[0], config.channels) if per_channel else scale_px.shape[:1]
        return torch.full(shape, config.primitives.global_bound, dtype=scale_px.dtype, device=scale_px.device)
    sigma_px = scale_px.max(dim=1).values
    scale = config.primitives.eta / (6 * sigma_px * config.optics.pixel_pitch**2)
    if not per_channel:
        return scale * min(config.wavelengths)
    return scale[:, None] * device_constants(config.wavelengths, scale_px.dtype, scale_px.device)


def term_bounds(scale_px: Tensor, config: FitConfig) -> dict[str, Tensor]:
    """The largest magnitude of each parameter of the phase terms beyond the curvature [N, P] (`phase.term_limits`:
    1/m for `axes`, rad for `tilt`) for primitives of scale `scale_px` (px) under `config`: what `activate` bounds
    them by, and what a `.cvq` file codes them as shares of."""
    return term_limits(config.phase, scale_px, config.primitives.eta, min(config.wavelengths),
                       config.optics.pixel_pitch)


def activate(raw: Gaussians, config: FitConfig) -> Primitives:
    """Apply method.md §2's activations; the curvature bound follows `primitives.bound` and `primitives.curvature`,
    and takes its share of the Nyquist limit beside the other phase terms (`phase.Phase.nyquist_shares`).

    `channel-bound` shares one raw curvature: every channel gets the same fraction of its own bound.
    """
    scale = scales_px(raw.scale)
    bound = curvature_bound(scale, config)
    phase = config.phase
    shares = phase.nyquist_shares()
    if shares.get("quadratic", 1.0) != 1.0:  # alone the paper's bound, as it was
        bound = bound * shares["quadratic"]
    share = torch.tanh(raw.curvature)
    if share.dim() < bound.dim():
        share = share[:, None]
    terms = activate_terms(raw.terms, phase, scale, config.primitives.eta, min(config.wavelengths),
                           config.optics.pixel_pitch) if phase.extra_terms else {}
    return Primitives(
        position_px=positions_px(raw.position, config.targets.width, config.targets.height),
        scale_px=scale,
        rotation_rad=raw.rotation,
        amplitude=raw.amplitude,
        phase_rad=torch.remainder(raw.phase, 2 * math.pi),
        opacity=torch.sigmoid(raw.opacity),
        curvature_per_m=bound * share,
        terms=terms,
    )


def field_energy(primitives: Primitives) -> Tensor:
    """Each primitive's field energy up to a constant factor: Σ_c (amplitude_c·opacity)² σx σy [N].

    A primitive's field is a Gaussian of that peak and those scales whatever its curvature (a chirp
    changes only the phase), and propagation to the planes preserves energy, so removing it changes the
    reconstructed fields by this much (squared L2), interference with the others aside."""
    weight = primitives.amplitude * primitives.opacity[:, None]
    return (weight**2).sum(dim=1) * primitives.scale_px.prod(dim=1)


def inverse_covariance(scale_px: Tensor, rotation_rad: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Entries (a, b, c) of Σ⁻¹ = [[a, b], [b, c]] in 1/px², for Σ = R S Sᵀ Rᵀ + 0.1·I.

    Σ = R diag(e) Rᵀ with the eigenvalues e = s² + 0.1, so Σ⁻¹ = R diag(1/e) Rᵀ: sums of positive
    terms for a and c, without the float32 cancellation of Σxx·Σyy − Σxy² that makes the determinant
    zero or negative for elongated primitives (one scale of 8000 px, the other of 1 px). method.md's clamp
    of the determinant at 1e-10 never applies: det Σ = e_x·e_y ≥ 0.01.
    """
    inverse = 1.0 / (scale_px * scale_px + COVARIANCE_REGULARISER_PX2)
    cos, sin = torch.cos(rotation_rad), torch.sin(rotation_rad)
    cos2, sin2 = cos * cos, sin * sin
    along, across = inverse[:, 0], inverse[:, 1]
    return cos2 * along + sin2 * across, cos * sin * (along - across), sin2 * along + cos2 * across


def major_sigma_px(scale_px: Tensor) -> Tensor:
    """σ_major (px): square root of Σ's largest eigenvalue. Σ = R (S² + 0.1·I) Rᵀ has the eigenvalues
    s_x² + 0.1 and s_y² + 0.1 whatever the rotation, so no matrix needs building."""
    return torch.sqrt(scale_px.max(dim=1).values ** 2 + COVARIANCE_REGULARISER_PX2)
