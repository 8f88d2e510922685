"""Process-wide memory allocator setting for long fits on Linux (glibc).

A fitting step creates and frees tensors of tens of MB. glibc serves blocks that large with fresh
`mmap` calls and returns them to the system when freed, so every step pays the kernel to zero and
map the same memory again (`benchmarks/choices.py` times it; docs/performance.md, "Measured choices").
Keeping freed memory in the process removes that cost without raising the peak of one fit; between
fits, `release_freed_memory` hands it back, so that the next fit's peak is its own.
"""

from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
LARGEST_INT = 2**31 - 1


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        return ctypes.CDLL(name)
    except OSError:
        return None


def keep_freed_memory() -> bool:
    """Ask glibc to serve large blocks from its heap and keep them when freed.

    Returns whether the setting took effect (False on other C libraries, where it does nothing).
    The commands that fit (`fit`, `encode`, `bench`) call it; a library user may call it once before fitting.
    """
    mallopt = getattr(_libc(), "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    trimmed_never = mallopt(M_TRIM_THRESHOLD, LARGEST_INT)
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(trimmed_never)


def release_freed_memory() -> bool:
    """Return the heap's free memory to the system (glibc `malloc_trim`), such as what `keep_freed_memory`
    kept from an earlier fit; returns whether any was released (False on other C libraries)."""
    trim = getattr(_libc(), "malloc_trim", None)
    if trim is None:
        return False
    trim.argtypes = [ctypes.c_size_t]
    return bool(trim(0))
