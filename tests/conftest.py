"""Shared fixtures: small, fast configurations (guard band narrowed for speed where physics allows)."""

import gc
import os
import sys

import numpy as np
import pytest
import torch
from PIL import Image

if not torch.cuda.is_available():
    # The Triton kernels' tests (test_ops_gpu.py) run them through Triton's interpreter on the CPU,
    # which Triton reads where a kernel is defined: before cvqpg's first Triton import.
    os.environ.setdefault("TRITON_INTERPRET", "1")

from cvqpg import FitConfig  # noqa: E402

torch.set_num_threads(2)


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
def finished_run(tmp_path_factory):
    """One finished run for every module: the demo scene at 32×24 px, RGB, two planes, 2 steps. Read it, or copy it
    (`shutil.copytree`) to change it: commands such as `eval` and `export` write into a run."""
    from cvqpg.cli import main

    out = tmp_path_factory.mktemp("finished") / "run"
    assert main(["fit", "--size", "32", "24", "--steps", "2", "--quiet", "--out", str(out)]) == 0
    return out
