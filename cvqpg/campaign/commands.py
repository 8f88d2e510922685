"""`cvqpg bench` and `cvqpg results` as the command line runs them: the grid planned and checked before anything
is fitted (`plan_bench`), its cells fitted under a stop request (`fit_bench`), its summary rewritten
(`summarise_bench`); `docs/results.md` and its figures from the recorded cells (`write_results`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..app.executors import ExecutorFlags, ExecutorOptions
from ..control import RunControl
from ..errors import UsageError
from .bench import BenchOutcome, BenchPlan, Cell, Overrides
from .presets import PRESETS


@dataclass(frozen=True)
class BenchRequest:
    """What `cvqpg bench` is asked: the grid (`preset`, changed by `overrides`) in the folder `out` (default:
    `runs/bench-<preset>`), the cells of one `shard` ("I/N"), run by the executor `flags` ask for; `reuse`: bench
    folders whose finished cells are copied, `fits`: bench folders whose models the rate–distortion cells take,
    `finetune`: their fine-tuning steps; `summary_only`: fit nothing."""

    preset: str
    out: str | None
    overrides: Overrides
    flags: ExecutorFlags
    shard: str | None = None
    reuse: tuple[Path, ...] = ()
    fits: tuple[Path, ...] = ()
    finetune: int = 0
    summary_only: bool = False


@dataclass(frozen=True)
class PlannedBench:
    """A checked bench: its plan, the cells of its shard, and their executor."""

    plan: BenchPlan
    cells: tuple[Cell, ...]
    executor: ExecutorOptions


def plan_bench(request: BenchRequest) -> PlannedBench:
    """The grid of `request`, every option checked (the folders it names, the options its preset takes, the
    executor) before anything is written."""
    from ..app.outputs import BENCH, check_continued
    from .bench import CELLS_DIR, make_plan, parse_shard
    if request.out is not None:
        check_continued(request.out, BENCH)  # before the plan reads the records there
    plan = make_plan(request.preset, request.out, request.overrides)
    preset = PRESETS[request.preset]
    for option, given in (("--fits", bool(request.fits)), ("--finetune", request.finetune != 0)):
        if given and (not preset.rate_distortion or preset.encode_fractions):
            raise UsageError(f"{option} is for the rate–distortion grids of fitted models (--preset compression or "
                             f"rate), not --preset {request.preset}")
    if request.finetune < 0:
        raise UsageError(f"--finetune {request.finetune}: give a number of steps ≥ 0")
    for option, folders in (("--fits", request.fits), ("--reuse", request.reuse)):
        for folder in folders:
            if not (Path(folder) / CELLS_DIR).is_dir():
                raise UsageError(f"{option} {folder}: not a bench folder (no {CELLS_DIR}/ in it)")
    if request.summary_only and not (plan.folder / CELLS_DIR).is_dir():
        raise UsageError(f"--summary-only: {plan.folder} holds no {CELLS_DIR}/ to summarise; fit the grid first, "
                         "or give its --out")
    check_continued(plan.folder, BENCH)
    executor = request.flags.options(request.overrides.device, "bench")
    cells = plan.shard(*parse_shard(request.shard)) if request.shard else plan.cells
    return PlannedBench(plan, cells, executor)


def describe_bench(planned: PlannedBench, request: BenchRequest) -> list[str]:
    """`--dry-run`: a line per cell of the shard with its status, and their count."""
    from .bench import describe_cells
    listing = describe_cells(planned.plan, planned.cells, request.reuse)
    return listing + [f"{len(planned.cells)} of {len(planned.plan.cells)} cells, in {planned.plan.folder}"]


def fit_bench(planned: PlannedBench, request: BenchRequest, progress: bool = True
              ) -> tuple[BenchOutcome, int | None]:
    """Fit the cells of `planned` (`bench.run_plan`) once their device and memory are checked; the outcome and
    the signal that stopped it (None where none did)."""
    from ..app import signals
    from ..app.allocator import keep_freed_memory
    from ..app.resources import check_fits_at_once
    from .bench import RateDistortionOptions, check_cells_device, peak_bytes, run_plan
    plan, cells, executor = planned.plan, planned.cells, planned.executor
    keep_freed_memory()
    check_cells_device(cells, executor)
    check_fits_at_once(peak_bytes(cells, 1), executor, plan.cells[0].run.device)
    check_finished_records(plan, cells, request.reuse)
    with signals.StopRequest() as stop_requested:
        outcome = run_plan(plan, cells, control=RunControl(progress=progress, stop_requested=stop_requested),
                           reuse=list(request.reuse),
                           rate_distortion=RateDistortionOptions(request.fits, request.finetune), executor=executor)
    return outcome, stop_requested.signals[0] if stop_requested.signals else None


def check_finished_records(plan: BenchPlan, cells: tuple[Cell, ...], reuse: tuple[Path, ...]) -> None:
    """The records of the finished cells, the folder's own and those that `--reuse` would copy, are ones the
    summary reads (`report.read_cell_record`, an `InputError` naming the first that is not): checked before the
    first cell is copied or fitted, not when the summary is written after them."""
    from .bench import DONE, reusable_record
    from .report import RECORD_KEYS, read_cell_record
    for cell in cells:
        folder = plan.cell_dir(cell)
        source = folder if plan.status(folder) == DONE else reusable_record(plan, cell, reuse)
        for name in RECORD_KEYS if source is not None else ():
            read_cell_record(source / name)


def summarise_bench(request: BenchRequest) -> Path:
    """(Re)write the bench folder's summary, tables, figures and report from its finished cells; summary.md."""
    from .bench import folder_plan
    from .report import write_summary
    return write_summary(folder_plan(request.preset, request.out, request.overrides,
                                     as_recorded=request.summary_only))


def write_results(root: str | Path, out: str | Path, overwrite: bool = False) -> list[Path]:
    """`cvqpg results`: the document `out` (`results.document`) and its figures beside it, from the recorded bench
    folders in `root`; the files written."""
    from ..app.outputs import DOCUMENT, output
    from ..app.signals import check_not_stopped
    from ..files import write_atomic
    from .results import check_recorded, document, write_figures
    if not Path(root).is_dir():
        raise UsageError(f"--root {root} is not a folder of recorded bench folders (e.g. results)")
    root = Path(root)
    check_recorded(root)
    with output(out, DOCUMENT, [], overwrite) as checked:
        text = document(root)  # what can refuse, before the first figure is drawn
        check_not_stopped()  # the figures are outputs too, beside the document that `output` gates
        figures = write_figures(root, checked.parent, overwrite)
        write_atomic(checked, text)
    return [checked, *figures]
