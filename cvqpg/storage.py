"""The fitted representation on disk, and the one place that decides a model file's format:
`model.safetensors` holds the activated primitives in physical units, with the configuration and optics
as metadata; a `.cvq` file holds them compressed (`codec`); checkpoints hold the loop state."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save

from .codec import (FINGERPRINT, MAGIC, PREFIX, SUFFIX, Compressed, bits_per_pixel, decode, file_bits,
                    file_fingerprint)
from .config import FitConfig
from .errors import ConfigError, ModelFileError, choices_error
from .files import atomic_file, write_atomic
from .primitives import REWRITE_MODEL, Primitives, TensorFields, check_settings
from .representation import representation

MODEL_FORMAT = "cvqpg-model"
MODEL_FORMAT_VERSION = "2"
RUN_KEY = "run"  # the metadata entry of the fit a model came from (`save_model`)
STORED_DTYPES = {"float32": torch.float32, "float16": torch.float16}


def model_metadata(primitives: Primitives | TensorFields, config: FitConfig, dtype: str,
                   run: dict[str, Any] | None = None) -> dict[str, str]:
    """What a model file says about itself: format, configuration, the optics in plain numbers, and the fit it
    came from (`run`, `runs.fit_fingerprint`) where it was fitted in a run folder."""
    return {**({} if run is None else {RUN_KEY: json.dumps(run)}),
            "format": MODEL_FORMAT, "format_version": MODEL_FORMAT_VERSION, "dtype": dtype,
            "config": json.dumps(config.to_dict()), "num_primitives": str(primitives.count),
            "width_px": str(config.targets.width), "height_px": str(config.targets.height),
            "pixel_pitch_m": repr(config.optics.pixel_pitch), "wavelengths_m": json.dumps(config.wavelengths),
            "plane_distances_m": json.dumps(config.plane_distances), "qpf": config.primitives.qpf,
            "units": json.dumps({**representation(config).units(config), **{term.physical: f"{term.unit} ({term.summary})"
                                                              for term in config.phase.extra_terms}})}


def save_model(path: str | Path, primitives: Primitives | TensorFields, config: FitConfig, dtype: str = "float32",
               run: dict[str, Any] | None = None) -> None:
    """Write the activated primitives, or a per-pixel hologram (physical units, the representation's `units`), and
    the optics, atomically; `run` binds the file to the fit of a run folder (`model_metadata`).

    `dtype="float16"` stores everything but the positions in float16 and about halves the file;
    positions stay float32 because float16's spacing grows to 2 px above 2048 px. Rendering casts
    back to float32.
    """
    if dtype not in STORED_DTYPES:
        raise choices_error("dtype", dtype, tuple(STORED_DTYPES))
    tensors = {name: t.detach().to("cpu", torch.float32 if name == "position_px" else STORED_DTYPES[dtype])
               .contiguous() for name, t in primitives.tensors().items()}
    write_atomic(path, save(tensors, metadata=model_metadata(primitives, config, dtype, run)))


def model_run(path: str | Path) -> Any:
    """The fit a model file records that it came from: `save_model`'s `run`, read as JSON; a `.cvq` file's fit
    fingerprint (bytes, `codec.file_fingerprint`); None where it records none (a file of a version that did not
    write it, or a `.cvq` file written without)."""
    path = _model_file(path)
    if is_compressed(path):
        with open(path, "rb") as handle:
            return file_fingerprint(handle.read(PREFIX.size + FINGERPRINT.size))
    try:
        with safe_open(str(path), framework="pt") as handle:
            recorded = (handle.metadata() or {}).get(RUN_KEY)
    except (SafetensorError, OSError) as error:
        raise ModelFileError(f"{path}: not a readable safetensors file ({error})") from None
    if recorded is None:
        return None
    try:
        return json.loads(recorded)
    except ValueError:
        raise ModelFileError(f"{path}: its record of the fit it came from is not JSON; {REWRITE_MODEL}") from None


def is_compressed(path: str | Path) -> bool:
    """Whether the file is read as a `.cvq` file: it starts with the magic number, or it is named `*.cvq`
    (so that a damaged one is reported as such, not as an unreadable safetensors file)."""
    path = Path(path)
    with open(path, "rb") as handle:
        return handle.read(len(MAGIC)) == MAGIC or path.suffix == SUFFIX


def read_compressed(path: str | Path) -> Compressed:
    """Decode a `.cvq` file."""
    path = Path(path)
    return decode(path.read_bytes(), str(path))


def _model_file(path: str | Path) -> Path:
    path = Path(path)
    if path.is_dir():
        raise ModelFileError(f"{path} is a folder, not a model file; move it away, or give the model file")
    if not path.is_file():
        raise ModelFileError(f"{path}: no such model file")
    return path


def _read_safetensors(path: Path, device: str | torch.device = "cpu"
                      ) -> tuple[Primitives | TensorFields, FitConfig, dict[str, str]]:
    """A model written by `save_model`, as float32 primitives on `device`, with the file's metadata."""
    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = handle.metadata() or {}
        tensors = load_file(str(path), device=str(device))
    except (SafetensorError, OSError) as error:
        raise ModelFileError(f"{path}: not a readable safetensors file ({error})") from None
    if metadata.get("format") != MODEL_FORMAT or metadata.get("format_version") != MODEL_FORMAT_VERSION:
        raise ModelFileError(f"{path}: not a cvqpg model of format version {MODEL_FORMAT_VERSION} "
                             f"(found format {metadata.get('format')!r} "
                             f"version {metadata.get('format_version')!r})")
    try:
        config = FitConfig.from_dict(json.loads(metadata["config"]))
    except (KeyError, ValueError, TypeError, AttributeError) as error:
        raise ModelFileError(f"{path}: its metadata holds no readable configuration ({type(error).__name__}: "
                             f"{error}); {REWRITE_MODEL}") from None
    except ConfigError as error:
        raise ModelFileError(f"{path}: its settings cannot work ({error}); {REWRITE_MODEL}") from None
    kind = representation(config)
    missing = [name for name in kind.units(config) if name not in tensors]
    if missing:
        raise ModelFileError(f"{path}: missing tensors {', '.join(missing)}")
    primitives = kind.from_tensors({name: t.float() for name, t in tensors.items()}, config)
    kind.check(primitives, config, str(path))
    check_settings(config, primitives.count, str(path))
    if metadata.get("num_primitives") != str(primitives.count):
        raise ModelFileError(f"{path}: its metadata says {metadata.get('num_primitives')} primitives, its tensors "
                             f"hold {primitives.count}; {REWRITE_MODEL}")
    return primitives, config, metadata


def load_model(path: str | Path, device: str | torch.device = "cpu") -> tuple[Primitives | TensorFields, FitConfig]:
    """Read a model written by `save_model`, or a compressed `.cvq` file, as float32 primitives (or a per-pixel
    hologram) on `device`."""
    path = _model_file(path)
    if is_compressed(path):
        compressed = read_compressed(path)
        return compressed.primitives.to(device), compressed.config
    primitives, config, _ = _read_safetensors(path, device)
    return primitives, config


def model_info(path: str | Path) -> dict[str, Any]:
    """Size accounting of a model file: primitives, their phase terms, parameters (per primitive and in all), bytes
    and bits per hologram pixel
    (all channels together); for a compressed file also the bits per attribute, the format's tools, the fit
    fingerprint (hex, None where the file carries none) and each stream's coding."""
    path = _model_file(path)
    extra: dict[str, Any] = {}
    if is_compressed(path):
        compressed = read_compressed(path)
        primitives, config, dtype = compressed.primitives, compressed.config, "compressed"
        extra = {"format_version": compressed.version, "bits": file_bits(compressed.bits, compressed.config),
                 "tools": sorted(compressed.tools),
                 "fit_fingerprint": None if compressed.fingerprint is None else compressed.fingerprint.hex(),
                 "streams": {s["name"]: {"coding": s["coding"], "bytes": s["bytes"]} for s in compressed.streams}}
    else:
        primitives, config, metadata = _read_safetensors(path)
        dtype = metadata.get("dtype", "float32")
    file_bytes = path.stat().st_size
    return {"file": str(path), "num_primitives": primitives.count, "primitive": config.primitives.kind,
            "phase": config.phase.name if config.primitives.kind != "pixel" else None,
            "params_per_primitive": config.params_per_primitive,
            "learnable_params": primitives.count * config.params_per_primitive,
            "stored_values": sum(t.numel() for t in primitives.tensors().values()), "dtype": dtype,
            "file_bytes": file_bytes, "hologram_px": [config.targets.width, config.targets.height],
            "channels": config.channels, "bits_per_pixel": bits_per_pixel(file_bytes, config), **extra}


def save_checkpoint(path: str | Path, payload: dict) -> None:
    """Write a loop state atomically: the previous checkpoint stays intact until the new one is whole."""
    with atomic_file(path) as handle:
        torch.save(payload, handle)


def load_checkpoint(path: str | Path) -> dict:
    """Read a checkpoint written by `save_checkpoint`."""
    try:
        return torch.load(Path(path), map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises several unrelated types for damaged files
        raise ModelFileError(f"{path}: unreadable checkpoint ({type(error).__name__}); delete it to restart "
                             "the run from step 0") from None
