"""cvqpg: holograms as complex-valued (quadratic-phase) Gaussian primitives.

The library API below is imported on first use (PEP 562), so that importing one module of the
package, as the first run's compile processes do, does not import all of them.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.4.0"

_API_MODULES = {
    "config": ("FitConfig", "LearningRates", "RunOptions"),
    "control": ("RunControl",),
    "errors": ("CvqpgError", "ConfigError", "InputError", "ModelFileError"),
    "depth": ("estimate_depth", "load_depth_model"),
    "display": ("Display", "read_lut"),
    "fitting": ("FitResult", "fit", "fit_scene", "hologram", "render", "render_hologram"),
    "metrics": ("MetricReport", "evaluate"),
    "optics": ("reconstruct",),
    "ops.field": ("Grid",),
    "ops.propagation": ("propagate", "transfer_function"),
    "primitives": ("Gaussians", "Primitives", "activate", "init_gaussians"),
    "ops.rasterize": ("rasterize",),
    "runs": ("evaluate_run", "write_run"),
    "scenes": ("builtin_pictures", "builtin_scene"),
    "storage": ("load_model", "save_model"),
    "targets": ("Scene", "build_scene", "load_scene"),
}
_MODULE_OF = {name: module for module, names in _API_MODULES.items() for name in names}

__all__ = [*_MODULE_OF, "__version__"]


def __getattr__(name: str) -> Any:
    if name not in _MODULE_OF:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_MODULE_OF[name]}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
