"""Where a command may write: checked before any work, so that a refused command changes nothing.

No command writes over a file or folder that existed before unless the caller says `overwrite`, and
none, even then, over its own input, a run folder, or a run's own record and model (the files that
make a folder a run). Messages name the parameter `out`, which the command line calls `--out`.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Iterable

from ..errors import InputError
from ..runs import CHECKPOINT_FILE, CONFIG_FILE, METRICS_FILE, MODEL_FILE

RUN_RECORD_FILES = (CONFIG_FILE, METRICS_FILE, MODEL_FILE, CHECKPOINT_FILE)


def is_run_folder(path: Path) -> bool:
    return (path / CONFIG_FILE).is_file()


def _refuse_inputs_and_records(path: Path, inputs: Iterable[Path]) -> None:
    resolved = path.resolve()
    for given in inputs:
        if Path(given).resolve() == resolved:
            raise InputError(f"`out` {path} is this command's own input; choose another path")
    if is_run_folder(path):
        raise InputError(f"`out` {path} is a run folder; choose a path outside it, or a new folder")
    if path.name in RUN_RECORD_FILES and is_run_folder(path.parent):
        raise InputError(f"`out` {path} is the run's own {path.name}; choose another file name")


def writable(folder: Path) -> bool:
    """Whether files can be created in `folder`, tried with a probe file that is removed at once (for
    root, `os.access` says yes even where the file system refuses, as in /proc)."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".cvqpg-probe-"):
            return True
    except OSError:
        return False


def _check_parent(path: Path) -> None:
    parent = path.parent
    if not parent.is_dir():
        what = "is a file" if parent.exists() else "does not exist"
        raise InputError(f"`out` {path}: the folder {parent} {what}; give a path in an existing folder")
    if not writable(parent):
        raise InputError(f"`out` {path}: the folder {parent} is not writable; choose another place")


def check_output_file(path: str | Path, inputs: Iterable[Path] = (), overwrite: bool = False) -> Path:
    """A file a command may write (atomically) at `path`; `InputError` naming what is in the way."""
    path = Path(path)
    _refuse_inputs_and_records(path, inputs)
    _check_parent(path)
    if path.is_dir():
        raise InputError(f"`out` {path} is a folder; give a file name")
    if path.exists() and not overwrite:
        raise InputError(f"`out` {path} exists; choose another path, or pass `overwrite` to replace it")
    return path


def check_new_folder(path: str | Path) -> Path:
    """A folder a command creates, with its missing parents, on success: nothing in the way, and its
    nearest existing ancestor writable."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"`out` {path} is a file; give a folder")
    for ancestor in path.parents:
        if ancestor.exists():
            if not ancestor.is_dir():
                raise InputError(f"`out` {path}: {ancestor} is a file, not a folder")
            if not writable(ancestor):
                raise InputError(f"`out` {path}: the folder {ancestor} is not writable; choose another place")
            break
    return path


def check_output_folder(path: str | Path, inputs: Iterable[Path] = (), overwrite: bool = False) -> Path:
    """A folder a command may fill (through `files.staged_folder`) at `path`; `InputError` naming what is
    in the way. An empty existing folder counts as new."""
    path = Path(path)
    _refuse_inputs_and_records(path, inputs)
    for given in inputs:
        if Path(given).resolve().is_relative_to(path.resolve()):
            raise InputError(f"`out` {path} holds this command's input {given}; choose another folder")
    _check_parent(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"`out` {path} is a file; give a folder")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise InputError(f"`out` {path} exists and is not empty; choose another folder, or pass `overwrite` "
                         "to replace it")
    return path
