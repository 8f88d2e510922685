"""Benchmark grids: scenes × colour × ratio × method × seed, one run folder per cell.

A cell is a `cvqpg fit` run in `<bench>/cells/<cell name>/`. Its `metrics.json`, which
`runs.write_run` writes last and atomically, is the only "done" marker: a folder holding just a
config, a checkpoint or partial files is not done and is resumed (from its checkpoint when the
settings match) or restarted. Shards split the full cell list by position, whatever is done, so
every node of a job array computes the same split. The tables, figures and report come from
`cvqpg.campaign.report`.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import math
import traceback
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..app.encoding import encode_steps
from ..app.executors import (DONE, FAILED, INTERRUPTED, NOT_STARTED, SKIPPED, ExecutorOptions, Task,
                             TaskStopped, ready, run_tasks, unless_stopped)
from ..app.outputs import place_problem
from ..app.provenance import machine_record
from ..app.runner import checkpoint_policy, fit_in_folder, resumed_state, write_fitted_run
from ..config import BEYOND_RECIPE, FLAT_NAMES, RECIPES, FitConfig, RunOptions
from ..control import SILENT, RunControl
from ..defaults import RATE_FINETUNE_STEPS
from ..errors import CvqpgError
from ..display import Display
from ..fitting import FitInterrupted, FitResult, FitState, estimated_peak_bytes, render
from ..metrics import evaluate, radial_error_spectrum
from ..runs import (CHECKPOINT_FILE, CONFIG_FILE, HISTORY_FILE, METRICS_FILE, MODEL_FILE, export_display, read_record,
                    read_run, scene_from_source, start_run, write_atomic, write_json)
from ..scenes import SCENES
from ..targets import Scene, check_depth_geometry, load_picture
from .presets import COLORS, METHODS, PRESETS

log = logging.getLogger("cvqpg")

CELLS_DIR = "cells"
SPECTRUM_FILE = "spectrum.json"
RD_FILE = "rd.json"
ENCODE_FILE = "encode.json"  # the `cvqpg encode` points of a rate grid's cell (`--preset encode`)
ENCODE_PARTIAL_FILE = "encode.partial.json"  # its points so far, each a whole fit: kept in git between sessions
ERROR_FILE = "error.log"
# The metrics.json entry of what the display shows of a model exported after its fit (`Method.exported`).
EXPORTED_KEY = "exported_display"
SPECTRUM_BINS = 32
FOLDER_SCENE_PLANES = 2

FITTED = "fitted"  # a rate–distortion cell whose fit is done and whose R-D points are not
REUSED = "reused"
# What a finished cell keeps in git (results/): enough to rebuild every table and figure; metrics.json last (the done
# mark). Cells fitted before history.csv existed lack it.
RECORD_FILES = (CONFIG_FILE, SPECTRUM_FILE, RD_FILE, ENCODE_PARTIAL_FILE, ENCODE_FILE, HISTORY_FILE, METRICS_FILE)
STARTED, MISSING = "started", "missing"
RESTORE_ENCODE = "restore it from git, or delete the encode grid's files of the cell to encode it again"


class BenchError(CvqpgError):
    """A benchmark request that cannot work; the message names the option and the fix."""


@dataclass(frozen=True)
class BenchScene:
    """A scene of the grid: its name, its input as `config.json` records it, and its plane count."""

    name: str
    source: dict[str, Any]
    planes: int


@dataclass(frozen=True)
class Cell:
    """One fit of the grid."""

    scene: BenchScene
    method: str
    config: FitConfig
    run: RunOptions = RunOptions()  # where it fits: no part of its settings

    @property
    def setting(self) -> str:
        """Colour and ratio, e.g. `rgb-20` (the paper's table rows)."""
        return setting_key(self.config.targets.color, self.config.primitives.ratio)

    @property
    def name(self) -> str:
        return f"{self.scene.name}_{self.setting}_{self.method.replace('+', '-plus')}_s{self.config.optimisation.seed}"


@dataclass(frozen=True)
class Overrides:
    """Command-line replacements of a preset's axes and fit options; None keeps the preset's."""

    scenes_dir: str | Path | None = None
    scene_names: Sequence[str] | None = None
    colors: Sequence[str] | None = None
    ratios: Sequence[float] | None = None
    methods: Sequence[str] | None = None
    seeds: Sequence[int] | None = None
    size: Sequence[int] | None = None
    steps: int | None = None
    curvature_warmup: int | None = None
    device: str | None = None
    backend: str | None = None


@dataclass(frozen=True)
class BenchPlan:
    """The whole grid of a bench folder, cells in a fixed order (scene, colour, ratio, method, seed)."""

    preset: str
    folder: Path
    scenes: tuple[BenchScene, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    cells: tuple[Cell, ...]

    def cell_dir(self, cell: Cell) -> Path:
        return self.folder / CELLS_DIR / cell.name

    @property
    def done_file(self) -> str:
        """The file whose presence marks a cell done: `encode.json` in the encode grid, `rd.json` in another
        rate–distortion grid, else `metrics.json`."""
        preset = PRESETS[self.preset]
        return ENCODE_FILE if preset.encode_fractions else RD_FILE if preset.rate_distortion else METRICS_FILE

    def status(self, folder: Path) -> str:
        """`cell_status` of a cell folder of this plan (or of another bench folder's), where an encode grid's cell
        whose `encode.json` lacks some of the preset's budgets is `fitted`: it runs again for those."""
        status = cell_status(folder, self.done_file)
        fractions = PRESETS[self.preset].encode_fractions
        if status == DONE and fractions and untried(read_record(folder / ENCODE_FILE, RESTORE_ENCODE), fractions,
                                                    PRESETS[self.preset].encode_rate_losses):
            return FITTED
        return status

    def shard(self, index: int, count: int) -> tuple[Cell, ...]:
        """Cells of shard `index` of `count` (1-based): every `count`-th cell from position index − 1."""
        return self.cells[index - 1::count]

    @property
    def settings(self) -> tuple[str, ...]:
        """Settings in the paper's order: RGB before grayscale, larger ratio first."""
        keys = {(COLORS.index(c.config.targets.color), -c.config.primitives.ratio, c.setting) for c in self.cells}
        return tuple(key for *_, key in sorted(keys))


@dataclass
class BenchOutcome:
    """What a run of cells did: a status per cell name, and the error of each failed cell."""

    statuses: dict[str, str] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)

    def count(self, status: str) -> int:
        return sum(s == status for s in self.statuses.values())

    def describe(self) -> str:
        """E.g. `3 done, 1 skipped, 0 interrupted, 0 not started, 0 failed`."""
        return ", ".join(f"{self.count(s)} {s}" for s in (DONE, SKIPPED, REUSED, INTERRUPTED, NOT_STARTED, FAILED))


def setting_key(color: str, ratio: float) -> str:
    return f"{color}-{ratio * 100:g}"


def setting_label(key: str) -> str:
    color, percent = key.split("-", 1)
    return f"{'RGB' if color == 'rgb' else 'Grayscale'} {percent}%"


def parse_shard(text: str) -> tuple[int, int]:
    """`i/n` with 1 ≤ i ≤ n → (i, n)."""
    try:
        index, count = (int(part) for part in text.split("/"))
    except ValueError:
        index, count = 0, 0
    if not 1 <= index <= count:
        raise BenchError(f"--shard {text}: expected i/n with 1 ≤ i ≤ n, e.g. --shard 1/4")
    return index, count


def folder_scenes(root: Path) -> tuple[BenchScene, ...]:
    """Scenes of a folder of `<name>/image.*` + `<name>/depth.png`; sub-folders without an image are ignored."""
    if not root.is_dir():
        raise BenchError(f"--scenes {root}: no such folder")
    scenes = []
    for sub in sorted(p for p in root.iterdir() if p.is_dir()):
        images = sorted(sub.glob("image.*"))
        if not images:
            continue
        if len(images) > 1:
            raise BenchError(f"scene {sub.name}: several image files ({', '.join(p.name for p in images)}); "
                             "keep one")
        depth = sub / "depth.png"
        if not depth.is_file():
            raise BenchError(f"scene {sub.name}: {depth} is missing; every scene folder needs image.* and depth.png")
        scenes.append(BenchScene(sub.name, {"image": str(images[0].resolve()), "depth": str(depth.resolve())},
                                 FOLDER_SCENE_PLANES))
    if not scenes:
        raise BenchError(f"--scenes {root}: no scene folders (<name>/image.* with <name>/depth.png) in it")
    return tuple(scenes)


def _choose(kind: str, given: Sequence[str] | None, default: tuple[str, ...], known: tuple[str, ...]
            ) -> tuple[str, ...]:
    chosen = default if given is None else given
    unknown = [v for v in chosen if v not in known]
    if unknown or not chosen:
        raise BenchError(f"--{kind} {' '.join(chosen)}: choose from {', '.join(known)}")
    return tuple(dict.fromkeys(chosen))


def cell_config(base: FitConfig, scene: BenchScene, color: str, ratio: float, method: str, seed: int) -> FitConfig:
    """The fit of one cell. Methods matched to another's parameter count get N·params(other)/params(own)
    primitives: Baseline⁺ 13/12 (RGB) or 9/8 (gray) of N, the chromatic comparisons 15/12 and 15/13. A method with
    its own recipe fits with it, one with its own step factors over that many times `base`'s steps."""
    spec = METHODS[method]
    if spec.display is not None:
        base = base.replace(display=Display.create(spec.display, aperture=spec.aperture))
    if spec.step_factors:
        base = base.with_steps(spec.steps_for(color, base.optimisation.steps))
    # with the primitive: a recipe's start may fit only its own (the per-pixel hologram's)
    recipe = {} if spec.recipe is None else {**RECIPES[spec.recipe].settings(), "recipe": spec.recipe}
    config = base.replace(color=color, ratio=ratio, seed=seed, num_planes=scene.planes, **recipe, **spec.changes)
    params_of = METHODS[method].params_of
    if params_of is not None:
        other = config.replace(**params_of)
        config = config.replace(num_gaussians=round(
            other.primitive_count * other.params_per_primitive / config.params_per_primitive))
    return config.validate()


def make_plan(preset: str, folder: str | Path | None = None, overrides: Overrides = Overrides()) -> BenchPlan:
    """The grid of a preset with command-line overrides; `folder` defaults to `runs/bench-<preset>`."""
    if preset not in PRESETS:
        raise BenchError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    spec = PRESETS[preset]
    recorded = recorded_scenes(default_folder(preset, folder))
    if overrides.scenes_dir is not None:
        listed = {s.name: s for s in folder_scenes(Path(overrides.scenes_dir))}
    elif spec.builtin_scenes:
        listed = {name: BenchScene(name, {"scene": name}, SCENES[name].planes) for name in SCENES}
    else:
        listed = recorded
        if not listed:
            raise BenchError(f"preset {preset!r} needs --scenes DIR (a folder of <name>/image.* and <name>/depth.png, "
                             "e.g. ../shared/scenes), or an --out folder whose cells record their scenes")
    # a scene that only the folder's cells record can still be named: its tables rebuild without its files
    available = {**recorded, **listed}
    default_names = spec.builtin_scenes if overrides.scenes_dir is None and spec.builtin_scenes else tuple(listed)
    names = _choose("scene-names", overrides.scene_names, default_names, tuple(available))
    colors = _choose("colors", overrides.colors, spec.colors, COLORS)
    methods = _choose("methods", overrides.methods, spec.methods, tuple(METHODS))
    ratios = spec.ratios if overrides.ratios is None else tuple(dict.fromkeys(overrides.ratios))
    seeds = (FitConfig().optimisation.seed,) if overrides.seeds is None else tuple(dict.fromkeys(overrides.seeds))
    width, height = spec.size if overrides.size is None else tuple(overrides.size)
    run = RunOptions(overrides.device or "cpu", overrides.backend or "auto").validate()

    def base(color: str) -> FitConfig:
        steps = spec.steps_for(color) if overrides.steps is None else overrides.steps
        return FitConfig.create(spec.recipe, width=width, height=height, steps=steps,
                                curvature_warmup=overrides.curvature_warmup)

    scenes = tuple(available[name] for name in names)
    cells = tuple(Cell(scene, method, cell_config(base(color), scene, color, ratio, method, seed), run)
                  for scene in scenes for color in colors for ratio in ratios for method in methods
                  for seed in seeds)
    return BenchPlan(preset, default_folder(preset, folder), scenes, methods, seeds, cells)


def folder_plan(preset: str, folder: str | Path | None = None, overrides: Overrides = Overrides(),
                as_recorded: bool = False) -> BenchPlan:
    """The grid that a bench folder's summary covers: `make_plan`'s, widened to every scene and colour that
    the folder's cells record. A run on some of them (`--scene-names`, `--colors`) thus rewrites the tables
    with the others' cells still in them. With `as_recorded` (tables rebuilt from the records alone,
    `--summary-only`) what `overrides` leaves to the preset comes from the folder's cells where they hold any
    (`recorded_overrides`), so that the summary describes the fits it tabulates."""
    if as_recorded:
        overrides = recorded_overrides(preset, default_folder(preset, folder), overrides)
    plan = make_plan(preset, folder, overrides)
    cells = recorded_cells(plan.folder)
    names = dict.fromkeys([*(scene.name for scene in plan.scenes), *(name for name, _ in cells)])
    colors = dict.fromkeys([*(cell.config.targets.color for cell in plan.cells), *(color for _, color in cells)])
    if len(names) == len(plan.scenes) and len(colors) == len({cell.config.targets.color for cell in plan.cells}):
        return plan
    return make_plan(preset, folder, dataclasses.replace(overrides, scene_names=tuple(names), colors=tuple(colors)))


def recorded_overrides(preset: str, folder: Path, overrides: Overrides) -> Overrides:
    """`overrides` completed from the cells that the bench `folder` records, where it records any: their scenes,
    colours and ratios (in the preset's order) and seeds, and the size, steps and curvature warm-up that all of
    them share; a setting the cells do not share, or that `overrides` gives, stays as it is. Methods stay the
    preset's: a cell's configuration does not name its method."""
    runs = _recorded_runs(folder)
    if not runs:
        return overrides
    configs = [config for _, config, _ in runs]

    def shared(values: Iterable[Any]) -> Any:
        distinct = set(values)
        return distinct.pop() if len(distinct) == 1 else None

    def in_listed_order(recorded: set[Any], listed: Iterable[Any]) -> list[Any]:
        listed = list(dict.fromkeys(listed))
        return [value for value in listed if value in recorded] + sorted(recorded - set(listed))

    preset_plan = make_plan(preset, folder, dataclasses.replace(overrides, scene_names=None, colors=None))
    return dataclasses.replace(
        overrides,
        scene_names=overrides.scene_names or in_listed_order({name for name, _, _ in runs},
                                                             (scene.name for scene in preset_plan.scenes)),
        colors=overrides.colors or in_listed_order({config.targets.color for config in configs},
                                                   (cell.config.targets.color for cell in preset_plan.cells)),
        ratios=overrides.ratios or in_listed_order({config.primitives.ratio for config in configs},
                                                   (cell.config.primitives.ratio for cell in preset_plan.cells)),
        seeds=overrides.seeds or sorted({config.optimisation.seed for config in configs}),
        size=overrides.size or shared((config.targets.width, config.targets.height) for config in configs),
        steps=overrides.steps or shared(config.optimisation.steps for config in configs),
        curvature_warmup=(overrides.curvature_warmup if overrides.curvature_warmup is not None
                          else shared(config.optimisation.curvature_warmup for config in configs)))


def default_folder(preset: str, folder: str | Path | None) -> Path:
    """`folder`, else `runs/bench-<preset>`; the encode grid works in the rate grid's folder."""
    shared = PRESETS[preset].encode_fractions and not PRESETS[preset].fits_first
    return Path(folder) if folder else Path("runs") / f"bench-{'rate' if shared else preset}"


def _recorded_runs(folder: Path) -> list[tuple[str, FitConfig, dict[str, Any]]]:
    """(scene name, configuration, source) of each cell of a bench folder that has its `config.json`."""
    runs = []
    for config_file in sorted((folder / CELLS_DIR).glob(f"*/{CONFIG_FILE}")):
        recorded, source = read_run(config_file.parent)
        name = Path(source["image"]).parent.name if "image" in source else source["scene"]
        runs.append((name, recorded, source))
    return runs


def recorded_scenes(folder: Path) -> dict[str, BenchScene]:
    """The file scenes that the cells of a bench folder were fitted on, by name, read from their
    `config.json`: the tables of a recorded folder (`results/`) rebuild without the scene files."""
    scenes = {name: BenchScene(name, source, recorded.targets.num_planes)
              for name, recorded, source in _recorded_runs(folder) if "image" in source}
    return dict(sorted(scenes.items()))


def recorded_cells(folder: Path) -> list[tuple[str, str]]:
    """(scene name, colour) of each cell that a bench folder records, in its cells' order."""
    return [(name, recorded.targets.color) for name, recorded, _ in _recorded_runs(folder)]


def cell_status(folder: Path, done_file: str = METRICS_FILE) -> str:
    """`done` (`done_file`), `fitted` (metrics.json where `done_file` is another), `interrupted` (a
    checkpoint), `failed` (an error log), `started` or `missing`."""
    if (folder / done_file).is_file():
        return DONE
    if (folder / METRICS_FILE).is_file():
        return FITTED
    if (folder / CHECKPOINT_FILE).is_file():
        return INTERRUPTED
    if (folder / ERROR_FILE).is_file():
        return FAILED
    return STARTED if (folder / CONFIG_FILE).is_file() else MISSING


def config_differences(folder: Path, config: FitConfig) -> list[str]:
    """Settings in which the run recorded in `folder` differs from `config`."""
    recorded, _ = read_run(folder)
    differences = [f"{name}={recorded.setting(name)!r} (plan: {config.setting(name)!r})" for name in FLAT_NAMES
                   if recorded.setting(name) != config.setting(name)]
    if recorded.display != config.display:
        differences.append(f"display={recorded.display.label()!r} (plan: {config.display.label()!r})")
    return differences


def describe_cells(plan: BenchPlan, cells: tuple[Cell, ...], reuse: Sequence[Path] = ()) -> list[str]:
    """One line per cell: status (`reusable` where a folder of `reuse` has finished it), name, N, steps, size."""
    def status(cell: Cell) -> str:
        own = plan.status(plan.cell_dir(cell))
        return "reusable" if own != DONE and reusable_record(plan, cell, reuse) is not None else own

    return [f"{status(c):>11}  {c.name}  N={c.config.primitive_count}  steps={c.config.optimisation.steps}  "
            f"{c.config.targets.width}×{c.config.targets.height}" for c in cells]


def peak_bytes(cells: tuple[Cell, ...], jobs: int) -> int:
    """Estimated memory (bytes) of `jobs` of the largest cells fitted at once on their device."""
    return jobs * max((estimated_peak_bytes(c.config, c.run.device) for c in cells), default=0)


def check_cells_device(cells: Sequence[Cell], executor: ExecutorOptions) -> None:
    """Cells on CUDA need a GPU that PyTorch sees here, unless they run on a Ray cluster given by its address
    (whose nodes have the GPUs; its driver, on a head node, may have none)."""
    if (executor.ray_address is None and not torch.cuda.is_available()
            and any(torch.device(cell.run.device).type == "cuda" for cell in cells)):
        raise BenchError("--device cuda: no CUDA GPU is visible to PyTorch; use --device cpu")


def check_inputs(plan: BenchPlan, cells: tuple[Cell, ...], reusable: Iterable[str] = ()) -> None:
    """Before any fit: the cells' folders are folders and their records files, not links (`outputs.place_problem`),
    every scene file of a cell still to fit (not done, nor `reusable`: copied from another bench folder) decodes,
    and no finished cell was fitted with other settings."""
    reusable = set(reusable)
    places = [(plan.folder / CELLS_DIR, True)] + [(plan.cell_dir(c), True) for c in cells] + [
        (plan.cell_dir(c) / name, False) for c in cells for name in RECORD_FILES]
    problem = next(filter(None, (place_problem(path, folder, "the bench") for path, folder in places)), None)
    if problem is not None:
        raise BenchError(f"{problem}; move it away, or choose another --out")
    todo = [c for c in cells if plan.status(plan.cell_dir(c)) != DONE and c.name not in reusable]
    for scene in {c.scene.name: c.scene for c in todo}.values():
        if "image" in scene.source:
            check_depth_geometry(load_picture(scene.source["image"]),
                                 load_picture(scene.source["depth"], "depth map"), resize_depth=False)
    if PRESETS[plan.preset].encode_fractions and not PRESETS[plan.preset].fits_first:
        unrated = [c.name for c in todo if not (plan.cell_dir(c) / RD_FILE).is_file()]
        if unrated:
            raise BenchError(f"{plan.folder} is not a finished rate grid ({len(unrated)} cells without {RD_FILE}, "
                             f"e.g. {unrated[0]}): run `cvqpg bench --preset rate` into the same --out first, "
                             "whose budgets and anchors the encode grid's points are set beside")
    for cell in cells:
        folder = plan.cell_dir(cell)
        if cell_status(folder) == DONE:
            differences = config_differences(folder, cell.config)
            if differences:
                raise BenchError(f"{folder} was fitted with other settings ({'; '.join(differences[:3])}); "
                                 "use another --out or delete that cell folder")


def _json_power(power: np.ndarray) -> list[float | None]:
    return [None if math.isnan(p) else float(p) for p in power]


def spectrum_record(recon: torch.Tensor, targets: torch.Tensor, bins: int = SPECTRUM_BINS) -> dict[str, Any]:
    """Radial error spectrum of float reconstructions [M, C, H, W] against the targets, for `spectrum.json`:
    over all channels (`power`) and, with several channels, per channel (`channel_power`)."""
    edges, power, counts = radial_error_spectrum(recon, targets, bins)
    record = {"bins": bins, "edges": edges.tolist(), "counts": counts.tolist(), "power": _json_power(power),
              "mse": float(((recon.double() - targets.double()) ** 2).mean())}
    if recon.shape[1] > 1:
        record["channel_power"] = [_json_power(radial_error_spectrum(recon[:, c], targets[:, c], bins)[1])
                                   for c in range(recon.shape[1])]
    return record


def adopt_finished(plan: BenchPlan, cells: tuple[Cell, ...], others: Sequence[Path],
                   control: RunControl = SILENT) -> list[Cell]:
    """Copy into the plan's folder the records (`RECORD_FILES`) of cells that another bench folder has
    finished with the same settings, so that grids sharing cells (the chromatic and ablation grids
    share their baseline and CVQPG cells with Table 1) fit them once, until `control` asks to stop. Returns the
    cells adopted."""
    adopted = []
    for cell in cells:
        folder = plan.cell_dir(cell)
        if plan.status(folder) == DONE:
            continue
        if control.should_stop():
            break
        source = reusable_record(plan, cell, others)
        if source is None:
            continue
        folder.mkdir(parents=True, exist_ok=True)
        for name in RECORD_FILES:
            if (source / name).is_file():
                write_atomic(folder / name, (source / name).read_bytes())
        adopted.append(cell)
    return adopted


def reusable_record(plan: BenchPlan, cell: Cell, others: Sequence[Path]) -> Path | None:
    """The first cell folder among the bench folders `others` that has finished `cell` with its settings."""
    for other in others:
        source = Path(other) / CELLS_DIR / cell.name
        if plan.status(source) == DONE and not config_differences(source, cell.config):
            return source
    return None


def _resume_state(folder: Path, cell: Cell) -> FitState | None:
    """The checkpoint's loop state when the folder holds one of this cell's settings; else a fresh run folder
    (also where its config.json or checkpoint cannot be used, with a note)."""
    if (folder / CONFIG_FILE).is_file():
        try:
            state = None if config_differences(folder, cell.config) else resumed_state(
                folder, cell.config, cell.run, cell.scene.source)
        except CvqpgError as error:
            log.warning(f"{error}; cell {cell.name} restarts from step 0")
        else:
            if state is not None:
                return state
    start_run(folder, cell.config, cell.scene.source, cell.run)
    return None


def run_cell(cell: Cell, folder: Path, control: RunControl = SILENT, checkpoint_every: int | None = None) -> str:
    """Fit one cell into `folder` (resuming its checkpoint) unless done; returns the cell's new status.

    Writes `spectrum.json` from the float reconstructions, then the run folder, whose `metrics.json`
    comes last. A stop request (`control`) saves a checkpoint and returns `interrupted`; the fit saves one every
    `checkpoint_every` steps too (`runner.checkpoint_policy`).
    """
    if (folder / METRICS_FILE).is_file():
        return SKIPPED
    if control.should_stop():
        return NOT_STARTED
    config = cell.config
    scene = scene_from_source(cell.scene.source, config)
    state = _resume_state(folder, cell)
    (folder / ERROR_FILE).unlink(missing_ok=True)
    try:
        result = fit_in_folder(folder, scene, config, cell.run, control, state, source=cell.scene.source,
                               **checkpoint_policy(checkpoint_every))
    except FitInterrupted:
        return INTERRUPTED
    recon = result.reconstructions
    write_json(folder / SPECTRUM_FILE, spectrum_record(recon, scene.targets.to(recon.device)))
    encoding = METHODS[cell.method].exported
    extra = None if encoding is None else {EXPORTED_KEY: exported_display(result, scene, encoding)}
    write_fitted_run(folder, result, scene, cell.scene.source, extra)
    return DONE


def exported_display(result: FitResult, scene: Scene, encoding: str) -> dict[str, Any]:
    """What the display of `encoding` shows of a fitted model, with the defaults `cvqpg export` shows it with
    (`runs.export_display`): the display and its metrics against the scene's targets."""
    display = export_display(result.config, encoding)
    _, shown = render(result.primitives, result.config.replace(display=display), backend=result.run.backend)
    return {"display": display.to_dict(), **evaluate(shown, scene.targets.to(shown.device)).to_dict()}


@dataclass(frozen=True)
class RateDistortionOptions:
    """How a rate–distortion grid's cells get their points: `fits`, bench folders whose kept models
    they take; `finetune_steps`, the steps of quantisation-aware fine-tuning at some of the codec's
    budgets (0: none; see `ratedistortion.finetuned_points`); `budget_fractions`, the preset's `--bpp` budgets
    (`ratedistortion.budget_points`, each fine-tuned for `RATE_FINETUNE_STEPS` as `cvqpg compress --bpp` is);
    `encode_fractions`, those of the encode grid (`run_encode_cell`), each encoded with each of
    `encode_rate_losses` (without and with the rate in the fit), after the cell's own rate grid record where
    `fits_first`."""

    fits: tuple[Path, ...] = ()
    finetune_steps: int = 0
    budget_fractions: tuple[float, ...] = ()
    encode_fractions: tuple[float, ...] = ()
    encode_rate_losses: tuple[bool, ...] = (False,)
    fits_first: bool = False


def fitted_model(cell: Cell, fits: Sequence[Path]) -> Path | None:
    """The model of the first bench folder in `fits` that finished this cell with the same settings and
    kept its `model.safetensors` (a recorded `results/` folder keeps none)."""
    for other in fits:
        source = Path(other) / CELLS_DIR / cell.name
        if ((source / MODEL_FILE).is_file() and cell_status(source) == DONE
                and not config_differences(source, cell.config)):
            return source / MODEL_FILE
    return None


def run_rate_distortion_cell(cell: Cell, folder: Path, options: RateDistortionOptions,
                             control: RunControl = SILENT, checkpoint_every: int | None = None) -> str:
    """A rate–distortion cell: take the fit from `options.fits` (its records copied) or fit it here, then
    write `rd.json` with the R-D points of its model against the scene's targets
    (`ratedistortion.cell_record`)."""
    from .ratedistortion import cell_record

    if (folder / RD_FILE).is_file():
        return SKIPPED
    model = fitted_model(cell, options.fits)
    if model is not None:
        folder.mkdir(parents=True, exist_ok=True)
        for name in RECORD_FILES:
            if (model.parent / name).is_file():
                write_atomic(folder / name, (model.parent / name).read_bytes())
    else:
        status = run_cell(cell, folder, control, checkpoint_every)
        if status not in (DONE, SKIPPED):
            return status
        model = folder / MODEL_FILE
        if not model.is_file():
            raise BenchError(f"{folder} holds a finished fit but no {MODEL_FILE}; give --fits DIR with that "
                             "cell's model, or delete the cell folder to refit it")
    if control.should_stop():
        return INTERRUPTED
    scene = scene_from_source(cell.scene.source, cell.config)
    write_json(folder / RD_FILE, cell_record(model, scene, finetune_steps=options.finetune_steps,
                                             budget_fractions=options.budget_fractions,
                                             budget_finetune_steps=RATE_FINETUNE_STEPS if options.budget_fractions
                                             else 0))
    return DONE


def encode_work_folder(bpp: float, rate_loss: bool = False) -> str:
    """The folder, in an encode cell's, of the fit at `bpp` (with the rate in its loss: `rate_loss`) while it runs:
    its checkpoint, kept when the cell stops (not in git, which keeps the finished points only)."""
    return f"encode-{bpp:.4f}bpp{'-rate' if rate_loss else ''}.partial"


def untried(record: dict[str, Any], fractions: Sequence[float], rate_losses: Sequence[bool] = (False,)) -> list[float]:
    """Those of `fractions` that a finished encode cell's record (`encode.json`) did not try with each of
    `rate_losses` (a record without `rate_losses` tried without the rate in the fit)."""
    tried_losses = record.get("rate_losses", [False])
    return [f for f in fractions if not any(math.isclose(f, tried) for tried in record.get("fractions", []))
            or not set(rate_losses) <= set(tried_losses)]


def run_encode_cell(cell: Cell, folder: Path, fractions: Sequence[float], control: RunControl = SILENT,
                    rate_losses: Sequence[bool] = (False,)) -> str:
    """An encode grid's cell: `cvqpg encode --bpp` of the cell's scene (`ratedistortion.encode_point`, the default
    recipe, `encode_steps` in the place of the cell's steps) at `fractions` of the rate its rate grid cell's
    budgets are fractions of, into `encode.json`. Each point is a whole fit; the finished ones are kept in
    `encode.partial.json`, so a stopped cell resumes at its first budget without a point, whose fit continues
    from the checkpoint in its folder (`encode_work_folder`). A finished cell whose `encode.json` lacks some of
    `fractions` (the grid gained a budget) is skipped no longer: it fits the budgets it lacks and keeps its points.
    Each budget is encoded with each of `rate_losses` (`ratedistortion.encode_point`'s `rate_loss`)."""
    from .ratedistortion import ENCODER, ENCODER_RATE, encode_point, rate_base

    base = rate_base(read_record(folder / RD_FILE, RESTORE_ENCODE))
    partial, finished_file = folder / ENCODE_PARTIAL_FILE, folder / ENCODE_FILE
    if partial.is_file():
        record = read_record(partial, RESTORE_ENCODE)
    elif finished_file.is_file():
        record = {key: value for key, value in read_record(finished_file, RESTORE_ENCODE).items() if key != "run"}
    else:
        record = {"fractions": [], "base_bpp": base, "points": [], "skipped_bpp": []}

    def lacks(fraction: float, rate_loss: bool) -> bool:
        label = ENCODER_RATE if rate_loss else ENCODER
        finished = [point["budget_bpp"] for point in record["points"]
                    if point["codec"] == label] + record["skipped_bpp"]
        return not any(math.isclose(fraction * base, done) for done in finished)

    if finished_file.is_file() and not partial.is_file() and not untried(record, fractions, rate_losses):
        return SKIPPED
    record["fractions"] = sorted({*record["fractions"], *fractions}, reverse=True)
    if any(rate_losses):  # a record without them encoded without the rate in the fit, as every older one
        record["rate_losses"] = sorted({*record.get("rate_losses", [False]), *rate_losses})
    fit_steps, finetune_steps = encode_steps(cell.config.optimisation.steps)
    config = cell.config.with_recipe(BEYOND_RECIPE).with_steps(fit_steps).validate()
    scene = scene_from_source(cell.scene.source, config)
    for fraction, rate_loss in itertools.product(fractions, rate_losses):
        bpp = fraction * base
        if not lacks(fraction, rate_loss):
            continue
        if control.should_stop():
            return INTERRUPTED
        try:
            point = encode_point(scene, config, cell.scene.source, bpp, folder / encode_work_folder(bpp, rate_loss),
                                 finetune_steps, cell.run, control, rate_loss)
        except FitInterrupted:
            return INTERRUPTED
        if point is None:
            record["skipped_bpp"].append(bpp)
        else:
            record["points"].append(dataclasses.asdict(point))
        write_json(partial, record)
    write_json(folder / ENCODE_FILE, {**record, "run": machine_record(torch.device(cell.run.device))})
    partial.unlink(missing_ok=True)
    return DONE


def _attempt(cell: Cell, folder: Path, rate_distortion: RateDistortionOptions | None, checkpoint_every: int | None,
             control: RunControl) -> tuple[str, str | None]:
    """A cell's task (`executors.Task.work`): `run_cell`, or `run_rate_distortion_cell` where `rate_distortion` is
    given, with a failure turned into a status, its traceback kept in the cell's `error.log`. Once the task is
    told to stop, no record that marks the cell finished is written (`executors.unless_stopped`)."""
    try:
        with unless_stopped(control, *(folder / name for name in (METRICS_FILE, RD_FILE, ENCODE_FILE))):
            return _cell_status(cell, folder, rate_distortion, checkpoint_every, control), None
    except TaskStopped:  # the cell stays unfinished, and resumes on the next run
        return INTERRUPTED, None
    except Exception as error:  # one broken cell must not cost the rest of the grid; it is reported
        folder.mkdir(parents=True, exist_ok=True)
        (folder / ERROR_FILE).write_text(traceback.format_exc())
        return FAILED, f"{type(error).__name__}: {error} (traceback in {folder / ERROR_FILE})"


def _cell_status(cell: Cell, folder: Path, rate_distortion: RateDistortionOptions | None,
                 checkpoint_every: int | None, control: RunControl) -> str:
    """`_attempt`'s work, by the grid's kind: the cell's fit, its rate–distortion points or its encode points."""
    if rate_distortion is not None and rate_distortion.encode_fractions:
        if rate_distortion.fits_first:
            status = run_rate_distortion_cell(cell, folder, rate_distortion, control, checkpoint_every)
            if status not in (DONE, SKIPPED):
                return status
        return run_encode_cell(cell, folder, rate_distortion.encode_fractions, control,
                               rate_distortion.encode_rate_losses)
    if rate_distortion is not None:
        return run_rate_distortion_cell(cell, folder, rate_distortion, control, checkpoint_every)
    return run_cell(cell, folder, control, checkpoint_every)


def run_plan(plan: BenchPlan, cells: tuple[Cell, ...] | None = None, jobs: int = 1,
             control: RunControl = RunControl(), reuse: Sequence[Path] = (),
             rate_distortion: RateDistortionOptions = RateDistortionOptions(), threads: int | None = None,
             executor: ExecutorOptions | None = None) -> BenchOutcome:
    """Fit every cell of `cells` (default: the whole plan) that is not done, `jobs` at a time; cells
    that a bench folder in `reuse` has finished with the same settings are copied, not fitted. In a
    rate–distortion grid a cell takes its model from the first folder of `rate_distortion.fits` that
    kept it.

    The cells run on `executor` (`executors.run_tasks`), by default the local one with `jobs` and `threads`: a
    spawn-context process pool for jobs > 1, each fit on `threads` threads, by default its share of the cores
    (cores // jobs, at least 1). `control` shows the grid's progress bar (the fits show none) and asks to stop:
    running fits then save a checkpoint and stop, and no new cell starts.
    """
    cells = plan.cells if cells is None else cells
    executor = (ExecutorOptions(jobs=jobs, threads=threads) if executor is None else executor).validate()
    check_cells_device(cells, executor)
    outcome = BenchOutcome()
    reusable = {cell.name for cell in cells
                if plan.status(plan.cell_dir(cell)) != DONE and reusable_record(plan, cell, reuse) is not None}
    todo = [cell for cell in cells if cell.name not in reusable and plan.status(plan.cell_dir(cell)) != DONE]
    check_inputs(plan, cells, reusable)
    # Ray connected and checked before the first cell is adopted: a refusal writes nothing
    with ready(executor if todo else ExecutorOptions(), plan.folder):
        adopted = {cell.name for cell in adopt_finished(plan, cells, reuse, control)}
        for cell in cells:
            if cell.name in reusable:  # not adopted where a stop came first
                outcome.statuses[cell.name] = REUSED if cell.name in adopted else NOT_STARTED
            elif plan.status(plan.cell_dir(cell)) == DONE:
                outcome.statuses[cell.name] = SKIPPED
        _run_cells(plan, todo, executor, control, rate_distortion, outcome)
    return outcome


def _run_cells(plan: BenchPlan, todo: list[Cell], executor: ExecutorOptions, control: RunControl,
               rate_distortion: RateDistortionOptions, outcome: BenchOutcome) -> None:
    """The tasks of the cells `todo` on `executor` (`run_plan`), their statuses and failures into `outcome`."""
    preset = PRESETS[plan.preset]
    rd_options = (dataclasses.replace(rate_distortion, budget_fractions=preset.budget_fractions,
                                      encode_fractions=preset.encode_fractions,
                                      encode_rate_losses=preset.encode_rate_losses, fits_first=preset.fits_first)
                  if preset.rate_distortion else None)
    tasks = [Task(cell.name, functools.partial(_attempt, cell, plan.cell_dir(cell), rd_options,
                                               executor.checkpoint_every), cell.config.optimisation.steps)
             for cell in todo]
    for name, (status, error) in run_tasks(tasks, executor, control, f"bench {plan.preset}", plan.folder,
                                           unit="cell").items():
        outcome.statuses[name] = status
        if error is not None:
            outcome.failures[name] = error

