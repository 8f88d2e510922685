"""`cvqpg batch`: the images of a folder of scenes or of a CSV manifest, each fitted into a run folder or a
`.cvq` file of one batch folder.

A batch folder holds, for each item NAME, its output: `NAME/`, a run folder as `cvqpg fit` leaves it, or
`NAME.cvq` as `cvqpg encode` writes it (with a budget). While the item is unfinished its work lies beside it,
in `NAME.partial/` or `NAME.cvq.partial/` with its checkpoint, and is moved into place when it is finished; an
item that failed on a bug leaves its traceback in `NAME.error.log`. `summary.csv` and `summary.md` list every
item; `BATCH_RECORDS/` holds the items in order and one record per item, which the summaries are made of
and which mark the folder as a batch folder.

The batch owns only what its records say it made: an item's record names the output the batch wrote for it by
its fingerprint (`fingerprint`), so that a folder or file that someone else put at `NAME` or `NAME.cvq` is never
taken for the item's output, nor replaced; it never writes through a symbolic link, and everything at the paths it
writes is checked for its kind before the first byte is written (`check_places`). An item is finished once its
record says so and its output is the one the record names. Each item is one task (`run_item`) that may run again
at any point, as a retried task does: it skips a finished item, resumes an unfinished one from its checkpoint and
tries a failed one again, and whatever stops it leaves the output whole or absent.
"""

from __future__ import annotations

import csv
import fcntl
import hashlib
import io
import json
import math
import os
import shutil
import time
import traceback
import unicodedata
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, Callable, Sequence

import torch
from PIL import Image

from ..config import DEFAULT_RECIPE, FitConfig, RunOptions
from ..control import RunControl
from ..defaults import BATCH_RECORDS, ENCODE_FINETUNE_STEPS, ENCODE_STEPS, PARTIAL_SUFFIX, SUFFIX
from ..errors import CvqpgError, InputError, allocation_failure, filesystem_refusal
from ..files import replace_folder, write_atomic
from ..fitting import FitInterrupted
from ..runs import CONFIG_FILE, METRICS_FILE, MODEL_FILE, read_run, scene_from_source, start_run, write_json
from ..search import CompressionSettings
from ..targets import EXIF_ORIENTATION, check_file, depth_geometry_note, other_aspect
from .encoding import (encode_budget, encode_config, encode_fit, encode_in_folder, encoding_record, read_encode,
                       start_encode)
from .executors import (DONE, FAILED, INTERRUPTED, NOT_STARTED, SKIPPED, ExecutorFlags, ExecutorOptions, Task,
                        TaskStopped, ready, run_tasks, unless_stopped)
from .outputs import open_lock
from .outputs import place_problem as outputs_place_problem
from .provenance import device_name
from .runner import checkpoint_policy, fit_in_folder, resumed_state, write_fitted_run

ITEMS_FILE = "items.json"
SUMMARY_CSV, SUMMARY_MD = "summary.csv", "summary.md"
ERROR_SUFFIX = ".error.log"
SUMMARY_LOCK = "summary.lock"
SUMMARY_SECONDS = 10.0  # the summaries are rewritten at most this often while the items run
IMAGE_STEM = "image"  # a scene folder's image: the item takes the folder's name
DEPTH_NAME = "depth.png"
# What a failure is owed to: the input (bad file, bad option), the file system, the memory, or a bug.
INPUT, FILESYSTEM, MEMORY, BUG = "input", "file system", "memory", "bug"
SUMMARY_COLUMNS = ("name", "status", "output", "psnr_db", "bytes", "bpp", "steps", "seconds", "device", "note",
                   "error")
NO_DEPTH_NOTE = "no depth map: fitted at one plane"
NAME_BYTES = 255  # the longest file name of the usual file systems
# The most bytes the batch adds to an item's name: its record's atomic write, `.batch/NAME.json.PID.partial` (a
# PID of up to 7 digits); `NAME.cvq.PID.partial` and `.NAME.replaced-PID` are shorter.
ADDED_NAME_BYTES = len(".json") + len(".1234567") + len(PARTIAL_SUFFIX)


def _whole(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise ValueError("is not a whole number") from None


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError("is not a number") from None
    if not math.isfinite(value):
        raise ValueError("is not a finite number")
    return value


# A manifest's columns: the item's files and name, then the options a row may give for itself, as
# `cvqpg batch` spells them (`planes` is `--planes`), each read by its type.
MANIFEST_FILES = ("image", "depth", "name")
ROW_OPTIONS: dict[str, Callable[[str], Any]] = {
    "color": str, "primitive": str, "recipe": str, "ratio": _finite, "num_gaussians": _whole, "steps": _whole,
    "seed": _whole, "planes": _whole, "bpp": _finite, "max_bytes": _whole}


@dataclass(frozen=True)
class BatchInput:
    """One item as the inputs name it: its name, image and depth map (None: none), and the options its manifest
    row gives (`ROW_OPTIONS`, as written; empty cells left out). `origin` names it in messages."""

    name: str
    image: Path
    depth: Path | None = None
    options: dict[str, str] = field(default_factory=dict)
    origin: str = ""


@dataclass(frozen=True)
class BatchSettings:
    """The command's options for every item: the `recipe` and the `FitConfig.create` settings given
    (`settings`; `color`, `num_planes` and `steps` left out or None take the item's defaults), where the fits
    run, the budget of a `.cvq` item (`bpp` or `max_bytes`; neither: a run folder), its fine-tuning steps and
    whether its fit has the rate in its loss (`rate_loss`, `search.CompressionSettings`),
    whether a depth map of another aspect ratio is stretched, and whether finished items are fitted again
    (`redo`), each replaced once its new output is finished."""

    recipe: str | None = DEFAULT_RECIPE  # None: `FitConfig.create`'s, by the item's primitive
    settings: dict[str, Any] = field(default_factory=dict)
    run: RunOptions = RunOptions()
    bpp: float | None = None
    max_bytes: int | None = None
    finetune_steps: int = ENCODE_FINETUNE_STEPS
    resize_depth: bool = False
    redo: bool = False
    rate_loss: bool = False


@dataclass(frozen=True)
class BatchItem:
    """One item's work in the batch `folder`: a fit of `config` on `source` on `run`, into the run folder
    `folder/name`, or with `budget` into the file `folder/name.cvq`; checkpoints every `checkpoint_every` steps
    (0: only when stopped; None: every `CHECKPOINT_SECONDS` of work). `note` goes into its summary row."""

    name: str
    folder: Path
    config: FitConfig
    source: dict[str, Any]
    run: RunOptions = RunOptions()
    budget: CompressionSettings | None = None
    note: str | None = None
    redo: bool = False
    checkpoint_every: int | None = None

    @property
    def output(self) -> Path:
        return self.folder / (f"{self.name}{SUFFIX}" if self.budget is not None else self.name)

    @property
    def work(self) -> Path:
        """Where the unfinished item lies, with its checkpoint."""
        return self.output.with_name(self.output.name + PARTIAL_SUFFIX)

    @property
    def log(self) -> Path:
        """Where a bug's traceback goes."""
        return self.folder / f"{self.name}{ERROR_SUFFIX}"

    def owned(self) -> bool:
        """Whether what lies at the output is the one that the item's record names: its fingerprint, or for a
        record of cvqpg 0.3 (which has none), a finished item's output."""
        record = read_item_record(self.folder, self.name) or {}
        if "fingerprint" in record:
            return record["fingerprint"] == fingerprint(self.output)
        return (record.get("status") == DONE and record.get("output") == self.output.name
                and (self.output.is_file() if self.budget is not None else (self.output / METRICS_FILE).is_file()))

    def finished(self) -> bool:
        """The item's record says it is done, and its output is the one the record names."""
        return (read_item_record(self.folder, self.name) or {}).get("status") == DONE and self.owned()


@dataclass
class BatchOutcome:
    """What a batch did: a status per item, and for each failed one its error line and what it is owed to
    (`INPUT`, `FILESYSTEM`, `MEMORY` or `BUG`)."""

    statuses: dict[str, str] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)
    kinds: dict[str, str] = field(default_factory=dict)

    def describe(self) -> str:
        """E.g. `3 done, 1 skipped, 0 interrupted, 0 not started, 1 failed`."""
        counts = [(status, sum(s == status for s in self.statuses.values()))
                  for status in (DONE, SKIPPED, INTERRUPTED, NOT_STARTED, FAILED)]
        return ", ".join(f"{count} {status}" for status, count in counts)


# The inputs.

def check_name(name: str, origin: str) -> str:
    """An item's name: one path component that names none of the batch's own files and no other item's work, in
    UTF-8 without control characters, short enough for what the batch keeps beside it (`ADDED_NAME_BYTES`)."""
    if (not name or name != name.strip() or "/" in name or "\\" in name or name.startswith(".")
            or name.endswith((PARTIAL_SUFFIX, SUFFIX, ERROR_SUFFIX)) or name in (SUMMARY_CSV, SUMMARY_MD)):
        raise InputError(f"{origin}: {name!r} cannot name an item (its output's file or folder name); give a name "
                         f"without a slash or a leading dot, not ending in {PARTIAL_SUFFIX}, {SUFFIX} or "
                         f"{ERROR_SUFFIX}")
    control = next((c for c in name if unicodedata.category(c) == "Cc"), None)
    if control is not None:
        raise InputError(f"{origin}: the name {name!r} holds a control character (U+{ord(control):04X}); give a "
                         "name of printable characters")
    try:
        size = len(name.encode("utf-8"))
    except UnicodeEncodeError:
        raise InputError(f"{origin}: the name {name!r} is not valid UTF-8; rename it") from None
    if size + ADDED_NAME_BYTES > NAME_BYTES:
        raise InputError(f"{origin}: the name {name[:24]}… is {size} bytes long, and the batch's files beside its "
                         f"output take at most {NAME_BYTES - ADDED_NAME_BYTES}; give a shorter name")
    return name


@dataclass(frozen=True)
class SceneFiles:
    """A scene folder's files: `NAME/image.*` and, where it has one, `NAME/depth.png`."""

    name: str
    image: Path
    depth: Path | None


def scene_folders(root: Path) -> tuple[SceneFiles, ...]:
    """The scene folders of `root` in name order (`<name>/image.*`, optional `<name>/depth.png`); sub-folders
    without an image are left out, and one with several images is an `InputError`."""
    scenes = []
    for sub in sorted(p for p in Path(root).iterdir() if p.is_dir() and not p.name.startswith(".")):
        images = sorted(sub.glob(f"{IMAGE_STEM}.*"))
        if len(images) > 1:
            raise InputError(f"scene {sub.name}: several image files ({', '.join(p.name for p in images)}); "
                             "keep one")
        if images:
            depth = sub / DEPTH_NAME
            scenes.append(SceneFiles(sub.name, images[0], depth if depth.exists() else None))
    return tuple(scenes)


def read_inputs(path: str | Path) -> tuple[BatchInput, ...]:
    """The items of a folder of scenes (`scene_folders`) or of a CSV manifest (`read_manifest`), names checked
    (`check_name`) and unique; `InputError` naming what cannot be read."""
    path = Path(path)
    if path.is_dir():
        items = tuple(BatchInput(check_name(s.name, f"scene folder {s.name}"), s.image, s.depth,
                                 origin=f"scene folder {path / s.name}") for s in scene_folders(path))
        if not items:
            raise InputError(f"{path} holds no scene folders (NAME/image.*, with an optional NAME/{DEPTH_NAME}); "
                             "give a folder of them or a CSV manifest")
        return items
    if not path.is_file():
        raise InputError(f"{path}: no such folder of scenes or CSV manifest")
    return read_manifest(path)


def read_manifest(path: Path) -> tuple[BatchInput, ...]:
    """A CSV manifest's items: one row each, with columns `image` (required), `depth`, `name` (default: the
    image's stem, or its folder's name for a scene folder's `image.*`) and `ROW_OPTIONS`; paths relative to the
    manifest's folder. `InputError` for an unreadable file, an unknown or missing column, a row without an image,
    or names that clash."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"manifest {path} cannot be read as a UTF-8 CSV file ({error})") from None
    try:
        return _manifest_items(path, csv.DictReader(io.StringIO(text)))
    except csv.Error as error:
        raise InputError(f"manifest {path} is not a CSV file cvqpg reads ({error})") from None


def _manifest_items(path: Path, reader: csv.DictReader) -> tuple[BatchInput, ...]:
    columns = [c.strip() for c in reader.fieldnames or []]
    known = (*MANIFEST_FILES, *ROW_OPTIONS)
    twice = next((c for i, c in enumerate(columns) if c in columns[:i]), None)
    if twice is not None:
        raise InputError(f"manifest {path}: the column {twice!r} is named twice in the header; keep one")
    unknown = [c for c in columns if c not in known]
    if unknown:
        raise InputError(f"manifest {path}: unknown column {unknown[0]!r}; the columns are {', '.join(known)}")
    if "image" not in columns:
        raise InputError(f"manifest {path} has no image column (a header line naming its columns comes first: "
                         f"{', '.join(known)})")
    items, rows = [], {}
    for line, raw in enumerate(reader, start=2):
        if None in raw:
            raise InputError(f"manifest {path} line {line} has more cells than the header has columns")
        row = {key.strip(): (value or "").strip() for key, value in raw.items()}
        if not any(row.values()):
            continue
        origin = f"manifest {path} line {line}"
        if not row["image"]:
            raise InputError(f"{origin} names no image")
        image = path.parent / row["image"]
        name = row.get("name") or (image.parent.name if image.stem == IMAGE_STEM else image.stem)
        if name in rows:
            raise InputError(f"{origin}: the name {name!r} is line {rows[name]}'s too; names are unique (give a "
                             "name column)")
        rows[name] = line
        depth = path.parent / row["depth"] if row.get("depth") else None
        options = {key: value for key, value in row.items() if key in ROW_OPTIONS and value}
        items.append(BatchInput(check_name(name, origin), image, depth, options, origin))
    if not items:
        raise InputError(f"manifest {path} lists no items")
    return tuple(items)


# One item's settings.

def row_options(item: BatchInput) -> dict[str, Any]:
    """The item's own options, read by their types (`ROW_OPTIONS`)."""
    options = {}
    for name, text in item.options.items():
        try:
            options[name] = ROW_OPTIONS[name](text)
        except ValueError as error:
            raise InputError(f"column {name}: {text!r} {error}") from None
    return options


def item_settings(settings: BatchSettings, options: dict[str, Any], has_depth: bool
                  ) -> tuple[FitConfig, CompressionSettings | None, str | None]:
    """The fit, the budget (None: a run folder) and the summary's note of an item with the command's `settings`
    and its own `options` (`row_options`): a row's `ratio` replaces the command's `num_gaussians`, a row's budget
    the command's. Without `num_planes`, an item fits 2 planes, or 1 without a depth map (with a note); more than
    one plane without a depth map is an `InputError`, as are settings that cannot work (a `ConfigError`)."""
    flat = {**settings.settings, **{k: v for k, v in options.items() if k not in ("recipe", "planes", "bpp",
                                                                                   "max_bytes")}}
    if "ratio" in options and "num_gaussians" not in options:
        flat["num_gaussians"] = None
    planes = options.get("planes", flat.pop("num_planes", None))
    note = None
    if planes is None:
        planes, note = (2, None) if has_depth else (1, NO_DEPTH_NOTE)
    elif planes > 1 and not has_depth:
        raise InputError(f"{planes} planes (`num_planes`) need a depth map; give one (a scene folder's "
                         f"{DEPTH_NAME}, a manifest's depth column), or set `num_planes` to 1")
    own_budget = "bpp" in options or "max_bytes" in options
    bpp, max_bytes = ((options.get("bpp"), options.get("max_bytes")) if own_budget
                      else (settings.bpp, settings.max_bytes))
    budget = CompressionSettings(bpp=bpp, max_bytes=max_bytes, finetune_steps=settings.finetune_steps,
                                 rate_loss=settings.rate_loss and (bpp is not None or max_bytes is not None))
    if flat.get("steps") is None:
        flat["steps"] = ENCODE_STEPS if budget.budgeted else FitConfig().optimisation.steps
    flat["color"] = flat.get("color") or "rgb"
    config = FitConfig.create(options.get("recipe", settings.recipe), num_planes=planes, **flat).validate()
    if budget.budgeted:
        encode_budget(config, budget)
    return config, budget if budget.budgeted else None, note


def check_settings(settings: BatchSettings) -> None:
    """The command's `settings` work for an item with a depth map and no options of its own (else a
    `CvqpgError`), so that settings that cannot work stop the batch before anything is written."""
    item_settings(settings, {}, has_depth=True)


def plan_item(item: BatchInput, folder: Path, settings: BatchSettings) -> BatchItem:
    """The work of `item` in the batch `folder` (`item_settings`); an `InputError` naming the item where its
    options cannot work."""
    try:
        config, budget, note = item_settings(settings, row_options(item), item.depth is not None)
    except CvqpgError as error:
        raise InputError(f"{item.origin}: {error}") from None
    source = {"image": str(item.image.resolve())}
    if item.depth is not None:
        source["depth"] = str(item.depth.resolve())
    if settings.resize_depth:
        source["resize_depth"] = True
        stretched = _stretched_depth(item)
        note = "; ".join(filter(None, (note, stretched)))
    return BatchItem(item.name, Path(folder), config, source, settings.run, budget, note, settings.redo)


def _stretched_depth(item: BatchInput) -> str | None:
    """The note of an item whose depth map has another aspect ratio than its image (stretched with
    `resize_depth`), read from the files' headers; None where it has the image's, or a file does not open (the
    item's fit says why)."""
    if item.depth is None:
        return None
    sizes = []
    try:
        for path in (item.image, item.depth):
            with Image.open(check_file(path)) as picture:  # a pipe is refused, not waited on
                turned = picture.getexif().get(EXIF_ORIENTATION, 1) in (5, 6, 7, 8)  # shown turned by 90°
                sizes.append(picture.size[::-1] if turned else picture.size)
    except Exception:  # any file Pillow cannot open fails the item's fit, with its own line
        return None
    return depth_geometry_note(*sizes) if other_aspect(*sizes) else None


# What the batch owns, and what lies at the paths it writes.

def fingerprint(output: Path) -> str | None:
    """What identifies an item's output: the SHA-256 of a `.cvq` file's bytes, or of a run folder's settings and
    model (`config.json`, `model.safetensors`, which `eval`, `export` or `compress` in it leave as they are);
    None where there is none, or it cannot be read."""
    digest = hashlib.sha256()
    try:
        if output.is_symlink():
            return None
        if output.is_file():
            digest.update(output.read_bytes())
        elif output.is_dir():
            for name in (CONFIG_FILE, MODEL_FILE):
                digest.update((output / name).read_bytes())
        else:
            return None
    except OSError:
        return None
    return digest.hexdigest()


def place_problem(path: Path, folder: bool) -> str | None:
    """What keeps the batch from writing a folder (`folder`) or a file at `path` (`outputs.place_problem`)."""
    return outputs_place_problem(path, folder, "the batch")


def item_problem(item: BatchItem) -> str | None:
    """What lies in the way of `item`'s work: at its output, something that is not the output its record names
    (a folder or file someone else put there, which the batch neither takes for the item's nor replaces); at its
    unfinished work, anything but an empty or a run folder; a link or another kind at its record or its log."""
    folder = item.budget is None
    problem = (place_problem(item.output, folder) or place_problem(item.work, True)
               or place_problem(item.log, False) or place_problem(_record_path(item.folder, item.name), False))
    if problem is not None:
        return problem
    if item.output.exists() and not item.owned():
        what = "run folder" if folder else f"{SUFFIX} file"
        return (f"{item.output} is not a {what} this batch wrote for the item {item.name} (its records name no such "
                "output); the batch neither counts it as done nor replaces it")
    if item.work.is_dir() and any(item.work.iterdir()) and not (item.work / CONFIG_FILE).is_file():
        return f"{item.work} holds files that are not an unfinished fit's"
    return None


def check_places(plan: "BatchPlan") -> None:
    """Everything at the paths the batch writes is the batch's, or absent, and of the kind the batch writes there
    (`place_problem`, `item_problem`): else an `InputError` naming the first path in the way, before anything is
    written."""
    folder = plan.folder
    records = folder / BATCH_RECORDS
    problems = [place_problem(records, True), *(place_problem(path, False) for path in (
        records / ITEMS_FILE, records / SUMMARY_LOCK, folder / SUMMARY_CSV, folder / SUMMARY_MD))]
    problems += [place_problem(_record_path(folder, name), False) for name in plan.refused]
    problems += [item_problem(item) for item in plan.items]
    problem = next((problem for problem in problems if problem is not None), None)
    if problem is not None:
        raise InputError(f"{problem}; move it away, or choose another batch folder")


# One item's work.

def _check_place(item: BatchItem) -> None:
    """`item_problem`, as an `InputError`: what appeared in the item's way since the batch began."""
    problem = item_problem(item)
    if problem is not None:
        raise InputError(f"{problem}; move it away and run the batch again")


def _same_fit(work: Path, config: FitConfig, source: dict[str, Any]) -> bool:
    """Whether the unfinished item in `work` was started for the fit of `config` on `source`."""
    try:
        return read_run(work) == (config, source)
    except CvqpgError:
        return False


def _fit_item(item: BatchItem, control: RunControl) -> str:
    """Fit `item` into its run folder, resuming its checkpoint: in `item.work`, moved into place when finished."""
    work = item.work
    same = _same_fit(work, item.config, item.source)
    if not (same and (work / METRICS_FILE).is_file()):  # else finished, but not yet moved into place
        scene = scene_from_source(item.source, item.config)
        state = None
        if same:
            try:
                state = resumed_state(work, item.config, item.run)
            except CvqpgError:  # a checkpoint that cannot be resumed: the item starts again
                state = None
        if state is None:
            start_run(work, item.config, item.source, item.run)
        try:
            result = fit_in_folder(work, scene, item.config, item.run, control, state,
                                   **checkpoint_policy(item.checkpoint_every))
        except FitInterrupted:
            return INTERRUPTED
        write_fitted_run(work, result, scene, item.source)
    _publish(item, _run_record(item, work), lambda: replace_folder(work, item.output))
    return DONE


def _publish(item: BatchItem, record: dict[str, Any], move: Callable[[], None]) -> None:
    """The item's record saying it is done (`record`, with its output's fingerprint), then its output moved into
    place (`move`); where the move fails, or is held back (a stop: `executors.unless_stopped`), the record is put
    back as it was, so that it names the output that lies there."""
    path, before = _record_path(item.folder, item.name), read_item_record(item.folder, item.name)
    write_record(item.folder, record)
    try:
        move()
    except BaseException:
        if before is None:
            path.unlink(missing_ok=True)
        else:
            write_json(path, before)
        raise


def _run_record(item: BatchItem, folder: Path) -> dict[str, Any]:
    """The summary row of the finished run folder `folder` (its metrics and model file)."""
    metrics = json.loads((folder / METRICS_FILE).read_text())
    size = (folder / MODEL_FILE).stat().st_size
    return {"name": item.name, "status": DONE, "output": item.output.name, "psnr_db": metrics["mean"]["psnr"],
            "bytes": size, "bpp": 8 * size / (item.config.targets.width * item.config.targets.height),
            "steps": metrics["steps"], "seconds": metrics["seconds"],
            "device": (metrics.get("run") or {}).get("device"), "note": item.note, "fingerprint": fingerprint(folder)}


def _encode_item(item: BatchItem, control: RunControl) -> str:
    """Encode `item` into its `.cvq` file (`app.encoding`'s workflow), resuming the checkpoint in `item.work`."""
    budget = encode_budget(item.config, item.budget)  # checked when planned; the budget in bytes
    config = encode_config(item.config, budget)
    finetune_steps, fit = item.budget.finetune_steps, item.budget.rate_fit(budget)
    scene = scene_from_source(item.source, config)
    work = item.work
    try:
        resumable = (read_encode(work) == (config, item.source, budget, finetune_steps)
                     and encode_fit(work) == fit)
    except CvqpgError:
        resumable = False
    if not resumable:  # an empty folder, or an unfinished fit of other settings (`item_problem`)
        if work.is_dir():
            shutil.rmtree(work)
        start_encode(work, config, item.source, budget, finetune_steps, item.run, fit)
    try:
        encoded = encode_in_folder(work, scene, config, budget, finetune_steps, item.run, control,
                                   **checkpoint_policy(item.checkpoint_every), fit=fit)
    except FitInterrupted:
        return INTERRUPTED
    record = encoding_record(encoded, item.output, budget)
    data = encoded.rate.choice.data
    _publish(item, {
        "name": item.name, "status": DONE, "output": item.output.name, "psnr_db": record["psnr"],
        "bytes": record["bytes"], "bpp": record["bits_per_pixel"], "steps": config.optimisation.steps,
        "seconds": encoded.seconds, "device": device_name(torch.device(item.run.device)), "note": item.note,
        "fingerprint": hashlib.sha256(data).hexdigest()}, lambda: write_atomic(item.output, data))
    shutil.rmtree(work)
    return DONE


def failure(error: Exception) -> tuple[str, str]:
    """What a failure is owed to (`INPUT`, `FILESYSTEM`, `MEMORY`, `BUG`) and its line."""
    if isinstance(error, CvqpgError):
        return INPUT, str(error)
    if (refusal := filesystem_refusal(error)) is not None:
        return FILESYSTEM, refusal
    if (shortage := allocation_failure(error)) is not None:
        return MEMORY, shortage
    return BUG, f"internal error ({type(error).__name__}: {error})"


def run_item(item: BatchItem, control: RunControl) -> tuple[str, str | None]:
    """Do `item`'s work (an `executors.Task`'s): its status and, where it failed, its error line. A finished item
    is `SKIPPED` (unless `item.redo`), one that a stop request (`control`) stopped is `INTERRUPTED` with its
    checkpoint, and one not begun `NOT_STARTED`. A failure is recorded, never raised: one line, and for a bug the
    traceback in the item's `NAME.error.log`. The item's record and the batch's summaries are rewritten."""
    if item.finished() and not item.redo:
        return SKIPPED, None
    if control.should_stop():
        return NOT_STARTED, None
    log = item.log
    try:
        _check_place(item)
        log.unlink(missing_ok=True)
        with unless_stopped(control, item.output):
            status = (_encode_item if item.budget is not None else _fit_item)(item, control)
    except TaskStopped:  # its finished work stays beside the output, which the next run moves into place
        status = INTERRUPTED
    except Exception as error:  # one item's failure must not cost the others; it is recorded
        kind, line = failure(error)
        if kind == BUG and place_problem(log, False) is None:
            log.write_text(traceback.format_exc())
            line += f"; traceback in {log}"
        write_record(item.folder, {"name": item.name, "status": FAILED, "output": item.output.name,
                                   "note": item.note, "error": line, "kind": kind})
        update_summary(item.folder)
        return FAILED, line
    if status == INTERRUPTED:
        write_record(item.folder, {"name": item.name, "status": INTERRUPTED, "output": item.work.name,
                                   "note": item.note})
    update_summary(item.folder)
    return status, None


# Records and summaries.

def _record_path(folder: Path, name: str) -> Path:
    return Path(folder) / BATCH_RECORDS / f"{name}.json"


def write_record(folder: Path, record: dict[str, Any]) -> None:
    """The item's record, keeping the fingerprint of the output the batch last wrote for it (`fingerprint`)
    unless `record` gives a new one: until a new output replaces it, that one is the batch's."""
    if "fingerprint" not in record:
        kept = (read_item_record(folder, record["name"]) or {}).get("fingerprint")
        if kept is not None:
            record = {**record, "fingerprint": kept}
    write_json(_record_path(folder, record["name"]), record)


def read_item_record(folder: Path, name: str) -> dict[str, Any] | None:
    """The record of the item `name`, or None where it has none (or an unreadable one)."""
    try:
        record = json.loads(_record_path(folder, name).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def summary_rows(folder: Path) -> list[dict[str, Any]]:
    """One row per item of the batch (`SUMMARY_COLUMNS`), in the items' order: its record, or where it has none
    its state as the folder shows it (its unfinished work: interrupted; else not started: an output without a
    record is not the batch's)."""
    folder = Path(folder)
    rows = []
    for item in json.loads((folder / BATCH_RECORDS / ITEMS_FILE).read_text()):
        record = read_item_record(folder, item["name"])
        if record is None:
            output, work = folder / item["output"], folder / (item["output"] + PARTIAL_SUFFIX)
            status = INTERRUPTED if work.exists() else NOT_STARTED
            record = {"name": item["name"], "status": status, "note": item["note"],
                      "output": (work if status == INTERRUPTED else output).name}
        rows.append({column: record.get(column) for column in SUMMARY_COLUMNS})
    return rows


def _cell(column: str, value: Any) -> str:
    if value is None:
        return ""
    if column in ("psnr_db", "bpp") and isinstance(value, float):
        return f"{value:.4f}"
    if column == "seconds":
        return f"{value:.1f}"
    return str(value)


def write_summary(folder: Path) -> tuple[Path, Path]:
    """`summary.csv` and `summary.md` of the batch `folder` (`summary_rows`), each written atomically."""
    folder = Path(folder)
    rows = summary_rows(folder)
    table = io.StringIO()
    writer = csv.writer(table, lineterminator="\n")
    writer.writerow(SUMMARY_COLUMNS)
    writer.writerows([_cell(column, row[column]) for column in SUMMARY_COLUMNS] for row in rows)
    counts = {}
    for row in rows:
        counts[row["status"]] = counts.get(row["status"], 0) + 1
    header = ("name", "status", "output", "PSNR (dB)", "bytes", "bpp", "steps", "seconds", "device", "note", "error")
    lines = [f"# Batch {folder.name}", "", f"{len(rows)} items: " + ", ".join(f"{n} {s}" for s, n in counts.items())
             + ".", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_cell(c, row[c]).replace("|", "\\|") for c in SUMMARY_COLUMNS) + " |" for row in rows]
    write_atomic(folder / SUMMARY_CSV, table.getvalue())
    write_atomic(folder / SUMMARY_MD, "\n".join(lines) + "\n")
    return folder / SUMMARY_CSV, folder / SUMMARY_MD


def update_summary(folder: Path, now: bool = False) -> None:
    """`write_summary`, one task at a time (a lock file in the records), so that the last to finish writes last;
    unless `now`, only where the summary is older than `SUMMARY_SECONDS` (a summary of N items reads N records,
    and thousands of items finishing one after another would otherwise wait on each other)."""
    folder = Path(folder)
    lock = open_lock(folder / BATCH_RECORDS / SUMMARY_LOCK, f"the batch folder {folder}")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            fresh = time.time() - (folder / SUMMARY_CSV).stat().st_mtime < SUMMARY_SECONDS
        except FileNotFoundError:
            fresh = False
        if now or not fresh:
            write_summary(folder)
    finally:
        os.close(lock)


# The batch.

def start_batch(folder: Path, inputs: Sequence[BatchInput], outputs: dict[str, str], notes: dict[str, str | None]
                ) -> None:
    """The batch folder's records: its items in order, each with its output's name and note."""
    records = Path(folder) / BATCH_RECORDS
    records.mkdir(parents=True, exist_ok=True)
    write_json(records / ITEMS_FILE, [{"name": item.name, "output": outputs[item.name], "note": notes.get(item.name)}
                                      for item in inputs])


@dataclass(frozen=True)
class BatchPlan:
    """A batch in `folder`: its `inputs` in order, the work of those whose settings work (`items`), and the error
    line of each of the others (`refused`, by name)."""

    folder: Path
    inputs: tuple[BatchInput, ...]
    items: tuple[BatchItem, ...]
    refused: dict[str, str]

    def output(self, name: str) -> str:
        """The name of the item's output in the folder (a refused item's: its name)."""
        return next((item.output.name for item in self.items if item.name == name), name)


def plan_batch(inputs: Sequence[BatchInput], folder: Path, settings: BatchSettings = BatchSettings()) -> BatchPlan:
    """The work of every item of `inputs` in the batch `folder` (`plan_item`), and the errors of those whose
    settings cannot work. The folder is made absolute: a task may run in another working folder (on Ray)."""
    folder, items, refused = Path(os.path.abspath(folder)), [], {}
    for given in inputs:
        try:
            items.append(plan_item(given, folder, settings))
        except CvqpgError as error:
            refused[given.name] = str(error)
    return BatchPlan(folder, tuple(inputs), tuple(items), refused)


def run_batch(plan: BatchPlan, options: ExecutorOptions = ExecutorOptions(), control: RunControl = RunControl()
              ) -> BatchOutcome:
    """Do the work of every item of `plan` that is not finished (`run_item`, one task each, run by `options`'
    executor, with its fits' checkpoints every `options.checkpoint_every` steps): `BatchOutcome`. A refused item
    fails at once. The summaries are written before the first task, as each finishes, and at the end."""
    folder, outcome = plan.folder, BatchOutcome()
    check_places(plan)
    todo = [replace(item, checkpoint_every=options.checkpoint_every) for item in plan.items
            if item.redo or not item.finished()]
    with ready(options if todo else ExecutorOptions(), folder):  # Ray, connected and checked before any write
        start_batch(folder, plan.inputs, {given.name: plan.output(given.name) for given in plan.inputs},
                    {item.name: item.note for item in plan.items})
        for name, error in plan.refused.items():
            outcome.statuses[name], outcome.failures[name], outcome.kinds[name] = FAILED, error, INPUT
            write_record(folder, {"name": name, "status": FAILED, "output": name, "error": error, "kind": INPUT})
        pending = {item.name for item in todo}
        for item in plan.items:
            if item.name not in pending:
                outcome.statuses[item.name] = SKIPPED
        for item in todo:  # its state as the folder shows it until the item says more; its output (`check_places`:
            work = item.work.exists()  # the batch's) named by its fingerprint
            record = {"name": item.name, "status": INTERRUPTED if work else NOT_STARTED,
                      "output": (item.work if work else item.output).name, "note": item.note}
            if item.output.exists():
                record["fingerprint"] = fingerprint(item.output)
            write_record(folder, record)
        update_summary(folder, now=True)
        tasks = [Task(item.name, partial(run_item, item), item.config.optimisation.steps) for item in todo]
        statuses = run_tasks(tasks, options, control, "batch", folder, "item")
    for name, (status, error) in statuses.items():
        outcome.statuses[name] = status
        if status == FAILED:
            record = read_item_record(folder, name) or {}
            outcome.failures[name] = record.get("error") or error or "failed"
            outcome.kinds[name] = record.get("kind", BUG)
            if record.get("status") != FAILED:  # the task's process died before it could say so
                write_record(folder, {"name": name, "status": FAILED, "output": plan.output(name),
                                      "error": outcome.failures[name], "kind": BUG})
    update_summary(folder, now=True)
    return outcome


def fit_batch(inputs: str | Path, out: str | Path, settings: BatchSettings, flags: ExecutorFlags = ExecutorFlags(),
              progress: bool = True) -> tuple[BatchOutcome, Path, int | None]:
    """`cvqpg batch`: every item of `inputs` (`read_inputs`) into the batch folder `out` (`run_batch`) by the
    executor `flags` ask for, everything checked first (the settings, the device, the memory of the largest item
    and of the fits at once); the outcome, the folder, and the signal that stopped it (None where none did)."""
    from ..fitting import estimated_peak_bytes
    from . import signals
    from .allocator import keep_freed_memory
    from .outputs import BATCH, check_continued, claimed
    from .resources import check_device, check_fits_at_once, check_memory
    device = settings.run.device
    check_device(device)
    check_settings(settings)
    executor = flags.options(device, "batch")
    folder = check_continued(out, BATCH)
    plan = plan_batch(read_inputs(inputs), folder, settings)
    peaks = {item.name: estimated_peak_bytes(item.config, device) for item in plan.items}
    if peaks:
        largest = max(plan.items, key=lambda item: peaks[item.name])
        check_memory(largest.config, device, remedy=f"reduce --size or --planes (item {largest.name})")
        check_fits_at_once(peaks[largest.name], executor, device)
    keep_freed_memory()
    with claimed(folder), signals.StopRequest() as stop_requested:
        outcome = run_batch(plan, executor, RunControl(progress=progress, stop_requested=stop_requested))
    return outcome, folder, stop_requested.signals[0] if stop_requested.signals else None
