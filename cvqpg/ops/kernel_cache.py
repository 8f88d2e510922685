"""Numba's disk cache of the CPU kernels, keyed on the sources of all of them.

Numba files a function's compiled code under a stamp of the function's own source file, but a kernel
compiles in functions and constants of other files (the shared helpers of `ops/cpu.py`, the SIMD
lanes of `rasterize/vectors.py`), whose edits that stamp does not see. Here every function defined
in a kernel file (`KERNEL_PATTERNS`) gets one stamp, a hash of all the kernel files: Numba drops a
cache index whose stamp differs from the current one, so an edit to any kernel file recompiles every
kernel. Where the cache lives stays as Numba chooses it (`NUMBA_CACHE_DIR` when set, else
`__pycache__` beside the module, else the user's cache folder). `register` must run before a kernel
module is imported: Numba picks a function's locator when its decorator runs.
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

from numba.core.caching import CacheImpl, _CacheLocator

OPS_FOLDER = Path(__file__).resolve().parent
KERNEL_PATTERNS = ("**/cpu.py", "**/vectors.py")  # every op's kernels, the shared ones, the SIMD lanes


@functools.cache
def kernel_files(root: Path = OPS_FOLDER) -> tuple[Path, ...]:
    """The kernel modules under `root` (the ops folder), sorted."""
    return tuple(sorted({path.resolve() for pattern in KERNEL_PATTERNS for path in root.glob(pattern)}))


def sources_key(root: Path = OPS_FOLDER) -> str:
    """SHA-256 (hex) of the kernel files under `root`: each one's path relative to `root` and its
    bytes, length-prefixed so that no two sets of files hash alike by where one ends."""
    digest = hashlib.sha256()
    for path in kernel_files(root):
        for part in (path.relative_to(root.resolve()).as_posix().encode(), path.read_bytes()):
            digest.update(len(part).to_bytes(8, "little"))
            digest.update(part)
    return digest.hexdigest()


@functools.cache
def kernel_sources_key() -> str:
    """`sources_key` of this package's kernels, read once per process."""
    return sources_key()


class KernelSourcesLocator(_CacheLocator):
    """The cache place that Numba's own locators pick for a function of a kernel file, stamped with
    `kernel_sources_key` instead of the hash of that file alone."""

    def __init__(self, located: _CacheLocator):
        self._located = located

    def ensure_cache_path(self) -> None:
        self._located.ensure_cache_path()

    def get_cache_path(self) -> str:
        return self._located.get_cache_path()

    def get_source_stamp(self) -> str:
        return kernel_sources_key()

    def get_disambiguator(self) -> str:
        return self._located.get_disambiguator()

    @classmethod
    def from_function(cls, py_func, py_file: str) -> KernelSourcesLocator | None:
        if Path(py_file).resolve() not in kernel_files():
            return None
        for locator in CacheImpl._locator_classes:
            located = None if locator is cls else locator.from_function(py_func, py_file)
            if located is not None:
                return cls(located)
        return None


def register() -> None:
    """Put `KernelSourcesLocator` first among the locators Numba tries (once)."""
    if KernelSourcesLocator not in CacheImpl._locator_classes:
        CacheImpl._locator_classes.insert(0, KernelSourcesLocator)
