"""Recipes are recorded choices, resolved when a configuration is made: the paper's stays one flag away, every
grid that compares with the paper pins it, short fits have their own recipe by name, and a budget in minutes
becomes a recorded step count and nothing else."""

import json
from pathlib import Path

import pytest
import torch

from cvqpg import FitConfig, load_model
from cvqpg.app import runner
from cvqpg.app.runner import timed_config
from cvqpg.campaign.bench import METHODS, PRESETS, make_plan
from cvqpg.campaign.results import CAMPAIGN, campaign_plan
from cvqpg.cli import main
from cvqpg.config import (BEYOND_RECIPE, BEYOND_SHORT_RECIPE, DEFAULT_RECIPE, LONG_RUN_BETAS, PAPER_BETAS,
                          PAPER_RECIPE, RECIPES, SHORT_RUN_STEPS)
from cvqpg.errors import ConfigError
from cvqpg.fitting import initial_state, steps_within
from cvqpg.scenes import builtin_scene

CONFIGS = Path(__file__).parent / "data" / "configs"


def test_the_default_configuration_is_the_default_recipe_and_each_recipe_is_recognised():
    assert FitConfig.create().recipe == DEFAULT_RECIPE
    for name, recipe in RECIPES.items():
        config = FitConfig.create(name, steps=300, color="gray")
        assert config.recipe == name and config.optimisation.betas == recipe.betas
        assert FitConfig.create(steps=300).with_recipe(name) == config.replace(color="rgb")
    assert FitConfig.create(init="targets").recipe == "custom"
    with pytest.raises(ConfigError, match="`recipe`.*paper"):
        FitConfig.create("fast")


def test_a_recipe_runs_the_same_algorithm_at_every_length():
    short, long = (FitConfig.create(BEYOND_RECIPE, steps=steps) for steps in (30, 8000))
    assert short.with_steps(8000) == long
    assert short.optimisation.betas == LONG_RUN_BETAS and short.optimisation.init == "edges"
    assert (short.loss.focus_weight, short.loss.product_weight) == (1.0, 1.0)


def test_the_short_recipe_is_chosen_by_name():
    config = FitConfig.create(BEYOND_SHORT_RECIPE, steps=300)
    assert config.optimisation.betas == PAPER_BETAS and config.optimisation.init == "targets"
    assert (config.loss.focus_weight, config.loss.product_weight) == (0.0, 0.0)
    small = config.replace(width=32, height=24, color="gray")
    optimizer = initial_state(small, builtin_scene("demo", small)).optimizer
    assert {tuple(group["betas"]) for group in optimizer.param_groups} == {PAPER_BETAS}


def test_a_flat_record_older_than_recipes_reads_as_the_paper_s():
    record = {k: v for k, v in json.loads((CONFIGS / "vb8933bb-none-long.json").read_text()).items()
              if k not in ("init", "density", "betas", "focus_weight", "product_weight")}
    assert FitConfig.from_dict(record).recipe == "paper"


@pytest.mark.parametrize(("steps", "recipe"), [(SHORT_RUN_STEPS, BEYOND_SHORT_RECIPE),
                                               (SHORT_RUN_STEPS + 1, BEYOND_RECIPE)])
def test_a_flat_record_s_unset_recipe_settings_resolve_by_its_own_steps(steps, recipe):
    record = {**json.loads((CONFIGS / "vb8933bb-none-short.json").read_text()), "steps": steps}
    config = FitConfig.from_dict(record)
    assert config.recipe == recipe and config == FitConfig.create(recipe, steps=steps, width=64, height=48)


def test_every_grid_that_compares_with_the_paper_pins_its_recipe():
    for name, preset in PRESETS.items():
        assert preset.recipe == (BEYOND_RECIPE if name.startswith("beyond") or name == "display" else "paper"), name
    for grid in CAMPAIGN:
        recipe = PRESETS[grid.preset].recipe
        for cell in campaign_plan(grid, Path("results")).cells:  # a per-pixel row fits with its own recipe
            assert cell.config.recipe == (METHODS[cell.method].recipe or recipe), cell.name
    assert {c.config.recipe for c in make_plan("quick").cells} == {"paper"}


def test_the_paper_time_grid_fixes_one_step_count_per_colour():
    preset = PRESETS["beyond-time"]
    assert preset.steps_for("gray") != preset.steps_for("rgb")
    grid = next(g for g in CAMPAIGN if g.preset == "beyond-time")
    plan = campaign_plan(grid, Path("results"))
    for cell in plan.cells:
        assert cell.config.optimisation.steps == preset.steps_for(cell.config.targets.color)
        assert cell.config.optimisation.curvature_warmup == round(cell.config.optimisation.steps / 5)


@pytest.mark.parametrize("seconds, each, steps", [(60.0, 0.05, 1199), (1.0, 2.0, 1), (10.0, 0.1, 99)])
def test_a_time_budget_holds_the_run_s_steps_plus_one_updates(seconds, each, steps):
    assert steps_within(seconds, each) == steps


def test_a_time_budget_is_timed_and_recorded_with_the_compile_time_it_spent(monkeypatch):
    # The fit after it only loads the kernels, so the budget's record is where the compilation shows
    monkeypatch.setattr(runner, "prepare_kernels", lambda config, run, show_status=True: 7.5)
    config = FitConfig.create(width=32, height=24, num_gaussians=30, steps=5, guard_band_px=8, color="gray")
    timed, record = timed_config(builtin_scene("demo", config), config, 0.01, progress=False)
    assert timed.optimisation.steps == steps_within(0.6, record["seconds_per_step"])
    assert record["minutes"] == 0.01 and record["seconds_per_step"] > 0
    assert record["compile_seconds"] == 7.5
    with pytest.raises(ConfigError, match="`time`"):
        timed_config(builtin_scene("demo", config), config, 0.0, progress=False)


@pytest.mark.parametrize("warmup, noted", [(None, False), (1000, True)])
def test_a_warm_up_given_with_a_time_budget_keeps_its_share_with_a_note(warmup, noted, monkeypatch, caplog):
    monkeypatch.setattr(runner, "prepare_kernels", lambda config, run, show_status=True: 0.0)
    monkeypatch.setattr(runner, "seconds_per_step", lambda scene, config, run: 0.1)
    config = FitConfig.create(width=32, height=24, num_gaussians=30, color="gray", curvature_warmup=warmup)
    with caplog.at_level("WARNING", logger="cvqpg"):
        timed = timed_config(builtin_scene("demo", config), config, 0.1, progress=False)[0]
    assert timed.optimisation.steps == 59 and timed.optimisation.curvature_warmup == (30 if noted else 12)
    assert ("the curvature warm-up of 1000 of 2000 steps keeps its share of the 59 steps the time allows: 30"
            in caplog.text) == noted


@pytest.mark.parametrize("recipe", [BEYOND_RECIPE, PAPER_RECIPE])
def test_the_same_time_on_a_machine_twice_as_fast_runs_the_same_algorithm_with_twice_the_steps(monkeypatch, recipe):
    monkeypatch.setattr(runner, "prepare_kernels", lambda config, run, show_status=True: 0.0)
    config = FitConfig.create(recipe, width=32, height=24, num_gaussians=30, color="gray")
    scene = builtin_scene("demo", config)
    timed = {}
    for machine, seconds_each in (("slow", 0.2), ("fast", 0.1)):
        monkeypatch.setattr(runner, "seconds_per_step", lambda scene, config, run, each=seconds_each: each)
        timed[machine] = timed_config(scene, config, 5.0, progress=False)[0]
    slow, fast = timed["slow"].optimisation, timed["fast"].optimisation
    assert (slow.steps, fast.steps) == (steps_within(300, 0.2), steps_within(300, 0.1)) == (1499, 2999)
    assert fast.curvature_warmup == round(fast.steps / 5) and slow.curvature_warmup == round(slow.steps / 5)
    assert timed["fast"].replace(steps=slow.steps, curvature_warmup=slow.curvature_warmup) == timed["slow"]
    assert timed["fast"].replace(steps=2000, curvature_warmup=400) == config
    assert timed["fast"].recipe == timed["slow"].recipe == recipe


def test_fit_records_the_recipe_and_the_time_budget_and_a_rerun_with_its_steps_is_exact(tmp_path, monkeypatch):
    # a step of 0.1 s: 11 steps in the budget, whatever this machine's speed (timing is the test above's)
    monkeypatch.setattr(runner, "seconds_per_step", lambda scene, config, run: 0.1)
    out, rerun = tmp_path / "run", tmp_path / "rerun"
    small = ["fit", "--scene", "demo", "--size", "32", "24", "--num-gaussians", "30", "--recipe", "paper", "--quiet"]
    assert main([*small, "--time", "0.02", "--out", str(out)]) == 0
    recorded = json.loads((out / "config.json").read_text())
    assert FitConfig.from_dict(recorded).recipe == "paper"
    assert recorded["source"]["time_budget"]["minutes"] == 0.02
    steps = recorded["optimisation"]["steps"]
    assert steps == steps_within(1.2, 0.1) and json.loads((out / "metrics.json").read_text())["steps"] == steps
    assert main([*small, "--steps", str(steps), "--out", str(rerun)]) == 0
    timed, again = (load_model(folder / "model.safetensors")[0].tensors() for folder in (out, rerun))
    assert all(torch.equal(timed[name], again[name]) for name in timed)


def test_steps_and_time_together_are_one_line(capsys, tmp_path):
    assert main(["fit", "--scene", "demo", "--steps", "3", "--time", "1", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--steps or --time" in err[0]
    assert not (tmp_path / "r").exists()
