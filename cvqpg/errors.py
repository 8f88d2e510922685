"""The one error family of the library: every problem a user can fix is a `CvqpgError`.

Messages name the parameter at fault in backticks, as the library spells it (`num_planes`,
`pixel_pitch`); the command line shows the same message with its own flag names (`--planes`,
`--pitch`). Errors of the machine rather than of the input, a refused write or a failed allocation, are
described by `filesystem_refusal` and `allocation_failure`. Anything else that escapes is a bug.
"""

from __future__ import annotations

import errno
import os
import re
import sys


class CvqpgError(Exception):
    """A problem with what the caller gave: a setting, an input file, a model or a folder."""


class ConfigError(CvqpgError, ValueError):
    """A setting that cannot work."""


class InputError(CvqpgError, ValueError):
    """An input image, depth map, scene or folder that cannot be used as given."""


class ModelFileError(CvqpgError, ValueError):
    """A model file or checkpoint that this version cannot read, or that does not belong where it is."""


class UsageError(CvqpgError):
    """A command's options that cannot work as given, or together (named by their flags): the command line prints
    it as one line and exits with code 2."""


def choices_error(name: str, value: object, choices: tuple[str, ...]) -> ConfigError:
    """The error for an enumerated setting given a value outside its choices."""
    return ConfigError(f"`{name}` {value!r} is not one of {', '.join(map(repr, choices))}")


# Refusals of the file system that a user resolves outside cvqpg, in the words of the message that names them,
# and what to do.
FILESYSTEM_REFUSALS = {errno.ENOSPC: "no space left on the device; free some space, or write elsewhere",
                       errno.EDQUOT: "disk quota exceeded; free some space, or write elsewhere",
                       errno.EACCES: "permission denied; check the folder's permissions, or write elsewhere",
                       errno.EPERM: "operation not permitted; check the folder's permissions, or write elsewhere",
                       errno.EROFS: "read-only file system; write elsewhere"}
# How much an allocation asked for, as PyTorch's CPU allocator ("you tried to allocate 123 bytes"), its CUDA one
# ("Tried to allocate 2.00 GiB") and NumPy ("Unable to allocate 1.00 GiB") report it.
ALLOCATION_SIZE = re.compile(r"(?:tried to allocate|unable to allocate) (\d+ bytes|\d+(?:\.\d+)? ?[KMGTP]?i?B)",
                             re.IGNORECASE)


def filesystem_refusal(error: BaseException) -> str | None:
    """One line for a write or read that the file system refused (full, over quota, not permitted, read-only),
    naming the path where the error gives it; None for any other error."""
    if not isinstance(error, OSError) or error.errno not in FILESYSTEM_REFUSALS:
        return None
    path = error.filename if error.filename is not None else error.filename2
    where = f"{os.fsdecode(path)}: " if path is not None else ""
    return f"{where}{FILESYSTEM_REFUSALS[error.errno]}"


def allocation_failure(error: BaseException) -> str | None:
    """One line for an allocation that failed for want of memory (host or GPU), with the size it asked for
    where the error says; None for any other error."""
    torch = sys.modules.get("torch")  # an error of torch's own type means torch is imported already
    if not (isinstance(error, MemoryError)
            or (isinstance(error, OSError) and error.errno == errno.ENOMEM)
            or (torch is not None and isinstance(error, torch.cuda.OutOfMemoryError))
            or (isinstance(error, RuntimeError) and "can't allocate memory" in str(error))):
        return None
    size = ALLOCATION_SIZE.search(str(error))
    if size is None:
        return "out of memory"
    amount = size.group(1)
    if amount.endswith(" bytes"):
        amount = f"{int(amount.split()[0]) / 2**30:.2f} GiB"
    return f"out of memory: an allocation of {amount} failed"
