"""The per-pixel hologram: one representation that the fit, its checkpoints, the model file and every command that
renders a model use; its model file is the pattern, and the Gaussians' codec refuses it in one line."""

import math

import pytest
import torch

from cvqpg import FitConfig
from cvqpg.app.runner import fit_in_folder, resumed_state, write_fitted_run
from cvqpg.config import PIXEL_RECIPE
from cvqpg.control import SILENT, RunControl
from cvqpg.errors import ConfigError, CvqpgError
from cvqpg.fitting import FitInterrupted, fit_scene, hologram, initial_state, render
from cvqpg.initialisation import implied_slm_field
from cvqpg.display import Display
from cvqpg.pixels import SMALL_PHASE_HALF_RANGE_RAD, PixelHologram, PixelPhase
from cvqpg.representation import PIXELS, representation
from cvqpg.runs import CHECKPOINT_FILE, MODEL_FILE, evaluate_run, render_model, scene_from_source, start_run
from cvqpg.storage import load_model, model_info, save_model

SOURCE = {"scene": "demo"}


def pixel_config(**changes) -> FitConfig:
    return FitConfig.create(**{"primitive": "pixel", "width": 32, "height": 24, "color": "gray", "steps": 6,
                               "guard_band_px": 16, **changes})


def test_a_pixel_configuration_takes_the_pixel_recipe_and_counts_its_pixels():
    config = pixel_config()
    assert config.recipe == PIXEL_RECIPE and representation(config) is PIXELS
    assert config.primitive_count == 32 * 24 and config.params_per_primitive == 2  # amplitude and phase
    assert config.replace(color="rgb").params_per_primitive == 6
    assert FitConfig.create().recipe != PIXEL_RECIPE  # Gaussians keep the default recipe


@pytest.mark.parametrize("init, primitive", [("edges", "pixel"), ("zero", "cvqpg"), ("zero", "flat")])
def test_an_initialisation_of_the_other_representation_is_refused_in_one_line(init, primitive):
    config = FitConfig.create(primitive=primitive, width=32, height=24)
    with pytest.raises(ConfigError, match=f"`init` {init} starts"):
        config.replace(init=init)


def test_the_initialisations_start_where_they_say():
    config = pixel_config()
    assert config.optimisation.init == "uniform"  # the pixel recipe's
    scene = scene_from_source(SOURCE, config)
    small = initial_state(config, scene).gaussians
    assert small.phase_rad.shape == (1, 24, 32) and small.phase_rad.abs().max() <= SMALL_PHASE_HALF_RANGE_RAD
    assert small.phase_rad.std() > 0.1
    assert torch.allclose(small.amplitude, scene.targets.mean().sqrt().expand(1, 24, 32))
    assert torch.count_nonzero(initial_state(config.replace(init="zero"), scene).gaussians.phase_rad) == 0
    implied = implied_slm_field(scene, config)
    start = initial_state(config.replace(init="targets"), scene).gaussians
    assert torch.allclose(start.amplitude, implied.abs()) and torch.allclose(
        torch.polar(torch.ones_like(start.phase_rad), start.phase_rad), implied / implied.abs(), atol=1e-5)


def test_the_hologram_is_the_pattern_itself():
    config = pixel_config()
    pixels = PixelHologram(torch.rand(1, 24, 32), torch.rand(1, 24, 32) * 10)
    physical = representation(config).activate(pixels, config)
    assert float(physical.phase_rad.max()) < 2 * math.pi
    assert torch.allclose(hologram(physical, config), pixels.amplitude * torch.exp(1j * pixels.phase_rad), atol=1e-5)


@pytest.mark.parametrize("optimizer", ["adan", pytest.param("adam", marks=pytest.mark.slow)])
def test_a_pixel_fit_raises_the_psnr_and_its_model_file_renders_it_back(tmp_path, optimizer):
    config = pixel_config(steps=15, optimizer=optimizer)
    scene = scene_from_source(SOURCE, config)
    result = fit_scene(scene, config, control=SILENT)
    assert result.history["psnr"][-1] > result.history["psnr"][0] + 1.0
    save_model(tmp_path / "model.safetensors", result.primitives, config)
    loaded, loaded_config = load_model(tmp_path / "model.safetensors")
    assert isinstance(loaded, PixelHologram) and loaded_config == config
    assert torch.equal(render(loaded, loaded_config)[1], result.reconstructions)
    info = model_info(tmp_path / "model.safetensors")
    assert info["num_primitives"] == 32 * 24 and info["learnable_params"] == 2 * 32 * 24
    assert info["stored_values"] == 2 * 32 * 24


@pytest.mark.slow
@pytest.mark.parametrize("optimizer", ["adan", "adam"])
def test_a_stopped_pixel_fit_resumes_bit_identically(tmp_path, optimizer):
    config = pixel_config(optimizer=optimizer)
    scene = scene_from_source(SOURCE, config)
    whole = fit_scene(scene, config, control=SILENT)
    folder = start_run(tmp_path / "run", config, SOURCE)
    asked = []
    stop = RunControl(progress=False, stop_requested=lambda: asked.append(True) or len(asked) > 3)
    with pytest.raises(FitInterrupted):
        fit_in_folder(folder, scene, config, control=stop)
    assert (folder / CHECKPOINT_FILE).is_file()
    resumed = fit_in_folder(folder, scene, config, control=SILENT, state=resumed_state(folder, config))
    for name, tensor in whole.gaussians.tensors().items():
        assert torch.equal(tensor, resumed.gaussians.tensors()[name]), name


@pytest.mark.slow
def test_a_pixel_run_evaluates_and_renders_and_refuses_the_codec_and_another_size(tmp_path):
    from cvqpg.app.compression import compression_input
    from cvqpg.app.encoding import encode_budget
    from cvqpg.search import CompressionSettings

    config = pixel_config(steps=3)
    scene = scene_from_source(SOURCE, config)
    folder = start_run(tmp_path / "run", config, SOURCE)
    result = fit_in_folder(folder, scene, config, control=SILENT)
    write_fitted_run(folder, result, scene, SOURCE)
    record = evaluate_run(folder)
    assert record["mean"]["psnr"] == pytest.approx(result.metrics.mean["psnr"], abs=1e-9)
    assert record["num_gaussians"] == 32 * 24
    rendered = render_model(folder, tmp_path / "render")
    assert "amplitude.png" in rendered["files"]
    with pytest.raises(CvqpgError, match="^the .cvq codec works on Gaussian primitives"):
        compression_input(folder / MODEL_FILE)
    with pytest.raises(CvqpgError, match="per-pixel hologram"):
        encode_budget(config, CompressionSettings())
    with pytest.raises(CvqpgError, match="render it at its own 32×24 px"):
        render_model(folder, tmp_path / "bigger", size=(64, 48))


def test_under_a_phase_only_display_the_pixels_are_a_phase_pattern_and_its_file_holds_the_phases(tmp_path):
    config = pixel_config().replace(display=Display.create("phase"))
    assert config.phase_only_pixels and config.params_per_primitive == 1
    pattern = initial_state(config, scene_from_source(SOURCE, config)).gaussians
    assert isinstance(pattern, PixelPhase) and set(representation(config).groups(config)) == {"phase_rad"}
    assert torch.allclose(hologram(pattern, config).abs(), torch.ones(1, 24, 32))
    save_model(tmp_path / "model.safetensors", representation(config).activate(pattern, config), config)
    loaded, _ = load_model(tmp_path / "model.safetensors")
    assert isinstance(loaded, PixelPhase) and set(loaded.tensors()) == {"phase_rad"}
    assert model_info(tmp_path / "model.safetensors")["learnable_params"] == 32 * 24
