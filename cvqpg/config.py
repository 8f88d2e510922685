"""Fit configuration: every setting of SPEC §2–§6 with the paper's value as default."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal

Color = Literal["rgb", "gray"]
Primitive = Literal["flat", "cvqpg"]
Bound = Literal["adaptive", "global"]
Qpf = Literal["mahalanobis", "standard"]

RGB_WAVELENGTHS_M = (639e-9, 532e-9, 473e-9)
GRAY_WAVELENGTH_M = 639e-9


@dataclass(frozen=True)
class LearningRates:
    """Per-group Adan learning rates (SPEC §6). Position is cosine-annealed to `position_final`."""

    position: float = 0.01
    position_final: float = 1e-3
    scale: float = 0.005
    color: float = 0.0025
    phase: float = 0.0025
    opacity: float = 0.025
    rotation: float = 0.001
    curvature: float = 0.001


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
    warmup: int = 400
    seed: int = 100
    pixel_pitch: float = 3.74e-6
    num_planes: int = 2
    plane_center: float = 3e-3
    plane_span: float = 4e-3
    eta: float = 0.9
    bound: Bound = "adaptive"
    global_bound: float = 200.0
    qpf: Qpf = "mahalanobis"
    lr: LearningRates = field(default_factory=LearningRates)
    betas: tuple[float, float, float] = (0.98, 0.92, 0.99)
    adan_eps: float = 1e-8
    grad_clip_norm: float = 1.0
    ssim_weight: float = 0.005
    target_noise: float = 1e-3
    guard_band_px: int = 144
    pad_multiple_px: int = 64
    defocus_sigma_px: float = 8.0
    depth_exponent: float = 1.0
    device: str = "cpu"
    backend: str = "auto"

    @property
    def channels(self) -> int:
        return 3 if self.color == "rgb" else 1

    @property
    def wavelengths(self) -> tuple[float, ...]:
        """One wavelength (m) per colour channel."""
        return RGB_WAVELENGTHS_M if self.color == "rgb" else (GRAY_WAVELENGTH_M,)

    @property
    def primitive_count(self) -> int:
        """N: explicit, or `ratio · W·H/2` (RGB) / `ratio · W·H/4` (grayscale), SPEC §2."""
        if self.num_gaussians is not None:
            return self.num_gaussians
        pixels_per_primitive = 2 if self.color == "rgb" else 4
        return int(round(self.ratio * self.width * self.height / pixels_per_primitive))

    @property
    def params_per_primitive(self) -> int:
        """Learnable scalars per primitive: 12/13 (RGB), 8/9 (grayscale)."""
        flat = 2 + 2 + 1 + 2 * self.channels + 1
        return flat + (1 if self.primitive == "cvqpg" else 0)

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

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "FitConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in data.items() if k in known}
        if isinstance(values.get("lr"), dict):
            values["lr"] = LearningRates(**values["lr"])
        if isinstance(values.get("betas"), list):
            values["betas"] = tuple(values["betas"])
        return cls(**values)


def padded_size(n: int, guard_px: int, multiple_px: int) -> int:
    """Length (px) of one axis after the guard band: at least `guard_px` per side, rounded up."""
    return int(math.ceil((n + 2 * guard_px) / multiple_px) * multiple_px)
