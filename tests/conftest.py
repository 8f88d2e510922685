"""Shared fixtures: small, fast configurations (guard band narrowed for speed where physics allows)."""

from __future__ import annotations

import gc
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
from filelock import FileLock
from PIL import Image

if TYPE_CHECKING:
    from cvqpg import FitConfig

# pytest-xdist runs the suite in as many worker processes as the machine has cores (`-n auto`, pyproject.toml):
# each takes one thread, as do the commands they start in subprocesses, since two workers of two threads each spent
# a third more CPU time on OpenMP's waiting threads. Run alone (`-n 0`), the suite takes two, as a fit does on a
# CI-like machine. Numba's pool keeps its size, so that tests may still ask for more (`numba.set_num_threads`).
# pytest caches the assertion-rewritten test modules as bytecode, unless writing bytecode is turned off
# (PYTHONDONTWRITEBYTECODE, as container images often set it): then every process of the suite would rewrite and
# compile each of them again, seconds per process. The suite keeps its own caches (`__pycache__`, ignored by git).
sys.dont_write_bytecode = False
XDIST_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
TEST_THREADS = 1 if XDIST_WORKER else 2
if XDIST_WORKER:
    os.environ.setdefault("OMP_NUM_THREADS", "1")


def pytest_configure(config: pytest.Config) -> None:
    """Where tests run (not in pytest-xdist's controller, which only hands them out and so imports no PyTorch):
    the threads above, and Triton's interpreter where there is no GPU."""
    if getattr(config.option, "dist", "no") != "no" and not hasattr(config, "workerinput"):
        return
    import numba
    import torch

    if not torch.cuda.is_available():
        # The Triton kernels' tests (test_ops_gpu.py) run them through Triton's interpreter on the CPU,
        # which Triton reads where a kernel is defined: before cvqpg's first Triton import.
        os.environ.setdefault("TRITON_INTERPRET", "1")
    torch.set_num_threads(TEST_THREADS)
    numba.set_num_threads(min(TEST_THREADS, numba.config.NUMBA_NUM_THREADS))


# What the session imported lives as long as the session: frozen, the full garbage collections that each fit's
# peak-memory reset runs skip its objects (0.2 s each, with what a first fit imports: matplotlib, transformers, ...).
# Collected first, so that no garbage is kept; again whenever a test imported many more modules.
_modules_frozen = 0


def _freeze_imports() -> None:
    global _modules_frozen
    if len(sys.modules) > _modules_frozen + 50:
        gc.collect()
        gc.freeze()
        _modules_frozen = len(sys.modules)


def pytest_collection_finish(session: pytest.Session) -> None:
    _freeze_imports()


def pytest_runtest_logfinish(nodeid: str, location: tuple) -> None:
    _freeze_imports()


def pytest_sessionfinish(session: pytest.Session) -> None:
    gc.unfreeze()  # the interpreter's exit frees what it holds, as without the freeze


@pytest.fixture
def tiny_config() -> FitConfig:
    """64×48 px, two planes, a narrow guard band: a fit step costs a few tens of ms."""
    from cvqpg import FitConfig

    return FitConfig.create(width=64, height=48, steps=20, curvature_warmup=5, guard_band_px=32)


def write_scenes(root):
    """Three scene folders as ../shared/scenes holds them, with tiny images; returns `root`."""
    for name in ("sushi", "tiger", "zebra"):
        (root / name).mkdir(parents=True)
        Image.new("RGB", (8, 6), (90, 120, 200)).save(root / name / "image.png")
        Image.fromarray(np.tile(np.linspace(0, 255, 8, dtype=np.uint8), (6, 1))).save(root / name / "depth.png")
    return root


@pytest.fixture
def scenes_dir(tmp_path):
    """Scene folders that a test may change (see `write_scenes`)."""
    return write_scenes(tmp_path / "scenes")


@pytest.fixture(scope="module")
def module_scenes_dir(tmp_path_factory):
    """Scene folders shared by a module's tests, left unchanged (see `write_scenes`)."""
    return write_scenes(tmp_path_factory.mktemp("scenes"))


@pytest.fixture(scope="session")
def built_once(tmp_path_factory) -> Callable[[str, Callable[[Path], None]], Path]:
    """`built_once(name, build)`: the folder that `build(folder)` makes, made once for the whole test session. Under
    pytest-xdist the first worker to ask makes it in the folder that all workers share; the others wait for it and
    read it. Its users must not change it (copy it to change it)."""

    def folder_built(name: str, build: Callable[[Path], None]) -> Path:
        if XDIST_WORKER is None:
            folder = tmp_path_factory.mktemp(name) / name
            build(folder)
            return folder
        folder = tmp_path_factory.getbasetemp().parent / name
        with FileLock(f"{folder}.lock"):
            if not folder.with_name(f"{name}.built").exists():
                build(folder)
                folder.with_name(f"{name}.built").touch()
        return folder

    return folder_built


@pytest.fixture(scope="session")
def finished_run(built_once):
    """One finished run for every module: the demo scene at 32×24 px, RGB, two planes, 2 steps. Read it, or copy it
    (`shutil.copytree`) to change it: commands such as `eval` and `export` write into a run."""
    from cvqpg.cli import main

    def fit(out: Path) -> None:
        assert main(["fit", "--size", "32", "24", "--steps", "2", "--quiet", "--out", str(out)]) == 0

    return built_once("finished_run", fit)
