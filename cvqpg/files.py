"""Atomic file writes: a reader never sees a half-written file, and the file's mode follows the umask.

Each write goes to a temporary sibling that replaces the target once it is whole and on disk. The
temporary file is created with `open`, so it gets the mode every other file of a run gets
(0666 less the umask); a file from `mkstemp`, or from a library that creates its files 0600 (the
safetensors writer does), would keep that mode through the rename.

A caller may hold back what is moved into place at a path (`gated`): a check runs before the rename, and
whatever it raises keeps the path as it was (the command line's outputs, once a command was told to stop).

An input is read only where it is a regular file (`input_file`) and its path one the file system takes
(`name_too_long`).
"""

from __future__ import annotations

import os
import shutil
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

from .errors import InputError

_GATES: ContextVar[tuple[tuple[Path, Callable[[], None]], ...]] = ContextVar("cvqpg_gates", default=())


@contextmanager
def gated(path: str | Path, check: Callable[[], None]) -> Iterator[None]:
    """Within the block (and this thread), `check()` runs before anything is moved into place at `path` (an
    atomic write of it, a folder replacing it); what it raises leaves `path` as it was."""
    token = _GATES.set((*_GATES.get(), (Path(os.path.abspath(path)), check)))
    try:
        yield
    finally:
        _GATES.reset(token)


def input_file(path: str | Path, role: str, what: str = "a file") -> Path:
    """The path of an input to read: an existing regular file (through links), else an `InputError` naming `role`
    and what is there instead. Never a pipe, whose read waits for a writer for ever, nor a device, whose read may
    never end (/dev/zero); `what` names the file the caller wants ("an image file")."""
    path = Path(path)
    if path.is_file():
        return path
    if not path.exists():
        raise InputError(f"{role} {path}: no such file; check the path")
    if path.is_dir():
        raise InputError(f"{role} {path} is a folder; give {what}")
    raise InputError(f"{role} {path} is neither a file nor a folder (a pipe, a device or a socket); give {what}")


def name_too_long(path: str | Path) -> str | None:
    """Where a path given to a command is longer than the file system takes (a name of it beyond 255 bytes, the
    whole beyond 4096; the usual limits where they cannot be asked): what is too long, else None. Looked up, such a
    path is an error of its own (`OSError: File name too long`), so an input is checked before it is opened."""
    path = Path(os.path.abspath(path))
    ancestor = next((folder for folder in path.parents if os.path.exists(folder)), path)
    name_max, path_max = (path_limit(ancestor, key, usual) for key, usual in (("PC_NAME_MAX", 255),
                                                                               ("PC_PATH_MAX", 4096)))
    if any(len(os.fsencode(part)) > name_max for part in path.parts):
        return f"a name longer than the file system takes ({name_max} bytes)"
    if len(os.fsencode(str(path))) > path_max:
        return f"a path longer than the file system takes ({path_max} bytes)"
    return None


def path_limit(folder: Path, key: str, usual: int) -> int:
    """The file system's `key` limit (`os.pathconf`: "PC_NAME_MAX", "PC_PATH_MAX") at `folder`, or `usual`."""
    try:
        return os.pathconf(folder, key)
    except (OSError, ValueError):
        return usual


def _before_moving_into(path: Path) -> None:
    target = Path(os.path.abspath(path))
    for gate, check in _GATES.get():
        if gate == target:
            check()


@contextmanager
def atomic_file(path: str | Path) -> Iterator[BinaryIO]:
    """A binary handle whose content replaces `path` when the block ends without an error.

    The temporary name carries the process id, so that several processes (the shards of a job
    array) may write the same file at once; the last whole one wins. On an error `path` is left
    as it was and the temporary file is removed.
    """
    path = Path(path)
    partial = path.with_name(f"{path.name}.{os.getpid()}.partial")
    try:
        with open(partial, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        _before_moving_into(path)
        os.replace(partial, path)
    except OSError as error:
        if error.filename is None:  # a full disk fails a write or a flush, which name no file
            error.filename = str(path)
        raise
    finally:
        partial.unlink(missing_ok=True)


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write `data` (text as UTF-8) to `path` atomically (see `atomic_file`)."""
    with atomic_file(path) as handle:
        handle.write(data.encode() if isinstance(data, str) else data)


def replace_folder(staged: Path, final: Path) -> None:
    """Put the finished folder `staged` at `final` (a sibling), replacing a folder there as a whole: the old
    folder is renamed aside first and deleted only once `staged` is in its place. A file or a symbolic link at
    `final` is never replaced (`InputError`, `staged` left as it is): what a command may replace is checked
    before (`app.outputs`), and anything else that appeared there meanwhile is the user's."""
    staged, final = Path(staged), Path(final)
    if final.is_symlink() or (final.exists() and not final.is_dir()):
        what = "a symbolic link" if final.is_symlink() else "a file"
        raise InputError(f"{final} ({what}) appeared while the command ran; it is left as it is: move it away and "
                         "run the command again")
    _before_moving_into(final)
    if not final.exists():
        os.replace(staged, final)
        return
    aside = final.with_name(f".{final.name}.replaced-{os.getpid()}")
    os.replace(final, aside)
    try:
        os.replace(staged, final)
    except OSError:
        os.replace(aside, final)
        raise
    shutil.rmtree(aside)


@contextmanager
def staged_folder(final: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """A fresh temporary folder beside `final` to write a command's outputs into; when the block ends
    without an error it becomes `final` (replacing an existing folder only with `overwrite`), and on an
    error it is deleted, so `final` is never half-written and nothing is left behind."""
    final = Path(final)
    staged = final.with_name(f".{final.name}.partial-{os.getpid()}")
    shutil.rmtree(staged, ignore_errors=True)
    staged.mkdir()
    try:
        yield staged
        if not overwrite and (final.is_file() or (final.is_dir() and any(final.iterdir()))):
            raise InputError(f"{final} appeared while the command ran; it is left as it is: choose another place, "
                             "or move it away and run the command again")
        replace_folder(staged, final)
    finally:
        shutil.rmtree(staged, ignore_errors=True)
