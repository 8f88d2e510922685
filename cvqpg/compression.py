"""Choosing how to compress a model: the budget search (each trial encodes, decodes as a reader would,
and renders), pruning, fine-tuning kept where it pays, and the workflows `compress_model` and
`decompress_file` over run folders and model files. The `.cvq` format itself is `codec`'s."""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch

from .codec import SUFFIX, BitDepths, bits_per_pixel, decode, encode
from .config import FitConfig
from .errors import ConfigError, ModelFileError
from .files import write_atomic
from .finetune import finetune
from .fitting import render
from .metrics import mean_psnr
from .primitives import Primitives, field_energy
from .runs import CONFIG_FILE, load_run_model, model_path, scene_from_source
from .storage import is_compressed, load_model, read_compressed, save_model
from .targets import Scene

# The budgets `max_drop` tries, coarsest first: the defaults shifted together.
LADDER = tuple(BitDepths().shifted(delta) for delta in range(-3, 7))
ASSUMED_FIT_PSNR_DB = 30.0


@dataclass
class Reference:
    """What a decoded render is scored against: the run's targets, or without a run the float model's
    own reconstruction (then `fit_psnr` is None)."""

    images: torch.Tensor  # [M, C, H, W]
    label: str
    fit_psnr: float | None


def reference_for(primitives: Primitives, config: FitConfig, scene_targets: torch.Tensor | None,
                  label: str = "the run's targets") -> Reference:
    """The scene's targets (named `label`) with the float model's PSNR on them, or the float model's
    reconstruction."""
    recon = render(primitives, config)[1]
    if scene_targets is not None:
        return Reference(scene_targets, label, mean_psnr(recon, scene_targets))
    return Reference(recon, "the float model's own reconstruction", None)


def psnr_drop(primitives: Primitives, config: FitConfig, reference: Reference) -> tuple[float, float]:
    """(PSNR in dB of `primitives`' render against the reference, drop in dB below the float model).

    Against the float model's own reconstruction the drop is estimated for a fit of
    `ASSUMED_FIT_PSNR_DB` whose error adds to the quantisation error:
    10·log10(1 + 10^((P_fit − Q)/10)), Q the PSNR against the float reconstruction.
    """
    value = mean_psnr(render(primitives, config)[1], reference.images)
    if reference.fit_psnr is not None:
        return value, reference.fit_psnr - value
    return value, 10 * math.log10(1 + 10 ** ((ASSUMED_FIT_PSNR_DB - value) / 10))


@dataclass
class Choice:
    """A chosen budget: the file's bytes, the decoded primitives, and its PSNR (dB) and drop (dB)."""

    bits: BitDepths
    data: bytes
    decoded: Primitives
    psnr: float
    drop: float


def trial(primitives: Primitives, config: FitConfig, bits: BitDepths, reference: Reference) -> Choice:
    """Encode at `bits`, decode the bytes as a reader would, and score the decoded render."""
    data = encode(primitives, config, bits)
    decoded = decode(data).primitives
    return Choice(bits, data, decoded, *psnr_drop(decoded, config, reference))


def choose_bits(primitives: Primitives, config: FitConfig, reference: Reference, max_drop: float,
                ladder: tuple[BitDepths, ...] = LADDER) -> Choice:
    """The smallest file found within `max_drop` dB: the coarsest rung of `ladder` that holds, then
    one attribute at a time one bit coarser, keeping the change that saves the most bytes, while the
    drop holds. Falls back to the finest rung when none holds."""
    best = None
    for bits in ladder:
        best = trial(primitives, config, bits, reference)
        if best.drop <= max_drop:
            break
    else:
        return best
    improved = True
    while improved:
        improved = False
        tries = [trial(primitives, config, candidate, reference)
                 for candidate in (best.bits.shifted_one(name) for name in best.bits.names())
                 if candidate is not None]
        holding = [t for t in tries if t.drop <= max_drop and len(t.data) < len(best.data)]
        if holding:
            best, improved = min(holding, key=lambda t: len(t.data)), True
    return best


def _check_prune_fraction(fraction: float) -> None:
    if not 0 <= fraction < 1:
        raise ConfigError(f"`prune_fraction` {fraction:g}: give the fraction of primitives to remove, "
                          "0 ≤ fraction < 1")


def strongest_first(primitives: Primitives, first: torch.Tensor | None = None) -> torch.Tensor:
    """Indices of the primitives by decreasing field energy (`field_energy`), ties in their order, those of
    the indices `first` ahead of all the others [N]."""
    energy = field_energy(primitives)
    if first is not None:
        energy = energy.index_fill(0, first, math.inf)
    return torch.argsort(energy, descending=True, stable=True)


def kept(primitives: Primitives, order: torch.Tensor, count: int) -> Primitives:
    """The first `count` primitives of `order` (e.g. `strongest_first`), in their own order."""
    chosen = order[:count].sort().values
    return type(primitives).from_tensors({name: tensor[chosen] for name, tensor in primitives.tensors().items()})


def prune(primitives: Primitives, fraction: float) -> Primitives:
    """The primitives without the `fraction` (0 ≤ fraction < 1) of least field energy (`field_energy`),
    the others in their order. The rest only regain the PSNR lost with fine-tuning (`finetune`)."""
    _check_prune_fraction(fraction)
    return kept(primitives, strongest_first(primitives), round((1 - fraction) * primitives.count))


def check_compression_settings(max_drop: float | None, finetune_steps: int, prune_fraction: float) -> None:
    """`ConfigError` naming the first setting of `compress_model` that cannot work."""
    if max_drop is not None and max_drop < 0:
        raise ConfigError(f"`max_drop` {max_drop:g}: give a drop in dB ≥ 0")
    if finetune_steps < 0:
        raise ConfigError(f"`finetune_steps` {finetune_steps}: give a number of steps ≥ 0")
    _check_prune_fraction(prune_fraction)
    if prune_fraction and not finetune_steps:
        raise ConfigError(f"`prune_fraction` {prune_fraction:g} needs `finetune_steps` > 0: pruned primitives "
                          "cost PSNR that only fine-tuning regains")


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
        return CompressionInput(model_file, *load_model(model_file), None)
    primitives, config, source = load_run_model(folder, model_file)
    return CompressionInput(model_file, primitives, config, scene_from_source(source, config))


def choice_record(choice: Choice, reference: Reference, config: FitConfig) -> dict[str, Any]:
    """A chosen file's size (bytes, bits per hologram pixel), bit depths, primitives, and PSNR and drop (dB)
    against the reference (with the float model's PSNR on it, where known)."""
    return {"bytes": len(choice.data), "bits_per_pixel": bits_per_pixel(len(choice.data), config),
            "bits": asdict(choice.bits), "num_primitives": choice.decoded.count, "reference": reference.label,
            "psnr_float": reference.fit_psnr, "psnr": choice.psnr, "drop": choice.drop}


def compression_record(given: CompressionInput, out: Path, choice: Choice, reference: Reference, seconds: float,
                       **settings: Any) -> dict[str, Any]:
    """What `compress_model` and `ratecontrol.compress_to_budget` report: the file written (`choice_record`)
    beside the model file it came from, `settings`, and the seconds the choice took."""
    model_bytes = given.model_file.stat().st_size
    return {"file": str(out), "model": str(given.model_file), **choice_record(choice, reference, given.config),
            "model_bytes": model_bytes, "ratio": model_bytes / len(choice.data), **settings, "seconds": seconds}


def compress_model(target: str | Path, out: str | Path | None = None, bits: BitDepths | None = None,
                   max_drop: float | None = None, finetune_steps: int = 0, prune_fraction: float = 0.0
                   ) -> dict[str, Any]:
    """Compress a run folder's model or a model file into a `.cvq` file (atomically) and report it.

    `bits` fixes the budget; otherwise `max_drop` (dB, default 0.1) picks it with `choose_bits`. A
    model inside a run folder is scored against the run's targets, a bare model file against its own
    reconstruction. `finetune_steps` > 0 first tunes the model at the budget (needs the run folder),
    after removing the `prune_fraction` of its primitives of least field energy (`prune`; it needs
    fine-tuning, and like it is kept only where it pays). `ratecontrol.compress_to_budget` compresses to
    a file size instead.
    """
    check_compression_settings(max_drop, finetune_steps, prune_fraction)
    given = compression_input(target, finetune_steps)
    primitives, config, scene = given.primitives, given.config, given.scene
    out = Path(out) if out is not None else given.model_file.with_suffix(SUFFIX)
    started = time.perf_counter()
    reference = reference_for(primitives, config, None if scene is None else scene.targets)
    max_drop = 0.1 if bits is None and max_drop is None else max_drop
    choice = (trial(primitives, config, bits, reference) if bits is not None
              else choose_bits(primitives, config, reference, max_drop))
    tuned = False
    if finetune_steps:
        # Tuned models hold coarser budgets: first try one bit below the choice everywhere, then the choice.
        start = prune(primitives, prune_fraction)
        for bits_tried in ((choice.bits,) if max_drop is None else (choice.bits.shifted(-1), choice.bits)):
            candidate = trial(finetune(start, config, scene, bits_tried, finetune_steps), config, bits_tried,
                              reference)
            if max_drop is None or candidate.drop <= max_drop:
                break
        if max_drop is not None and candidate.drop <= max_drop:
            candidate = choose_bits(candidate.decoded, config, reference, max_drop, ladder=(candidate.bits,))
        # Kept only where it pays: smaller within the drop, or a smaller drop at a fixed budget.
        tuned = (len(candidate.data) <= len(choice.data) and candidate.drop <= max(max_drop, choice.drop)
                 if max_drop is not None else candidate.drop < choice.drop)
        choice = candidate if tuned else choice
    seconds = time.perf_counter() - started
    write_atomic(out, choice.data)
    return compression_record(given, out, choice, reference, seconds, max_drop=max_drop,
                              finetune_steps=finetune_steps, finetune_kept=tuned, prune_fraction=prune_fraction)


def decompress_file(path: str | Path, out: str | Path | None = None) -> Path:
    """Decode a `.cvq` file into a float32 `model.safetensors`-format file (atomically)."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: no such file")
    compressed = read_compressed(path)
    out = Path(out) if out is not None else path.with_name(f"{path.stem}.decoded.safetensors")
    save_model(out, compressed.primitives, compressed.config)
    return out
