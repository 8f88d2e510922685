"""A fit into a run folder, as the command line and the campaign run it: the kernels compiled ahead
with a status line, checkpoints in the folder, peak memory measured, and the run record written with
the results."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import torch

from ..config import FitConfig
from ..fitting import CheckpointPolicy, FitResult, FitState, fit_scene, initial_state, state_from_payload
from ..runs import CHECKPOINT_FILE, write_run
from ..storage import load_checkpoint, save_checkpoint
from ..targets import Scene
from .compilation import prepare_kernels
from .provenance import peak_memory, reset_peak_memory, run_record

CHECKPOINT_SECONDS = 180.0


def resumed_state(folder: Path, config: FitConfig) -> FitState | None:
    """The loop state of the folder's checkpoint for a fit of `config`, or None where it has none."""
    checkpoint = Path(folder) / CHECKPOINT_FILE
    return state_from_payload(load_checkpoint(checkpoint), config) if checkpoint.is_file() else None


def fit_in_folder(folder: Path, scene: Scene, config: FitConfig, state: FitState | None = None,
                  progress: bool = True, checkpoint_every_steps: int | None = None,
                  checkpoint_every_seconds: float | None = CHECKPOINT_SECONDS,
                  stop_requested: Callable[[], bool] | None = None) -> FitResult:
    """`fit_scene` with the folder's checkpoint policy, after compiling the CPU kernels (a status line
    when `progress`); the state records the compile time and the peak memory of every segment, so a
    resumed fit reports the whole run's. Raises `FitInterrupted` after saving on a stop request."""
    folder = Path(folder)
    device = torch.device(config.device)
    # The kernels first: a cold compile starts its second process before this one imports the optimiser.
    compile_seconds = prepare_kernels(config, show_status=progress)
    state = state or initial_state(config)
    state.compile_seconds += compile_seconds
    reset_peak_memory(device)

    def save(current: FitState) -> None:
        current.note_peak_memory(peak_memory(device))
        save_checkpoint(folder / CHECKPOINT_FILE, current.to_payload())

    policy = CheckpointPolicy(save=save, every_steps=checkpoint_every_steps, every_seconds=checkpoint_every_seconds)
    result = fit_scene(scene, config, progress=progress, state=state, checkpoint=policy,
                       stop_requested=stop_requested)
    state.note_peak_memory(peak_memory(device))
    result.peak_memory = state.peak_memory
    return result


def write_fitted_run(folder: Path, result: FitResult, scene: Scene, source: dict[str, Any]) -> Path:
    """`write_run` with the run record of this process: code, machine, times and peak memory."""
    record = run_record(torch.device(result.config.device), result.seconds, result.compile_seconds,
                        result.peak_memory)
    return write_run(folder, result, scene, source, record)
