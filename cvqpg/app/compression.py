"""`cvqpg compress` and `cvqpg decompress` over run folders and model files: the float model read with its
run's scene, the file chosen by the search (`cvqpg.search`) written atomically, and what the commands report;
`compress_to` and `decompress_to` write by the output rule (`app.outputs`)."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from ..codec import bits_per_pixel, with_fingerprint
from ..config import FitConfig
from ..control import SILENT, RunControl
from ..defaults import RATE_FINETUNE_STEPS, SUFFIX
from ..errors import ConfigError, ModelFileError
from ..files import write_atomic
from ..primitives import Primitives
from ..representation import require_gaussians
from ..runs import CONFIG_FILE, fingerprint_digest, load_run_model, model_path, scene_from_source
from ..search import (LADDER, Choice, CompressionSettings, FixedBits, MaxDrop, Reference, finetuned, pruned_count,
                      rate_control, reference_for, search)
from ..storage import is_compressed, load_model, model_run, read_compressed, save_model
from ..targets import Scene


@dataclass
class CompressionInput:
    """A float model to compress: its file, primitives and settings, and its run's scene (None for a model
    file outside a run folder)."""

    model_file: Path
    primitives: Primitives
    config: FitConfig
    scene: Scene | None


def compression_input(target: str | Path, finetune_steps: int = 0) -> CompressionInput:
    """The float model of a run folder, or a model file with its run's scene where it lies in one;
    `ConfigError` where `finetune_steps` > 0 but there is no run folder whose targets it could tune on."""
    model_file = model_path(target)
    if not model_file.is_file():
        raise ModelFileError(f"{target}: no such run folder or model file")
    if is_compressed(model_file):
        raise ModelFileError(f"{model_file}: already compressed; give the float model")
    folder = model_file.parent if (model_file.parent / CONFIG_FILE).is_file() else None
    if finetune_steps and folder is None:
        raise ConfigError(f"`finetune_steps` needs the run folder's inputs; {model_file} is not in a run folder")
    if folder is None:
        primitives, config = load_model(model_file)
        source = None
    else:
        primitives, config, source = load_run_model(folder, model_file)
    require_gaussians(config, "the .cvq codec", f"{model_file} is the pattern itself (`cvqpg info --half` stores it "
                      "in float16)")
    return CompressionInput(model_file, primitives, config, None if source is None else scene_from_source(source,
                                                                                                         config))


def choice_record(choice: Choice, reference: Reference, config: FitConfig) -> dict[str, Any]:
    """A chosen file's size (bytes, bits per hologram pixel), bit depths, primitives, and PSNR and drop (dB)
    against the reference (with the float model's PSNR on it, where known)."""
    return {"bytes": len(choice.data), "bits_per_pixel": bits_per_pixel(len(choice.data), config),
            "bits": asdict(choice.bits), "num_primitives": choice.decoded.count, "reference": reference.label,
            "psnr_float": reference.fit_psnr, "psnr": choice.psnr, "drop": choice.drop}


def compression_record(given: CompressionInput, out: Path, choice: Choice, reference: Reference, seconds: float,
                       **settings: Any) -> dict[str, Any]:
    """What `compress_model` reports: the file written (`choice_record`) beside the model file it came from,
    `settings`, and the seconds the choice took."""
    model_bytes = given.model_file.stat().st_size
    return {"file": str(out), "model": str(given.model_file), **choice_record(choice, reference, given.config),
            "model_bytes": model_bytes, "ratio": model_bytes / len(choice.data), **settings, "seconds": seconds}


def compress_model(target: str | Path, settings: CompressionSettings = CompressionSettings(),
                   out: str | Path | None = None, control: RunControl = SILENT) -> dict[str, Any]:
    """Compress a run folder's model or a model file into a `.cvq` file (atomically, default: the model's path
    with `SUFFIX`) as `settings` ask, and report it (`compression_record`).

    A model inside a run folder is scored against the run's targets, a bare model file against its own
    reconstruction. Within a budget (`bpp`, `max_bytes`) rate control chooses the primitives and depths
    (`search.rate_control`, with a progress bar where `control.progress`), fine-tuned for `finetune_steps`
    (default: `RATE_FINETUNE_STEPS` in a run folder, none for a bare model file, which has no targets to tune
    on). Otherwise the depths are `bits` or the smallest within `max_drop` (`search.search`), and
    `finetune_steps` > 0 (needs the run folder; default 0) tunes the model at them after removing its
    `prune_fraction` of least field energy, kept only where it pays (`search.finetuned`).
    """
    given = compression_input(target, settings.finetune_steps or 0)
    primitives, config, scene = given.primitives, given.config, given.scene
    if settings.prune_fraction:
        pruned_count(primitives.count, settings.prune_fraction)  # refused before the search, not after it
    out = Path(out) if out is not None else given.model_file.with_suffix(SUFFIX)
    started = time.perf_counter()
    reference = reference_for(primitives, config, None if scene is None else scene.targets)
    goal = settings.goal(config)
    if settings.budgeted:
        steps = settings.finetune_steps
        steps = steps if steps is not None else RATE_FINETUNE_STEPS if scene is not None else 0
        chosen = rate_control(primitives, config, reference, goal, scene, steps, control,
                              settings.rate_fit(goal) if settings.rate_loss else None)
        choice, recorded = chosen.choice, chosen.record(goal)
    else:
        steps = settings.finetune_steps or 0
        ladder = (settings.bits,) if isinstance(goal, FixedBits) else LADDER
        choice, tuned = search(primitives, config, reference, goal, ladder, control), False
        if steps:
            choice, tuned = finetuned(primitives, config, reference, goal, scene, choice, steps,
                                      settings.prune_fraction, control)
        recorded = {"max_drop": goal.max_drop if isinstance(goal, MaxDrop) else None, "finetune_steps": steps,
                    "finetune_kept": tuned, "prune_fraction": settings.prune_fraction}
    seconds = time.perf_counter() - started
    fingerprint = fingerprint_digest(model_run(given.model_file))
    write_atomic(out, choice.data if fingerprint is None else with_fingerprint(choice.data, fingerprint))
    return compression_record(given, out, choice, reference, seconds, **recorded)


def decompress_file(path: str | Path, out: str | Path | None = None) -> Path:
    """Decode a `.cvq` file into a float32 `model.safetensors`-format file (atomically)."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: no such file")
    compressed = read_compressed(path)
    out = Path(out) if out is not None else path.with_name(f"{path.stem}.decoded.safetensors")
    save_model(out, compressed.primitives, compressed.config)
    return out


def compress_to(target: str | Path, settings: CompressionSettings = CompressionSettings(),
                out: str | Path | None = None, overwrite: bool = False, control: RunControl = SILENT
                ) -> dict[str, Any]:
    """`cvqpg compress`: `compress_model` into `out` (default: the model's path with `SUFFIX`) by the output rule
    (`app.outputs`: an existing `.cvq` file replaced only with `overwrite`, never the model itself). Without a stop
    request of its own, `control` asks the command's signals (`signals.raised_if_stopped`) at each of the search's
    checks."""
    from .outputs import CVQ, output
    from .signals import raised_if_stopped
    control = replace(control, stop_requested=control.stop_requested or raised_if_stopped)
    model = model_path(target)
    if not model.is_file() or is_compressed(model):  # compress_model says what the target is
        return compress_model(target, settings, out, control)
    with output(out or model.with_suffix(SUFFIX), CVQ, [model], overwrite) as checked:
        return compress_model(target, settings, checked, control)


def decompress_to(path: str | Path, out: str | Path | None = None, overwrite: bool = False) -> Path:
    """`cvqpg decompress`: `decompress_file` into `out` (default: `<stem>.decoded.safetensors` beside the file) by
    the output rule (`app.outputs`)."""
    from .outputs import MODEL, output
    path = Path(path)
    with output(out or path.with_name(f"{path.stem}.decoded.safetensors"), MODEL, [path], overwrite) as checked:
        return decompress_file(path, checked)
