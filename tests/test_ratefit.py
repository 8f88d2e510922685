"""The rate in the fit (`cvqpg.ratefit`): the noise's schedule, λ's controller, the gate that lets the rate switch
primitives off, and a fit and an encode with them."""

import pytest
import torch

from cvqpg import FitConfig
from cvqpg.app.encoding import encode_fit, encode_scene, stand_in, start_encode
from cvqpg.codec import BitDepths
from cvqpg.errors import ConfigError
from cvqpg.fitting import fit_scene
from cvqpg.ratefit import (ANNEAL_SHARE, FULL, GATE_BINS, PLAIN, RateController, RateFit, RateObjective, noise_share,
                           presence, silent_removed)
from cvqpg.scenes import builtin_scene
from cvqpg.search import Budget, CompressionSettings


def test_the_noise_stands_for_the_rounding_until_the_last_steps_then_gives_way_to_it():
    steps = 100
    assert [noise_share(step, steps) for step in (0, round((1 - ANNEAL_SHARE) * steps))] == [1.0, 1.0]
    assert noise_share(85, steps) == pytest.approx(0.5) and noise_share(steps, steps) == 0.0


def test_lambda_grows_while_the_file_is_over_its_target_and_shrinks_below_it():
    controller = RateController(1000, weight=1e-3)
    grown = [controller.update(1500) for _ in range(5)][-1]
    assert grown > 1e-3 * 1.5
    assert controller.update(500) < grown
    for _ in range(10_000):
        controller.update(10**9)
    assert controller.weight == 10.0


def test_the_gate_closes_on_primitives_far_below_the_strongest_and_silent_ones_are_removed():
    config = FitConfig.create(width=48, height=32, color="gray", num_gaussians=5)
    primitives = stand_in(config, 5)
    tensors = primitives.tensors()
    tensors["opacity"] = torch.ones(5)
    tensors["amplitude"] = torch.tensor([[1.0], [0.5], [GATE_BINS / 255 / 2], [1e-6], [0.0]])
    primitives = type(primitives).from_tensors(tensors)
    gate = presence(primitives, config, BitDepths())
    assert gate[:2].tolist() == [1.0, 1.0] and gate[2] == pytest.approx(0.5) and gate[4] == 0
    assert silent_removed(primitives, config, BitDepths()).count == 3


def test_rate_loss_needs_a_budget_and_gives_encode_every_lever():
    with pytest.raises(ConfigError, match="rate_loss"):
        CompressionSettings(rate_loss=True)
    budget = Budget(4000, "`max_bytes` 4000")
    assert CompressionSettings(max_bytes=4000).rate_fit(budget) == PLAIN
    assert CompressionSettings(max_bytes=4000, rate_loss=True).rate_fit(budget) == RateFit(**FULL, target_bytes=4000)


def tiny(color: str = "gray") -> FitConfig:
    return FitConfig.create(width=40, height=32, color=color, num_planes=1, num_gaussians=60, steps=8,
                            curvature_warmup=2, guard_band_px=16)


@pytest.mark.slow
def test_a_fit_with_the_rate_in_its_loss_records_lambda_and_the_estimate_and_ends_on_the_file_s_values():
    config = tiny()
    target = 300  # far below what 60 primitives take: λ grows at every step
    objective = RateObjective(RateFit(**FULL, target_bytes=target), config)
    fitted = fit_scene(builtin_scene("demo", config), config, objective=objective)
    lambdas = fitted.history["rate_lambda"]
    assert len(lambdas) == config.optimisation.steps + 1 and lambdas == sorted(lambdas) and lambdas[-1] > lambdas[0]
    assert all(size > target for size in fitted.history["rate_bytes"])


@pytest.mark.slow
def test_encode_with_rate_loss_writes_a_file_within_the_budget_and_its_folder_records_the_levers(tmp_path):
    config = tiny()
    settings = CompressionSettings(max_bytes=900, finetune_steps=2, rate_loss=True)
    encoded = encode_scene(builtin_scene("demo", config), config, settings)
    assert len(encoded.rate.choice.data) <= 900
    fit = settings.rate_fit(settings.budget(config))
    start_encode(tmp_path / "work", config, {"scene": "demo"}, settings.budget(config), 2, fit=fit)
    assert encode_fit(tmp_path / "work") == fit
    start_encode(tmp_path / "plain", config, {"scene": "demo"}, settings.budget(config), 2)
    assert encode_fit(tmp_path / "plain") == PLAIN
