"""Former names of functions, kept for one release: each still works and warns where it moved.

A name that moved out of a module that stays is served by that module's `__getattr__` (`moved_attribute`), as
`cvqpg.campaign.bench` serves the names that moved to `cvqpg.app.executors`. Everything here goes in `REMOVED_IN`.
"""

from __future__ import annotations

import importlib
import warnings
from typing import Any

REMOVED_IN = "0.4.0"


def warn_moved(old: str, new: str, stacklevel: int) -> None:
    """The `DeprecationWarning` of a name that moved; `stacklevel` as `warnings.warn` counts it from here."""
    warnings.warn(f"`{old}` moved to `{new}`; the old name goes in cvqpg {REMOVED_IN}", DeprecationWarning,
                  stacklevel=stacklevel)


def moved_attribute(module: str, name: str, moved: dict[str, str]) -> Any:
    """For a module's `__getattr__`: `name` from the module `moved[name]` it moved to, with a warning."""
    if name not in moved:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    warn_moved(f"{module}.{name}", f"{moved[name]}.{name}", stacklevel=4)  # the line that read it
    return getattr(importlib.import_module(moved[name]), name)
