"""Rate control: a `.cvq` file of at most a given size (`cvqpg compress --bpp`/`--max-bytes`, `cvqpg encode`).

The file never exceeds the budget, because every size is measured by encoding, never estimated. At each
rung of `RUNGS`, a search over how many primitives are kept (those of most field energy) finds the
largest model that fits. The finest rung that keeps every primitive is also filled up to the budget with
finer bit depths, one attribute at a time, since dropping primitives costs far more than coarser bits (on a
640×480 grayscale fit, dropping the weakest 8% cost 2.9 dB where one rung coarser for all cost 0.9 dB).
The candidate whose decoded render scores best among those within 5% below the budget wins (`CLOSE`; where
none is, the largest file). Fine-tuning with the quantisers in the loop (`finetune`) at
those depths starts from a few more primitives than fit (`TUNING_HEADROOM`), since tuning moves the
entropy-coded size a little either way, and a last search keeps as many of the tuned primitives as fit.
Those that set the codec's ranges are kept first, so that the file's bins stay the ones the tuning trained
on. The tuned file is kept where the same rule prefers it: it scores better when both land within 5% below
the budget, and otherwise the larger file wins.

bpp is bits per hologram pixel, 8·bytes / (W·H), all channels together, as `cvqpg info` reports it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch
from tqdm.auto import tqdm

from .codec import MAX_BITS, SUFFIX, BitDepths, bits_per_pixel, encode, range_holders
from .compression import (Choice, Reference, check_compression_settings, choice_record, compression_input,
                          compression_record, kept, reference_for, strongest_first, trial)
from .config import FitConfig
from .defaults import ENCODE_FINETUNE_STEPS, ENCODE_STEPS, RATE_FINETUNE_STEPS
from .errors import ConfigError
from .files import write_atomic
from .finetune import finetune
from .fitting import FitInterrupted, FitResult, fit_scene
from .primitives import Primitives, activate, init_gaussians
from .targets import Scene

# Fine-tuning moves a file's size by a few percent (small fits grew by 1–5%); tuning a model 4% above the
# budget leaves the last search primitives to drop where it shrinks, rather than a file well below it.
TUNING_HEADROOM = 0.04
# `cvqpg encode` fits more primitives than the budget holds at the default bit depths, so that the rate
# search can choose between coarser depths for all of them and the default depths for the strongest.
ENCODE_HEADROOM = 1.2
# The budgets tried: `compression.LADDER`'s rungs (the defaults shifted together, −3 … +6 bits), then finer ones
# up to every attribute's finest depth, so that a budget the whole model fits in at +6 still has rungs to fill it.
RUNGS = tuple(dict.fromkeys(BitDepths().shifted(delta) for delta in range(-3, MAX_BITS)))
COARSEST = RUNGS[0]
# The budget is the rate the caller asked for: the best-scoring file within 5% below it is chosen, and where
# none lands there the largest, whatever it scores (a barely fitted model's score can even rise as bits go).
CLOSE = 0.95


def encode_steps(steps: int) -> tuple[int, int]:
    """`cvqpg encode`'s float and quantisation-aware steps in the place of a fit of `steps` steps: `ENCODE_STEPS`
    and `ENCODE_FINETUNE_STEPS` for a Table 1 fit's 2000, in proportion for others (one float step at least)."""
    share = steps / FitConfig().steps
    return max(round(share * ENCODE_STEPS), 1), round(share * ENCODE_FINETUNE_STEPS)


def check_budget_values(bpp: float | None, max_bytes: int | None) -> None:
    """`ConfigError` naming the budget unless exactly one of `bpp` and `max_bytes` is given, positive and finite
    (checked before the model it applies to is read)."""
    if (bpp is None) == (max_bytes is None):
        raise ConfigError("give one budget: `bpp` or `max_bytes`")
    if bpp is not None and not (isinstance(bpp, (int, float)) and math.isfinite(bpp) and bpp > 0):
        shown = f"{bpp:g}" if isinstance(bpp, (int, float)) else repr(bpp)
        raise ConfigError(f"`bpp` {shown}: give a positive, finite number of bits per hologram pixel")
    if max_bytes is not None and not (isinstance(max_bytes, int) and not isinstance(max_bytes, bool)
                                      and max_bytes > 0):
        raise ConfigError(f"`max_bytes` {max_bytes}: give a positive whole number of bytes")


@dataclass(frozen=True)
class Budget:
    """The most bytes a file may take, and how the caller gave it (for messages)."""

    max_bytes: int
    given: str

    @classmethod
    def of(cls, config: FitConfig, bpp: float | None = None, max_bytes: int | None = None) -> "Budget":
        """The budget of `bpp` bits per hologram pixel (the file at most ⌊bpp·W·H/8⌋ bytes) or of
        `max_bytes` bytes, one of them; `ConfigError` naming it where it is not positive and finite."""
        check_budget_values(bpp, max_bytes)
        if bpp is not None:
            size = math.floor(bpp * config.width * config.height / 8)
            return cls(size, f"`bpp` {bpp:g} ({size} bytes for {config.width}×{config.height} px)")
        return cls(max_bytes, f"`max_bytes` {max_bytes}")

    def check(self, smallest: int, config: FitConfig) -> None:
        """`ConfigError` where the budget is below `smallest`, the smallest file the model can be written as."""
        if self.max_bytes < smallest:
            raise ConfigError(f"{self.given} is below the smallest file the format can write for this model: "
                              f"{smallest} bytes ({bits_per_pixel(smallest, config):.3f} bpp), its header "
                              "(optics, ranges, stream descriptors) and one primitive at the coarsest bit depths")


def smallest_file(primitives: Primitives, config: FitConfig) -> int:
    """Bytes of the smallest file rate control can write of `primitives`: the strongest alone at `COARSEST`."""
    return len(encode(kept(primitives, strongest_first(primitives), 1), config, COARSEST))


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


def _sizes(primitives: Primitives, order: torch.Tensor, config: FitConfig, bits: BitDepths) -> Callable[[int], int]:
    """The file's bytes at `bits` with the first n primitives of `order`, as a function of n."""
    return lambda count: len(encode(kept(primitives, order, count), config, bits))


def _lands_close(choice: Choice, budget: Budget) -> bool:
    return len(choice.data) >= CLOSE * budget.max_bytes


def _best(choices: list[Choice], budget: Budget) -> Choice:
    """The best-scoring of `choices` that land close to the budget; where none does, the largest."""
    close = [choice for choice in choices if _lands_close(choice, budget)]
    if not close:
        return max(choices, key=lambda choice: len(choice.data))
    return max(close, key=lambda choice: choice.psnr)


def _finer_while_fitting(primitives: Primitives, config: FitConfig, reference: Reference, budget: Budget,
                         choice: Choice, check_stop: Callable[[], None]) -> Choice:
    """`choice` of every primitive with the rest of the budget spent on finer bit depths, which a rung of
    `RUNGS` (every attribute a bit finer, about 7% of the file) overshoots: one attribute one bit finer at a
    time, the change that scores best, while the file fits and it lands short of the budget or the score
    rises. `check_stop` runs before each round of trials."""
    while True:
        check_stop()
        finer = [bits for bits in (choice.bits.shifted_one(name, 1) for name in choice.bits.names())
                 if bits is not None and len(encode(primitives, config, bits)) <= budget.max_bytes]
        if not finer:
            return choice
        candidate = _best([trial(primitives, config, bits, reference) for bits in finer], budget)
        if _lands_close(choice, budget) and candidate.psnr <= choice.psnr:
            return choice
        choice = candidate


@dataclass
class RateChoice:
    """The file rate control chose (`choice`: bytes, bit depths, decoded primitives, PSNR), the fine-tuning
    steps it ran and whether their file was kept."""

    choice: Choice
    finetune_steps: int
    finetune_kept: bool

    def record(self, budget: Budget) -> dict[str, Any]:
        """The budget and the fine-tuning, as the records of `compress_to_budget` and `encoding_record` hold them."""
        return {"max_bytes": budget.max_bytes, "finetune_steps": self.finetune_steps,
                "finetune_kept": self.finetune_kept}


def rate_control(primitives: Primitives, config: FitConfig, reference: Reference, budget: Budget,
                 scene: Scene | None = None, finetune_steps: int = 0, progress: bool = False,
                 stop_requested: Callable[[], bool] | None = None) -> RateChoice:
    """The best-scoring `.cvq` file of `primitives` within `budget` (see the module docstring), fine-tuned
    for `finetune_steps` on `scene`'s targets where a scene is given. `ConfigError` where the budget is
    below `smallest_file`. A progress bar (`progress`) shows the rate (bpp) and PSNR (dB) of each rung and,
    while fine-tuning, the PSNR of the quantised render. When `stop_requested()` turns true it stops before
    its next rung or tuning step with `FitInterrupted` (after the fit of `primitives`, whose checkpoint the
    caller keeps)."""
    budget.check(smallest_file(primitives, config), config)

    def check_stop() -> None:
        if stop_requested is not None and stop_requested():
            raise FitInterrupted(config.steps + 1, during="rate control")

    steps = finetune_steps if scene is not None else 0
    order = strongest_first(primitives)
    with tqdm(total=len(RUNGS) + steps, disable=not progress, desc="rate", unit="step", dynamic_ncols=True) as bar:

        def show(choice: Choice, psnr: float | None = None) -> None:
            bar.set_postfix(bpp=f"{bits_per_pixel(len(choice.data), config):.3f}",
                            psnr=f"{choice.psnr if psnr is None else psnr:.2f}dB", refresh=False)

        rungs = []
        for bits in RUNGS:
            check_stop()
            count = largest_fitting(_sizes(primitives, order, config, bits), budget.max_bytes, primitives.count)
            if count:
                rungs.append(trial(kept(primitives, order, count), config, bits, reference))
                show(rungs[-1])
            bar.update()
        whole = [choice for choice in rungs if choice.decoded.count == primitives.count]
        if whole:  # the finest rung that keeps every primitive, filled up to the budget
            rungs.append(_finer_while_fitting(primitives, config, reference, budget,
                                              max(whole, key=lambda choice: len(choice.data)), check_stop))
        best = _best(rungs, budget)
        show(best)
        if not steps:
            return RateChoice(best, 0, False)

        def tuning(_step: int, psnr: float) -> None:
            show(best, psnr)
            bar.update()
            check_stop()

        start = largest_fitting(_sizes(primitives, order, config, best.bits),
                                math.floor(budget.max_bytes * (1 + TUNING_HEADROOM)), primitives.count)
        tuned = finetune(kept(primitives, order, start), config, scene, best.bits, steps, on_step=tuning)
        tuned_order = strongest_first(tuned, first=range_holders(tuned))
        count = largest_fitting(_sizes(tuned, tuned_order, config, best.bits), budget.max_bytes, tuned.count)
        candidate = trial(kept(tuned, tuned_order, count), config, best.bits, reference) if count else best
        paid = _best([best, candidate], budget) is not best
        show(candidate if paid else best)
        return RateChoice(candidate if paid else best, steps, paid)


def compress_to_budget(target: str | Path, out: str | Path | None = None, bpp: float | None = None,
                       max_bytes: int | None = None, finetune_steps: int | None = None, progress: bool = False
                       ) -> dict[str, Any]:
    """Compress a run folder's model or a model file into a `.cvq` file (atomically) of at most `bpp` bits
    per hologram pixel or `max_bytes` bytes, and report it (`compression.compression_record`, with the
    budget). `finetune_steps` defaults to `RATE_FINETUNE_STEPS` in a run folder and to 0 for a model file
    outside one, which has no targets to tune on (scored against its own reconstruction)."""
    if finetune_steps is not None:
        check_compression_settings(None, finetune_steps, 0.0)
    given = compression_input(target, finetune_steps or 0)
    budget = Budget.of(given.config, bpp, max_bytes)
    steps = finetune_steps if finetune_steps is not None else RATE_FINETUNE_STEPS if given.scene is not None else 0
    out = Path(out) if out is not None else given.model_file.with_suffix(SUFFIX)
    started = time.perf_counter()
    reference = reference_for(given.primitives, given.config, None if given.scene is None else given.scene.targets)
    chosen = rate_control(given.primitives, given.config, reference, budget, given.scene, steps, progress)
    seconds = time.perf_counter() - started
    write_atomic(out, chosen.choice.data)
    return compression_record(given, out, chosen.choice, reference, seconds, **chosen.record(budget))


def stand_in(config: FitConfig, count: int, seed: int = 0) -> Primitives:
    """`count` random primitives of the fit's shape, coded about as a fitted model is: the initialisation's
    positions, scales and amplitudes, with phases and curvatures spread over their whole range (a fit
    starts them at 0, which would code in almost no bits)."""
    raw = init_gaussians(count, config.channels, config.width, config.height, seed,
                         per_channel_curvature=config.curvature == "per-channel")
    generator = torch.Generator().manual_seed(seed)
    raw.phase.uniform_(0, 2 * math.pi, generator=generator)
    raw.curvature.uniform_(-1, 1, generator=generator)
    return activate(raw, config)


def encode_budget(config: FitConfig, bpp: float | None = None, max_bytes: int | None = None) -> Budget:
    """The budget of a fit of `config` to be encoded (`encode_scene`), checked before any fitting: positive,
    finite, and not below the smallest file of a model of its shape (`stand_in`, `smallest_file`)."""
    budget = Budget.of(config, bpp, max_bytes)
    budget.check(smallest_file(stand_in(config, 1), config), config)
    return budget


def primitives_for_budget(config: FitConfig, max_bytes: int) -> int:
    """How many primitives to fit for a file of `max_bytes` bytes: `ENCODE_HEADROOM` times the count whose
    file at the default bit depths takes the budget, from the header's bytes and the bytes per primitive
    measured on `stand_in` models; 1 at least, W·H at most."""
    header = len(encode(stand_in(config, 1), config, BitDepths()))
    count = max(config.primitive_count, 2)
    # Positions cost fewer bits the denser the primitives (Morton gaps): measured again at the first estimate
    for _ in range(2):
        per_primitive = (len(encode(stand_in(config, count), config, BitDepths())) - header) / (count - 1)
        count = min(max(round((max_bytes - header) / per_primitive), 2), config.width * config.height)
    return min(max(round(count * ENCODE_HEADROOM), 1), config.width * config.height)


def encode_config(config: FitConfig, budget: Budget) -> FitConfig:
    """`config` with the primitive count that `primitives_for_budget` picks for `budget`: the fit `cvqpg encode`
    runs."""
    return config.replace(num_gaussians=primitives_for_budget(config, budget.max_bytes)).validate()


@dataclass
class Encoding:
    """What `encode_fitted` made: the fit (its settings name the primitives fitted), the file chosen, and the
    wall and process CPU seconds of rate control and fine-tuning."""

    fit: FitResult
    reference: Reference
    rate: RateChoice
    rate_seconds: float
    rate_cpu_seconds: float

    @property
    def seconds(self) -> float:
        """Encoding time (s): the fit's loop, over every segment of a resumed fit, and rate control."""
        return self.fit.seconds + self.rate_seconds

    @property
    def cpu_seconds(self) -> float | None:
        """The process's CPU time (s, all threads) over `seconds`; None where a segment of the fit went unmeasured."""
        return None if self.fit.cpu_seconds is None else self.fit.cpu_seconds + self.rate_cpu_seconds


def encode_fitted(fitted: FitResult, scene: Scene, budget: Budget, finetune_steps: int = ENCODE_FINETUNE_STEPS,
                  progress: bool = False, stop_requested: Callable[[], bool] | None = None) -> Encoding:
    """Rate-control a fit of `scene` (of `encode_config`'s settings) into a file within `budget`, fine-tuned for
    `finetune_steps` on the scene's targets; a progress bar (`progress`) shows the search's bpp and PSNR. A stop
    request (`stop_requested()` true) ends it between two rungs or tuning steps with `fitting.FitInterrupted`."""
    check_compression_settings(None, finetune_steps, 0.0)
    started, cpu_started = time.perf_counter(), time.process_time()
    primitives = fitted.primitives  # activated once: `FitResult.primitives` activates on every access
    reference = reference_for(primitives, fitted.config, scene.targets, "the scene's targets")
    rate = rate_control(primitives, fitted.config, reference, budget, scene, finetune_steps, progress,
                        stop_requested)
    return Encoding(fitted, reference, rate, time.perf_counter() - started, time.process_time() - cpu_started)


def encode_scene(scene: Scene, config: FitConfig, budget: Budget, finetune_steps: int = ENCODE_FINETUNE_STEPS,
                 progress: bool = False, stop_requested: Callable[[], bool] | None = None) -> Encoding:
    """Fit `scene` with `encode_config`'s primitive count (replacing `config`'s) for `config.steps` (`cvqpg encode`
    fits for `ENCODE_STEPS`) and `encode_fitted` the model into a file within `budget` (`encode_budget`).
    Progress bars (`progress`) show the fit's PSNR, then the rate search's bpp and PSNR. When
    `stop_requested()` turns true the fit or the rate control stops between two steps (`fitting.FitInterrupted`);
    `app.runner.encode_in_folder` runs the same with checkpoints."""
    check_compression_settings(None, finetune_steps, 0.0)
    fitted = fit_scene(scene, encode_config(config, budget), progress=progress, stop_requested=stop_requested)
    return encode_fitted(fitted, scene, budget, finetune_steps, progress, stop_requested)


def encoding_record(encoded: Encoding, out: str | Path, budget: Budget) -> dict[str, Any]:
    """What `cvqpg encode` reports of its file (`compression.choice_record`, the budget, the fine-tuning) and
    of the fit: the primitives it fitted and its seconds."""
    return {"file": str(out), **choice_record(encoded.rate.choice, encoded.reference, encoded.fit.config),
            **encoded.rate.record(budget), "fitted_primitives": encoded.fit.config.primitive_count,
            "fit_seconds": encoded.fit.seconds, "fit_cpu_seconds": encoded.fit.cpu_seconds}
