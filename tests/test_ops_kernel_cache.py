"""Numba's cache of the CPU kernels is keyed on all the kernel sources (`cvqpg.ops.kernel_cache`): an edit
to any kernel file, including one that another kernel only compiles in, recompiles every kernel."""

import inspect
import os
import re
import shutil
import subprocess
import sys

import pytest
from numba.core.caching import CacheImpl

from cvqpg.ops import kernel_cache
from cvqpg.ops.field import cpu as field_kernels
from cvqpg.ops.kernel_cache import OPS_FOLDER, KernelSourcesLocator, kernel_files, sources_key


# What makes a module a kernel file: Numba compiles it (a jitted function, an intrinsic or an overload).
COMPILED = re.compile(r"@(?:nb\.|numba\.)?(?:njit|jit|vectorize|intrinsic|overload)\b")


def test_the_kernel_files_are_every_module_that_numba_compiles():
    compiled = {path.resolve() for path in OPS_FOLDER.rglob("*.py") if COMPILED.search(path.read_text())}
    assert OPS_FOLDER / "rasterize" / "cpu.py" in compiled and OPS_FOLDER / "rasterize" / "vectors.py" in compiled
    assert set(kernel_files()) == compiled


def test_the_key_is_a_function_of_the_kernel_files_contents(tmp_path):
    """Copies of the kernel files keep the key; an edit to any one of them changes it."""
    for path in kernel_files():
        copy = tmp_path / path.relative_to(OPS_FOLDER)
        copy.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, copy)
    (tmp_path / "reference.py").write_text("# not a kernel file: no part of the key\n")
    key = sources_key(tmp_path)
    assert key == sources_key(OPS_FOLDER) == kernel_cache.kernel_sources_key()
    keys = {key}
    for path in kernel_files(tmp_path):
        original = path.read_bytes()
        path.write_bytes(original + b"\n# edited\n")
        keys.add(sources_key(tmp_path))
        path.write_bytes(original)
        assert sources_key(tmp_path) == key
    assert len(keys) == len(kernel_files()) + 1


def test_the_kernels_are_stamped_with_the_key_where_numba_would_cache_them():
    kernel = field_kernels.clamped_intensity.py_func
    locator = field_kernels.clamped_intensity._cache._impl.locator
    numbas = next(filter(None, (cls.from_function(kernel, inspect.getfile(kernel)) for cls in CacheImpl._locator_classes
                                if cls is not KernelSourcesLocator)))
    assert isinstance(locator, KernelSourcesLocator)
    assert locator.get_source_stamp() == kernel_cache.kernel_sources_key() != numbas.get_source_stamp()
    assert (locator.get_cache_path(), locator.get_disambiguator()) == (numbas.get_cache_path(),
                                                                        numbas.get_disambiguator())


# A fresh process that calls one kernel and prints how many functions Numba compiled; its argument, if
# any, stands in for the key of the kernel sources, as an edit to a kernel file would change it.
COMPILES = """
import sys
from numba.core import event
from cvqpg.ops import kernel_cache
if len(sys.argv) > 1:
    kernel_cache.kernel_sources_key = lambda: sys.argv[1]
from cvqpg.ops.rasterize import cpu
with event.install_recorder("numba:compile") as recorder:
    cpu.lane_image_width(640, 3)
print(len(recorder.buffer))
"""


def compiles(cache_dir, *key: str) -> int:
    done = subprocess.run([sys.executable, "-c", COMPILES, *key], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)})
    assert done.returncode == 0, done.stderr
    return int(done.stdout.split()[-1])


@pytest.mark.slow
def test_a_cached_kernel_is_compiled_again_after_the_key_changes(tmp_path):
    assert compiles(tmp_path) > 0  # an empty cache
    assert compiles(tmp_path) == 0  # loaded from the cache
    assert compiles(tmp_path, "an edited kernel file") > 0
    assert compiles(tmp_path, "an edited kernel file") == 0
    assert compiles(tmp_path) > 0  # and back
