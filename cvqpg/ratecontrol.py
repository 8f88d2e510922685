"""Deprecated since 0.2.0, removed in 0.3.0 (`deprecations.REMOVED_IN`): rate control is `cvqpg.search`, the
`compress --bpp` and `encode` workflows `cvqpg.app.compression` and `cvqpg.app.encoding`. The old names below keep
working until then."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Callable

from .app.compression import compress_model
from .app.encoding import (ENCODE_HEADROOM, Encoding, encode_config, encode_steps, encoding_record,
                           primitives_for_budget, stand_in)
from .app.encoding import encode_budget as _encode_budget
from .app.encoding import encode_fitted as _encode_fitted
from .app.encoding import encode_scene as _encode_scene
from .config import FitConfig
from .control import RunControl
from .defaults import ENCODE_FINETUNE_STEPS, ENCODE_STEPS, RATE_FINETUNE_STEPS
from .deprecations import REMOVED_IN
from .fitting import FitResult
from .primitives import Primitives
from .search import (CLOSE, COARSEST, TUNING_HEADROOM, Budget, CompressionSettings, RateChoice, Reference,
                     largest_fitting, smallest_file)
from .search import LADDER as RUNGS
from .search import rate_control as _rate_control
from .targets import Scene

warnings.warn("`cvqpg.ratecontrol` moved to `cvqpg.search` (`rate_control`, `Budget`), `cvqpg.app.compression` and "
              f"`cvqpg.app.encoding` (the compress and encode workflows); the old name goes in cvqpg {REMOVED_IN}",
              DeprecationWarning, stacklevel=2)

__all__ = ["CLOSE", "COARSEST", "ENCODE_FINETUNE_STEPS", "ENCODE_HEADROOM", "ENCODE_STEPS", "RATE_FINETUNE_STEPS",
           "RUNGS", "TUNING_HEADROOM", "Budget", "Encoding", "RateChoice", "check_budget_values",
           "compress_to_budget", "encode_budget", "encode_config", "encode_fitted", "encode_scene", "encode_steps",
           "encoding_record", "largest_fitting", "primitives_for_budget", "rate_control", "smallest_file",
           "stand_in"]


def _control(progress: bool, stop_requested: Callable[[], bool] | None) -> RunControl:
    return RunControl(progress=progress, stop_requested=stop_requested)


def check_budget_values(bpp: float | None, max_bytes: int | None) -> None:
    """`search.CompressionSettings` checks these where it is made."""
    CompressionSettings(bpp=bpp, max_bytes=max_bytes).budget(FitConfig())


def rate_control(primitives: Primitives, config: FitConfig, reference: Reference, budget: Budget,
                 scene: Scene | None = None, finetune_steps: int = 0, progress: bool = False,
                 stop_requested: Callable[[], bool] | None = None) -> RateChoice:
    """`search.rate_control` with a `RunControl` of `progress` and `stop_requested`."""
    return _rate_control(primitives, config, reference, budget, scene, finetune_steps,
                         _control(progress, stop_requested))


def compress_to_budget(target: str | Path, out: str | Path | None = None, bpp: float | None = None,
                       max_bytes: int | None = None, finetune_steps: int | None = None, progress: bool = False
                       ) -> dict[str, Any]:
    """`app.compression.compress_model` within a budget."""
    settings = CompressionSettings(bpp=bpp, max_bytes=max_bytes, finetune_steps=finetune_steps)
    settings.budget(FitConfig())
    return compress_model(target, settings, out, _control(progress, None))


def encode_budget(config: FitConfig, bpp: float | None = None, max_bytes: int | None = None) -> Budget:
    """`app.encoding.encode_budget` of these values."""
    return _encode_budget(config, CompressionSettings(bpp=bpp, max_bytes=max_bytes))


def encode_fitted(fitted: FitResult, scene: Scene, budget: Budget, finetune_steps: int = ENCODE_FINETUNE_STEPS,
                  progress: bool = False, stop_requested: Callable[[], bool] | None = None) -> Encoding:
    """`app.encoding.encode_fitted` with a `RunControl` of `progress` and `stop_requested`."""
    return _encode_fitted(fitted, scene, budget, finetune_steps, _control(progress, stop_requested))


def encode_scene(scene: Scene, config: FitConfig, budget: Budget, finetune_steps: int = ENCODE_FINETUNE_STEPS,
                 progress: bool = False, stop_requested: Callable[[], bool] | None = None) -> Encoding:
    """`app.encoding.encode_scene` within `budget`."""
    settings = CompressionSettings(max_bytes=budget.max_bytes, finetune_steps=finetune_steps)
    return _encode_scene(scene, config, settings, _control(progress, stop_requested))
