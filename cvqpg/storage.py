"""The fitted representation on disk: `model.safetensors` with its configuration as metadata."""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from .config import FitConfig
from .primitives import Gaussians

MODEL_FORMAT = "cvqpg-model"
MODEL_FORMAT_VERSION = "1"


class ModelFileError(ValueError):
    """A model file that this version cannot read; the message says what is wrong."""


def save_model(path: str | Path, gaussians: Gaussians, config: FitConfig) -> None:
    """Write the raw parameters (bit-exact) and the configuration, atomically."""
    path = Path(path)
    tensors = {name: t.detach().to("cpu").contiguous() for name, t in gaussians.tensors().items()}
    metadata = {"format": MODEL_FORMAT, "format_version": MODEL_FORMAT_VERSION,
                "config": json.dumps(config.to_dict())}
    partial = path.with_name(path.name + ".partial")
    save_file(tensors, str(partial), metadata=metadata)
    partial.replace(path)


def load_model(path: str | Path, device: str | torch.device = "cpu") -> tuple[Gaussians, FitConfig]:
    """Read a model written by `save_model`."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: no such model file")
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
    config = FitConfig.from_dict(json.loads(metadata["config"]))
    missing = [name for name in Gaussians.__dataclass_fields__ if name not in tensors]
    if missing:
        raise ModelFileError(f"{path}: missing tensors {', '.join(missing)}")
    gaussians = Gaussians.from_tensors(tensors)
    count, channels = gaussians.count, config.channels
    expected = {"position": (count, 2), "scale": (count, 2), "rotation": (count,),
                "color": (count, channels), "phase": (count, channels), "opacity": (count,),
                "curvature": (count,)}
    for name, shape in expected.items():
        if tuple(tensors[name].shape) != shape:
            raise ModelFileError(f"{path}: tensor {name!r} has shape {tuple(tensors[name].shape)}, "
                                 f"expected {shape}")
    return gaussians, config


def save_checkpoint(path: str | Path, payload: dict) -> None:
    """Write a loop state atomically: the previous checkpoint stays intact until the new one is whole."""
    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    with open(partial, "wb") as handle:
        torch.save(payload, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(partial, path)


def load_checkpoint(path: str | Path) -> dict:
    """Read a checkpoint written by `save_checkpoint`."""
    try:
        return torch.load(Path(path), map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises several unrelated types for damaged files
        raise ModelFileError(f"{path}: unreadable checkpoint ({type(error).__name__}); delete it to restart "
                             "the run from step 0") from None
