"""Where a command may write: one rule for every command's output, checked before any work (so that a refused
command changes nothing) and again, under a lock, before anything is written.

The rule:
- A new path, or an empty folder, is always a command's to write.
- Something that exists is replaced only with `overwrite`, and only where it is of the command's own kind
  (`Kind`): a run folder for `fit`, a render folder for `render`, a `.cvq` file for `compress`, an HTML page for
  `view`, ... (an empty file counts as any kind); never a folder or file of another kind, which is the user's.
- Never, even with `overwrite`: the command's own input, a folder that holds it, a run's own files (those `fit`
  writes), the current folder or one that holds it, or a symbolic link (which would send the output where the
  user did not name).
- Nothing is moved into place at an output once the command was told to stop (Ctrl-C, SIGTERM), even where the
  signal's exception was swallowed: `claimed` gates the output's path (`files.gated`) with
  `signals.check_not_stopped`.
- One writer at a time: `claimed` holds an exclusive lock beside the output while the command works, so that a
  second command writing the same output stops with a one-line error instead of both succeeding. An output
  inside a run folder (a `.cvq` file, `export/`, `metrics.json` that `eval` rewrites, ...) also holds the run
  folder with a shared lock (`claimed_in_run`): several such commands may write into one run at once, but none
  while a fit resumes or replaces that run (a fit holds its run folder exclusively), nor a fit while they do.

Messages name the parameter `out`, which the command line calls `--out`, unless the caller names another.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

from ..defaults import BATCH_RECORDS
from ..errors import InputError
from ..files import gated, path_limit, staged_folder
from ..runs import CHECKPOINT_FILE, CONFIG_FILE, HISTORY_FILE, METRICS_FILE, MODEL_FILE, PLANE_IMAGES
from .signals import check_not_stopped

# What `fit` writes in a run folder (and an estimated depth map): no other command writes over them.
RUN_FILES = (CONFIG_FILE, METRICS_FILE, MODEL_FILE, CHECKPOINT_FILE, HISTORY_FILE, "depth.png", "curve.png",
             "amplitude.png", "phase.png", *PLANE_IMAGES)
LOCK_SUFFIX = ".cvqpg-lock"
HEAD_BYTES = 64  # enough of a file's start to recognise its kind
# The most bytes that cvqpg adds to an output's name for what it keeps beside it: a staged folder or a replaced one
# (".NAME.partial-PID", ".NAME.replaced-PID", a PID of up to 7 digits), the lock, an atomic write, a fit's
# "NAME.partial".
ADDED_NAME_BYTES = 18


def is_run_folder(path: Path) -> bool:
    try:
        return (Path(path) / CONFIG_FILE).is_file()
    except OSError:  # a name too long to look up, which `check_output` names
        return False


def _head(path: Path) -> bytes:
    try:
        with open(path, "rb") as handle:
            return handle.read(HEAD_BYTES)
    except OSError:
        return b""


def _is_cvq(path: Path) -> bool:
    from ..codec import MAGIC  # the codec imports the entropy coder, which only this check needs here

    return _head(path).startswith(MAGIC)


def _is_safetensors(path: Path) -> bool:
    """A safetensors file: an 8-byte little-endian header length, then a JSON header."""
    head = _head(path)
    return len(head) > 8 and 0 < int.from_bytes(head[:8], "little") <= path.stat().st_size - 8 \
        and head[8:9] == b"{"


def _is_page(path: Path) -> bool:
    return _head(path).lstrip().lower().startswith((b"<!doctype html", b"<html"))


def _is_markdown(path: Path) -> bool:
    if path.suffix.lower() != ".md":
        return False
    try:
        path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return False
    return True


def _is_png(path: Path) -> bool:
    return _head(path).startswith(b"\x89PNG\r\n\x1a\n")


def _holds(*names: str) -> Callable[[Path], bool]:
    return lambda path: all((path / name).exists() for name in names)


@dataclass(frozen=True)
class Kind:
    """What a command writes at its output: a folder or a file, and how an existing one is recognised as one that
    `overwrite` may replace (`recognised(path)`)."""

    name: str  # with its article, as messages say it
    folder: bool
    recognised: Callable[[Path], bool]


RUN = Kind("a run folder", True, is_run_folder)
RENDER = Kind("a render folder (amplitude.png, phase.png, recon_*.png)", True, _holds("amplitude.png", "phase.png"))
EXPORT = Kind("an export folder (metrics.json, display_plane*.png, ...)", True,
              _holds(METRICS_FILE, "display_plane0.png"))
BENCH = Kind("a bench folder (cells/, summary.md, ...)", True, _holds("cells"))
BATCH = Kind(f"a batch folder (summary.csv, {BATCH_RECORDS}/, ...)", True, _holds(BATCH_RECORDS))
CVQ = Kind("a compressed model (.cvq) file", False, _is_cvq)
MODEL = Kind("a safetensors model file", False, _is_safetensors)
PAGE = Kind("an HTML page", False, _is_page)
DOCUMENT = Kind("a Markdown (.md) document", False, _is_markdown)
FIGURE = Kind("a PNG image", False, _is_png)


def writable(folder: Path) -> bool:
    """Whether files can be created in `folder`, tried with a probe file that is removed at once (for
    root, `os.access` says yes even where the file system refuses, as in /proc, or the folder is immutable)."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".cvqpg-probe-"):
            return True
    except OSError:
        return False


def _place(path: Path, role: str) -> Path:
    """`path` without `.` and `..` components (lexically), refused where it names the current folder or one
    that holds it (which a command cannot replace: `--out .`)."""
    absolute = Path(os.path.abspath(path))
    if Path.cwd().is_relative_to(absolute):
        raise InputError(f"{role} {path} is the current folder, or holds it; choose another place")
    return Path(os.path.normpath(path))


def _check_length(path: Path, given: Path, role: str) -> None:
    """Every name of `path`, and its own with what cvqpg adds beside it (`ADDED_NAME_BYTES`), within the file
    system's limits (where they cannot be asked, the usual 255 bytes a name and 4096 a path)."""
    ancestor = next(folder for folder in Path(os.path.abspath(path)).parents if os.path.exists(folder))
    name_max, path_max = (path_limit(ancestor, key, usual) for key, usual in (("PC_NAME_MAX", 255),
                                                                               ("PC_PATH_MAX", 4096)))
    longest = max(path.parts, key=lambda part: len(os.fsencode(part)))
    if len(os.fsencode(path.name)) + ADDED_NAME_BYTES > name_max or len(os.fsencode(longest)) > name_max:
        raise InputError(f"{role} {given}: a name longer than the file system takes ({name_max} bytes, less "
                         f"{ADDED_NAME_BYTES} for what cvqpg keeps beside the output); choose a shorter name")
    if len(os.fsencode(os.path.abspath(path))) + ADDED_NAME_BYTES > path_max:
        raise InputError(f"{role} {given}: a path longer than the file system takes ({path_max} bytes); choose a "
                         "shorter one")


def _refuse_fixed(path: Path, given: Path, inputs: Iterable[Path], role: str) -> None:
    """What no command writes over, even with `overwrite`: links, what is neither a file nor a folder (a device,
    a pipe), its inputs and the folders that hold them, and a run's own files."""
    if path.is_symlink():
        raise InputError(f"{role} {given} is a symbolic link (to {os.readlink(path)}); give the place itself, or "
                         "a new path")
    if path.exists() and not (path.is_file() or path.is_dir()):
        raise InputError(f"{role} {given} is neither a file nor a folder (a device, a pipe or a socket); give a "
                         "new path")
    try:
        resolved = path.resolve()
    except (RuntimeError, OSError):  # Python's own words for a loop of symbolic links on the way
        raise InputError(f"{role} {given} lies through a loop of symbolic links; give a path without it") from None
    for source in inputs:
        source_resolved = Path(source).resolve()
        if source_resolved == resolved:
            raise InputError(f"{role} {given} is this command's own input; choose another path")
        if source_resolved.is_relative_to(resolved):
            raise InputError(f"{role} {given} holds this command's input {source}; choose another place")
    if is_run_folder(path.parent) and any(path.match(pattern) for pattern in RUN_FILES):
        raise InputError(f"{role} {given} is the run's own {path.name}; choose another file name")


def _check_parent(path: Path, given: Path, role: str, make_parents: bool) -> None:
    """The folder the output goes in exists and is writable; with `make_parents`, its nearest existing
    ancestor (the command creates the rest)."""
    for ancestor in path.parents:
        if ancestor.exists() or not make_parents:
            if not ancestor.is_dir():
                what = "is a file" if ancestor.exists() else "does not exist"
                raise InputError(f"{role} {given}: the folder {ancestor} {what}; give a path in an existing folder")
            if not writable(ancestor):
                raise InputError(f"{role} {given}: the folder {ancestor} is not writable; choose another place")
            return


def _check_existing(path: Path, given: Path, kind: Kind, overwrite: bool, role: str) -> None:
    """Something at `path`: replaced only with `overwrite` and where it is of `kind`."""
    if kind.folder and not path.is_dir():
        raise InputError(f"{role} {given} is a file; give a folder")
    if not kind.folder and path.is_dir():
        raise InputError(f"{role} {given} is a folder; give a file name")
    if path.is_dir() and not any(path.iterdir()):
        return  # an empty folder counts as new
    if kind.folder and not kind.recognised(path):
        raise InputError(f"{role} {given} is not {kind.name}: it holds other files, which `overwrite` does not "
                         "replace; choose another place, or move them away")
    if not kind.folder and path.stat().st_size and not kind.recognised(path):
        raise InputError(f"{role} {given} is not {kind.name}, which is all `overwrite` replaces; choose another "
                         "path")
    if not overwrite:
        raise InputError(f"{role} {given} exists; choose another path, or pass `overwrite` to replace it")
    if kind.folder:
        inner = next((p for p in path.iterdir() if p.is_dir() and not p.is_symlink()), None)
        if inner is not None and kind is not RUN:
            raise InputError(f"{role} {given} holds a folder ({inner.name}) that {kind.name} does not; "
                             "`overwrite` does not replace it; give a new or empty folder")
        if not writable(path):
            raise InputError(f"{role} {given} cannot be replaced (the folder is not writable); choose another place")


def check_output(path: str | Path, kind: Kind, inputs: Iterable[Path] = (), overwrite: bool = False,
                 role: str = "`out`", make_parents: bool = False) -> Path:
    """The path a command may write its output of `kind` at, by the module's rule, or an `InputError` naming what
    is in the way. `make_parents`: the command creates missing folders above it."""
    if not kind.folder and str(path).endswith(os.sep):
        raise InputError(f"{role} {path} names a folder (it ends in {os.sep}); give a file name")
    given = Path(path)
    path = _place(given, role)
    _check_length(path, given, role)
    _refuse_fixed(path, given, inputs, role)
    _check_parent(path, given, role, make_parents)
    if path.exists():
        if kind is not RUN and is_run_folder(path):
            raise InputError(f"{role} {given} is a run folder; choose a path outside it, or a new folder")
        _check_existing(path, given, kind, overwrite, role)
    return path


def check_continued(path: str | Path, kind: Kind, role: str = "`out`") -> Path:
    """A folder of `kind` that a command adds to (a bench folder): new, empty or already of that kind."""
    given = Path(path)
    path = _place(given, role)
    _check_length(path, given, role)
    _refuse_fixed(path, given, (), role)
    _check_parent(path, given, role, make_parents=True)
    if path.exists() and not (path.is_dir() and (not any(path.iterdir()) or kind.recognised(path))):
        what = "a run folder" if is_run_folder(path) else "a file" if not path.is_dir() else "a folder of other files"
        raise InputError(f"{role} {given} is {what}, not {kind.name}; give a new folder or {kind.name}")
    return path


def place_problem(path: Path, folder: bool, writer: str = "cvqpg") -> str | None:
    """What keeps `writer` (as messages name it) from writing a folder (`folder`) or a file at `path`: a symbolic
    link (never written through), or something of another kind; None where nothing is there, or a folder or file
    as asked."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return None
    except OSError as error:
        return f"{path} cannot be looked at ({error.strerror})"
    if stat.S_ISLNK(mode):
        return f"{path} is a symbolic link, which {writer} does not write through"
    if folder and not stat.S_ISDIR(mode):
        return f"{path} is {'a file' if stat.S_ISREG(mode) else 'not a folder'}, where {writer} keeps a folder"
    if not folder and not stat.S_ISREG(mode):
        return (f"{path} is {'a folder' if stat.S_ISDIR(mode) else 'neither a file nor a folder'}, where {writer} "
                "writes a file")
    return None


def _missing_folders(path: Path) -> list[Path]:
    return [folder for folder in path.parents if not folder.exists()][::-1]


@contextmanager
def claimed(path: str | Path, role: str = "`out`", shared: bool = False) -> Iterator[None]:
    """An exclusive lock on the output `path` for the block: a hidden lock file beside it, held with `flock` (so
    that a killed command holds none). A second command claiming the same path gets an `InputError`. With
    `shared`, a lock that other shared claims may hold at once, but no exclusive one. Missing folders above
    `path` are created, and removed again where the block fails and leaves them empty. Nothing is moved into place
    at `path` within the block once the command was told to stop (`signals.check_not_stopped`)."""
    path = Path(path)
    lock = path.with_name(f".{path.name}{LOCK_SUFFIX}")
    created = _missing_folders(path)
    try:
        for folder in created:
            folder.mkdir()
        handle = _locked(lock, path, role, shared)
    except BaseException:
        _remove_empty(created)
        raise
    try:
        with gated(path, check_not_stopped):
            yield
    except BaseException:
        _release(lock, handle)
        _remove_empty(created)
        raise
    _release(lock, handle)


def open_lock(lock: Path, role: str) -> int:
    """A descriptor of the lock file `lock`, created where it is missing; an `InputError` naming `role` where
    something else is there (a folder, a pipe, a link, ...), which no command waits on, or it cannot be made."""
    def refused(what: str) -> InputError:
        return InputError(f"{role}: its lock file {lock} {what}; remove it (cvqpg makes it again), or choose "
                          "another place")

    try:
        existing = os.lstat(lock).st_mode
    except FileNotFoundError:
        existing = None
    except OSError as error:
        raise refused(f"cannot be looked at ({error.strerror})") from None
    if existing is not None and not stat.S_ISREG(existing):
        raise refused(f"is {_kind_name(existing)}, not a regular file")
    try:
        handle = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o666)
    except OSError as error:
        raise InputError(f"{role}: cannot write its lock file {lock} ({error.strerror}); choose another place") \
            from None
    if not stat.S_ISREG(os.fstat(handle).st_mode):  # put there since the look
        os.close(handle)
        raise refused("is not a regular file")
    return handle


def _kind_name(mode: int) -> str:
    """What a file of `mode` is, with its article."""
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a pipe"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a device"), (stat.S_ISBLK, "a device")):
        if test(mode):
            return name
    return "a file"


def _locked(lock: Path, path: Path, role: str, shared: bool) -> int:
    """A descriptor of `lock` holding its `flock`; retried where another command removed the file meanwhile."""
    while True:
        handle = open_lock(lock, f"{role} {path}")
        try:
            fcntl.flock(handle, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except OSError as error:
            os.close(handle)
            if error.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise InputError(f"{role} {path}: cannot lock it ({error.strerror}); choose another place") from None
            raise InputError(f"{role} {path} is being written by another cvqpg command; wait until it ends, or "
                             "choose another path") from None
        try:
            if stat.S_ISREG(os.fstat(handle).st_mode) and os.fstat(handle).st_ino == os.stat(lock).st_ino:
                return handle
        except FileNotFoundError:
            pass
        os.close(handle)


def _release(lock: Path, handle: int) -> None:
    """Remove the lock file while holding it exclusively, so that no one locks a file about to vanish; a shared
    holder that cannot take it exclusively leaves the file to the last holder (a failed conversion drops the
    shared lock, so of several holders leaving at once one always succeeds)."""
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(handle)
        return
    lock.unlink(missing_ok=True)
    os.close(handle)


def enclosing_run(path: Path) -> Path | None:
    """The run folder that `path` lies in (at any depth), or None."""
    return next((folder for folder in Path(os.path.abspath(path)).parents if is_run_folder(folder)), None)


@contextmanager
def claimed_in_run(path: str | Path, role: str = "`out`") -> Iterator[None]:
    """`claimed(path)`, and where `path` lies in a run folder, that folder claimed shared first (`claimed`): a
    fit that would resume or replace the run waits for no one, it stops; and this command stops while one runs."""
    run = enclosing_run(Path(path))
    if run is None:
        with claimed(path, role):
            yield
        return
    with claimed(run, f"{role} {path}: its run folder", shared=True), claimed(path, role):
        yield


def _remove_empty(folders: list[Path]) -> None:
    for folder in reversed(folders):
        try:
            folder.rmdir()
        except OSError:
            return


@contextmanager
def output(path: str | Path, kind: Kind, inputs: Iterable[Path] = (), overwrite: bool = False,
           role: str = "`out`") -> Iterator[Path]:
    """`check_output`'s path, claimed (`claimed_in_run`) for the block and checked again once claimed: a file output
    is written in the block (atomically, `files.write_atomic`)."""
    inputs = list(inputs)
    path = check_output(path, kind, inputs, overwrite, role)
    with claimed_in_run(path, role):
        yield check_output(path, kind, inputs, overwrite, role)


@contextmanager
def staged_output(path: str | Path, kind: Kind, inputs: Iterable[Path] = (), overwrite: bool = False,
                  role: str = "`out`") -> Iterator[Path]:
    """A fresh folder to fill (`files.staged_folder`) that becomes the folder output `path` (`output`'s rule)
    once the block succeeds: the path is claimed, and checked again before it is replaced."""
    with output(path, kind, inputs, overwrite, role) as final, staged_folder(final, overwrite) as staged:
        yield staged
        check_output(final, kind, inputs, overwrite, role)
