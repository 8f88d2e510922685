"""Fit configuration: every setting of method.md §2–§6 with the paper's value as default, and the recipes
(`RECIPES`): the paper's, and the default one, which differs from it in Adan's β2, where its positions are
drawn and, in short runs, its loss (docs/beyond.md)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

from .errors import ConfigError, choices_error

Color = Literal["rgb", "gray"]
Primitive = Literal["flat", "cvqpg"]
Bound = Literal["adaptive", "global"]
Qpf = Literal["mahalanobis", "standard"]
Curvature = Literal["shared", "per-channel", "channel-bound"]
Backend = Literal["auto", "numba", "triton", "torch"]
Init = Literal["uniform", "targets", "edges", "auto"]
COLORS: tuple[str, ...] = get_args(Color)
PRIMITIVES: tuple[str, ...] = get_args(Primitive)
BOUNDS: tuple[str, ...] = get_args(Bound)
QPFS: tuple[str, ...] = get_args(Qpf)
CURVATURES: tuple[str, ...] = get_args(Curvature)
BACKENDS: tuple[str, ...] = get_args(Backend)
INITS: tuple[str, ...] = get_args(Init)
DEVICE_TYPES = ("cpu", "cuda")

RGB_WAVELENGTHS_M = (639e-9, 532e-9, 473e-9)
GRAY_WAVELENGTH_M = 639e-9


@dataclass(frozen=True)
class LearningRates:
    """Per-group Adan learning rates (method.md §6). Position is cosine-annealed to `position_final`."""

    position: float = 0.01
    position_final: float = 1e-3
    scale: float = 0.005
    amplitude: float = 0.0025
    phase: float = 0.0025
    opacity: float = 0.025
    rotation: float = 0.001
    curvature: float = 0.001


@dataclass(frozen=True)
class DensityControl:
    """Relocation at a fixed N (docs/beyond.md): at every `every` share of the steps, until the `until`
    share, the `fraction` of primitives with the least field energy are moved onto splits of others, drawn
    with a probability proportional to the reconstruction's error where they sit."""

    every: float = 0.05
    until: float = 0.6
    fraction: float = 0.02

    def event_steps(self, steps: int) -> tuple[int, ...]:
        """The steps (indices) before whose update primitives are relocated, for a run of `steps` steps."""
        interval = max(1, round(self.every * steps))
        return tuple(range(interval, int(self.until * steps), interval))


CURVATURE_WARMUP_SHARE = 400 / 2000  # the paper's curvature warm-up share of the steps


def default_curvature_warmup(steps: int) -> int:
    """The curvature warm-up (steps) of a run of `steps` steps: the paper's 400 of 2000, in proportion."""
    return round(steps * CURVATURE_WARMUP_SHARE)


# Names that recorded configurations (config.json, model metadata) used before a rename, and their names now.
RENAMED_FIELDS = {"warmup": "curvature_warmup"}
RENAMED_LEARNING_RATES = {"color": "amplitude"}


@dataclass(frozen=True)
class FitConfig:
    """Everything a fit depends on. Lengths in metres unless the name says px."""

    width: int = 640
    height: int = 480
    color: Color = "rgb"
    primitive: Primitive = "cvqpg"
    ratio: float = 0.2
    num_gaussians: int | None = None
    steps: int = 2000
    curvature_warmup: int | None = None  # steps with γ frozen at 0; None: default_curvature_warmup(steps)
    seed: int = 100
    pixel_pitch: float = 3.74e-6
    num_planes: int = 2
    plane_center: float = 3e-3
    plane_span: float = 4e-3
    eta: float = 0.9
    bound: Bound = "adaptive"
    global_bound: float = 200.0
    qpf: Qpf = "mahalanobis"
    curvature: Curvature = "shared"
    lr: LearningRates = field(default_factory=lambda: RECIPES[DEFAULT_RECIPE]["lr"])
    # The default recipe's (`RECIPES`), as `lr`; `initialisation.resolved_init` resolves `auto`.
    init: Init = field(default_factory=lambda: RECIPES[DEFAULT_RECIPE]["init"])
    density: DensityControl | None = field(default_factory=lambda: RECIPES[DEFAULT_RECIPE]["density"])
    # Adan's (β1, β2, β3), as `lr`; None: `adan_betas` resolves them by the run's length.
    betas: tuple[float, float, float] | None = field(default_factory=lambda: RECIPES[DEFAULT_RECIPE]["betas"])
    adan_eps: float = 1e-8
    grad_clip_norm: float = 1.0
    ssim_weight: float = 0.005
    # The weights of the loss's masked and correlation MSE terms (method.md §6: 1 each), as `lr`; None:
    # `loss_weights` resolves them by the run's length.
    focus_weight: float | None = field(default_factory=lambda: RECIPES[DEFAULT_RECIPE]["focus_weight"])
    product_weight: float | None = field(default_factory=lambda: RECIPES[DEFAULT_RECIPE]["product_weight"])
    target_noise: float = 1e-3
    guard_band_px: int = 144
    pad_multiple_px: int = 64
    defocus_sigma_px: float = 8.0
    depth_exponent: float = 1.0
    device: str = "cpu"
    backend: Backend = "auto"
    wavelengths_m: tuple[float, ...] | None = None

    @property
    def recipe(self) -> str:
        """The name of the recipe (`RECIPES`) whose settings this configuration has, or 'custom'."""
        return next((name for name, settings in RECIPES.items()
                     if all(getattr(self, k) == v for k, v in settings.items())), "custom")

    def with_recipe(self, name: str) -> "FitConfig":
        """This configuration with the settings of the recipe `name` (`RECIPES`)."""
        if name not in RECIPES:
            raise choices_error("recipe", name, tuple(RECIPES))
        return self.replace(**RECIPES[name])

    @property
    def loss_weights(self) -> tuple[float, float]:
        """The weights of the loss's masked and correlation MSE terms; one that is None is 0 in runs of at most
        `SHORT_RUN_STEPS` steps and the paper's 1 in longer ones (docs/beyond.md, "The loss")."""
        auto = 0.0 if self.steps <= SHORT_RUN_STEPS else 1.0
        return tuple(auto if w is None else w for w in (self.focus_weight, self.product_weight))

    @property
    def adan_betas(self) -> tuple[float, float, float]:
        """Adan's (β1, β2, β3): `betas`, or where None the paper's in runs of at most `SHORT_RUN_STEPS` steps and
        `LONG_RUN_BETAS` in longer ones (docs/beyond.md)."""
        if self.betas is not None:
            return self.betas
        return PAPER_BETAS if self.steps <= SHORT_RUN_STEPS else LONG_RUN_BETAS

    @property
    def curvature_warmup_steps(self) -> int:
        """Steps with the curvature frozen at γ = 0: `curvature_warmup`, or the paper's share of `steps`."""
        if self.curvature_warmup is None:
            return default_curvature_warmup(self.steps)
        return self.curvature_warmup

    @property
    def channels(self) -> int:
        return 3 if self.color == "rgb" else 1

    @property
    def wavelengths(self) -> tuple[float, ...]:
        """One wavelength (m) per colour channel: `wavelengths_m`, or the paper's."""
        if self.wavelengths_m is not None:
            return tuple(self.wavelengths_m)
        return RGB_WAVELENGTHS_M if self.color == "rgb" else (GRAY_WAVELENGTH_M,)

    @property
    def primitive_count(self) -> int:
        """N: explicit, or `ratio · W·H/2` (RGB) / `ratio · W·H/4` (grayscale), method.md §2."""
        if self.num_gaussians is not None:
            return self.num_gaussians
        pixels_per_primitive = 2 if self.color == "rgb" else 4
        return int(round(self.ratio * self.width * self.height / pixels_per_primitive))

    @property
    def learnable_curvatures(self) -> int:
        """Curvature parameters per primitive: none (flat), one per channel (`per-channel`), else one."""
        if self.primitive != "cvqpg":
            return 0
        return self.channels if self.curvature == "per-channel" else 1

    @property
    def params_per_primitive(self) -> int:
        """Learnable scalars per primitive: 12/13/15 (RGB flat/CVQPG/per-channel), 8/9 (grayscale)."""
        return 2 + 2 + 1 + 2 * self.channels + 1 + self.learnable_curvatures

    @property
    def plane_distances(self) -> tuple[float, ...]:
        """Propagation distances (m): `linspace(d − V/2, d + V/2, M)` (one plane: d − V/2, as linspace)."""
        start = self.plane_center - self.plane_span / 2
        step = self.plane_span / max(self.num_planes - 1, 1)
        return tuple(start + m * step for m in range(self.num_planes))

    def replace(self, **changes: Any) -> "FitConfig":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def on_device(self, device: str) -> "FitConfig":
        """The same fit rendered on `device`: a backend that cannot run there (`numba` off the CPU,
        `triton` off CUDA) becomes `auto`, which changes the last bits of a render only."""
        kind = device.split(":")[0]
        runs_there = {"numba": kind == "cpu", "triton": kind == "cuda"}.get(self.backend, True)
        return self.replace(device=device, backend=self.backend if runs_there else "auto")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "FitConfig":
        """The configuration a `to_dict` recorded, also under the names of earlier versions; other keys
        (a run's `source`, settings that no longer exist) are ignored."""
        known = {f.name for f in dataclasses.fields(cls)}
        data = {RENAMED_FIELDS.get(k, k): v for k, v in data.items()}
        # A record older than a recipe's setting has the paper's value for it.
        values = {**RECIPES[PAPER_RECIPE], **{k: v for k, v in data.items() if k in known}}
        if isinstance(values.get("density"), dict):
            values["density"] = DensityControl(**values["density"])
        if isinstance(values.get("lr"), dict):
            values["lr"] = LearningRates(**{RENAMED_LEARNING_RATES.get(k, k): v for k, v in values["lr"].items()})
        for name in ("betas", "wavelengths_m"):
            if isinstance(values.get(name), list):
                values[name] = tuple(values[name])
        return cls(**values)

    def validate(self) -> "FitConfig":
        """Raise `ConfigError` naming the first setting that cannot work, and what to do."""
        for name, choices in (("color", COLORS), ("primitive", PRIMITIVES), ("bound", BOUNDS), ("qpf", QPFS),
                              ("curvature", CURVATURES), ("backend", BACKENDS), ("init", INITS)):
            if getattr(self, name) not in choices:
                raise choices_error(name, getattr(self, name), choices)
        if not isinstance(self.device, str) or self.device.split(":")[0] not in DEVICE_TYPES:
            raise choices_error("device", self.device, DEVICE_TYPES)
        for name in ("width", "height", "steps", "seed", "num_planes", "guard_band_px", "pad_multiple_px"):
            if not _is_integer(getattr(self, name)):
                raise ConfigError(f"`{name}` must be a whole number, got {getattr(self, name)!r}")
        for name in ("num_gaussians", "curvature_warmup"):
            if getattr(self, name) is not None and not _is_integer(getattr(self, name)):
                raise ConfigError(f"`{name}` must be a whole number or None, got {getattr(self, name)!r}")
        numbers = {"ratio": self.ratio, "pixel_pitch": self.pixel_pitch, "plane_center": self.plane_center,
                   "plane_span": self.plane_span, "eta": self.eta, "global_bound": self.global_bound,
                   "adan_eps": self.adan_eps, "grad_clip_norm": self.grad_clip_norm,
                   "ssim_weight": self.ssim_weight, "target_noise": self.target_noise,
                   "defocus_sigma_px": self.defocus_sigma_px, "depth_exponent": self.depth_exponent,
                   **{f"lr.{k}": v for k, v in dataclasses.asdict(self.lr).items()},
                   **{f"betas[{i}]": b for i, b in enumerate(self.betas or ())},
                   **{f"density.{k}": v for k, v in (dataclasses.asdict(self.density) if self.density else {}).items()},
                   **{f"wavelengths_m[{i}]": w for i, w in enumerate(self.wavelengths_m or ())},
                   **{k: w for k, w in (("focus_weight", self.focus_weight), ("product_weight", self.product_weight))
                      if w is not None}}
        for name, value in numbers.items():
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
                raise ConfigError(f"`{name}` must be a finite number, got {value!r}")
        positive = {"steps": self.steps, "ratio": self.ratio, "pixel_pitch": self.pixel_pitch,
                    "plane_span": self.plane_span if self.num_planes > 1 else 1.0,
                    "num_planes": self.num_planes, "eta": self.eta, "pad_multiple_px": self.pad_multiple_px}
        for name, value in positive.items():
            if not value > 0:
                raise ConfigError(f"`{name}` must be positive, got {value}")
        for name in ("seed", "ssim_weight", "focus_weight", "product_weight"):
            if getattr(self, name) is not None and getattr(self, name) < 0:
                raise ConfigError(f"`{name}` must be 0 or more, got {getattr(self, name)}")
        if self.density is not None and not (0 < self.density.every <= 1 and 0 <= self.density.until <= 1
                                             and 0 <= self.density.fraction < 1):
            raise ConfigError(f"`density` {self.density}: `every` must lie in (0, 1], `until` in [0, 1] (shares of "
                              "the steps) and `fraction` in [0, 1)")
        if self.guard_band_px < 0:
            raise ConfigError(f"`guard_band_px` must be 0 or more, got {self.guard_band_px}")
        if self.width < MIN_SIZE_PX or self.height < MIN_SIZE_PX:
            raise ConfigError(f"size {self.width}×{self.height} px is too small: `width` and `height` need at "
                              f"least {MIN_SIZE_PX} px (the SSIM window)")
        if any(not d > 0 for d in self.plane_distances):
            raise ConfigError(f"plane distances {', '.join(f'{d:g}' for d in self.plane_distances)} m must all "
                              "be positive: raise `plane_center` or shrink `plane_span`")
        if len(self.wavelengths) != self.channels or any(not w > 0 for w in self.wavelengths):
            raise ConfigError(f"`wavelengths_m` {self.wavelengths}: need {self.channels} positive value(s) "
                              f"for `color` {self.color!r}")
        kind = self.device.split(":")[0]
        if self.backend == "numba" and kind != "cpu":
            raise ConfigError(f"`backend` 'numba' runs on the CPU only, not on {self.device}; use `backend` auto "
                              "(or torch) with `device` cuda")
        if self.backend == "triton" and kind == "cpu":
            raise ConfigError("`backend` 'triton' runs on the GPU only; use `backend` auto (or numba, torch) with "
                              "`device` cpu")
        if not 0 <= self.curvature_warmup_steps <= self.steps:
            raise ConfigError(f"`curvature_warmup` {self.curvature_warmup_steps} must lie in 0..`steps` "
                              f"({self.steps})")
        count, pixels = self.primitive_count, self.width * self.height
        if not 0 < count <= pixels:
            raise ConfigError(f"{count} Gaussians for {pixels} pixels: need between 1 and the pixel count; "
                              "change `ratio` or `num_gaussians`")
        return self


# A run of at most this many steps is short: the default recipe draws its positions from the targets' energy
# rather than their edges, keeps the paper's Adan β2 and trains it without the masked and correlation terms; each
# pays there and not in longer runs, or the other way round (docs/beyond.md).
SHORT_RUN_STEPS = 400
PAPER_BETAS = (0.98, 0.92, 0.99)  # method.md §6
LONG_RUN_BETAS = (0.98, 0.99, 0.99)  # β2 averages the gradient's differences over ~100 steps, not ~12
# The recorded choices of a fit beyond its problem (method.md §6; docs/beyond.md): `FitConfig.with_recipe`.
PAPER_RECIPE, BEYOND_RECIPE = "paper", "beyond"
RECIPES: dict[str, dict[str, Any]] = {
    PAPER_RECIPE: {"lr": LearningRates(), "init": "uniform", "density": None, "focus_weight": 1.0,
                   "product_weight": 1.0, "betas": PAPER_BETAS},
    BEYOND_RECIPE: {"lr": LearningRates(), "init": "auto", "density": None, "focus_weight": None,
                    "product_weight": None, "betas": None},
}
DEFAULT_RECIPE = BEYOND_RECIPE  # measured better than the paper's on every scene (docs/beyond.md)


def _is_integer(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


MIN_SIZE_PX = 16


def padded_size(n: int, guard_px: int, multiple_px: int) -> int:
    """Length (px) of one axis after the guard band: at least `guard_px` per side, rounded up."""
    return int(math.ceil((n + 2 * guard_px) / multiple_px) * multiple_px)
