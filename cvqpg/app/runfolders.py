"""The commands over a finished run folder or a model file in one: `cvqpg eval`, `export`, `info`, `render` and
`view`, each checked (the run finished, the device, the memory of its work) before it writes, and writing by the
output rule (`app.outputs`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from ..control import RunControl
from ..errors import UsageError
from .resources import check_device, check_memory
from .signals import raised_if_stopped

# What each command here is asked between the stages of its work: a stop signal, even one whose exception a
# callback swallowed, stops it there.
STOPPABLE = RunControl(progress=False, stop_requested=raised_if_stopped)

if TYPE_CHECKING:
    from ..view import ViewRecord


def finished_run(folder: Path) -> Path:
    """A run folder that holds a model, or a UsageError saying what it is instead."""
    from ..runs import CONFIG_FILE, METRICS_FILE, MODEL_FILE
    if folder.is_dir() and not (folder / CONFIG_FILE).is_file() and (folder.parent / CONFIG_FILE).is_file():
        raise UsageError(f"{folder} is a folder, not a model file of the run {folder.parent}; give the run folder "
                         "or one of its model files")
    if not (folder / CONFIG_FILE).is_file():
        raise UsageError(f"{folder} is not a run folder (no {CONFIG_FILE}); give a folder written by "
                         "`cvqpg fit`")
    model = folder / MODEL_FILE
    if model.is_dir():
        raise UsageError(f"{model} is a folder, not the run's model file; move it away, or fit the run again")
    if not model.is_file() and (folder / METRICS_FILE).is_file():
        raise UsageError(f"{folder} is a finished run whose {MODEL_FILE} is gone; fit it again (cvqpg fit "
                         "--overwrite)")
    if not model.is_file():
        raise UsageError(f"{folder} holds no {MODEL_FILE}: the run has not finished (cvqpg fit --resume "
                         f"{folder})")
    return folder


def run_and_model(target: Path) -> tuple[Path, Path | None]:
    """A run folder and None (its own model), or the run folder that holds the model file `target`."""
    from ..runs import CONFIG_FILE
    if not target.is_file():
        return finished_run(target), None
    if not (target.parent / CONFIG_FILE).is_file():
        raise UsageError(f"{target}: a model file needs its run folder's {CONFIG_FILE} (the targets); "
                         "keep it inside the run folder")
    return target.parent, target


def evaluate(target: str | Path, device: str = "cpu") -> tuple[Path, dict[str, Any]]:
    """`cvqpg eval`: the run folder of `target` (a run folder, or a model file in one) and the metrics record of
    its model, rewritten there (`runs.evaluate_run`)."""
    from ..runs import CONFIG_FILE, evaluate_run, evaluation_file, read_run
    from .outputs import claimed_in_run, place_problem
    check_device(device)
    folder, model = run_and_model(Path(target))
    check_memory(read_run(folder)[0], device, "evaluation", f"the run's {CONFIG_FILE} asks for it: evaluate it "
                 "where more memory is free")
    record = evaluation_file(folder, model)
    with claimed_in_run(record, "the metrics record"):
        if (problem := place_problem(record, folder=False, writer="`cvqpg eval`")) is not None:
            raise UsageError(f"{problem}; move it away, and evaluate the run again")
        return folder, evaluate_run(folder, model, device)


def export(target: str | Path, encoding: str | None, levels: int | None, slm: tuple[int, int] | None,
           aperture: float | None, out: str | Path | None = None, overwrite: bool = False, device: str = "cpu",
           lut: str | Path | None = None) -> tuple[Path, dict[str, Any]]:
    """`cvqpg export`: the phase-only patterns of `target`'s model and their simulated display (`runs.export_run`)
    in the folder `out` (default: the run's `export`, or `export-<model stem>` for a model file); the folder and
    the export's record. A setting None is the run's display's (`runs.export_display`); `aperture` 0 is none,
    `lut` a lookup table's file (`display.read_lut`)."""
    from ..display import read_lut
    from ..runs import EXPORT_FOLDER, MODEL_FILE, export_run, read_run
    from .outputs import EXPORT, staged_output
    check_device(device)
    folder, model = run_and_model(Path(target))
    if aperture is not None and not 0 <= aperture <= math.sqrt(2):
        raise UsageError(f"--aperture {aperture:g}: give a radius in [0, √2] (a fraction of Nyquist; from √2 "
                         "on it passes every frequency, as 0 does: no filter)")
    out = Path(out) if out else folder / (EXPORT_FOLDER if model is None else f"{EXPORT_FOLDER}-{model.stem}")
    check_memory(read_run(folder)[0], device, "export", "give a smaller --slm", size=slm)
    with staged_output(out, EXPORT, [folder, model or folder / MODEL_FILE], overwrite) as staged:
        record = export_run(folder, encoding, levels, slm, "auto" if aperture is None else aperture or None, staged,
                            model, device, None if lut is None else read_lut(lut), STOPPABLE)
    return out, record


def info(target: str | Path, half: bool = False, overwrite: bool = False) -> dict[str, Any]:
    """`cvqpg info`: the size of a model file or a run's model (`storage.model_info`); with `half`, the run's
    float16 copy stored beside its model, and its PSNR change (`runs.half_precision_model`)."""
    from ..runs import HALF_MODEL_FILE, MODEL_FILE, half_precision_model
    from ..storage import model_info
    from .outputs import MODEL, output
    target = Path(target)
    if not half:
        return model_info(finished_run(target) / MODEL_FILE if target.is_dir() else target)
    if target.is_file():
        raise UsageError(f"--half stores a float16 copy beside a run's model: give the run folder, not {target}")
    folder = finished_run(target)
    with output(folder / HALF_MODEL_FILE, MODEL, [folder / MODEL_FILE], overwrite):
        return half_precision_model(folder)


def render(target: str | Path, size: tuple[int, int] | None = None, distances: Sequence[float] | None = None,
           out: str | Path | None = None, overwrite: bool = False, device: str = "cpu") -> tuple[Path, dict[str, Any]]:
    """`cvqpg render`: a model's hologram and reconstructions (`runs.render_model`), resampled to `size` (W, H)
    px, at `distances` (m; default: its planes), in the folder `out` (default: the run's `render`, or
    `<model stem>-render` beside a model file); the folder and the render's record."""
    from ..config import check_distances
    from ..runs import RENDER_FOLDER, check_distinct_files, read_run, render_model
    from ..storage import load_model
    from .outputs import RENDER, staged_output
    check_device(device)
    target = Path(target)
    if target.is_dir():
        finished_run(target)
    elif not target.is_file():
        raise UsageError(f"{target}: no such run folder or model file")
    out = Path(out) if out else (target / RENDER_FOLDER if target.is_dir()
                                 else target.with_name(target.stem + "-render"))
    if distances is not None:
        check_distances(distances, "`distance`", " (e.g. 0.001 for 1 mm)")
        check_distinct_files(distances)
    config = read_run(target)[0] if target.is_dir() else load_model(target)[1]
    check_memory(config, device, "render", "give a smaller --size or fewer --distance values", size=size,
                 planes=None if distances is None else len(distances))
    with staged_output(out, RENDER, [target], overwrite) as staged:
        record = render_model(target, staged, size, distances, device, STOPPABLE)
    return out, record


def view(run_dirs: Sequence[str | Path], distances: tuple[float, float, float], out: str | Path | None = None,
         overwrite: bool = False, progress: bool = True) -> ViewRecord:
    """`cvqpg view`: the page of one or two finished runs' focal sweeps (`view.write_view`) over `distances`
    (START and STOP in m, COUNT), at `out` (default: `view.default_page`)."""
    from ..runs import read_run
    from ..view import SWEEP_BATCH, check_sweep, default_page, write_view
    from .outputs import PAGE, output
    if len(run_dirs) > 2:
        raise UsageError(f"{len(run_dirs)} run folders: give one or two")
    folders = [finished_run(Path(folder)) for folder in run_dirs]
    start, stop, count = distances
    if not float(count).is_integer():
        raise UsageError(f"--distances {start:g} {stop:g} {count:g}: COUNT is a whole number of distances")
    check_sweep(start, stop, int(count))
    for folder in folders:
        check_memory(read_run(folder)[0], "cpu", "view", "give a smaller COUNT to --distances",
                     planes=min(SWEEP_BATCH, int(count)))
    with output(out or default_page(folders), PAGE, folders, overwrite) as page:
        return write_view(folders, page, (start, stop, int(count)), progress, STOPPABLE)


def view_of_run(folder: Path, progress: bool = True) -> ViewRecord:
    """A fit's own view page (`cvqpg fit --view`), replacing the run's earlier one."""
    from ..defaults import VIEW_FILE
    from ..view import write_view
    from .outputs import PAGE, output
    with output(folder / VIEW_FILE, PAGE, [folder], overwrite=True) as page:
        return write_view([folder], page, progress=progress, control=STOPPABLE)
