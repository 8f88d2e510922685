"""Shared fixtures: small, fast configurations (guard band narrowed for speed where physics allows)."""

import os

import pytest
import torch

if not torch.cuda.is_available():
    # The Triton kernels' tests (test_triton.py) run them through Triton's interpreter on the CPU,
    # which Triton reads where a kernel is defined: before cvqpg's first Triton import.
    os.environ.setdefault("TRITON_INTERPRET", "1")

from cvqpg import FitConfig  # noqa: E402

torch.set_num_threads(2)


@pytest.fixture
def tiny_config() -> FitConfig:
    """64×48 px, two planes, a narrow guard band: a fit step costs a few tens of ms."""
    return FitConfig(width=64, height=48, steps=20, warmup=5, guard_band_px=32)
