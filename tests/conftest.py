"""Shared fixtures: small, fast configurations (guard band narrowed for speed where physics allows)."""

import pytest
import torch

from cvqpg import FitConfig

torch.set_num_threads(2)


@pytest.fixture
def tiny_config() -> FitConfig:
    """64×48 px, two planes, a narrow guard band: a fit step costs a few tens of ms."""
    return FitConfig(width=64, height=48, steps=20, warmup=5, guard_band_px=32)
