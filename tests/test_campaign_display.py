"""`cvqpg bench --preset display`: the rows of what a phase-only SLM shows, each through one fit of a tiny grid, and
the display table of `cvqpg results` from them."""

import json
import math

import pytest

from cvqpg.campaign.bench import EXPORTED_KEY, METHODS, Overrides, make_plan, run_plan
from cvqpg.campaign.presets import DISPLAY_METHODS, PIXEL_STEPS_PER_CVQPG_STEP, PRESETS
from cvqpg.campaign.report import collect
from cvqpg.campaign.results import CAMPAIGN, GridResults, display_claims, display_scene_table, display_table
from cvqpg.control import SILENT
from cvqpg.display import Display
from cvqpg.runs import METRICS_FILE, export_run
from cvqpg.storage import load_model

TINY = {"size": (32, 24), "steps": 4, "curvature_warmup": 1}


def test_the_display_grid_fits_every_row_through_its_display(module_scenes_dir, tmp_path):
    plan = make_plan("display", tmp_path / "bench", Overrides(scenes_dir=module_scenes_dir, scene_names=["sushi"],
                                                              **TINY))
    configs = {(c.method, c.config.targets.color): c.config for c in plan.cells}
    assert {method for method, _ in configs} == set(DISPLAY_METHODS) == set(PRESETS["display"].methods)
    for (method, color), config in configs.items():
        spec = METHODS[method]
        assert config.display == (Display.create(spec.display, aperture=spec.aperture) if spec.display
                                  else Display()), method
        assert config.primitives.kind == spec.changes["primitive"]
        assert config.recipe == (spec.recipe or PRESETS["display"].recipe)
        steps = 4 if not spec.step_factors else max(1, round(4 * PIXEL_STEPS_PER_CVQPG_STEP[color]))
        assert config.optimisation.steps == steps, method
    phase = configs[("pixel-phase", "gray")]
    assert phase.phase_only_pixels and phase.display.aperture == configs[("cvqpg-dpac", "gray")].display.aperture

    cells = tuple(c for c in plan.cells if c.config.targets.color == "gray")
    outcome = run_plan(plan, cells, control=SILENT)
    assert outcome.count("done") == len(cells) and not outcome.failures
    exported = plan.cell_dir(next(c for c in cells if c.method == "cvqpg-exported"))
    record = json.loads((exported / METRICS_FILE).read_text())
    assert record[EXPORTED_KEY]["display"] == Display.create("dpac").to_dict()
    # the exported display is `cvqpg export`'s
    shown = export_run(exported, out=tmp_path / "export")["phase_only_display"]["mean"]["psnr"]
    assert math.isclose(record[EXPORTED_KEY]["mean"]["psnr"], shown, abs_tol=1e-3)
    phase = plan.cell_dir(next(c for c in cells if c.method == "pixel-phase"))
    pattern, _ = load_model(phase / "model.safetensors")
    assert set(pattern.tensors()) == {"phase_rad"}

    grid = GridResults(next(g for g in CAMPAIGN if g.preset == "display"), plan, collect(plan))
    table = display_table(grid, "gray-10")
    assert [row[0] for row in table.rows] == [METHODS[m].label for m in DISPLAY_METHODS]
    assert all(row[1] == "1" for row in table.rows)  # one scene each
    assert float(table.rows[0][2]) == pytest.approx(record[EXPORTED_KEY]["mean"]["psnr"], abs=1e-3)
    assert display_scene_table(grid, "gray-10").rows[0][0] == "sushi"
    claims = display_claims(grid)
    assert any(line.startswith("CVQPG fitted through the display against fitted complex and exported, Grayscale 10%: ")
               and "per scene sushi" in line for line in claims)
    assert any("at equal time, Grayscale 10%: " in line and "fit seconds" in line for line in claims)
    assert any(line.endswith("RGB 10%: not measured yet.") for line in claims)
