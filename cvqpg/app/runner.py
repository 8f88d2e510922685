"""A fit into a run folder, as the command line and the campaign run it: the kernels compiled ahead
with a status line, checkpoints in the folder, peak memory measured, and the run record written with
the results. An encode (`cvqpg encode`, `app.encoding`) fits in such a folder too."""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import Any

import torch

from ..config import FitConfig, RunOptions, check_time_budget, default_curvature_warmup
from ..control import RunControl
from ..defaults import CHECKPOINT_SECONDS
from ..errors import CvqpgError, ModelFileError
from ..fitting import (CheckpointPolicy, FitInterrupted, FitResult, FitState, fit_scene, initial_state,
                       seconds_per_step, state_from_payload, steps_within)
from ..ratefit import RateObjective
from ..runs import CHECKPOINT_FILE, CONFIG_FILE, RESTORE_RUN, fit_fingerprint, read_record, same_fit, write_run
from ..storage import load_checkpoint, save_checkpoint
from ..targets import Scene
from .compilation import prepare_kernels
from .provenance import code_commit, peak_memory, reset_peak_memory, run_record

log = logging.getLogger("cvqpg")

FINGERPRINT_KEY = "run_fingerprint"
# Checkpoints of earlier versions hold a SHA-256 of their config.json's settings (`legacy_fingerprint`): all but
# these keys, and but the settings that versions before recipes lacked where they hold those versions' values.
LEGACY_UNHASHED = ("cvqpg_version", "source", "device", "backend")
LEGACY_VALUES = {"init": "uniform", "density": None}


def legacy_fingerprint(record: dict[str, Any]) -> str:
    """The fingerprint that versions before `FINGERPRINT_SCHEMA` wrote into a checkpoint, from the `config.json`
    `record` that the same version wrote beside it."""
    settings = {k: v for k, v in record.items()
                if k not in LEGACY_UNHASHED and not (k in LEGACY_VALUES and v == LEGACY_VALUES[k])}
    return hashlib.sha256(json.dumps({"config": settings, "source": record.get("source")},
                                     sort_keys=True).encode()).hexdigest()


def belongs_to_run(recorded: object, folder: Path, config: FitConfig, source: dict[str, Any]) -> bool:
    """Whether a checkpoint's fingerprint `recorded` is that of the fit of `config` on `source` in `folder`:
    the settings it recorded read as `config` and the same inputs, or for a checkpoint of an earlier version,
    the hash of the folder's `config.json` (which must hold `config`)."""
    if isinstance(recorded, dict):
        return same_fit(recorded, fit_fingerprint(config, source))
    record = read_record(Path(folder) / CONFIG_FILE, RESTORE_RUN)
    return (isinstance(recorded, str) and recorded == legacy_fingerprint(record) and record.get("source") == source
            and FitConfig.from_dict(record) == config)


def recorded_source(folder: Path, source: dict[str, Any] | None) -> dict[str, Any]:
    """`source`, or where None the run's inputs as the folder's `config.json` records them: as written, so
    that a path kept relative to the run folder (an estimated depth map) fingerprints the same wherever the
    folder is."""
    return read_record(Path(folder) / CONFIG_FILE, RESTORE_RUN)["source"] if source is None else source


def resumed_state(folder: Path, config: FitConfig, run: RunOptions = RunOptions(),
                  source: dict[str, Any] | None = None) -> FitState | None:
    """The loop state on `run` of the folder's checkpoint for a fit of `config` on `source` (default: as the
    folder's `config.json` records it), or None where it has none. `ModelFileError` where the checkpoint belongs
    to another run: another fingerprint (`belongs_to_run`), or, in one of a version that wrote none, primitives
    of other shapes; or where it is not a loop state this version can read."""
    checkpoint = Path(folder) / CHECKPOINT_FILE
    if not checkpoint.is_file():
        return None
    payload = load_checkpoint(checkpoint)
    recorded = payload.get(FINGERPRINT_KEY) if isinstance(payload, dict) else None
    if recorded is not None and not belongs_to_run(recorded, folder, config, recorded_source(folder, source)):
        raise ModelFileError(f"{checkpoint} belongs to another run (written for other settings or inputs than "
                             f"{Path(folder) / CONFIG_FILE} records): delete it to restart from step 0")
    try:
        return state_from_payload(payload, config, run, str(checkpoint))
    except CvqpgError:
        raise
    except (AttributeError, KeyError, TypeError, ValueError, RuntimeError) as error:  # a payload of other content
        raise ModelFileError(f"{checkpoint} is not a loop state this version wrote ({type(error).__name__}: "
                             f"{error}): delete it to restart from step 0") from None


def checkpoint_policy(every: int | None) -> dict[str, Any]:
    """`fit_in_folder`'s checkpoint arguments for a `--checkpoint-every` of `every` steps: 0 saves only when the
    fit is stopped, None every `CHECKPOINT_SECONDS` of work."""
    return {"checkpoint_every_steps": every if every else None,
            "checkpoint_every_seconds": None if every == 0 else CHECKPOINT_SECONDS}


def fit_in_folder(folder: Path, scene: Scene, config: FitConfig, run: RunOptions = RunOptions(),
                  control: RunControl = RunControl(), state: FitState | None = None,
                  checkpoint_every_steps: int | None = None,
                  checkpoint_every_seconds: float | None = CHECKPOINT_SECONDS, source: dict[str, Any] | None = None,
                  checkpoint_at_end: bool = False, objective: RateObjective | None = None) -> FitResult:
    """`fit_scene` on `run` under `control` with the folder's checkpoint policy, after compiling the CPU kernels
    (a status line when `control.progress`); the state records the compile time and the peak memory of every
    segment, so a resumed fit reports the whole run's, and checkpoints record the run's fingerprint
    (`fit_fingerprint` of `config` and `source`, default: as the folder's `config.json` records it). Raises
    `FitInterrupted` after saving on a stop request, also on one asked during the last step or the final render.
    `checkpoint_at_end` saves the finished loop too, for work that follows the fit in the same folder: resumed
    from it, the fit returns at once with the same result. An `objective` puts the rate in the fit's loss
    (`fitting.fit_scene`)."""
    folder = Path(folder)
    fingerprint = fit_fingerprint(config, recorded_source(folder, source))
    device = torch.device(run.device)
    # The kernels first: a cold compile starts its second process before this one imports the optimiser.
    compile_seconds = prepare_kernels(config, run, show_status=control.progress)
    code_commit()  # cached for the run record: the commit of the code this process runs, not of a later one
    state = state or initial_state(config, scene, run)
    state.compile_seconds += compile_seconds
    reset_peak_memory(device)

    def save(current: FitState) -> None:
        current.note_peak_memory(peak_memory(device))
        save_checkpoint(folder / CHECKPOINT_FILE, {**current.to_payload(), FINGERPRINT_KEY: fingerprint})

    policy = CheckpointPolicy(save=save, every_steps=checkpoint_every_steps, every_seconds=checkpoint_every_seconds)
    result = fit_scene(scene, config, run, control, state=state, checkpoint=policy, objective=objective)
    stopped = not checkpoint_at_end and control.should_stop()  # asked during the last step or the final render
    if checkpoint_at_end or stopped:
        save(state)
    if stopped:
        raise FitInterrupted(state.step, during="its final render")
    state.note_peak_memory(peak_memory(device))
    result.peak_memory = state.peak_memory
    return result


def timed_config(scene: Scene, config: FitConfig, minutes: float, run: RunOptions = RunOptions(),
                 progress: bool = True) -> tuple[FitConfig, dict]:
    """`config` over the step count whose fit takes about `minutes` here on `run` (the kernels compiled first,
    then a few steps timed: `fitting.seconds_per_step`), and what a run records of the choice: the budget, the
    seconds per step, and the seconds spent compiling the kernels (the fit itself then only loads them). Only
    the steps change, and the curvature warm-up with them (`FitConfig.with_steps`): the algorithm is the same
    on a fast machine and a slow one."""
    check_time_budget(minutes)
    compile_seconds = prepare_kernels(config, run, show_status=progress)
    seconds_each = seconds_per_step(scene, config, run)
    steps = steps_within(60 * minutes, seconds_each)
    timed = config.with_steps(steps).validate()
    given = config.optimisation
    if given.curvature_warmup != default_curvature_warmup(given.steps):  # a warm-up of the caller's, not the share
        log.warning(f"the curvature warm-up of {given.curvature_warmup} of {given.steps} steps keeps its share of "
                    f"the {steps} steps the time allows: {timed.optimisation.curvature_warmup}")
    return timed, {"minutes": minutes, "seconds_per_step": seconds_each, "compile_seconds": compile_seconds}


def write_fitted_run(folder: Path, result: FitResult, scene: Scene, source: dict[str, Any],
                     extra: dict[str, Any] | None = None) -> Path:
    """`write_run` with the run record of this process: code, machine, times and peak memory; `extra` goes into
    `metrics.json` too."""
    record = run_record(torch.device(result.run.device), result.seconds, result.cpu_seconds,
                        result.compile_seconds, result.peak_memory)
    return write_run(folder, result, scene, source, record, extra)
