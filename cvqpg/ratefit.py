"""The rate in the fit (`cvqpg encode --bpp` with `--fit rate`): distortion + λ·rate, quantisation-aware.

`RateFit` says which levers a fit pulls, each alone or together:

- `noise`: every value rendered through the file's quantisers at `bits` from the first step (`rate.coded`), with
  additive uniform noise of one bin standing for the rounding, annealed to the rounding itself (straight
  through) over the fit's last `ANNEAL_SHARE` of steps, so that the fit ends on the values the file holds;
- `rate`: λ times the file's bits per hologram pixel (`rate.coded`'s estimate) added to the fit's loss. λ is
  set by the budget with a controller during the fit (`RateController`): each step it grows where the estimate
  exceeds `target_bytes` and shrinks where it falls below, multiplicatively. One fit, no probes: probing fits
  for λ would cost a share of the fit's time each, and the bits a λ buys move as the fit does;
- `depths`: the depths the noise and the rate stand for chosen per file where the noise starts to give way
  (`ANNEAL_SHARE`): the finest rung of the search's ladder at which the rate model's estimate of the whole model
  fits the budget (`rung_within`), in place of the default depths;
- `prune`: a primitive's bits weighed by a gate that closes as its weight |amplitude·opacity| falls below
  `GATE_BINS` bins of the amplitude quantiser, so that the rate term can switch off a primitive that costs more
  bits than it earns; primitives whose weight codes to 0 are removed before coding (`silent_removed`).

`RateObjective` is one fit's state of it: the controller's λ, and what `fitting.update` asks each step (the
primitives to render, the rate term to add). Today's fit is `RateFit` with every lever off (`PLAIN`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from .bitdepths import LADDER, BitDepths
from .codec import quantiser
from .config import FitConfig
from .primitives import Primitives
from .rate import coded, estimate

# The noise gives way to rounding over the fit's last 30% of steps.
ANNEAL_SHARE = 0.3
# A primitive's bits count fully once its weight reaches 4 bins of the amplitude quantiser at `bits`.
GATE_BINS = 4.0
# λ (loss per bit per pixel) starts small and moves by at most e^GAIN·½ per step: a factor 2 in about 5 steps.
INITIAL_LAMBDA, LEAST_LAMBDA, MOST_LAMBDA = 1e-3, 1e-7, 10.0
GAIN = 0.3


@dataclass(frozen=True)
class RateFit:
    """Which levers a fit pulls (see the module docstring), the depths `bits` its quantisers stand for, and the
    file size `target_bytes` the rate term steers the estimate to (None: no rate term)."""

    noise: bool = False
    rate: bool = False
    prune: bool = False
    bits: BitDepths = BitDepths()
    target_bytes: int | None = None
    depths: bool = False

    @property
    def active(self) -> bool:
        """Whether the fit differs from today's float fit."""
        return self.noise or self.rate or self.prune or self.depths

    def record(self) -> dict:
        """The settings as JSON (an encode's `budget.json`)."""
        return {"noise": self.noise, "rate": self.rate, "prune": self.prune, "bits": asdict(self.bits),
                "target_bytes": self.target_bytes, "depths": self.depths}

    @classmethod
    def from_record(cls, record: dict) -> "RateFit":
        return cls(bool(record["noise"]), bool(record["rate"]), bool(record["prune"]), BitDepths(**record["bits"]),
                   None if record["target_bytes"] is None else int(record["target_bytes"]),
                   bool(record.get("depths", False)))


PLAIN = RateFit()
FULL = dict(noise=True, rate=True, prune=True)  # the new fit: every lever


def anneal_start(steps: int) -> int:
    """The first step of a fit of `steps` steps at which the noise gives way to rounding."""
    return math.floor((1 - ANNEAL_SHARE) * steps) + 1


def rung_within(primitives: Primitives, config: FitConfig, max_bytes: int) -> BitDepths:
    """The finest rung of the search's ladder (`bitdepths.LADDER`, the defaults shifted together) at which the rate
    model's estimate of `primitives`' file is at most `max_bytes`; the coarsest where none is."""
    detached, chosen = primitives.detached(), LADDER[0]
    for bits in LADDER:  # sizes grow with the rung
        if estimate(detached, config, bits).file_bytes > max_bytes:
            break
        chosen = bits
    return chosen


def noise_share(step: int, steps: int) -> float:
    """How much of one bin of uniform noise stands for the rounding at `step` of a fit of `steps` steps (1 until
    the last `ANNEAL_SHARE` of steps, then down linearly to 0 at the last step, rounding straight through)."""
    start = (1 - ANNEAL_SHARE) * steps
    return 1.0 if step <= start else max(0.0, (steps - step) / max(steps - start, 1.0))


def presence(primitives: Primitives, config: FitConfig, bits: BitDepths) -> Tensor:
    """Each primitive's gate (0..1, differentiable [N]): its largest weight |amplitude·opacity| over
    `GATE_BINS` bins of the amplitude quantiser at `bits`, at most 1."""
    weight = (primitives.amplitude * primitives.opacity[:, None]).abs().amax(dim=1)
    top = float(weight.detach().max().clamp(min=1e-12))
    step = quantiser("amplitude", {"amplitude": [0.0, top]}, bits.amplitude).step
    return (weight / (GATE_BINS * step)).clamp(max=1.0).double()


@dataclass
class RateController:
    """λ during a fit: multiplied by e^(GAIN·e) after each step, e = estimated/target − 1 within ±½."""

    target_bytes: int
    weight: float = INITIAL_LAMBDA

    def update(self, estimated_bytes: int) -> float:
        error = min(max(estimated_bytes / self.target_bytes - 1, -0.5), 0.5)
        self.weight = min(max(self.weight * math.exp(GAIN * error), LEAST_LAMBDA), MOST_LAMBDA)
        return self.weight


class RateObjective:
    """One fit's rate term: what it renders at each step and what it adds to the loss (`step`)."""

    def __init__(self, settings: RateFit, config: FitConfig, weight: float | None = None):
        self.settings, self.config = settings, config
        self.controller = None if not settings.rate else RateController(
            settings.target_bytes, INITIAL_LAMBDA if weight is None else weight)
        self.last_bytes: int | None = None
        self.bits = settings.bits  # the depths the quantisers stand for now (`depths` moves them once)

    def resume(self, weight: float) -> None:
        """Take up λ where a fit left it (its history's last `rate_lambda`)."""
        if self.controller is not None:
            self.controller.weight = weight

    @property
    def weight(self) -> float:
        """λ now (loss per bit per hologram pixel; 0 without a rate term)."""
        return 0.0 if self.controller is None else self.controller.weight

    def step(self, primitives: Primitives, step: int, steps: int, generator: torch.Generator | None
             ) -> tuple[Primitives, Tensor | None]:
        """The primitives to render at `step` of `steps` and the term to add to the loss (None: none): through the
        quantisers with noise where `noise`, λ·bpp where `rate`, each primitive's bits gated where `prune`."""
        settings = self.settings
        if settings.depths and settings.target_bytes is not None and step == anneal_start(steps):
            self.bits = rung_within(primitives, self.config, settings.target_bytes)
        share = noise_share(step, steps) if settings.noise else 0.0
        result = coded(primitives, self.config, self.bits, share, generator)
        self.last_bytes = result.rate.file_bytes
        shown = result.primitives if settings.noise else primitives
        if self.controller is None:
            return shown, None
        per_primitive = result.rate.primitive_bits
        if settings.prune:
            per_primitive = per_primitive * presence(primitives, self.config, self.bits)
        pixels = self.config.targets.width * self.config.targets.height
        term = self.controller.weight * per_primitive.sum().to(primitives.position_px.device) / pixels
        self.controller.update(result.rate.file_bytes)
        return shown, term.float()


def silent_removed(primitives: Primitives, config: FitConfig, bits: BitDepths) -> Primitives:
    """`primitives` without those whose every weight codes to 0 at `bits` (less than half a bin of the amplitude
    quantiser at the depth of the finest-offset value), which render nothing and cost bits; one at least kept."""
    weight = (primitives.amplitude * primitives.opacity[:, None]).detach().abs()
    top = float(weight.max().clamp(min=1e-12))
    # the finest depth a value can take (`codec.MAX_OFFSET` above the median), so that nothing visible goes
    step = quantiser("amplitude", {"amplitude": [0.0, top]}, min(bits.amplitude + 2, 16)).step
    keep = weight.amax(dim=1) >= step / 2
    if not bool(keep.any()):
        keep[weight.amax(dim=1).argmax()] = True
    return type(primitives).from_tensors({name: tensor[keep] for name, tensor in primitives.tensors().items()})
