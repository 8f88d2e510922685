"""Fitting: the optimisation loop of method.md §6 and rendering of a fitted model.

A library call here computes and returns: it compiles nothing ahead, prints nothing but its
progress bar, and measures no memory; the command line (`cvqpg.app`) does those around it."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import torch
from PIL import Image
from torch import Tensor
from tqdm.auto import tqdm

from .config import FitConfig, RunOptions, padded_size
from .control import RunControl
from .errors import InputError, ModelFileError
from .metrics import MetricReport, evaluate
from .ops.loss import multiplane_loss, noisy_targets, standard_normal
from .optics import reconstruct
from .primitives import Gaussians, Primitives, TensorFields
from .representation import param_groups, representation
from .targets import Scene, load_scene

if TYPE_CHECKING:
    from pytorch_optimizer import Adan

    from .ratefit import RateObjective


@dataclass
class FitResult:
    """A fitted model with its settings, final metrics and per-step history."""

    gaussians: Gaussians | TensorFields  # the raw parameters of the configuration's representation
    config: FitConfig
    metrics: MetricReport
    hologram: Tensor  # [C, H, W] complex, of the fitted model
    reconstructions: Tensor  # [M, C, H, W] clamped intensities the metrics were taken on
    history: dict[str, list[float]] = field(default_factory=dict)
    seconds: float = 0.0
    skipped_steps: int = 0
    sanitised_steps: int = 0
    peak_memory: dict[str, Any] = field(default_factory=dict)  # what the caller noted in the state (FitState)
    compile_seconds: float = 0.0  # what the caller noted: kernel compilation outside `seconds`
    cpu_seconds: float | None = None  # the process's CPU time over `seconds` (FitState.cpu_seconds)
    run: RunOptions = field(default_factory=RunOptions)  # where it was fitted

    @property
    def primitives(self) -> Primitives | TensorFields:
        """The fitted model's activated, physical parameters (what a model file stores)."""
        return representation(self.config).activate(self.gaussians, self.config)


def hologram(primitives: Primitives | TensorFields, config: FitConfig, backend: str = "auto") -> Tensor:
    """Complex hologram [C, H, W] of a model's physical parameters (`representation`) on `config`'s W×H SLM grid,
    with the kernels of `backend` (`config.resolve_backend`) on the parameters' device."""
    return representation(config).field(primitives, config, backend)


def render_hologram(gaussians: Gaussians | TensorFields, config: FitConfig, backend: str = "auto") -> Tensor:
    """Complex hologram [C, H, W] of raw parameters under `config` (differentiable)."""
    return hologram(representation(config).activate(gaussians, config), config, backend)


def render(primitives: Primitives | TensorFields, config: FitConfig, distances_m: Sequence[float] | None = None,
           backend: str = "auto") -> tuple[Tensor, Tensor]:
    """Hologram [C, H, W] and clamped reconstructions [M, C, H, W] at `config`'s planes (or at
    `distances_m`, m), without gradients, with the kernels of `backend`."""
    with torch.no_grad():
        field = hologram(primitives, config, backend)
        return field, reconstruct(field, config, distances_m, backend)


def trainable_groups(config: FitConfig) -> tuple[str, ...]:
    """The learning rates of the parameter groups the optimiser owns (`representation.param_groups`): the flat
    primitive has no curvature, a per-pixel hologram an amplitude and a phase or the phase alone."""
    return tuple(representation(config).groups(config).values())


def make_optimizer(gaussians: Gaussians | TensorFields, config: FitConfig) -> Adan | torch.optim.Adam:
    """The optimiser of `optimisation.optimizer` with one group per parameter kind and its learning rate (method.md
    §6): Adan (pytorch-optimizer) with `betas`, or torch's Adam with `betas`' first two, both without weight decay.
    Adam keeps its step count on the parameters' device (`capturable` on CUDA), where an undone update restores
    it (`apply_gradients`)."""
    settings = config.optimisation
    groups = param_groups(gaussians, config)
    if settings.optimizer == "adam":
        device = groups[0]["params"][0].device
        return torch.optim.Adam(groups, betas=settings.betas[:2], eps=settings.adan_eps,
                                capturable=device.type == "cuda")
    # Imported here: pytorch-optimizer imports transformers where it is installed (a second or more),
    # which the first run's compile processes, importing this module, do not need.
    from pytorch_optimizer import Adan

    return Adan(groups, betas=settings.betas, eps=settings.adan_eps, weight_decay=0.0, max_grad_norm=0.0)


def position_learning_rate(step: int, config: FitConfig) -> float:
    """Cosine annealing from `lr.position` to `lr.position_final` over the run's `steps + 1` updates."""
    progress = step / (config.optimisation.steps + 1)
    lr = config.optimisation.lr
    return lr.position_final + (lr.position - lr.position_final) * (1 + math.cos(math.pi * progress)) / 2


def psnr_from_mse(mse: Tensor) -> Tensor:
    """Mean over planes of −10·log10(MSE) (dB), data range 1, as a 0-dim tensor on MSE's device."""
    return (-10 * torch.log10(mse.clamp(min=1e-12))).mean()


@dataclass
class FitState:
    """Everything the loop carries between steps; a checkpoint stores exactly this."""

    gaussians: Gaussians | TensorFields  # the raw parameters of the configuration's representation
    optimizer: Adan
    generator: torch.Generator
    step: int = 0  # the next step index to run
    history: dict[str, list[float]] = field(default_factory=lambda: {"loss": [], "psnr": []})
    seconds: float = 0.0
    # The process's CPU seconds (all its threads) over the same spans as `seconds`: beside them they show how
    # much of the cores a fit had. None once a segment went unmeasured (a checkpoint of a version without them).
    cpu_seconds: float | None = 0.0
    skipped_steps: int = 0
    sanitised_steps: int = 0
    # Noted by the caller, kept in checkpoints: the largest peak memory of the segments run so far (a
    # resumed fit runs in several), and kernel compilation before their first steps, outside `seconds`.
    peak_memory: dict[str, Any] = field(default_factory=dict)
    compile_seconds: float = 0.0

    def note_peak_memory(self, peak: dict[str, Any]) -> None:
        """Keep the larger of the recorded peak and `peak` (`{"peak_memory_bytes": ..., ...}`)."""
        self.peak_memory = max(self.peak_memory, peak, key=lambda p: p.get("peak_memory_bytes", -1))

    def settle(self, outcomes: list[StepOutcome]) -> list[tuple[float, float]]:
        """Read queued steps back in one transfer: append their loss and PSNR to the history and count
        the skipped and sanitised ones; returns (loss, PSNR) per step.

        A skipped step's tensors were restored on the device; what Adan keeps on the host is rolled
        back here: its step counter (bias correction) and, for the latest step only, the moments it
        created for a parameter on its first update. When the loop reads back after every step (the
        CPU) a skipped step thus leaves the optimiser exactly as it was; on CUDA the steps queued
        after a skip until the next read use a counter one too high, and moments that a skipped
        first update created stay.
        """
        if not outcomes:
            return []
        values = torch.stack([torch.stack([o.loss.double(), o.psnr.double(), o.skipped.double(),
                                           o.sanitised.double()]) for o in outcomes]).tolist()
        for outcome, (loss, psnr, skipped, sanitised) in zip(outcomes, values):
            self.history["loss"].append(loss)
            self.history["psnr"].append(psnr)
            self.skipped_steps += int(skipped)
            self.sanitised_steps += int(sanitised)
            if skipped:
                for group in self.optimizer.param_groups:
                    if "step" in group:  # Adan counts on the host; Adam's count, on the device, was restored
                        group["step"] -= 1
        if values[-1][2]:
            for parameter in outcomes[-1].fresh_state:
                self.optimizer.state.pop(parameter, None)
        return [(loss, psnr) for loss, psnr, _, _ in values]

    def to_payload(self) -> dict:
        """Plain tensors and numbers, for `torch.save`."""
        return {"gaussians": {k: v.detach().cpu() for k, v in self.gaussians.tensors().items()},
                "optimizer": self.optimizer.state_dict(), "generator": self.generator.get_state(),
                "step": self.step, "history": self.history, "seconds": self.seconds, "cpu_seconds": self.cpu_seconds,
                "skipped_steps": self.skipped_steps, "sanitised_steps": self.sanitised_steps,
                "peak_memory": self.peak_memory, "compile_seconds": self.compile_seconds,
                "device": self.generator.device.type}


def initial_state(config: FitConfig, scene: Scene | None = None, run: RunOptions = RunOptions()) -> FitState:
    """The state on `run.device` before step 0: the initialisation of `config.optimisation.init`
    (`representation.initial`; those drawn from the targets need the `scene`), the optimiser and the noise
    generator."""
    device = torch.device(run.device)
    gaussians = representation(config).initial(config, scene, run.device)
    for name in representation(config).groups(config):
        gaussians.parameter(name).requires_grad_(True)
    optimizer = make_optimizer(gaussians, config)
    generator = torch.Generator(device=device).manual_seed(config.optimisation.seed)
    return FitState(gaussians, optimizer, generator)


def blank_state(config: FitConfig, run: RunOptions = RunOptions()) -> FitState:
    """A state of `config`'s shapes whose values do not matter (a checkpoint overwrites them): the paper's
    initialisation, which needs no scene."""
    return initial_state(config.replace(init="uniform"), run=run)


def state_from_payload(payload: dict, config: FitConfig, run: RunOptions = RunOptions(),
                       name: str = "the checkpoint") -> FitState:
    """Inverse of `FitState.to_payload` on `run.device`. A checkpoint (`name` in messages) from another
    device type is refused (`ModelFileError`): CPU and CUDA noise generators have different states; so is
    one whose primitives have other shapes than `config` gives them."""
    written_on = payload.get("device", "cpu")
    if written_on != torch.device(run.device).type:
        raise ModelFileError(f"{name} was written on {written_on}, this run is on {run.device}: "
                             f"resume it with `device` {written_on}, or delete the checkpoint to restart from "
                             "step 0")
    state = blank_state(config, run)
    with torch.no_grad():
        for key, tensor in state.gaussians.tensors().items():
            stored = payload["gaussians"][key]
            if stored.shape != tensor.shape:
                raise ModelFileError(f"{name} belongs to another run (its {key} has shape {tuple(stored.shape)}, "
                                     f"this run's {tuple(tensor.shape)}): delete it to restart from step 0")
            tensor.copy_(stored)
    state.optimizer.load_state_dict(payload["optimizer"])
    state.generator.set_state(payload["generator"])
    state.step, state.history, state.seconds = payload["step"], payload["history"], payload["seconds"]
    state.cpu_seconds = payload.get("cpu_seconds")
    state.skipped_steps, state.sanitised_steps = payload["skipped_steps"], payload["sanitised_steps"]
    state.peak_memory = payload.get("peak_memory", {})
    state.compile_seconds = payload.get("compile_seconds", 0.0)
    return state


def hologram_loss(field: Tensor, scene: Scene, config: FitConfig, generator: torch.Generator,
                  backend: str = "auto") -> tuple[Tensor, Tensor]:
    """method.md §6's training loss of a complex hologram [C, H, W]: propagated to the scene's planes and
    compared with its targets under fresh noise drawn from `generator`; returns it and the plain MSE. Where
    both terms that see the noisy targets weigh 0, no noise is drawn: it would enter nothing."""
    loss = config.loss
    weights = (loss.focus_weight, loss.product_weight)
    noisy = scene.targets
    if any(weights):
        noise = standard_normal(scene.targets.shape, generator, backend)
        noisy = noisy_targets(scene.targets, noise, loss.target_noise)
    return multiplane_loss(reconstruct(field, config, backend=backend), scene.targets, scene.masks, noisy,
                           loss.ssim_weight, backend, *weights)


@dataclass
class StepOutcome:
    """One update's numbers, left on the device until the loop reads them back (`FitState.settle`)."""

    step: int
    loss: Tensor  # 0-dim
    psnr: Tensor  # 0-dim, dB: the progress PSNR, mean over planes
    skipped: Tensor  # 0-dim bool: the update was undone
    sanitised: Tensor  # 0-dim bool: some gradient entries were replaced by 0
    fresh_state: tuple[Tensor, ...] = ()  # parameters whose optimiser state this update created


def update(state: FitState, scene: Scene, config: FitConfig, backend: str = "auto",
           objective: RateObjective | None = None) -> StepOutcome:
    """One update of method.md §6: render, propagate, loss, sanitise and clip gradients, Adan, without
    reading anything back to the host (on CUDA the step is queued, not waited for). With an `objective`
    (`ratefit.RateObjective`), the primitives render as it gives them and its rate term adds to the loss (the
    rate model runs on the host, so that such a step waits for the device); its λ enters the history
    (`rate_lambda`).

    A step whose loss is not finite, or whose update would leave a parameter non-finite, is undone
    on the device (`apply_gradients`); `FitState.settle` counts it and rolls back what Adan keeps on
    the host.
    """
    gaussians, step = state.gaussians, state.step
    representation(config).before_update(gaussians, config, step)
    if objective is None:
        loss, mse = hologram_loss(render_hologram(gaussians, config, backend), scene, config, state.generator,
                                  backend)
    else:
        shown, term = objective.step(representation(config).activate(gaussians, config), step,
                                     config.optimisation.steps, state.generator)
        loss, mse = hologram_loss(hologram(shown, config, backend), scene, config, state.generator, backend)
        if term is not None:
            loss = loss + term
        state.history.setdefault("rate_lambda", []).append(objective.weight)
        state.history.setdefault("rate_bytes", []).append(objective.last_bytes)
    optimizer = state.optimizer
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    fresh = tuple(p for group in optimizer.param_groups for p in group["params"]
                  if p.grad is not None and p not in optimizer.state)
    loss = loss.detach()
    sanitised, skipped = apply_gradients(optimizer, config, step, torch.isfinite(loss))
    return StepOutcome(step, loss, psnr_from_mse(mse), skipped, sanitised, fresh)


def optimisation_step(state: FitState, scene: Scene, config: FitConfig, backend: str = "auto"
                      ) -> tuple[float, float]:
    """`update`, read back at once: the loss and the progress PSNR (dB); counts a skipped or sanitised
    step in `state`. `state.step` is left to the caller."""
    return state.settle([update(state, scene, config, backend)])[0]


def all_finite(tensors: list[Tensor]) -> Tensor:
    """Whether every entry of every tensor is finite, as a 0-dim bool tensor (no host read)."""
    return torch.stack([torch.isfinite(t).all() for t in tensors]).all()


def surely_false(flag: Tensor) -> bool:
    """Whether a 0-dim bool `flag` is known to be false without waiting for a device: read where that
    costs nothing (the CPU), else never known. Lets the CPU skip work that the flag makes a no-op."""
    return flag.device.type == "cpu" and not bool(flag)


def apply_gradients(optimizer: Adan, config: FitConfig, step: int, finite_loss: Tensor | None = None
                    ) -> tuple[Tensor, Tensor]:
    """Non-finite gradient entries → 0 (method.md §6), clip to the global norm, anneal position, Adan.

    The update is undone, parameters and Adan's moments alike, where `finite_loss` is false or a
    parameter came out non-finite: they are copied into one buffer before it and put back with
    `torch.where`, so the choice is made on the device and nothing waits for it. Returns the flags
    (sanitised: some gradient entry was replaced, on a step whose loss was finite; skipped: the update
    was undone) as 0-dim bool tensors.
    """
    params = [p for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
    grads = [p.grad for p in params]
    finite_grads = all_finite(grads)
    if not surely_false(~finite_grads):
        for grad in grads:
            torch.nan_to_num_(grad, nan=0.0, posinf=0.0, neginf=0.0)
    torch.nn.utils.clip_grad_norm_(params, config.optimisation.grad_clip_norm)
    for group in optimizer.param_groups:
        if group["name"] == "position":
            group["lr"] = position_learning_rate(step, config)
    kept = params + [t for p in params for t in optimizer.state.get(p, {}).values() if isinstance(t, Tensor)]
    before = torch.cat([t.detach().reshape(-1) for t in kept])
    optimizer.step()
    finite_loss = finite_grads.new_ones(()) if finite_loss is None else finite_loss
    skipped = ~(finite_loss & all_finite(params))
    if not surely_false(skipped):
        with torch.no_grad():
            for tensor, previous in zip(kept, before.split([t.numel() for t in kept])):
                torch.where(skipped, previous.view_as(tensor), tensor, out=tensor)
    return finite_loss & ~finite_grads, skipped


PROBE_STEPS = 12


def seconds_per_step(scene: Scene, config: FitConfig, run: RunOptions = RunOptions(),
                     probe_steps: int = PROBE_STEPS) -> float:
    """Seconds one update of a fit of `config` takes here on `run`, timed over `probe_steps` updates of a
    throwaway state after one untimed update (first-call costs), past the warm-ups of the phase terms, where most
    steps are."""
    scene = scene.to(run.device)
    state = initial_state(config, scene, run)
    first = max(config.optimisation.curvature_warmup, config.terms_warmup)
    for step in range(first, first + probe_steps + 1):
        if step == first + 1:
            start = time.perf_counter()
        state.step = step
        optimisation_step(state, scene, config, run.backend)
    return (time.perf_counter() - start) / probe_steps


def steps_within(seconds: float, seconds_each: float) -> int:
    """The step count of a run whose `steps + 1` updates of `seconds_each` s fit into `seconds` s (≥ 1)."""
    return max(1, int(seconds / seconds_each) - 1)


READBACK_SECONDS = 0.5


def readback_due(device: torch.device, seconds_since_readback: float) -> bool:
    """Whether the loop reads the queued steps back now: after every step on the CPU, where a read
    costs nothing and keeps Adan's host-side state exact after a skipped step (`FitState.settle`);
    on CUDA every `READBACK_SECONDS`, as each read waits for the GPU to finish its queue."""
    return device.type == "cpu" or seconds_since_readback >= READBACK_SECONDS


@dataclass(frozen=True)
class PeakMemoryModel:
    """A fit's peak memory as a fixed base plus a cost per pixel of every plane and channel."""

    base_bytes: int
    bytes_per_plane_pixel: int


# Each set above the peaks measured from 640×480 to 3840×2160 (docs/performance.md): the process's RSS
# on the CPU ("Display resolutions"), torch.cuda.max_memory_allocated on an H200 ("Whole fits on the H200").
PEAK_MEMORY = {"cpu": PeakMemoryModel(base_bytes=2**30, bytes_per_plane_pixel=165),
               "cuda": PeakMemoryModel(base_bytes=2**29, bytes_per_plane_pixel=256)}


# The measured sizes pad to at most this many times their pixels (a 144 px guard band at 640×480: 2.3); a wider
# guard band (a size of a few px, or a band that a config.json asks for) costs its padded pixels at that share.
PADDED_PIXELS_PER_PIXEL = 4


def estimated_peak_bytes(config: FitConfig, device: str = "cpu", size: tuple[int, int] | None = None,
                         planes: int | None = None) -> int:
    """Rough peak memory (bytes) of a fit of `config` on `device`, or of a render of its model at `size` (W, H)
    px to `planes` planes (default: the config's): its RSS on the CPU, its allocated memory on a GPU
    (`PEAK_MEMORY`), counting the guard band's padded pixels where they dominate (`PADDED_PIXELS_PER_PIXEL`)."""
    model = PEAK_MEMORY[torch.device(device).type]
    width, height = size or (config.targets.width, config.targets.height)
    optics = config.optics
    padded = (padded_size(width, optics.guard_band_px, optics.pad_multiple_px)
              * padded_size(height, optics.guard_band_px, optics.pad_multiple_px))
    pixels = max(width * height, padded // PADDED_PIXELS_PER_PIXEL)
    count = config.targets.num_planes if planes is None else planes
    return int(model.base_bytes + model.bytes_per_plane_pixel * count * config.channels * pixels)


@dataclass(frozen=True)
class CheckpointPolicy:
    """When to hand the loop state to `save`: every `every_steps` steps (if set), else every
    `every_seconds` of work (if set); always when the loop is asked to stop."""

    save: Callable[[FitState], None]
    every_steps: int | None = None
    every_seconds: float | None = 180.0

    def due(self, steps_done: int, seconds_since_save: float) -> bool:
        if self.every_steps is not None:
            return steps_done % self.every_steps == 0
        return self.every_seconds is not None and seconds_since_save >= self.every_seconds


class FitInterrupted(Exception):
    """The loop stopped on request after saving a checkpoint at `step`; `during` names the work after the loop
    that stopped instead (rate control, say), whose checkpoint is then the finished fit's."""

    def __init__(self, step: int, during: str | None = None):
        super().__init__(f"stopped before step {step}" if during is None
                         else f"stopped during {during}, after the fit's last step")
        self.step = step


def fit(image: str | Path | Image.Image | Tensor, depth: str | Path | Image.Image | Tensor | None = None,
        config: FitConfig | None = None, run: RunOptions = RunOptions(), control: RunControl = RunControl()
        ) -> FitResult:
    """Fit an image (file, PIL image or [C, H, W] tensor) and its depth map; see `fit_scene`."""
    config = FitConfig.create() if config is None else config
    return fit_scene(load_scene(image, depth, config), config, run, control)


def fit_scene(scene: Scene, config: FitConfig | None = None, run: RunOptions = RunOptions(),
              control: RunControl = RunControl(), state: FitState | None = None,
              checkpoint: CheckpointPolicy | None = None, objective: RateObjective | None = None) -> FitResult:
    """Fit N primitives to a scene's targets on `run` (device and kernels); returns the fitted model and its
    final metrics. `config` defaults to `FitConfig.create()` (the default recipe).

    Runs the reference loop's `steps + 1` updates (indices 0..steps); curvature is frozen at γ = 0 for the
    first `optimisation.curvature_warmup` of them. Pass a `state` (from a checkpoint) to continue a run: the
    result is bit-identical to an uninterrupted one on CPU. `control` shows the progress bar, asks to stop
    (the loop then saves a checkpoint between two steps and raises `FitInterrupted`) and hears of each step.
    The CPU kernels compile on their first call (Numba caches them on disk); `cvqpg.app.compilation`
    compiles them ahead with a status line.

    The steps run without host synchronisations; the loop reads their losses back (`readback_due`:
    after every step on the CPU, every `READBACK_SECONDS` on CUDA, and before a checkpoint and at
    the end), and reports each step to `control` as it reads it back. An `objective` (`ratefit.RateObjective`)
    puts the file's quantisers and rate in the loss (`update`); a resumed fit takes up its λ where it was.
    """
    config = (FitConfig.create() if config is None else config).validate()
    run.validate()
    steps = config.optimisation.steps
    expected = (config.targets.num_planes, config.channels, config.targets.height, config.targets.width)
    if tuple(scene.targets.shape) != expected:
        raise InputError(f"the scene's targets are {tuple(scene.targets.shape)} (planes, channels, height, width) "
                         f"but the configuration fits {expected}; build the scene with the same configuration")
    device = torch.device(run.device)
    scene = scene.to(device)
    state = state or initial_state(config, scene, run)
    if objective is not None and state.history.get("rate_lambda"):
        objective.resume(state.history["rate_lambda"][-1])
    last_save, clock, cpu_clock = time.perf_counter(), time.perf_counter(), time.process_time()
    bar = tqdm(range(state.step, steps + 1), initial=state.step, total=steps + 1, disable=not control.progress,
               desc=f"fit {config.primitives.kind}", unit="step", dynamic_ncols=True)
    pending: list[StepOutcome] = []

    def read_back() -> None:
        nonlocal clock, cpu_clock
        for outcome, (loss, psnr) in zip(pending, state.settle(pending)):
            control.report(outcome.step, loss, psnr)
        if pending:
            bar.set_postfix(loss=f"{state.history['loss'][-1]:.4f}", psnr=f"{state.history['psnr'][-1]:.2f}dB",
                            refresh=False)
        pending.clear()
        now, cpu_now = time.perf_counter(), time.process_time()
        state.seconds += now - clock
        if state.cpu_seconds is not None:
            state.cpu_seconds += cpu_now - cpu_clock
        clock, cpu_clock = now, cpu_now

    for step in bar:
        if control.should_stop():
            read_back()
            if checkpoint is not None:
                checkpoint.save(state)
            raise FitInterrupted(step)
        pending.append(update(state, scene, config, run.backend, objective))
        state.step = step + 1
        now = time.perf_counter()
        saving = checkpoint is not None and state.step <= steps and checkpoint.due(state.step, now - last_save)
        if saving or state.step > steps or readback_due(device, now - clock):
            read_back()
        if saving:
            checkpoint.save(state)
            last_save = time.perf_counter()
    fitted = state.gaussians.detached()
    hologram, recon = render(representation(config).activate(fitted, config), config, backend=run.backend)
    metrics = evaluate(recon, scene.targets)
    return FitResult(fitted, config, metrics, hologram, recon, state.history, state.seconds,
                     state.skipped_steps, state.sanitised_steps, state.peak_memory, state.compile_seconds,
                     state.cpu_seconds, run)
