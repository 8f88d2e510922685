"""Recipes are recorded choices: the paper's stays one flag away and every grid that compares with the
paper pins it; a budget in minutes becomes a recorded step count."""

import json
from pathlib import Path

import pytest
import torch

from cvqpg import FitConfig, load_model
from cvqpg.app import runner
from cvqpg.app.runner import timed_config
from cvqpg.campaign.bench import PRESETS, make_plan
from cvqpg.campaign.results import CAMPAIGN, campaign_plan
from cvqpg.cli import main
from cvqpg.config import (BEYOND_RECIPE, DEFAULT_RECIPE, LONG_RUN_BETAS, PAPER_BETAS, RECIPES, SHORT_RUN_STEPS,
                          DensityControl)
from cvqpg.errors import ConfigError
from cvqpg.fitting import initial_state, steps_within
from cvqpg.scenes import builtin_scene


def test_the_default_configuration_is_the_default_recipe_and_each_recipe_is_recognised():
    assert FitConfig().recipe == DEFAULT_RECIPE
    for name in RECIPES:
        assert FitConfig(steps=300, color="gray").with_recipe(name).recipe == name
    assert FitConfig().replace(init="targets").recipe == "custom"
    with pytest.raises(ConfigError, match="`recipe`.*paper"):
        FitConfig().with_recipe("fast")


def test_a_record_older_than_recipes_reads_as_the_paper_s():
    record = FitConfig().with_recipe(BEYOND_RECIPE).to_dict()
    for key in RECIPES[BEYOND_RECIPE]:
        record.pop(key)
    assert FitConfig.from_dict(record).recipe == "paper"


def test_a_record_older_than_the_loss_weights_has_the_paper_s_loss():
    record = FitConfig().with_recipe(BEYOND_RECIPE).to_dict()
    for key in ("focus_weight", "product_weight"):
        record.pop(key)
    config = FitConfig.from_dict(record)
    assert (config.focus_weight, config.product_weight) == (1.0, 1.0) and config.recipe == "custom"


def test_a_recorded_density_control_reads_back():
    config = FitConfig(density=DensityControl(every=0.1, until=0.5, fraction=0.03), init="targets")
    assert FitConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config


@pytest.mark.parametrize("density", [DensityControl(every=0.0), DensityControl(until=1.5),
                                     DensityControl(fraction=1.0), DensityControl(every=float("nan"))])
def test_density_settings_that_cannot_work_are_refused(density):
    with pytest.raises(ConfigError, match="density"):
        FitConfig(density=density).validate()


def test_every_grid_that_compares_with_the_paper_pins_its_recipe():
    for name, preset in PRESETS.items():
        assert preset.recipe == (BEYOND_RECIPE if name.startswith("beyond") else "paper"), name
    for grid in CAMPAIGN:
        recipe = PRESETS[grid.preset].recipe
        assert {cell.config.recipe for cell in campaign_plan(grid, Path("results")).cells} == {recipe}
    assert {c.config.recipe for c in make_plan("quick").cells} == {"paper"}


def test_the_paper_time_grid_fixes_one_step_count_per_colour():
    preset = PRESETS["beyond-time"]
    assert preset.steps_for("gray") != preset.steps_for("rgb")
    grid = next(g for g in CAMPAIGN if g.preset == "beyond-time")
    plan = campaign_plan(grid, Path("results"))
    for cell in plan.cells:
        assert cell.config.steps == preset.steps_for(cell.config.color)
        assert cell.config.curvature_warmup_steps == round(cell.config.steps / 5)


@pytest.mark.parametrize("seconds, each, steps", [(60.0, 0.05, 1199), (1.0, 2.0, 1), (10.0, 0.1, 99)])
def test_a_time_budget_holds_the_run_s_steps_plus_one_updates(seconds, each, steps):
    assert steps_within(seconds, each) == steps


def test_a_time_budget_is_timed_and_recorded_with_the_compile_time_it_spent(monkeypatch):
    # The fit after it only loads the kernels, so the budget's record is where the compilation shows
    monkeypatch.setattr(runner, "prepare_kernels", lambda config, show_status=True: 7.5)
    config = FitConfig(width=32, height=24, num_gaussians=30, steps=5, guard_band_px=8, color="gray")
    timed, record = timed_config(builtin_scene("demo", config), config, 0.01, progress=False)
    assert timed.steps == steps_within(0.6, record["seconds_per_step"])
    assert record["minutes"] == 0.01 and record["seconds_per_step"] > 0
    assert record["compile_seconds"] == 7.5
    with pytest.raises(ConfigError, match="`time`"):
        timed_config(builtin_scene("demo", config), config, 0.0, progress=False)


def test_fit_records_the_recipe_and_the_time_budget_and_a_rerun_with_its_steps_is_exact(tmp_path):
    out, rerun = tmp_path / "run", tmp_path / "rerun"
    small = ["fit", "--scene", "demo", "--size", "32", "24", "--num-gaussians", "30", "--recipe", "paper", "--quiet"]
    assert main([*small, "--time", "0.02", "--out", str(out)]) == 0
    recorded = json.loads((out / "config.json").read_text())
    assert FitConfig.from_dict(recorded).recipe == "paper"
    assert recorded["source"]["time_budget"]["minutes"] == 0.02
    assert json.loads((out / "metrics.json").read_text())["steps"] == recorded["steps"]
    assert main([*small, "--steps", str(recorded["steps"]), "--out", str(rerun)]) == 0
    timed, again = (load_model(folder / "model.safetensors")[0].tensors() for folder in (out, rerun))
    assert all(torch.equal(timed[name], again[name]) for name in timed)


def test_steps_and_time_together_are_one_line(capsys, tmp_path):
    assert main(["fit", "--scene", "demo", "--steps", "3", "--time", "1", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--steps or --time" in err[0]
    assert not (tmp_path / "r").exists()


def test_the_default_recipe_drops_the_masked_and_correlation_terms_in_short_runs_only():
    beyond = FitConfig().with_recipe(BEYOND_RECIPE)
    assert beyond.replace(steps=SHORT_RUN_STEPS).validate().loss_weights == (0.0, 0.0)
    assert beyond.replace(steps=SHORT_RUN_STEPS + 1).validate().loss_weights == (1.0, 1.0)
    assert FitConfig().with_recipe("paper").replace(steps=300).loss_weights == (1.0, 1.0)
    assert beyond.replace(focus_weight=0.5, steps=300).loss_weights == (0.5, 0.0)


def test_the_default_recipe_raises_adan_s_beta2_in_longer_runs_only_and_the_optimiser_gets_it():
    beyond = FitConfig().with_recipe(BEYOND_RECIPE)
    assert beyond.replace(steps=SHORT_RUN_STEPS).validate().adan_betas == PAPER_BETAS == (0.98, 0.92, 0.99)
    assert beyond.replace(steps=SHORT_RUN_STEPS + 1).validate().adan_betas == LONG_RUN_BETAS == (0.98, 0.99, 0.99)
    assert FitConfig().with_recipe("paper").replace(steps=8000).adan_betas == PAPER_BETAS
    assert beyond.replace(betas=(0.9, 0.95, 0.999), steps=300).adan_betas == (0.9, 0.95, 0.999)
    assert FitConfig.from_dict(json.loads(json.dumps(beyond.to_dict()))) == beyond
    small = beyond.replace(width=32, height=24, color="gray")
    scene = builtin_scene("demo", small)
    for steps, betas in ((SHORT_RUN_STEPS, PAPER_BETAS), (2000, LONG_RUN_BETAS)):
        optimizer = initial_state(small.replace(steps=steps), scene).optimizer
        assert {tuple(group["betas"]) for group in optimizer.param_groups} == {betas}
