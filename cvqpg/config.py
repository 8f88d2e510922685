"""Fit configuration: every setting of method.md §2–§6 with the paper's value as default, grouped by concern
(`TargetSettings`, `OpticsSettings`, `PrimitiveSettings`, `OptimisationSettings`, `LossSettings`, and the display
the loss sees, `display.Display`) into one `FitConfig`, and the recipes (`RECIPES`) that choose what the paper
leaves to the fit: the paper's own, and the default one (docs/beyond.md). Where a fit runs (`RunOptions`: device and kernels) is no part of it.

A recipe is resolved when the configuration is made (`FitConfig.create`): every setting is a concrete value,
which `config.json` records. `FitConfig.from_dict` reads the records of every earlier version."""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import json
import math
import os
from dataclasses import dataclass, field
from typing import Any, Literal, Sequence, get_args

from .display import Display
from .errors import ConfigError, choices_error
from .phase import CONSTANT, Phase, check_phase_settings, parse_phase

Color = Literal["rgb", "gray"]
Primitive = Literal["flat", "cvqpg", "pixel"]
Bound = Literal["adaptive", "global"]
Qpf = Literal["mahalanobis", "standard"]
Curvature = Literal["shared", "per-channel", "channel-bound"]
Backend = Literal["auto", "numba", "triton", "torch"]
Init = Literal["uniform", "targets", "edges", "zero"]
Optimizer = Literal["adan", "adam"]
COLORS: tuple[str, ...] = get_args(Color)
PRIMITIVES: tuple[str, ...] = get_args(Primitive)
BOUNDS: tuple[str, ...] = get_args(Bound)
QPFS: tuple[str, ...] = get_args(Qpf)
CURVATURES: tuple[str, ...] = get_args(Curvature)
BACKENDS: tuple[str, ...] = get_args(Backend)
INITS: tuple[str, ...] = get_args(Init)
OPTIMIZERS: tuple[str, ...] = get_args(Optimizer)
GAUSSIAN_ONLY_INITS = ("edges",)  # where a Gaussian's position starts
PIXEL_ONLY_INITS = ("zero",)  # a per-pixel hologram's flat phase
DEVICE_TYPES = ("cpu", "cuda")
# The choices of every enumerated setting (flat names); the range of every number is in `RANGES`.
CHOICES: dict[str, tuple[str, ...]] = {"color": COLORS, "primitive": PRIMITIVES, "bound": BOUNDS, "qpf": QPFS,
                                       "curvature": CURVATURES, "init": INITS, "optimizer": OPTIMIZERS}

RGB_WAVELENGTHS_M = (639e-9, 532e-9, 473e-9)
GRAY_WAVELENGTH_M = 639e-9
PAPER_BETAS = (0.98, 0.92, 0.99)  # method.md §6
ADAM_BETAS = (0.9, 0.999, 0.99)  # Adam's usual β1 and β2; Adam has no third (Adan's β3, left at the paper's)
LONG_RUN_BETAS = (0.98, 0.99, 0.99)  # β2 averages the gradient's differences over ~100 steps, not ~12
CURVATURE_WARMUP_SHARE = 400 / 2000  # the paper's curvature warm-up share of the steps
MIN_SIZE_PX = 16  # the SSIM window
MAX_LEARNING_RATE = 10.0
CONFIG_SCHEMA = 3  # the layout `FitConfig.to_dict` writes; records without the key are the flat layout before it


def _check_range(name: str, value: Any, low: float, high: float, kind: str) -> None:
    """`ConfigError` unless `value` is a number of `kind` in its range: `integer` (a whole number in [low, high]),
    `number` (finite, in [low, high]), `positive` (in (low, high]) or `fraction` (in [low, high)). Cheap where
    the value is good: every configuration made runs it for every setting."""
    if kind == "integer":
        problem = None if _is_integer(value) else "must be a whole number in"
    elif _is_integer(value) or (isinstance(value, float) and math.isfinite(value)):
        problem = None
    else:
        problem = "must be a finite number in"
    if problem is None:
        if low < value <= high if kind == "positive" else low <= value < high if kind == "fraction" else \
                low <= value <= high:
            return
        problem = "must lie in"
    low_text, high_text = (str(v) if isinstance(v, int) else f"{v:g}" for v in (low, high))
    interval = {"positive": f"({low_text}, {high_text}]", "fraction": f"[{low_text}, {high_text})"}.get(
        kind, f"[{low_text}, {high_text}]")
    raise ConfigError(f"`{name}` {problem} {interval}, got {value!r}")


def _is_integer(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_fields(section: object) -> None:
    """`ConfigError` naming the first field of a settings section outside its choices (`CHOICES`) or its range
    (`RANGES`), by its flat name."""
    for key, name in _flat_names(type(section)):
        value = getattr(section, key)
        if name in CHOICES:
            if value not in CHOICES[name]:
                raise choices_error(name, value, CHOICES[name])
        elif name in RANGES and not (value is None and name in OPTIONAL):
            _check_range(name, value, *RANGES[name])


@functools.cache
def _flat_names(section_class: type) -> tuple[tuple[str, str], ...]:
    """(field, flat name) of each field of a settings section that has a flat name (`FLAT_NAMES`), in field order."""
    section = next(name for name, known in SECTION_CLASSES.items() if known is section_class)
    names = {key: flat for flat, (owner, key) in FLAT_NAMES.items() if owner == section}
    return tuple((f.name, names[f.name]) for f in dataclasses.fields(section_class) if f.name in names)


def default_curvature_warmup(steps: int) -> int:
    """The curvature warm-up (steps) of a run of `steps` steps: the paper's 400 of 2000, in proportion."""
    return round(steps * CURVATURE_WARMUP_SHARE)


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
    axes: float = 0.001  # the phase terms beyond the paper's (cvqpg/phase.py)
    tilt: float = 0.001

    def __post_init__(self) -> None:
        for key in (f.name for f in dataclasses.fields(self)):
            _check_range(f"lr.{key}", getattr(self, key), 0.0, MAX_LEARNING_RATE, "number")


@dataclass(frozen=True)
class TargetSettings:
    """The targets: W×H px, colour, the depth planes (centre and span in m) and their defocus (method.md §5)."""

    width: int = 640
    height: int = 480
    color: Color = "rgb"
    num_planes: int = 2
    plane_center: float = 3e-3
    plane_span: float = 4e-3
    defocus_sigma_px: float = 8.0
    depth_exponent: float = 1.0

    def __post_init__(self) -> None:
        _check_fields(self)
        check_distances(self.plane_distances, "plane distances", ": change `plane_center` or `plane_span`")

    @property
    def plane_distances(self) -> tuple[float, ...]:
        """Propagation distances (m): `linspace(d − V/2, d + V/2, M)` (one plane: d − V/2, as linspace)."""
        start = self.plane_center - self.plane_span / 2
        step = self.plane_span / max(self.num_planes - 1, 1)
        return tuple(start + m * step for m in range(self.num_planes))


@dataclass(frozen=True)
class OpticsSettings:
    """The SLM and its light: pixel pitch (m), wavelengths (m; None: the paper's for the colour), and the guard
    band around the hologram (px, rounded up to a multiple of `pad_multiple_px`) (method.md §3)."""

    pixel_pitch: float = 3.74e-6
    wavelengths_m: tuple[float, ...] | None = None
    guard_band_px: int = 144
    pad_multiple_px: int = 64

    def __post_init__(self) -> None:
        _check_fields(self)
        if self.wavelengths_m is not None:
            if not isinstance(self.wavelengths_m, tuple):
                raise ConfigError(f"`wavelengths_m` must be a tuple of numbers (m), got {self.wavelengths_m!r}")
            for index, wavelength in enumerate(self.wavelengths_m):
                _check_range(f"wavelengths_m[{index}]", wavelength, *WAVELENGTH_RANGE_M, "number")


@dataclass(frozen=True)
class PrimitiveSettings:
    """The primitives: kind, count (`count`, or `ratio` of the pixels, method.md §2) and curvature bound (§4)."""

    kind: Primitive = "cvqpg"
    ratio: float = 0.2
    count: int | None = None
    bound: Bound = "adaptive"
    global_bound: float = 200.0  # 1/m
    eta: float = 0.9
    qpf: Qpf = "mahalanobis"
    curvature: Curvature = "shared"
    phase: str | None = None  # the phase terms (`phase.PHASES`); None: the kind's (flat: constant, cvqpg: quadratic)

    def __post_init__(self) -> None:
        _check_fields(self)
        check_phase(self)


@dataclass(frozen=True)
class OptimisationSettings:
    """The loop (method.md §6): its steps, the curvature's warm-up (steps with γ frozen at 0; `steps + 1`: all),
    the seed, the optimiser (the paper's Adan, or Adam, whose β1 and β2 are `betas`' first two) with its learning
    rates, betas and ε, the gradient clip norm, and where the primitives start (`init`)."""

    steps: int = 2000
    curvature_warmup: int = 400
    terms_warmup: int | None = None  # steps with the phase terms beyond the curvature frozen at 0; None: as γ
    seed: int = 100
    lr: LearningRates = field(default_factory=LearningRates)
    betas: tuple[float, float, float] = PAPER_BETAS
    adan_eps: float = 1e-8
    grad_clip_norm: float = 1.0
    init: Init = "uniform"
    optimizer: Optimizer = "adan"

    def __post_init__(self) -> None:
        _check_fields(self)
        # steps + 1: the curvature never trains (the loop's last update has index `steps`)
        _check_range("curvature_warmup", self.curvature_warmup, 0, self.steps + 1, "integer")
        if self.terms_warmup is not None:
            _check_range("terms_warmup", self.terms_warmup, 0, self.steps + 1, "integer")
        if not isinstance(self.lr, LearningRates):
            raise ConfigError(f"`lr` must be LearningRates, got {self.lr!r}")
        if not (isinstance(self.betas, tuple) and len(self.betas) == 3):
            raise ConfigError(f"`betas` must be three numbers (β1, β2, β3), got {self.betas!r}")
        for index, beta in enumerate(self.betas):
            _check_range(f"betas[{index}]", beta, 0.0, 1.0, "fraction")


@dataclass(frozen=True)
class LossSettings:
    """The loss's weights (method.md §6: SSIM 0.005, the masked and correlation MSE terms 1 each) and the
    relative noise on the targets that the last two see."""

    ssim_weight: float = 0.005
    focus_weight: float = 1.0
    product_weight: float = 1.0
    target_noise: float = 1e-3

    def __post_init__(self) -> None:
        _check_fields(self)


@dataclass(frozen=True)
class Recipe:
    """The choices a fit makes beyond its problem, by name: the optimiser, its learning rates and betas, where the
    primitives start, and the weights of the loss's masked and correlation terms."""

    name: str
    summary: str
    lr: LearningRates
    betas: tuple[float, float, float]
    init: Init
    focus_weight: float
    product_weight: float
    optimizer: Optimizer = "adan"

    def settings(self) -> dict[str, Any]:
        """The recipe's settings under their `FitConfig.create` names."""
        return {"lr": self.lr, "betas": self.betas, "init": self.init, "focus_weight": self.focus_weight,
                "product_weight": self.product_weight, "optimizer": self.optimizer}


RECIPES: dict[str, Recipe] = {}


def register_recipe(recipe: Recipe) -> Recipe:
    """Make `recipe` available by its name (`FitConfig.create(recipe=...)`, `cvqpg fit --recipe`)."""
    RECIPES[recipe.name] = recipe
    return recipe


PAPER_RECIPE = register_recipe(Recipe(
    "paper", "the paper's settings (method.md §6)", LearningRates(), PAPER_BETAS, "uniform", 1.0, 1.0)).name
BEYOND_RECIPE = register_recipe(Recipe(
    "beyond", "positions at the targets' edges, Adan's β2 0.99 (docs/beyond.md)",
    LearningRates(), LONG_RUN_BETAS, "edges", 1.0, 1.0)).name
# Short fits (some hundred steps): each choice pays there and not in long ones, or the other way round.
BEYOND_SHORT_RECIPE = register_recipe(Recipe(
    "beyond-short", "for a few hundred steps: positions at the targets' energy, the paper's β2, no masked or "
    "correlation terms (docs/beyond.md)", LearningRates(), PAPER_BETAS, "targets", 0.0, 0.0)).name
# The per-pixel hologram's (`primitive` pixel): its optimiser, learning rate and start screened (docs/beyond.md).
PIXEL_LEARNING_RATE = 0.01
PIXEL_RECIPE = register_recipe(Recipe(
    "pixel", "for the per-pixel hologram: Adam at 0.01 from a small random phase, the paper's loss "
    "(docs/beyond.md)", LearningRates(amplitude=PIXEL_LEARNING_RATE, phase=PIXEL_LEARNING_RATE), ADAM_BETAS,
    "uniform", 1.0, 1.0, "adam")).name
DEFAULT_RECIPE = BEYOND_RECIPE  # measured better than the paper's on every scene (docs/beyond.md)
CUSTOM_RECIPE = "custom"  # what `FitConfig.recipe` says where a setting differs from its recipe's

SECTIONS = ("targets", "optics", "primitives", "optimisation", "loss")
# `FitConfig.create`'s and `FitConfig.replace`'s flat names: (section, field) each.
FLAT_NAMES: dict[str, tuple[str, str]] = {
    **{name: ("targets", name) for name in ("width", "height", "color", "num_planes", "plane_center", "plane_span",
                                             "defocus_sigma_px", "depth_exponent")},
    **{name: ("optics", name) for name in ("pixel_pitch", "wavelengths_m", "guard_band_px", "pad_multiple_px")},
    "primitive": ("primitives", "kind"), "num_gaussians": ("primitives", "count"),
    **{name: ("primitives", name) for name in ("ratio", "bound", "global_bound", "eta", "qpf", "curvature",
                                                "phase")},
    **{name: ("optimisation", name) for name in ("steps", "curvature_warmup", "terms_warmup", "seed", "lr", "betas",
                                                  "adan_eps", "grad_clip_norm", "init", "optimizer")},
    **{name: ("loss", name) for name in ("ssim_weight", "focus_weight", "product_weight", "target_noise")},
}
# Names that flat records (config.json, model metadata) used before a rename, and their names now.
RENAMED_FIELDS = {"warmup": "curvature_warmup"}
RENAMED_LEARNING_RATES = {"color": "amplitude"}
# A flat record of a run of at most this many steps resolved its unset (None, `auto`) recipe settings to the
# short-run choices (`BEYOND_SHORT_RECIPE`'s), a longer one to the long-run choices.
SHORT_RUN_STEPS = 400


@dataclass(frozen=True)
class FitConfig:
    """Everything a fit's numbers depend on, by concern, and the name of the recipe its choices come from.
    Lengths in metres unless the name says px. Make one with `create` (flat names, a recipe)."""

    targets: TargetSettings = field(default_factory=TargetSettings)
    optics: OpticsSettings = field(default_factory=OpticsSettings)
    primitives: PrimitiveSettings = field(default_factory=PrimitiveSettings)
    optimisation: OptimisationSettings = field(default_factory=OptimisationSettings)
    loss: LossSettings = field(default_factory=LossSettings)
    display: Display = field(default_factory=Display)
    recipe: str = field(default=PAPER_RECIPE, compare=False)  # a label: two configurations compare by settings

    def __post_init__(self) -> None:
        for name in SECTIONS:
            if not isinstance(getattr(self, name), SECTION_CLASSES[name]):
                raise ConfigError(f"`{name}` must be {SECTION_CLASSES[name].__name__}, got {getattr(self, name)!r}")
        # What depends on settings of two sections: the wavelengths on the colour, the count on the size.
        wavelengths = self.wavelengths
        if len(wavelengths) != self.channels:
            raise ConfigError(f"`wavelengths_m` {wavelengths}: need {self.channels} value(s) for `color` "
                              f"{self.targets.color!r}")
        check_sampling(wavelengths, self.optics.pixel_pitch, "`wavelengths_m`", "keep every `wavelengths_m` below it, "
                       "or give a larger `pixel_pitch`")
        count, pixels = self.primitive_count, self.targets.width * self.targets.height
        if not 0 < count <= pixels:
            raise ConfigError(f"{count} Gaussians for {pixels} pixels: need between 1 and the pixel count; "
                              "change `ratio` or `num_gaussians`")
        # and where the representation starts on the primitive
        pixel = self.primitives.kind == "pixel"
        foreign = GAUSSIAN_ONLY_INITS if pixel else PIXEL_ONLY_INITS
        if self.optimisation.init in foreign:
            raise ConfigError(f"`init` {self.optimisation.init} starts {'Gaussians' if pixel else 'a per-pixel hologram'}"
                              f" and `primitive` is {self.primitives.kind}: choose one of "
                              f"{', '.join(i for i in INITS if i not in foreign)}")
        if not isinstance(self.display, Display):
            raise ConfigError(f"`display` must be Display, got {self.display!r}")
        self.display.canvas_for(self.targets.height, self.targets.width)

    @classmethod
    def create(cls, recipe: str | None = None, **settings: Any) -> "FitConfig":
        """A configuration from flat names (`FLAT_NAMES`: `width`, `steps`, `pixel_pitch`, ...), with the recipe
        `recipe`'s settings where not given (None: `DEFAULT_RECIPE`, or `PIXEL_RECIPE` for `primitive` pixel); an
        unset (None) `curvature_warmup` is the paper's share of `steps`. `recipe` names the result's recipe, or
        `custom` where a given setting differs from it."""
        if recipe is None:
            recipe = PIXEL_RECIPE if settings.get("primitive") == "pixel" else DEFAULT_RECIPE
        if recipe not in RECIPES:
            raise choices_error("recipe", recipe, tuple(RECIPES))
        own = {k: v for k, v in settings.items() if not (k == "curvature_warmup" and v is None)}
        own.update(phase_settings(own.get("primitive"), own.get("phase")) if "phase" in own else {})
        steps = own.get("steps", OptimisationSettings.steps)
        warmup = default_curvature_warmup(steps) if _is_integer(steps) else 0  # `validate` names bad steps
        # one change: a recipe's start may fit only the primitive given with it (the per-pixel hologram's)
        made = cls().replace(**{**RECIPES[recipe].settings(), "recipe": recipe, "curvature_warmup": warmup, **own})
        return made if made.with_recipe(recipe) == made else made.replace(recipe=CUSTOM_RECIPE)

    def replace(self, **changes: Any) -> "FitConfig":
        """This configuration with settings changed: flat names (`FLAT_NAMES`), whole sections, or `recipe`.
        Nothing else follows (`with_steps` scales the warm-up with the steps)."""
        sections = {name: {} for name in SECTIONS}
        top = {}
        for name, value in changes.items():
            if name in FLAT_NAMES:
                section, key = FLAT_NAMES[name]
                sections[section][key] = tuple(value) if isinstance(value, list) else value
            elif name in SECTIONS or name in ("display", "recipe"):
                top[name] = value
            else:
                raise ConfigError(f"`{name}` is not a setting; the settings are {', '.join(FLAT_NAMES)}")
        merged = {name: dataclasses.replace(top.get(name, getattr(self, name)), **values)
                  for name, values in sections.items() if values}
        return dataclasses.replace(self, **{**top, **merged})

    def with_recipe(self, name: str) -> "FitConfig":
        """This configuration with the settings of the recipe `name` (`RECIPES`)."""
        if name not in RECIPES:
            raise choices_error("recipe", name, tuple(RECIPES))
        return self.replace(**RECIPES[name].settings(), recipe=name)

    def with_steps(self, steps: int) -> "FitConfig":
        """The same algorithm over `steps` steps: the curvature warm-up keeps its share of them."""
        current = self.optimisation
        share = steps / current.steps if current.steps else 0
        terms = None if current.terms_warmup is None else round(share * current.terms_warmup)
        return self.replace(steps=steps, curvature_warmup=round(share * current.curvature_warmup),
                            terms_warmup=terms)

    @property
    def channels(self) -> int:
        return 3 if self.targets.color == "rgb" else 1

    @property
    def wavelengths(self) -> tuple[float, ...]:
        """One wavelength (m) per colour channel: `optics.wavelengths_m`, or the paper's."""
        if self.optics.wavelengths_m is not None:
            return tuple(self.optics.wavelengths_m)
        return RGB_WAVELENGTHS_M if self.targets.color == "rgb" else (GRAY_WAVELENGTH_M,)

    @property
    def primitive_count(self) -> int:
        """N: `primitives.count`, or `ratio · W·H/2` (RGB) / `ratio · W·H/4` (grayscale), method.md §2; a per-pixel
        hologram's W·H pixels."""
        if self.primitives.kind == "pixel":
            return self.targets.width * self.targets.height
        if self.primitives.count is not None:
            return self.primitives.count
        pixels_per_primitive = 2 if self.targets.color == "rgb" else 4
        return int(round(self.primitives.ratio * self.targets.width * self.targets.height / pixels_per_primitive))

    @property
    def phase(self) -> Phase:
        """The phase terms of the primitives (`cvqpg.phase`): none for the flat primitive, `primitives.phase` or
        the paper's quadratic term for CVQPG."""
        if self.primitives.kind != "cvqpg":
            return Phase(())
        return parse_phase(self.primitives.phase or "quadratic")

    @property
    def learnable_curvatures(self) -> int:
        """Parameters of the paper's curvature per primitive: none without it (flat), one per channel
        (`per-channel`), else one."""
        if self.primitives.kind != "cvqpg" or not self.phase.has("quadratic"):
            return 0
        return self.channels if self.primitives.curvature == "per-channel" else 1

    @property
    def params_per_primitive(self) -> int:
        """Learnable scalars per primitive: 12/13/15 (RGB flat/CVQPG/per-channel), 8/9 (grayscale), two more for each
        of the phase terms `axes` and `tilt`; per pixel of a per-pixel hologram, an amplitude and a phase per channel
        (a phase pattern: the phases alone)."""
        if self.primitives.kind == "pixel":
            return self.channels * (1 if self.phase_only_pixels else 2)
        extra = sum(term.parameters for term in self.phase.extra_terms)
        return 2 + 2 + 1 + 2 * self.channels + 1 + self.learnable_curvatures + extra

    @property
    def terms_warmup(self) -> int:
        """Steps with the phase terms beyond the curvature frozen at 0: `optimisation.terms_warmup`, or γ's."""
        warmup = self.optimisation.terms_warmup
        return self.optimisation.curvature_warmup if warmup is None else warmup

    @property
    def phase_only_pixels(self) -> bool:
        """Whether a per-pixel hologram of this configuration is a phase pattern (one phase per pixel and channel)
        rather than a complex hologram: where its display shows the bare phase."""
        return self.display.encoding == "phase"

    @property
    def plane_distances(self) -> tuple[float, ...]:
        """Propagation distances (m) of the target planes (`TargetSettings.plane_distances`)."""
        return self.targets.plane_distances

    def to_dict(self) -> dict[str, Any]:
        """The record `config.json` and model files keep (JSON types), with its layout's `config_schema`."""
        return {"config_schema": CONFIG_SCHEMA, **json.loads(json.dumps(dataclasses.asdict(self)))}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "FitConfig":
        """The configuration a `to_dict` recorded, or a flat record of an earlier version (`from_flat_record`).
        Other keys (a run's `source`, its `run` options) are ignored; a setting the record lacks has its default,
        the value versions before it fitted with."""
        if "config_schema" not in data:
            return from_flat_record(data)
        sections = {}
        for name in SECTIONS:
            section_class = SECTION_CLASSES[name]
            known = {f.name for f in dataclasses.fields(section_class)}
            values = {k: v for k, v in dict(data.get(name) or {}).items() if k in known}
            if isinstance(values.get("lr"), dict):
                values["lr"] = LearningRates(**values["lr"])
            sections[name] = section_class(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
        return cls(**sections, display=Display.from_dict(data.get("display")),
                   recipe=str(data.get("recipe", CUSTOM_RECIPE)))

    def validate(self) -> "FitConfig":
        """This configuration: every setting is checked where a configuration is made (a `ConfigError` naming the
        first that cannot work, with the values it may take), so one that exists is valid."""
        return self

    def setting(self, name: str) -> Any:
        """The value of the setting of flat name `name` (`FLAT_NAMES`)."""
        section, key = FLAT_NAMES[name]
        return getattr(getattr(self, section), key)


SECTION_CLASSES = {"targets": TargetSettings, "optics": OpticsSettings, "primitives": PrimitiveSettings,
                   "optimisation": OptimisationSettings, "loss": LossSettings}

# The range of every number (flat names): (lowest, highest, kind), both ends allowed. Lengths in m.
MAX_SIZE_PX = 65536
def check_sampling(wavelengths_m: Sequence[float], pixel_pitch: float, what: str, remedy: str) -> None:
    """Refuse a wavelength (m) of √2 × the pixel pitch (m) or more: the sampled spectrum's corners then lie beyond
    1/λ, where the propagation's transfer function (odak's, whose numbers the paper reports) is not a number."""
    limit = math.sqrt(2) * pixel_pitch
    if max(wavelengths_m) >= limit:
        raise ConfigError(f"{what}: a wavelength of {max(wavelengths_m):g} m needs a pixel pitch above "
                          f"{max(wavelengths_m) / math.sqrt(2):g} m (λ/√2), and the pitch is {pixel_pitch:g} m, "
                          f"which takes wavelengths below {limit:g} m; {remedy}")


WAVELENGTH_RANGE_M = (100e-9, 20e-6)  # deep UV to far infrared: what BLASM's scalar optics can mean
MIN_DISTANCE_M, MAX_DISTANCE_M = 1e-6, 10.0
MAX_SEED = 2**62  # the initialisation's own generators draw from seed + an offset: both fit in 64 bits
RANGES: dict[str, tuple[float, float, str]] = {
    "width": (MIN_SIZE_PX, MAX_SIZE_PX, "integer"), "height": (MIN_SIZE_PX, MAX_SIZE_PX, "integer"),
    "num_planes": (1, 256, "integer"), "plane_center": (-MAX_DISTANCE_M, MAX_DISTANCE_M, "number"),
    "plane_span": (0.0, MAX_DISTANCE_M, "number"), "defocus_sigma_px": (0.0, 1e4, "number"),
    "depth_exponent": (1e-3, 1e3, "positive"),
    "pixel_pitch": (1e-7, 1e-3, "number"), "guard_band_px": (0, 2**14, "integer"),
    "pad_multiple_px": (1, 2**12, "integer"),
    "ratio": (0.0, 4.0, "positive"), "num_gaussians": (1, 2**31, "integer"), "global_bound": (0.0, 1e9, "number"),
    "eta": (0.0, 100.0, "positive"),
    "steps": (1, 10**8, "integer"), "seed": (0, MAX_SEED, "integer"), "adan_eps": (0.0, 1.0, "positive"),
    "grad_clip_norm": (0.0, 1e9, "positive"),
    "ssim_weight": (0.0, 1e6, "number"), "focus_weight": (0.0, 1e6, "number"), "product_weight": (0.0, 1e6, "number"),
    "target_noise": (0.0, 1.0, "number"),
}
OPTIONAL = ("num_gaussians",)


MAX_TIME_MINUTES = 365 * 24 * 60  # a fit's time budget: a year


def check_distances(distances_m: Sequence[float], name: str, remedy: str = "") -> None:
    """`ConfigError` unless every distance (m) lies in [`MIN_DISTANCE_M`, `MAX_DISTANCE_M`], where propagation
    means something; `name` and `remedy` frame the message."""
    if not all(MIN_DISTANCE_M <= d <= MAX_DISTANCE_M for d in distances_m):
        raise ConfigError(f"{name} {', '.join(f'{d:g}' for d in distances_m)} m must lie in "
                          f"[{MIN_DISTANCE_M:g}, {MAX_DISTANCE_M:g}] m{remedy}")


def check_time_budget(minutes: float) -> None:
    """`ConfigError` unless a fit's time budget is a positive number of minutes, at most `MAX_TIME_MINUTES`."""
    if not 0 < minutes <= MAX_TIME_MINUTES:
        raise ConfigError(f"`time` {minutes:g} min: give a positive number of minutes, at most {MAX_TIME_MINUTES} "
                          "(a year)")


def phase_settings(primitive: str | None, phase: str | None) -> dict[str, Any]:
    """`primitive` and `phase` as a configuration holds them: `constant` is the flat primitive and `quadratic`
    CVQPG's own (both recorded as the kind, without a phase), any other phase a CVQPG primitive's. Another
    `primitive` with a phase is left for `PrimitiveSettings` to refuse."""
    if phase is None or primitive not in (None, "cvqpg") and phase != CONSTANT:
        return {} if phase is None else {"phase": phase}
    if phase in (CONSTANT, "quadratic"):
        return {"primitive": "flat" if phase == CONSTANT else "cvqpg", "phase": None}
    return {"primitive": "cvqpg", "phase": phase}


def check_phase(primitives: PrimitiveSettings) -> None:
    """`ConfigError` unless `primitives.phase` names a phase (`phase.PHASES`) of a CVQPG primitive that goes with
    its other settings (None: the kind's own)."""
    phase, kind = primitives.phase, primitives.kind
    if phase is None:
        return
    parsed = parse_phase(phase)
    if not (kind == "flat" and parsed.name == CONSTANT or kind == "cvqpg" and parsed.name != CONSTANT):
        raise ConfigError(f"`phase` {phase} with `primitive` {kind}: the flat primitive is the constant phase, "
                          "CVQPG's are the others; give `phase` alone, for Gaussian primitives")
    check_phase_settings(parsed, primitives.curvature, primitives.bound)


def from_flat_record(data: dict[str, Any]) -> FitConfig:
    """A flat record of a version before `CONFIG_SCHEMA` (config.json, model metadata) as the configuration it
    ran with: renamed settings under their names now; a recipe setting the record lacks at the paper's value
    (versions before recipes fitted with it); unset ones (None, `auto`) resolved by the record's own steps,
    as those versions resolved them when the fit ran. Its device and backend are `RunOptions.from_dict`'s."""
    data = {RENAMED_FIELDS.get(k, k): v for k, v in data.items()}
    values = {**RECIPES[PAPER_RECIPE].settings(), **{k: v for k, v in data.items() if k in FLAT_NAMES}}
    if isinstance(values.get("lr"), dict):
        values["lr"] = LearningRates(**{RENAMED_LEARNING_RATES.get(k, k): v for k, v in values["lr"].items()})
    steps = values.get("steps", OptimisationSettings.steps)
    short = _is_integer(steps) and steps <= SHORT_RUN_STEPS
    resolved = RECIPES[BEYOND_SHORT_RECIPE if short else BEYOND_RECIPE].settings()
    for name in ("betas", "focus_weight", "product_weight"):
        if values.get(name) is None:
            values[name] = resolved[name]
    if values.get("init") == "auto":
        # Versions whose `auto` started long runs from the edges recorded unset betas; earlier ones started
        # them from the paper's uniform draws.
        values["init"] = resolved["init"] if short or data.get("betas", ()) is None else "uniform"
    warmup = values.get("curvature_warmup")
    if warmup is None and _is_integer(steps):
        values["curvature_warmup"] = default_curvature_warmup(steps)
    elif _is_integer(warmup) and _is_integer(steps) and warmup > steps + 1:
        values["curvature_warmup"] = steps + 1  # the first versions kept 400 in shorter runs: never trained
    recipe = next((name for name, r in RECIPES.items() if all(values[k] == v or (isinstance(v, tuple) and
                   tuple(values[k]) == v) for k, v in r.settings().items())), CUSTOM_RECIPE)
    return FitConfig().replace(**values, recipe=recipe)


# Which kernels run where: one rule (`resolve_backend`) for validation and for the ops alike.
BACKEND_NAMES = ("numba", "torch", "triton")


@functools.cache
def triton_installed() -> bool:
    """Whether the triton package is importable (CUDA builds of torch ship it)."""
    return importlib.util.find_spec("triton") is not None


def triton_interpreting() -> bool:
    """Whether Triton runs its kernels on the CPU through its interpreter (`TRITON_INTERPRET=1`, for tests)."""
    return os.environ.get("TRITON_INTERPRET") == "1"


def device_kind(device: object) -> str:
    """`cpu` or `cuda` of a device or its name (`cuda:1`); `ConfigError` for any other."""
    kind = getattr(device, "type", None) or (device.split(":")[0] if isinstance(device, str) else None)
    if kind not in DEVICE_TYPES:
        raise choices_error("device", device, DEVICE_TYPES)
    return kind


def resolve_backend(backend: str, device: object) -> str:
    """The kernels that run a fit on `device`: `auto` → the Numba kernels on the CPU, the Triton kernels on
    CUDA where Triton is installed, the PyTorch reference elsewhere; a named backend where it can run there,
    else `ConfigError` saying what can."""
    kind = device_kind(device)
    if backend == "auto":
        if kind == "cpu":
            return "numba"
        return "triton" if triton_installed() else "torch"
    if backend not in BACKEND_NAMES:
        raise choices_error("backend", backend, BACKENDS)
    if backend == "numba" and kind != "cpu":
        raise ConfigError(f"`backend` numba runs on the CPU, not on {device}; use `backend` torch (or auto) with "
                          "`device` cuda")
    if backend == "triton" and not triton_installed():
        raise ConfigError("`backend` triton needs the triton package: pip install triton, or use `backend` torch")
    if backend == "triton" and kind != "cuda" and not triton_interpreting():
        raise ConfigError(f"`backend` triton runs on CUDA, not on {device}; use `backend` numba or torch "
                          "with `device` cpu")
    return backend


@dataclass(frozen=True)
class RunOptions:
    """Where a fit or render runs: the torch `device` (`cpu`, `cuda`, `cuda:1`) and the kernels (`backend`,
    `resolve_backend`). They change the last bits of a render only, never the configuration."""

    device: str = "cpu"
    backend: Backend = "auto"

    def __post_init__(self) -> None:
        # Which backends run on this machine is `validate`'s: a record of a run elsewhere still reads.
        if not isinstance(self.device, str):
            raise choices_error("device", self.device, DEVICE_TYPES)
        device_kind(self.device)
        if self.backend not in BACKENDS:
            raise choices_error("backend", self.backend, BACKENDS)

    def validate(self) -> "RunOptions":
        """These options, or `ConfigError` where the backend cannot run on the device here (`resolve_backend`)."""
        resolve_backend(self.backend, self.device)
        return self

    @property
    def kernels(self) -> str:
        """The backend that runs here (`resolve_backend`)."""
        return resolve_backend(self.backend, self.device)

    def on_device(self, device: str) -> "RunOptions":
        """The same options on `device`: a backend that cannot run there becomes `auto`."""
        moved = dataclasses.replace(self, device=device)
        try:
            moved.validate()
        except ConfigError:
            return dataclasses.replace(moved, backend="auto")
        return moved

    def to_dict(self) -> dict[str, str]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "RunOptions":
        """The options a record holds: a `config.json`'s `run`, or a flat record's `device` and `backend`."""
        values = data.get("run") if isinstance(data.get("run"), dict) else data
        return cls(device=str(values.get("device", "cpu")), backend=values.get("backend", "auto"))


def padded_size(n: int, guard_px: int, multiple_px: int) -> int:
    """Length (px) of one axis after the guard band: at least `guard_px` per side, rounded up."""
    return int(math.ceil((n + 2 * guard_px) / multiple_px) * multiple_px)
