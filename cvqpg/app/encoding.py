"""`cvqpg encode`: an image fitted straight into a `.cvq` file of at most a given size. The fit takes as many
primitives as the budget holds at the default depths, with headroom (`encode_config`), then rate control
(`search.rate_control`) chooses the primitives and depths of the file and fine-tunes them. In a folder
(`start_encode`, `encode_in_folder`) the fit keeps checkpoints beside its budget, so that an interrupted encode
resumes (`read_encode`). The command itself: its plan, new or resumed, checked before anything is written
(`encode_plan`, `resumed_encode_plan`), then run into its file (`encode_planned`)."""

from __future__ import annotations

import math
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import torch

from ..bitdepths import BitDepths
from ..codec import encode
from ..config import FitConfig, RunOptions
from ..control import SILENT, RunControl
from ..defaults import (BUDGET_FILE, CHECKPOINT_SECONDS, DEPTH_FILE, ENCODE_FINETUNE_STEPS, ENCODE_STEPS,
                        PARTIAL_SUFFIX, SUFFIX)
from ..errors import ConfigError, InputError, UsageError
from ..fitting import FitResult, fit_scene
from ..primitives import Primitives, activate, init_gaussians
from ..ratefit import PLAIN, RateFit, RateObjective, silent_removed
from ..representation import require_gaussians
from ..runs import read_record, read_run, start_run, write_json
from ..search import Budget, CompressionSettings, RateChoice, Reference, rate_control, reference_for, smallest_file
from ..targets import Scene
from .compression import choice_record
from .inputs import FitInputs
from .runner import fit_in_folder, resumed_state

if TYPE_CHECKING:
    from PIL import Image

# `cvqpg encode` fits more primitives than the budget holds at the default bit depths, so that the rate
# search can choose between coarser depths for all of them and the default depths for the strongest.
ENCODE_HEADROOM = 1.2


def encode_steps(steps: int) -> tuple[int, int]:
    """`cvqpg encode`'s float and quantisation-aware steps in the place of a fit of `steps` steps: `ENCODE_STEPS`
    and `ENCODE_FINETUNE_STEPS` for a Table 1 fit's 2000, in proportion for others (one float step at least)."""
    share = steps / FitConfig().optimisation.steps
    return max(round(share * ENCODE_STEPS), 1), round(share * ENCODE_FINETUNE_STEPS)


def stand_in(config: FitConfig, count: int, seed: int = 0) -> Primitives:
    """`count` random primitives of the fit's shape, coded about as a fitted model is: the initialisation's
    positions, scales and amplitudes, with phases and curvatures spread over their whole range (a fit
    starts them at 0, which would code in almost no bits)."""
    raw = init_gaussians(count, config.channels, config.targets.width, config.targets.height, seed,
                         per_channel_curvature=config.primitives.curvature == "per-channel",
                         terms=tuple(term.name for term in config.phase.extra_terms))
    generator = torch.Generator().manual_seed(seed)
    raw.phase.uniform_(0, 2 * math.pi, generator=generator)
    raw.curvature.uniform_(-1, 1, generator=generator)
    for tensor in raw.terms.values():
        tensor.uniform_(-1, 1, generator=generator)
    return activate(raw, config)


def encode_budget(config: FitConfig, settings: CompressionSettings) -> Budget:
    """The budget of `settings` for a fit of `config` to be encoded, checked before any fitting: not below the
    smallest file of a model of its shape (`stand_in`, `search.smallest_file`); a per-pixel fit is refused."""
    require_gaussians(config, "`cvqpg encode` (the .cvq codec)", "fit it with `cvqpg fit`, whose model file is the "
                      "pattern")
    budget = settings.budget(config)
    budget.check(smallest_file(stand_in(config, 1), config), config)
    return budget


def primitives_for_budget(config: FitConfig, max_bytes: int) -> int:
    """How many primitives to fit for a file of `max_bytes` bytes: `ENCODE_HEADROOM` times the count whose
    file at the default bit depths takes the budget, from the header's bytes and the bytes per primitive
    measured on `stand_in` models; 1 at least, W·H at most."""
    header = len(encode(stand_in(config, 1), config, BitDepths()))
    count = max(config.primitive_count, 2)
    pixels = config.targets.width * config.targets.height
    # Positions cost fewer bits the denser the primitives (Morton gaps): measured again at the first estimate
    for _ in range(2):
        per_primitive = (len(encode(stand_in(config, count), config, BitDepths())) - header) / (count - 1)
        count = min(max(round((max_bytes - header) / per_primitive), 2), pixels)
    return min(max(round(count * ENCODE_HEADROOM), 1), pixels)


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
    fit_levers: RateFit = PLAIN  # the rate in the fit's loss (`ratefit`), none by default

    @property
    def seconds(self) -> float:
        """Encoding time (s): the fit's loop, over every segment of a resumed fit, and rate control."""
        return self.fit.seconds + self.rate_seconds

    @property
    def cpu_seconds(self) -> float | None:
        """The process's CPU time (s, all threads) over `seconds`; None where a segment of the fit went unmeasured."""
        return None if self.fit.cpu_seconds is None else self.fit.cpu_seconds + self.rate_cpu_seconds


def encode_fitted(fitted: FitResult, scene: Scene, budget: Budget, finetune_steps: int = ENCODE_FINETUNE_STEPS,
                  control: RunControl = SILENT, fit: RateFit = PLAIN) -> Encoding:
    """Rate-control a fit of `scene` (of `encode_config`'s settings, made with `fit`'s levers) into a file within
    `budget`, fine-tuned for `finetune_steps` on the scene's targets (with the fit's rate term and last λ where it
    had one); where the fit pruned by rate, the primitives whose weight codes to 0 go first
    (`ratefit.silent_removed`). A progress bar (`control.progress`) shows the search's bpp and PSNR. A stop
    request (`control`) ends it between two rungs or tuning steps with `fitting.FitInterrupted`."""
    started, cpu_started = time.perf_counter(), time.process_time()
    primitives = fitted.primitives  # activated once: `FitResult.primitives` activates on every access
    if fit.prune:
        primitives = silent_removed(primitives, fitted.config, fit.bits)
    reference = reference_for(primitives, fitted.config, scene.targets, "the scene's targets")
    weights = fitted.history.get("rate_lambda")
    rate = rate_control(primitives, fitted.config, reference, budget, scene, finetune_steps, control,
                        fit if fit.rate else None, weights[-1] if weights else None)
    return Encoding(fitted, reference, rate, time.perf_counter() - started, time.process_time() - cpu_started, fit)


def encode_scene(scene: Scene, config: FitConfig, settings: CompressionSettings, control: RunControl = SILENT
                 ) -> Encoding:
    """Fit `scene` with `encode_config`'s primitive count (replacing `config`'s) for its steps (`cvqpg encode`
    fits for `ENCODE_STEPS`) and `encode_fitted` the model into a file within the budget of `settings`
    (`encode_budget`), fine-tuned for its `finetune_steps` (default `ENCODE_FINETUNE_STEPS`). Progress bars
    (`control.progress`) show the fit's PSNR, then the rate search's bpp and PSNR; `control.on_step` is told the
    fit's steps. A stop request (`control`) stops the fit or the rate control between two steps
    (`fitting.FitInterrupted`); `encode_in_folder` runs the same with checkpoints."""
    budget = encode_budget(config, settings)
    steps = ENCODE_FINETUNE_STEPS if settings.finetune_steps is None else settings.finetune_steps
    fit, config = settings.rate_fit(budget), encode_config(config, budget)
    fitted = fit_scene(scene, config, control=control, objective=objective_for(fit, config))
    return encode_fitted(fitted, scene, budget, steps, control, fit)


def objective_for(fit: RateFit, config: FitConfig) -> RateObjective | None:
    """The fit's rate term for `fit`'s levers (None: today's float fit)."""
    return RateObjective(fit, config) if fit.active else None


def encoding_record(encoded: Encoding, out: str | Path, budget: Budget) -> dict[str, Any]:
    """What `cvqpg encode` reports of its file (`compression.choice_record`, the budget, the fine-tuning) and
    of the fit: the primitives it fitted and its seconds."""
    return {"file": str(out), **choice_record(encoded.rate.choice, encoded.reference, encoded.fit.config),
            **encoded.rate.record(budget), "fitted_primitives": encoded.fit.config.primitive_count,
            "fit_seconds": encoded.fit.seconds, "fit_cpu_seconds": encoded.fit.cpu_seconds,
            **({"rate_fit": encoded.fit_levers.record(),
                "rate_lambda": encoded.fit.history.get("rate_lambda", [None])[-1]} if encoded.fit_levers.active
               else {})}


def start_encode(folder: Path, config: FitConfig, source: dict[str, Any], budget: Budget, finetune_steps: int,
                 run: RunOptions = RunOptions(), fit: RateFit = PLAIN) -> Path:
    """A folder for an encode of `config` (`encode_config`'s) into `budget` on `run`: a run folder
    (`runs.start_run`) that also records the budget, the fine-tuning steps and, where the fit has the rate in its
    loss, its levers (`BUDGET_FILE`)."""
    start_run(folder, config, source, run)
    write_json(Path(folder) / BUDGET_FILE, {"max_bytes": budget.max_bytes, "given": budget.given,
                                            "finetune_steps": finetune_steps,
                                            **({"rate_fit": fit.record()} if fit.active else {})})
    return Path(folder)


def encode_fit(folder: Path) -> RateFit:
    """The levers an encode's folder records for its fit (`start_encode`; none: today's float fit)."""
    recorded = read_record(Path(folder) / BUDGET_FILE, "delete the folder and encode again")
    try:
        return RateFit.from_record(recorded["rate_fit"]) if "rate_fit" in recorded else PLAIN
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{Path(folder) / BUDGET_FILE} holds a malformed `rate_fit`; delete the folder and "
                         "encode again") from None


def read_encode(folder: Path) -> tuple[FitConfig, dict[str, Any], Budget, int]:
    """What `start_encode` recorded: settings, inputs, budget and fine-tuning steps; `InputError` naming the
    folder where it holds no encode."""
    path = Path(folder) / BUDGET_FILE
    if not path.is_file():
        raise InputError(f"{folder} holds no encode (no {BUDGET_FILE}); give a folder that `cvqpg encode` left")
    config, source = read_run(folder)
    recorded = read_record(path, "delete the folder and encode again")
    try:  # checked as they enter again, as `CompressionSettings` (a `ConfigError` is a `ValueError`)
        settings = CompressionSettings(max_bytes=recorded["max_bytes"], finetune_steps=recorded["finetune_steps"])
        budget = Budget(settings.max_bytes, str(recorded["given"]))
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{path} lacks the budget or the fine-tuning steps; delete the folder and encode "
                         "again") from None
    try:  # as `encode_budget` checked it before the fit, so that a changed file stops the resume before its steps
        Budget(budget.max_bytes, f"the budget of {budget.max_bytes} bytes in {path}").check(
            smallest_file(stand_in(config, 1), config), config)
    except ConfigError as error:
        raise InputError(f"{error}; delete the folder and encode again") from None
    return config, source, budget, settings.finetune_steps


def encode_in_folder(folder: Path, scene: Scene, config: FitConfig, budget: Budget, finetune_steps: int,
                     run: RunOptions = RunOptions(), control: RunControl = SILENT,
                     checkpoint_every_steps: int | None = None,
                     checkpoint_every_seconds: float | None = CHECKPOINT_SECONDS, fit: RateFit = PLAIN) -> Encoding:
    """`encode_fitted` of a fit of `config` on `run` in `folder` (made by `start_encode`), from the folder's
    checkpoint where it has one. The fit checkpoints as `runner.fit_in_folder` (by default every
    `CHECKPOINT_SECONDS`) and at its end, and a stop request (`control`) raises `FitInterrupted`: within the fit
    after saving, within rate control with the finished fit saved, which a resume then rate-controls again. `fit`
    (`start_encode`'s, `encode_fit`) says which levers of the rate the fit pulls."""
    fitted = fit_in_folder(folder, scene, config, run, control, resumed_state(folder, config, run),
                           checkpoint_every_steps, checkpoint_every_seconds, checkpoint_at_end=True,
                           objective=objective_for(fit, config))
    return encode_fitted(fitted, scene, budget, finetune_steps, control, fit)


@dataclass
class EncodePlan:
    """What `cvqpg encode` will do: fit and encode in `work` (`OUT.partial`, from its checkpoint when
    `resumed`) into the file `out`, within `budget`."""

    work: Path
    out: Path
    config: FitConfig
    source: dict[str, Any]
    budget: Budget
    finetune_steps: int
    run: RunOptions
    scene: Scene
    resumed: bool = False
    depth: Image.Image | None = None  # an estimated depth map, saved in `work` once it exists
    role: str = "`out`"  # how messages name `out`
    fit: RateFit = PLAIN  # the rate in the fit's loss (`ratefit`; `--rate-loss`)


def resumed_encode_plan(folder: str | Path, overwrite: bool = False) -> EncodePlan:
    """The plan that continues the interrupted encode in `folder` (`FILE.partial`) with its own settings and
    budget; with `overwrite`, a file at `FILE` is replaced."""
    from ..runs import read_run_options, scene_from_source
    from .inputs import source_files
    from .outputs import CVQ, check_output
    from .resources import check_device
    work = Path(os.path.abspath(folder))  # `--resume .` names the folder too
    config, source, budget, finetune_steps = read_encode(work)
    if not work.name.endswith(PARTIAL_SUFFIX):
        raise UsageError(f"--resume {work}: an encode's folder is named after its file, FILE{PARTIAL_SUFFIX}")
    run = read_run_options(work)
    check_device(run.device)
    role = f"--resume {work}: its file"
    out = check_output(work.with_name(work.name[:-len(PARTIAL_SUFFIX)]), CVQ, source_files(source), overwrite, role)
    return EncodePlan(work, out, config, source, budget, finetune_steps, run, scene_from_source(source, config),
                      resumed=True, role=role, fit=encode_fit(work))


def stranded_encode(work: Path) -> str:
    """What lies at a new encode's work folder `FILE.partial`, which the encode does not take over, and what to do."""
    if work.is_symlink() or not work.is_dir():
        return f"{work} is in the way of the encode's work folder (not a folder); move it away"
    if not (work / BUDGET_FILE).is_file():
        return f"{work} is in the way of the encode's work folder (it holds no encode's {BUDGET_FILE}); move it away"
    return f"{work} holds an interrupted encode; continue it with cvqpg encode --resume {work}, or delete it"


def encode_plan(inputs: FitInputs, out: str | None, bpp: float | None = None, max_bytes: int | None = None,
                finetune_steps: int = ENCODE_FINETUNE_STEPS, overwrite: bool = False, rate_loss: bool = False
                ) -> EncodePlan:
    """The plan of a new encode of `inputs` into the file `out` of at most `bpp` bits per pixel or `max_bytes`
    bytes (`encode_budget`), with `encode_config`'s primitive count, in its work folder `OUT.partial`; with
    `rate_loss`, the rate in the fit's loss (`CompressionSettings.rate_fit`)."""
    from .inputs import config_and_source, scene_and_depth, source_files
    from .outputs import CVQ, check_output
    from .resources import check_device, check_memory
    if bpp is None and max_bytes is None:
        raise UsageError("one of the arguments --bpp --max-bytes is required")
    if out is None:
        raise UsageError(f"give the {SUFFIX} file to write with --out FILE")
    config, source = config_and_source(inputs)
    run = inputs.run_options()
    check_device(run.device)
    settings = CompressionSettings(bpp=bpp, max_bytes=max_bytes, finetune_steps=finetune_steps, rate_loss=rate_loss)
    budget = encode_budget(config, settings)
    checked = check_output(out, CVQ, source_files(source), overwrite)
    work = checked.with_name(checked.name + PARTIAL_SUFFIX)
    if work.exists() or work.is_symlink():
        raise UsageError(stranded_encode(work))
    config = encode_config(config, budget)
    check_memory(config, run.device)
    scene, depth = scene_and_depth(source, config)
    if depth is not None:
        source["depth"] = DEPTH_FILE  # kept in the encode's folder until the file is written
    return EncodePlan(work, checked, config, source, budget, settings.finetune_steps, run, scene, depth=depth,
                      fit=settings.rate_fit(budget))


def encode_planned(plan: EncodePlan, overwrite: bool = False, progress: bool = True
                   ) -> tuple[int, dict[str, Any] | None]:
    """Fit and encode in `plan.work` (`fitplan.resumable`) and write the file `plan.out`, then remove the work
    folder: 0 and the file's record (`encoding_record`), or the exit code of the signal that stopped it and None."""
    from ..files import write_atomic
    from .allocator import keep_freed_memory
    from .fitplan import resumable
    from .inputs import source_files
    from .outputs import CVQ, output
    records = []
    keep_freed_memory()

    def body(stop_requested: Callable[[], bool]) -> None:
        if not plan.resumed:
            start_encode(plan.work, plan.config, plan.source, plan.budget, plan.finetune_steps, plan.run, plan.fit)
        if plan.depth is not None:
            plan.depth.save(plan.work / DEPTH_FILE)
        encoded = encode_in_folder(plan.work, plan.scene, plan.config, plan.budget, plan.finetune_steps, plan.run,
                                   RunControl(progress=progress, stop_requested=stop_requested), fit=plan.fit)
        write_atomic(plan.out, encoded.rate.choice.data)
        records.append(encoding_record(encoded, plan.out, plan.budget))

    with output(plan.out, CVQ, source_files(plan.source), overwrite, plan.role):
        code = resumable(plan.work, "encode", body)
    if code:
        return code, None
    shutil.rmtree(plan.work)
    return 0, records[0]
