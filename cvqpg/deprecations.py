"""Former names of modules and functions, kept for one release: each still works and warns where it moved.

A module's former name (`import cvqpg.bench`) is served by a finder that `cvqpg/__init__.py` installs: it imports
the module from its new place under the old name as well, with a `DeprecationWarning`. A function that moved
out of a module that stays is served by that module's `__getattr__` (`moved_attribute`). Everything here goes
in `REMOVED_IN`.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings
from types import ModuleType
from typing import Any

REMOVED_IN = "0.3.0"
MOVED_MODULES = {
    "cvqpg.allocator": "cvqpg.app.allocator",
    "cvqpg.compilation": "cvqpg.app.compilation",
    "cvqpg.provenance": "cvqpg.app.provenance",
    "cvqpg.bench": "cvqpg.campaign.bench",
    "cvqpg.figures": "cvqpg.campaign.figures",
    "cvqpg.ratedistortion": "cvqpg.campaign.ratedistortion",
    "cvqpg.report": "cvqpg.campaign.report",
    "cvqpg.results": "cvqpg.campaign.results",
    "cvqpg.rasterization": "cvqpg.ops.rasterize.reference",
}


def warn_moved(old: str, new: str, stacklevel: int) -> None:
    """The `DeprecationWarning` of a name that moved; `stacklevel` as `warnings.warn` counts it from here."""
    warnings.warn(f"`{old}` moved to `{new}`; the old name goes in cvqpg {REMOVED_IN}", DeprecationWarning,
                  stacklevel=stacklevel)


class _MovedModuleLoader(importlib.abc.Loader):
    """Gives the module at its new place, which stays that module: its own `__spec__` is put back after the
    import system has set the former name's on it."""

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        warn_moved(spec.name, MOVED_MODULES[spec.name], stacklevel=3)  # the importer's line (importlib's skipped)
        module = importlib.import_module(MOVED_MODULES[spec.name])
        self._own_spec = module.__spec__
        return module

    def exec_module(self, module: ModuleType) -> None:
        module.__spec__ = self._own_spec


class MovedModuleFinder(importlib.abc.MetaPathFinder):
    """Finds a module's former name (`MOVED_MODULES`), for `_MovedModuleLoader` to import from its new place."""

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        if fullname not in MOVED_MODULES:
            return None
        return importlib.util.spec_from_loader(fullname, _MovedModuleLoader())


def install_moved_modules() -> None:
    """Let the former module names import (once per process)."""
    if not any(isinstance(finder, MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.append(MovedModuleFinder())


def moved_attribute(module: str, name: str, moved: dict[str, str]) -> Any:
    """For a module's `__getattr__`: `name` from the module `moved[name]` it moved to, with a warning."""
    if name not in moved:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    warn_moved(f"{module}.{name}", f"{moved[name]}.{name}", stacklevel=4)  # the line that read it
    return getattr(importlib.import_module(moved[name]), name)
