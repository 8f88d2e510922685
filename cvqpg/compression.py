"""Deprecated since 0.2.0, removed in 0.3.0 (`deprecations.REMOVED_IN`): the search is `cvqpg.search`, the
`compress` and `decompress` workflows `cvqpg.app.compression`. The old names below keep working until then."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from .app.compression import (CompressionInput, choice_record, compression_input, compression_record,
                              decompress_file)
from .app.compression import compress_model as _compress_model
from .codec import BitDepths
from .config import FitConfig
from .deprecations import REMOVED_IN
from .primitives import Primitives, field_energy
from .search import (ASSUMED_FIT_PSNR_DB, LADDER, Choice, CompressionSettings, MaxDrop, Reference, kept, prune,
                     psnr_drop, reference_for, search, strongest_first, trial)

warnings.warn("`cvqpg.compression` moved to `cvqpg.search` (the search) and `cvqpg.app.compression` (`compress_model`, "
              f"`decompress_file`); the old name goes in cvqpg {REMOVED_IN}", DeprecationWarning, stacklevel=2)

__all__ = ["ASSUMED_FIT_PSNR_DB", "LADDER", "Choice", "CompressionInput", "Reference", "check_compression_settings",
           "choice_record", "choose_bits", "compress_model", "compression_input", "compression_record",
           "decompress_file", "field_energy", "kept", "prune", "psnr_drop", "reference_for", "strongest_first",
           "trial"]


def choose_bits(primitives: Primitives, config: FitConfig, reference: Reference, max_drop: float,
                ladder: tuple[BitDepths, ...] = LADDER) -> Choice:
    """`search.search` within `MaxDrop(max_drop)`."""
    return search(primitives, config, reference, MaxDrop(max_drop), ladder)


def check_compression_settings(max_drop: float | None, finetune_steps: int, prune_fraction: float) -> None:
    """`search.CompressionSettings` checks these where it is made."""
    CompressionSettings(max_drop=max_drop, finetune_steps=finetune_steps, prune_fraction=prune_fraction)


def compress_model(target: str | Path, out: str | Path | None = None, bits: BitDepths | None = None,
                   max_drop: float | None = None, finetune_steps: int = 0, prune_fraction: float = 0.0
                   ) -> dict[str, Any]:
    """`app.compression.compress_model` with these settings."""
    settings = CompressionSettings(bits=bits, max_drop=max_drop, finetune_steps=finetune_steps,
                                   prune_fraction=prune_fraction)
    return _compress_model(target, settings, out)
