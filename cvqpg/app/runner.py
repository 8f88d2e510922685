"""A fit into a run folder, as the command line and the campaign run it: the kernels compiled ahead
with a status line, checkpoints in the folder, peak memory measured, and the run record written with
the results. An encode (`cvqpg encode`, `app.encoding`) fits in such a folder too."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Callable

import torch

from ..config import FitConfig
from ..defaults import CHECKPOINT_SECONDS
from ..errors import ConfigError, CvqpgError, ModelFileError
from ..fitting import (CheckpointPolicy, FitResult, FitState, fit_scene, initial_state, seconds_per_step,
                       state_from_payload, steps_within)
from ..runs import CHECKPOINT_FILE, CONFIG_FILE, RESTORE_RUN, read_record, write_run
from ..storage import load_checkpoint, save_checkpoint
from ..targets import Scene
from .compilation import prepare_kernels
from .provenance import code_commit, peak_memory, reset_peak_memory, run_record

# Settings a resumed run may change: they move the last bits of a render only.
UNFINGERPRINTED = ("device", "backend")
# Settings that versions before recipes did not have, at the value those versions fitted with: left out of
# the fingerprint at that value, so that their checkpoints still resume.
LEGACY_VALUES = {"init": "uniform", "density": None}
FINGERPRINT_KEY = "run_fingerprint"


def run_fingerprint(config: FitConfig, source: dict[str, Any]) -> str:
    """What a checkpoint records of the run it belongs to: a SHA-256 of its settings (but `UNFINGERPRINTED`,
    and `LEGACY_VALUES` where they hold) and its inputs (`source`, as `config.json` records it)."""
    settings = {k: v for k, v in config.to_dict().items()
                if k not in UNFINGERPRINTED and not (k in LEGACY_VALUES and v == LEGACY_VALUES[k])}
    return hashlib.sha256(json.dumps({"config": settings, "source": source}, sort_keys=True).encode()).hexdigest()


def recorded_source(folder: Path, source: dict[str, Any] | None) -> dict[str, Any]:
    """`source`, or where None the run's inputs as the folder's `config.json` records them: as written, so
    that a path kept relative to the run folder (an estimated depth map) fingerprints the same wherever the
    folder is."""
    return read_record(Path(folder) / CONFIG_FILE, RESTORE_RUN)["source"] if source is None else source


def resumed_state(folder: Path, config: FitConfig, source: dict[str, Any] | None = None) -> FitState | None:
    """The loop state of the folder's checkpoint for a fit of `config` on `source` (default: as the folder's
    `config.json` records it), or None where it has none. `ModelFileError` where the checkpoint belongs to
    another run: another fingerprint (`run_fingerprint`), or, in one of a version that wrote none, primitives
    of other shapes; or where it is not a loop state this version wrote."""
    checkpoint = Path(folder) / CHECKPOINT_FILE
    if not checkpoint.is_file():
        return None
    payload = load_checkpoint(checkpoint)
    recorded = payload.get(FINGERPRINT_KEY) if isinstance(payload, dict) else None
    if recorded is not None and recorded != run_fingerprint(config, recorded_source(folder, source)):
        raise ModelFileError(f"{checkpoint} belongs to another run (written for other settings or inputs than "
                             f"{Path(folder) / CONFIG_FILE} records): delete it to restart from step 0")
    try:
        return state_from_payload(payload, config, str(checkpoint))
    except CvqpgError:
        raise
    except (AttributeError, KeyError, TypeError, ValueError, RuntimeError) as error:  # a payload of other content
        raise ModelFileError(f"{checkpoint} is not a loop state this version wrote ({type(error).__name__}: "
                             f"{error}): delete it to restart from step 0") from None


def fit_in_folder(folder: Path, scene: Scene, config: FitConfig, state: FitState | None = None,
                  progress: bool = True, checkpoint_every_steps: int | None = None,
                  checkpoint_every_seconds: float | None = CHECKPOINT_SECONDS,
                  stop_requested: Callable[[], bool] | None = None, source: dict[str, Any] | None = None,
                  checkpoint_at_end: bool = False) -> FitResult:
    """`fit_scene` with the folder's checkpoint policy, after compiling the CPU kernels (a status line
    when `progress`); the state records the compile time and the peak memory of every segment, so a
    resumed fit reports the whole run's, and checkpoints record the run's fingerprint (`run_fingerprint`
    of `config` and `source`, default: as the folder's `config.json` records it). Raises `FitInterrupted`
    after saving on a stop request. `checkpoint_at_end` saves the finished loop too, for work that follows the
    fit in the same folder: resumed from it, the fit returns at once with the same result."""
    folder = Path(folder)
    fingerprint = run_fingerprint(config, recorded_source(folder, source))
    device = torch.device(config.device)
    # The kernels first: a cold compile starts its second process before this one imports the optimiser.
    compile_seconds = prepare_kernels(config, show_status=progress)
    code_commit()  # cached for the run record: the commit of the code this process runs, not of a later one
    state = state or initial_state(config, scene)
    state.compile_seconds += compile_seconds
    reset_peak_memory(device)

    def save(current: FitState) -> None:
        current.note_peak_memory(peak_memory(device))
        save_checkpoint(folder / CHECKPOINT_FILE, {**current.to_payload(), FINGERPRINT_KEY: fingerprint})

    policy = CheckpointPolicy(save=save, every_steps=checkpoint_every_steps, every_seconds=checkpoint_every_seconds)
    result = fit_scene(scene, config, progress=progress, state=state, checkpoint=policy,
                       stop_requested=stop_requested)
    if checkpoint_at_end:
        save(state)
    state.note_peak_memory(peak_memory(device))
    result.peak_memory = state.peak_memory
    return result


def timed_config(scene: Scene, config: FitConfig, minutes: float, progress: bool = True) -> tuple[FitConfig, dict]:
    """`config` with the step count whose fit takes about `minutes` here (the kernels compiled first, then a
    few steps timed: `fitting.seconds_per_step`), and what a run records of the choice: the budget, the
    seconds per step, and the seconds spent compiling the kernels (the fit itself then only loads them)."""
    if not minutes > 0:
        raise ConfigError(f"`time` {minutes} min: give a positive number of minutes")
    compile_seconds = prepare_kernels(config, show_status=progress)
    seconds_each = seconds_per_step(scene, config)
    steps = steps_within(60 * minutes, seconds_each)
    return config.replace(steps=steps).validate(), {"minutes": minutes, "seconds_per_step": seconds_each,
                                                    "compile_seconds": compile_seconds}


def write_fitted_run(folder: Path, result: FitResult, scene: Scene, source: dict[str, Any]) -> Path:
    """`write_run` with the run record of this process: code, machine, times and peak memory."""
    record = run_record(torch.device(result.config.device), result.seconds, result.cpu_seconds,
                        result.compile_seconds, result.peak_memory)
    return write_run(folder, result, scene, source, record)
