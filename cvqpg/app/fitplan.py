"""`cvqpg fit`: what it will do (`FitPlan`, a new fit or one resumed from its folder's checkpoint), everything
checked before the first byte is written; the fit in its work folder `RUN.partial`, which a stop request leaves
with a checkpoint to resume (`resumable`); and the finished run put in its place (`fit_planned`)."""

from __future__ import annotations

import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from ..config import FitConfig, RunOptions, check_time_budget
from ..control import RunControl
from ..defaults import BUDGET_FILE, DEPTH_FILE, PARTIAL_SUFFIX
from ..errors import CvqpgError, UsageError
from .inputs import FitInputs, config_and_source, scene_and_depth
from . import signals
from .resources import check_device, check_memory

if TYPE_CHECKING:
    from PIL import Image

    from ..fitting import FitState
    from ..targets import Scene


@dataclass
class FitPlan:
    """What `cvqpg fit` will do: fit in `work` (with the loop state `state`, when resuming), and put the
    finished run at `final` (the same folder, or `work` renamed; an existing run there is replaced)."""

    work: Path
    final: Path
    config: FitConfig
    run: RunOptions
    source: dict[str, Any]
    scene: Scene
    state: FitState | None = None
    depth: Image.Image | None = None  # an estimated depth map, saved in the run once `work` exists
    role: str = "`out`"  # how messages name `final`


def check_fit_destination(final: Path, overwrite: bool, role: str = "`out`") -> Path:
    """`--out` may be a new or empty folder, or a run that `--overwrite` replaces; never a file, a link or a
    folder of other files (`app.outputs`' rule). `role` names the place in messages."""
    from .outputs import RUN, check_output, is_run_folder
    if is_run_folder(final) and not final.is_symlink() and not overwrite:
        raise UsageError(f"{final} already holds a run; choose another --out, pass --overwrite to replace it "
                         f"once the new fit succeeds, or --resume {final}")
    return check_output(final, RUN, overwrite=overwrite, role=role, make_parents=True)


def run_finished(folder: str | Path) -> bool:
    """Whether the run folder holds a finished run (its metrics), which there is nothing to resume of."""
    from ..runs import METRICS_FILE
    return (Path(folder) / METRICS_FILE).is_file()


def finished_note(folder: str | Path) -> str:
    """What `fit --resume` says of a finished run: nothing to resume, and where it is a work folder `RUN.partial`
    that was never moved into place, what to do with it."""
    name = Path(os.path.abspath(folder)).name
    if name.endswith(PARTIAL_SUFFIX):
        return (f"{folder}: this fit is finished, nothing to resume; it was never moved into place: rename it to "
                f"{name[:-len(PARTIAL_SUFFIX)]}")
    return f"{folder}: this run is finished; nothing to resume"


def resume_plan(folder: str | Path, overwrite: bool) -> FitPlan:
    """The plan that continues the interrupted run in `folder` from its checkpoint, with its own settings; with
    `overwrite`, a run where the folder's finished run goes (`RUN` of `RUN.partial`) is replaced."""
    from ..runs import CHECKPOINT_FILE, CONFIG_FILE, read_run, read_run_options, scene_from_source
    from .outputs import is_run_folder
    from .runner import resumed_state
    work = Path(os.path.abspath(folder))  # `--resume .` names the folder too
    if not (work / CONFIG_FILE).is_file():
        raise UsageError(f"--resume {work}: not a run folder (no {CONFIG_FILE})")
    if (work / BUDGET_FILE).is_file():
        raise UsageError(f"--resume {work} is an encode's folder; continue it with cvqpg encode --resume {work}")
    if (work / CHECKPOINT_FILE).exists() and not (work / CHECKPOINT_FILE).is_file():
        raise UsageError(f"--resume {work}: its {CHECKPOINT_FILE} is not a file; move it away to restart the run "
                         "from step 0")
    config, source = read_run(work)
    run = read_run_options(work)
    check_device(run.device)
    final = work.with_name(work.name[:-len(PARTIAL_SUFFIX)]) if work.name.endswith(PARTIAL_SUFFIX) else work
    role = f"--resume {work}: its run's folder"
    if final != work:
        if is_run_folder(final) and not overwrite:
            raise UsageError(f"{final} holds a run that this fit replaces when it finishes; pass --overwrite to "
                             "confirm")
        check_fit_destination(final, overwrite, role)
    check_memory(config, run.device, remedy=f"the run's {CONFIG_FILE} asks for it: resume it where more memory is "
                 "free")
    scene = scene_from_source(source, config)
    return FitPlan(work, final, config, run, source, scene, resumed_state(work, config, run), role=role)


def stranded_work(work: Path) -> str:
    """What lies at a new fit's work folder `OUT.partial`, which the fit does not take over, and what to do."""
    from ..runs import CONFIG_FILE, METRICS_FILE
    if work.is_symlink() or not work.is_dir():
        return f"{work} is in the way of the fit's work folder (not a folder); move it away"
    if not (work / CONFIG_FILE).is_file():
        return f"{work} is in the way of the fit's work folder (it holds no fit's {CONFIG_FILE}); move it away"
    if run_finished(work):
        final = work.with_name(work.name[:-len(PARTIAL_SUFFIX)])
        return (f"{work} holds a finished fit that was never moved into place; rename it to {final.name}, or "
                "delete it")
    return f"{work} holds an interrupted fit; continue it with cvqpg fit --resume {work}, or delete it"


def default_out(source: dict[str, Any], config: FitConfig) -> Path:
    """`runs/<time>-<input>-<color>-<primitive>`."""
    label = source.get("scene") or Path(source["image"]).stem
    return Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{label}-{config.targets.color}-{config.primitives.kind}"


def new_plan(inputs: FitInputs, out: str | None, overwrite: bool, minutes: float | None = None,
             checkpoint_every: int | None = None, progress: bool = True) -> FitPlan:
    """The plan of a new fit of `inputs` into `out` (default: `default_out`), in its work folder `OUT.partial`;
    with `minutes`, for the step count that takes about that long here (`runner.timed_config`, which records
    the choice in the source's `time_budget`)."""
    from .runner import timed_config
    if checkpoint_every is not None and checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every {checkpoint_every}: give a number of steps ≥ 1, or 0 for "
                         "checkpoints only when interrupted")
    if minutes is not None and inputs.settings["steps"] is not None:
        raise UsageError("give --steps or --time, not both")
    if minutes is not None:
        check_time_budget(minutes)
    config, source = config_and_source(inputs)
    run = inputs.run_options()
    check_device(run.device)
    final = check_fit_destination(Path(out) if out else default_out(source, config), overwrite)
    work = final.with_name(final.name + PARTIAL_SUFFIX)
    if work.exists() or work.is_symlink():
        raise UsageError(stranded_work(work))
    check_memory(config, run.device)
    scene, depth = scene_and_depth(source, config)
    if depth is not None:
        source["depth"] = DEPTH_FILE  # kept in the run folder, wherever it moves
    if minutes is not None:
        config, source["time_budget"] = timed_config(scene, config, minutes, run, progress=progress)
    return FitPlan(work, final, config, run, source, scene, depth=depth)


def resumable(work: Path, command: str, body: Callable[[Callable[[], bool]], None]) -> int:
    """Run `body(stop_requested)`, which fits in `work` with checkpoints: 0 when it finishes. A stop request
    (Ctrl-C, SIGTERM) keeps the checkpoint and returns the signal's exit code, with the line that resumes it; a
    failure removes what this command made, unless a checkpoint holds work worth resuming."""
    from ..fitting import FitInterrupted
    from ..runs import CHECKPOINT_FILE
    created = [folder for folder in (work, *work.parents) if not folder.exists()]
    try:
        with signals.StopRequest() as stop_requested:  # looked up here, so that a test may replace it
            body(stop_requested)
    except FitInterrupted as stop:
        print(f"cvqpg {command}: {stop}; checkpoint saved. Continue with: "
              f"cvqpg {command} --resume {work}", file=sys.stderr)
        return 128 + stop_requested.signals[0]
    except BaseException as error:
        if (work / CHECKPOINT_FILE).is_file():
            ended = "stopped" if isinstance(error, (KeyboardInterrupt, signals.Terminated)) else "failed"
            print(f"cvqpg {command}: {ended}; the fit's last checkpoint is kept: cvqpg {command} --resume {work}",
                  file=sys.stderr)
        else:
            for folder in created:
                shutil.rmtree(folder, ignore_errors=True)
        raise
    return 0


def fit_planned(plan: FitPlan, checkpoint_every: int | None = None, progress: bool = True,
                overwrite: bool = False) -> tuple[int, dict[str, Any] | None]:
    """Fit in `plan.work` (`resumable`, checkpoints every `checkpoint_every` steps: `runner.checkpoint_policy`)
    and put the run at `plan.final`: 0 and the run's metrics record, or the exit code of the signal that stopped
    it and None."""
    from ..files import gated, replace_folder
    from ..runs import METRICS_FILE, read_record, start_run
    from .allocator import keep_freed_memory
    from .outputs import claimed
    from .runner import checkpoint_policy, fit_in_folder, write_fitted_run

    def body(stop_requested: Callable[[], bool]) -> None:
        if plan.state is None:
            start_run(plan.work, plan.config, plan.source, plan.run)
        if plan.depth is not None:
            plan.depth.save(plan.work / DEPTH_FILE)
        result = fit_in_folder(plan.work, plan.scene, plan.config, plan.run,
                               RunControl(progress=progress, stop_requested=stop_requested), plan.state,
                               **checkpoint_policy(checkpoint_every))
        signals.check_not_stopped()  # asked after the last step: the run is not marked finished
        write_fitted_run(plan.work, result, plan.scene, plan.source)

    keep_freed_memory()
    # in place (a resumed folder not named RUN.partial), metrics.json marks the run finished: it is the output
    with claimed(plan.final, plan.role), gated(plan.final / METRICS_FILE, signals.check_not_stopped):
        if plan.final != plan.work:
            check_fit_destination(plan.final, overwrite, plan.role)
        code = resumable(plan.work, "fit", body)
        if not code and plan.final != plan.work:
            try:  # the place is checked again: anything of the user's that appeared there meanwhile stays
                check_fit_destination(plan.final, overwrite, plan.role)
                replace_folder(plan.work, plan.final)
            except CvqpgError as error:
                raise UsageError(f"{error}; the finished run is kept in {plan.work}") from None
    return code, None if code else read_record(plan.final / METRICS_FILE, "fit it again")
