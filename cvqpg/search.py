"""The search for a `.cvq` file of a model: the bit depths it is written at and the primitives it keeps.

Every candidate is a trial (`trial`): encoded, decoded as a reader would, and rendered, so that sizes are
measured, never estimated. Candidates come from one ladder (`LADDER`, the codec's default depths shifted
together, coarsest first) and are chosen among one way (`Goal.best`): of those that meet the goal, the one
it prefers, and where none does, the largest file. Two goals:

- `MaxDrop` (`cvqpg compress --max-drop`) prefers the smallest file whose render stays within a PSNR drop.
- `Budget` (`cvqpg compress --bpp/--max-bytes`, `cvqpg encode`) never exceeds a size, and prefers the
  best-scoring file among those within 5% below it (`CLOSE`; a barely fitted model's score can even rise as
  bits go, so the budget the caller asked for is what it gets).

`search` walks the ladder, keeping at each rung as many primitives as the goal allows (all of them within a
drop; within a budget the most that fit, those of most field energy first: `strongest_first`), and stops
where no finer rung can be preferred. From the finest rung that keeps every primitive it then moves one
attribute one bit at a time toward the goal's limit (`refine`): coarser within a drop, finer within a
budget, whose rungs (every attribute a bit finer, about 7% of the file) overshoot it. Within a budget
dropping primitives costs far more than coarser bits (on a 640×480 grayscale fit, dropping the weakest 8%
cost 2.9 dB where one rung coarser for all cost 0.9 dB), which is why every primitive's rung is filled.

`rate_control` adds quantisation-aware fine-tuning (`finetune`) to a budget's search: at the chosen depths,
from a few more primitives than fit (`TUNING_HEADROOM`), since tuning moves the entropy-coded size a little
either way, and a last count of the tuned primitives that fit, those that set the codec's ranges first, so
that the file's bins stay those the tuning trained on. `finetuned` does the same for a drop or fixed depths,
after pruning (`prune`). Either keeps the tuned file only where the goal prefers it.

`CompressionSettings` holds what a caller asks for, checked once, where it is made. bpp is bits per hologram
pixel, 8·bytes / (W·H), all channels together, as `cvqpg info` reports it.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from typing import Any, Callable, ClassVar, Sequence

import torch
from tqdm.auto import tqdm

from .bitdepths import LADDER, BitDepths
from .codec import bits_per_pixel, decode, encode, range_holders
from .config import RANGES, FitConfig
from .control import SILENT, RunControl
from .errors import ConfigError
from .finetune import finetune
from .fitting import FitInterrupted, render
from .metrics import mean_psnr
from .primitives import Primitives, field_energy
from .ratefit import FULL, PLAIN, RateFit, RateObjective
from .targets import Scene

# The depths every search tries are `LADDER`'s (`bitdepths`), coarsest first.
COARSEST = LADDER[0]
# The drop `cvqpg compress` aims at where it is given no goal.
DEFAULT_MAX_DROP_DB = 0.1
MAX_BUDGET_BYTES = 2**53  # budgets stay exact in float64 arithmetic (bits per pixel, ratios)
ASSUMED_FIT_PSNR_DB = 30.0
# A budget is met by a file within 5% below it.
CLOSE = 0.95
# Fine-tuning moves a file's size by a few percent (small fits grew by 1–5%); tuning a model 4% above the
# budget leaves the last count primitives to drop where it shrinks, rather than a file well below it.
TUNING_HEADROOM = 0.04


@dataclass
class Reference:
    """What a decoded render is scored against: the run's targets, or without a run the float model's
    own reconstruction (then `fit_psnr` is None)."""

    images: torch.Tensor  # [M, C, H, W]
    label: str
    fit_psnr: float | None


def reference_for(primitives: Primitives, config: FitConfig, scene_targets: torch.Tensor | None,
                  label: str = "the run's targets") -> Reference:
    """The scene's targets (named `label`) with the float model's PSNR on them, or the float model's
    reconstruction."""
    recon = render(primitives, config)[1]
    if scene_targets is not None:
        return Reference(scene_targets, label, mean_psnr(recon, scene_targets))
    return Reference(recon, "the float model's own reconstruction", None)


def psnr_drop(primitives: Primitives, config: FitConfig, reference: Reference) -> tuple[float, float]:
    """(PSNR in dB of `primitives`' render against the reference, drop in dB below the float model).

    Against the float model's own reconstruction the drop is estimated for a fit of
    `ASSUMED_FIT_PSNR_DB` whose error adds to the quantisation error:
    10·log10(1 + 10^((P_fit − Q)/10)), Q the PSNR against the float reconstruction.
    """
    value = mean_psnr(render(primitives, config)[1], reference.images)
    if reference.fit_psnr is not None:
        return value, reference.fit_psnr - value
    return value, 10 * math.log10(1 + 10 ** ((ASSUMED_FIT_PSNR_DB - value) / 10))


@dataclass
class Choice:
    """A candidate file: its bit depths, bytes, decoded primitives, and PSNR (dB) and drop (dB)."""

    bits: BitDepths
    data: bytes
    decoded: Primitives
    psnr: float
    drop: float


def trial(primitives: Primitives, config: FitConfig, bits: BitDepths, reference: Reference) -> Choice:
    """Encode at `bits`, decode the bytes as a reader would, and score the decoded render."""
    data = encode(primitives, config, bits)
    decoded = decode(data).primitives
    return Choice(bits, data, decoded, *psnr_drop(decoded, config, reference))


def strongest_first(primitives: Primitives, first: torch.Tensor | None = None) -> torch.Tensor:
    """Indices of the primitives by decreasing field energy (`field_energy`), ties in their order, those of
    the indices `first` ahead of all the others [N]."""
    energy = field_energy(primitives)
    if first is not None:
        energy = energy.index_fill(0, first, math.inf)
    return torch.argsort(energy, descending=True, stable=True)


def kept(primitives: Primitives, order: torch.Tensor, count: int) -> Primitives:
    """The first `count` primitives of `order` (e.g. `strongest_first`), in their own order."""
    chosen = order[:count].sort().values
    return type(primitives).from_tensors({name: tensor[chosen] for name, tensor in primitives.tensors().items()})


def prune(primitives: Primitives, fraction: float) -> Primitives:
    """The primitives without the `fraction` (0 ≤ fraction < 1, as `CompressionSettings` checks it) of least
    field energy (`field_energy`), the others in their order. The rest only regain the PSNR lost with
    fine-tuning (`finetune`)."""
    return kept(primitives, strongest_first(primitives), pruned_count(primitives.count, fraction))


def pruned_count(count: int, fraction: float) -> int:
    """How many of `count` primitives `prune` keeps; `ConfigError` where that is none."""
    keep = round((1 - fraction) * count)
    if keep < 1:
        raise ConfigError(f"`prune_fraction` {fraction:g} removes all {count} primitives; give a smaller fraction "
                          f"(below {1 - 0.5 / count:.6g})")
    return keep


def largest_fitting(size: Callable[[int], int], max_bytes: int, top: int) -> int:
    """The largest count n in 1..`top` that a search finds with `size(n)` ≤ `max_bytes` bytes, 0 where
    not even one fits. Sizes grow with n but not strictly (an entropy-coded stream of more symbols can
    be a few bytes shorter), so n is one whose successor does not fit, not always the largest of all.

    Sizes grow about linearly, so each probe is where the line through the bracket's ends meets the
    budget, a few encodes instead of a bisection's log2(top); a probe that leaves more than half of the
    bracket is followed by a bisection step, so the search never takes more than about twice as many."""
    smallest = size(1)
    if smallest > max_bytes:
        return 0
    largest = size(top)
    if largest <= max_bytes:
        return top
    low, high, size_low, size_high = 1, top, smallest, largest  # size(low) fits, size(high) does not
    bisect = False
    while high - low > 1:
        width = high - low
        if bisect:
            probe = (low + high) // 2
        else:
            probe = low + (max_bytes - size_low) * width // max(size_high - size_low, 1)
        probe = min(max(probe, low + 1), high - 1)
        measured = size(probe)
        if measured <= max_bytes:
            low, size_low = probe, measured
        else:
            high, size_high = probe, measured
        bisect = not bisect and 2 * (high - low) > width
    return low


def file_sizes(primitives: Primitives, order: torch.Tensor, config: FitConfig, bits: BitDepths
               ) -> Callable[[int], int]:
    """The file's bytes at `bits` with the first n primitives of `order`, as a function of n."""
    return lambda count: len(encode(kept(primitives, order, count), config, bits))


def smallest_file(primitives: Primitives, config: FitConfig) -> int:
    """Bytes of the smallest file a search can write of `primitives`: the strongest alone at `COARSEST`."""
    return len(encode(kept(primitives, strongest_first(primitives), 1), config, COARSEST))


def _size(choice: Choice) -> int:
    return len(choice.data)


class Goal(ABC):
    """What a search looks for: which candidates meet it (`holds`), which of those it prefers (`preference`),
    how many primitives a rung keeps, and which way from the ladder's rung it refines (`direction`: +1 finer
    bits, −1 coarser). `work` names the search in the message of a stop request."""

    direction: ClassVar[int]
    work: ClassVar[str]

    @abstractmethod
    def holds(self, choice: Choice) -> bool:
        """Whether `choice` meets the goal."""

    @abstractmethod
    def preference(self, choice: Choice) -> float:
        """How much the goal prefers `choice` among those that meet it (larger is preferred)."""

    def best(self, choices: Sequence[Choice]) -> Choice:
        """The one way every search chooses: the preferred (the first where tied) of `choices` that meet the
        goal; where none does, the largest file."""
        held = [choice for choice in choices if self.holds(choice)]
        return max(held, key=self.preference) if held else max(choices, key=_size)

    def count(self, primitives: Primitives, order: torch.Tensor, config: FitConfig, bits: BitDepths) -> int:
        """How many primitives of `order` a file at `bits` keeps (0: none can be written): all of them."""
        return primitives.count

    def affordable(self, primitives: Primitives, config: FitConfig, bits: BitDepths) -> bool:
        """Whether a file of `primitives` at `bits` is worth a trial (measured without rendering): always."""
        return True

    def settled(self, choice: Choice) -> bool:
        """Whether no finer rung than `choice`'s can be preferred, so that the ladder's walk ends there."""
        return False


@dataclass(frozen=True)
class MaxDrop(Goal):
    """The smallest file whose decoded render stays within `max_drop` dB of the float model's PSNR."""

    max_drop: float
    direction: ClassVar[int] = -1
    work: ClassVar[str] = "the bit-depth search"

    def holds(self, choice: Choice) -> bool:
        return choice.drop <= self.max_drop

    def preference(self, choice: Choice) -> float:
        return -len(choice.data)

    def settled(self, choice: Choice) -> bool:
        return self.holds(choice)  # finer rungs are larger files


@dataclass(frozen=True)
class FixedBits(Goal):
    """The best-scoring file at depths the caller fixed (`cvqpg compress --bits`, searched on a ladder of those
    depths alone): no other depths are tried, and a fine-tuned file is kept where it drops less."""

    direction: ClassVar[int] = 0
    work: ClassVar[str] = "the bit-depth search"

    def holds(self, choice: Choice) -> bool:
        return True

    def preference(self, choice: Choice) -> float:
        return -choice.drop

    def affordable(self, primitives: Primitives, config: FitConfig, bits: BitDepths) -> bool:
        return False

    def settled(self, choice: Choice) -> bool:
        return True


@dataclass(frozen=True)
class Budget(Goal):
    """At most `max_bytes` bytes, as the caller gave them (`given`, for messages): the best-scoring file within
    `CLOSE` below the budget."""

    max_bytes: int
    given: str
    direction: ClassVar[int] = 1
    work: ClassVar[str] = "rate control"

    @classmethod
    def of(cls, config: FitConfig, bpp: float | None = None, max_bytes: int | None = None) -> "Budget":
        """The budget of `bpp` bits per hologram pixel (the file at most ⌊bpp·W·H/8⌋ bytes) or of `max_bytes`
        bytes, one of them, as `CompressionSettings` checks them."""
        if bpp is not None:
            exact = bpp * config.targets.width * config.targets.height / 8
            if not exact <= MAX_BUDGET_BYTES:
                raise ConfigError(f"`bpp` {bpp:g} asks for {exact:g} bytes for {config.targets.width}×"
                                  f"{config.targets.height} px; give a budget of at most {MAX_BUDGET_BYTES} bytes")
            size = math.floor(exact)
            return cls(size, f"`bpp` {bpp:g} ({size} bytes for {config.targets.width}×{config.targets.height} px)")
        return cls(max_bytes, f"`max_bytes` {max_bytes}")

    def check(self, smallest: int, config: FitConfig) -> None:
        """`ConfigError` where the budget is below `smallest`, the smallest file the model can be written as."""
        if self.max_bytes < smallest:
            raise ConfigError(f"{self.given} is below the smallest file the format can write for this model: "
                              f"{smallest} bytes ({bits_per_pixel(smallest, config):.3f} bpp), its header "
                              "(optics, ranges, stream descriptors) and one primitive at the coarsest bit depths")

    def holds(self, choice: Choice) -> bool:
        return len(choice.data) >= CLOSE * self.max_bytes

    def preference(self, choice: Choice) -> float:
        return choice.psnr

    def count(self, primitives: Primitives, order: torch.Tensor, config: FitConfig, bits: BitDepths) -> int:
        return largest_fitting(file_sizes(primitives, order, config, bits), self.max_bytes, primitives.count)

    def affordable(self, primitives: Primitives, config: FitConfig, bits: BitDepths) -> bool:
        return len(encode(primitives, config, bits)) <= self.max_bytes


def _check_stop(control: RunControl, config: FitConfig, goal: Goal) -> None:
    """`FitInterrupted` once `control` asks to stop (after the fit of the model, whose checkpoint the caller
    keeps)."""
    if control.should_stop():
        raise FitInterrupted(config.optimisation.steps + 1, during=goal.work)


def refine(primitives: Primitives, config: FitConfig, reference: Reference, goal: Goal, choice: Choice,
           control: RunControl = SILENT) -> Choice:
    """`choice` (of every primitive) moved one attribute one bit at a time in `goal.direction`, to the trial
    the goal prefers (`Goal.best`), while the goal prefers it to where it stands."""
    while True:
        _check_stop(control, config, goal)
        depths = [bits for bits in (choice.bits.shifted_one(name, goal.direction) for name in choice.bits.names())
                  if bits is not None and goal.affordable(primitives, config, bits)]
        if not depths:
            return choice
        candidate = goal.best([trial(primitives, config, bits, reference) for bits in depths])
        if goal.best([choice, candidate]) is choice:
            return choice
        choice = candidate


def search(primitives: Primitives, config: FitConfig, reference: Reference, goal: Goal,
           ladder: Sequence[BitDepths] = LADDER, control: RunControl = SILENT,
           on_rung: Callable[[Choice | None], None] | None = None) -> Choice:
    """The file of `primitives` that `goal` chooses (see the module docstring): a trial at each rung of `ladder`
    (coarsest first) with the primitives the goal keeps there, until one settles it, and the finest rung that
    keeps every primitive refined (`refine`). `on_rung` is told each rung's trial (None where not one primitive
    fits). A stop request (`control`) raises `FitInterrupted` before the next rung or round of refinement."""
    order = strongest_first(primitives)
    rungs = []
    for bits in ladder:
        _check_stop(control, config, goal)
        count = goal.count(primitives, order, config, bits)
        rung = trial(kept(primitives, order, count), config, bits, reference) if count else None
        if on_rung is not None:
            on_rung(rung)
        if rung is not None:
            rungs.append(rung)
            if goal.settled(rung):
                break
    whole = [choice for choice in rungs if choice.decoded.count == primitives.count]
    if whole:
        rungs.append(refine(primitives, config, reference, goal, max(whole, key=_size), control))
    return goal.best(rungs)


@dataclass
class RateChoice:
    """The file rate control chose (`choice`: bytes, bit depths, decoded primitives, PSNR), the fine-tuning
    steps it ran and whether their file was kept."""

    choice: Choice
    finetune_steps: int
    finetune_kept: bool

    def record(self, budget: Budget) -> dict[str, Any]:
        """The budget and the fine-tuning, as the records of a rate-controlled file hold them."""
        return {"max_bytes": budget.max_bytes, "finetune_steps": self.finetune_steps,
                "finetune_kept": self.finetune_kept}


def rate_control(primitives: Primitives, config: FitConfig, reference: Reference, budget: Budget,
                 scene: Scene | None = None, finetune_steps: int = 0, control: RunControl = SILENT,
                 rate_loss: RateFit | None = None, rate_weight: float | None = None) -> RateChoice:
    """The best-scoring `.cvq` file of `primitives` within `budget` (`search`), fine-tuned for `finetune_steps`
    on `scene`'s targets where a scene is given. `ConfigError` where the budget is below `smallest_file`. A
    progress bar (`control.progress`) shows the rate (bpp) and PSNR (dB) of each rung and, while fine-tuning,
    the PSNR of the quantised render. A stop request (`control`) ends it before its next rung or tuning step
    with `FitInterrupted` (after the fit of `primitives`, whose checkpoint the caller keeps). With `rate_loss`
    (`ratefit.RateFit`), the tuning's loss also weighs the file's bits at the chosen depths by a λ that a
    controller steers to the budget, from `rate_weight` (a rate-aware fit's last λ; None: the controller's start)."""
    budget.check(smallest_file(primitives, config), config)
    steps = finetune_steps if scene is not None else 0
    with tqdm(total=len(LADDER) + steps, disable=not control.progress, desc="rate", unit="step",
              dynamic_ncols=True) as bar:

        def show(choice: Choice, psnr: float | None = None) -> None:
            bar.set_postfix(bpp=f"{bits_per_pixel(len(choice.data), config):.3f}",
                            psnr=f"{choice.psnr if psnr is None else psnr:.2f}dB", refresh=False)

        def rung_done(rung: Choice | None) -> None:
            if rung is not None:
                show(rung)
            bar.update()

        best = search(primitives, config, reference, budget, control=control, on_rung=rung_done)
        show(best)
        if not steps:
            return RateChoice(best, 0, False)

        def tuning(_step: int, _loss: float, psnr: float) -> None:
            show(best, psnr)
            bar.update()

        order = strongest_first(primitives)
        start = largest_fitting(file_sizes(primitives, order, config, best.bits),
                                math.floor(budget.max_bytes * (1 + TUNING_HEADROOM)), primitives.count)
        objective = None if rate_loss is None else RateObjective(
            replace(rate_loss, noise=False, bits=best.bits, target_bytes=budget.max_bytes), config, rate_weight)
        tuned = finetune(kept(primitives, order, start), config, scene, best.bits, steps,
                         control=RunControl(progress=False, stop_requested=control.stop_requested, on_step=tuning),
                         objective=objective)
        tuned_order = strongest_first(tuned, first=range_holders(tuned))
        count = budget.count(tuned, tuned_order, config, best.bits)
        candidate = trial(kept(tuned, tuned_order, count), config, best.bits, reference) if count else best
        chosen = budget.best([best, candidate])
        show(chosen)
        return RateChoice(chosen, steps, chosen is not best)


def finetuned(primitives: Primitives, config: FitConfig, reference: Reference, goal: MaxDrop | FixedBits,
              scene: Scene, choice: Choice, steps: int, prune_fraction: float = 0.0, control: RunControl = SILENT
              ) -> tuple[Choice, bool]:
    """`choice` or, where `goal` prefers it (`Goal.best`), a file of `primitives` fine-tuned for `steps` on
    `scene`'s targets after pruning `prune_fraction` of them (`prune`), and whether that file won. The tuning
    runs at `choice`'s depths; within a drop (`MaxDrop`) first at one bit coarser everywhere, since tuned models
    hold coarser depths, and a tuned file that holds is searched coarser from its depths."""
    start = prune(primitives, prune_fraction)
    depths = (choice.bits.shifted(-1), choice.bits) if isinstance(goal, MaxDrop) else (choice.bits,)
    for bits in depths:
        candidate = trial(finetune(start, config, scene, bits, steps, control=control), config, bits, reference)
        if goal.holds(candidate):
            break
    if isinstance(goal, MaxDrop) and goal.holds(candidate):
        candidate = search(candidate.decoded, config, reference, goal, ladder=(candidate.bits,), control=control)
    chosen = goal.best([choice, candidate])
    return chosen, chosen is not choice


def _number(value: Any) -> bool:
    """Whether `value` is a finite int or float (not a bool)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _shown(value: Any) -> str:
    return f"{value:g}" if isinstance(value, (int, float)) else repr(value)


@dataclass(frozen=True)
class CompressionSettings:
    """How to compress a model, checked once, where it is made (`ConfigError` naming the first setting that
    cannot work). One goal at most: fixed `bits`, a `max_drop` (dB), or a budget of `bpp` bits per hologram
    pixel or `max_bytes` bytes; with none, a drop of `DEFAULT_MAX_DROP_DB`. `finetune_steps` of
    quantisation-aware fine-tuning (None: the workflow's default), after removing the `prune_fraction`
    (0 ≤ fraction < 1) of the primitives of least field energy, which needs fine-tuning and, within a
    budget, is the rate control's to choose. `rate_loss` (a budget's only) puts the file's bits in the loss
    (`ratefit`): of `cvqpg encode`'s fit, quantisation-aware, and of every fine-tuning within the budget."""

    bits: BitDepths | None = None
    max_drop: float | None = None
    bpp: float | None = None
    max_bytes: int | None = None
    finetune_steps: int | None = None
    prune_fraction: float = 0.0
    rate_loss: bool = False

    def __post_init__(self) -> None:
        goals = [f"`{name}`" for name in ("bits", "max_drop", "bpp", "max_bytes") if getattr(self, name) is not None]
        if len(goals) > 1:
            raise ConfigError(f"give one goal, not {' and '.join(goals)}")
        if self.bits is not None:
            self.bits.validate()
        if self.max_drop is not None and not (_number(self.max_drop) and self.max_drop >= 0):
            raise ConfigError(f"`max_drop` {_shown(self.max_drop)}: give a drop in dB ≥ 0")
        if self.budgeted and self.prune_fraction:
            raise ConfigError("`prune_fraction` applies to `bits` and `max_drop`; with `bpp` or `max_bytes` the rate "
                              "control chooses the primitives to keep")
        steps = self.finetune_steps
        if steps is not None and not (isinstance(steps, int) and not isinstance(steps, bool) and steps >= 0):
            raise ConfigError(f"`finetune_steps` {steps}: give a number of steps ≥ 0")
        if steps is not None and steps > RANGES["steps"][1]:
            raise ConfigError(f"`finetune_steps` {steps}: give at most {RANGES['steps'][1]} steps, as a fit's")
        if not (_number(self.prune_fraction) and 0 <= self.prune_fraction < 1):
            raise ConfigError(f"`prune_fraction` {_shown(self.prune_fraction)}: give the fraction of primitives to "
                              "remove, 0 ≤ fraction < 1")
        if self.prune_fraction and not steps:
            raise ConfigError(f"`prune_fraction` {self.prune_fraction:g} needs `finetune_steps` > 0: pruned "
                              "primitives cost PSNR that only fine-tuning regains")
        if self.bpp is not None and not (_number(self.bpp) and self.bpp > 0):
            raise ConfigError(f"`bpp` {_shown(self.bpp)}: give a positive, finite number of bits per hologram pixel")
        if self.rate_loss and not self.budgeted:
            raise ConfigError("`rate_loss` steers the file's bits to a budget: give `bpp` or `max_bytes` with it")
        if self.max_bytes is not None and not (isinstance(self.max_bytes, int) and not isinstance(self.max_bytes, bool)
                                               and 0 < self.max_bytes <= MAX_BUDGET_BYTES):
            raise ConfigError(f"`max_bytes` {self.max_bytes}: give a positive whole number of bytes, at most "
                              f"{MAX_BUDGET_BYTES}")

    @property
    def budgeted(self) -> bool:
        """Whether the goal is a file size (`bpp` or `max_bytes`)."""
        return self.bpp is not None or self.max_bytes is not None

    def budget(self, config: FitConfig) -> Budget:
        """The budget for a model of `config`'s size; `ConfigError` where the settings give none."""
        if not self.budgeted:
            raise ConfigError("give one budget: `bpp` or `max_bytes`")
        return Budget.of(config, self.bpp, self.max_bytes)

    def rate_fit(self, budget: Budget) -> RateFit:
        """What `cvqpg encode`'s fit pulls for these settings within `budget`: every lever of `ratefit` with
        `rate_loss`, none without (today's float fit)."""
        return RateFit(**FULL, target_bytes=budget.max_bytes) if self.rate_loss else PLAIN

    def goal(self, config: FitConfig) -> Goal:
        """What the search looks for with a model of `config`'s size."""
        if self.budgeted:
            return self.budget(config)
        if self.bits is not None:
            return FixedBits()
        return MaxDrop(DEFAULT_MAX_DROP_DB if self.max_drop is None else self.max_drop)
