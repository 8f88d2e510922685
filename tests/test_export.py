"""From fitted primitives to an SLM: DPAC, quantisation, the simulated 4f display, model files, rendering."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from cvqpg import FitConfig, load_model, save_model
from cvqpg.cli import main
from cvqpg.config import ConfigError
from cvqpg.display import Display
from cvqpg.patterns import checkerboard, double_phase, level_phases, place_on_canvas, quantise
from cvqpg.optics import reconstruct
from cvqpg.fitting import render
from cvqpg.primitives import Primitives
from cvqpg.runs import rescaled



def random_field(channels: int, height: int, width: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    amplitude = torch.rand(channels, height, width, generator=g)
    phase = (2 * torch.rand(channels, height, width, generator=g) - 1) * math.pi
    return torch.polar(amplitude, phase)


def circular_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a - b + math.pi, 2 * math.pi) - math.pi


def test_dpac_of_a_unit_amplitude_field_is_its_phase_on_both_checkerboard_halves():
    field = torch.polar(torch.ones(2, 6, 8), random_field(2, 6, 8, seed=1).angle())
    pattern = double_phase(field)
    odd = checkerboard(6, 8)
    for half in (odd, ~odd):
        assert circular_distance(pattern[:, half], field.angle()[:, half]).abs().max() < 1e-3


def test_dpac_neighbours_average_to_the_field():
    field = random_field(3, 6, 8, seed=2)
    pattern = double_phase(field)
    assert pattern.min() >= 0 and pattern.max() < 2 * math.pi
    # on each pixel, the two phases φ ± arccos(A) average to A·e^{iφ}: check via the pair the pixel would pair with
    odd = checkerboard(6, 8)
    offset = torch.arccos(field.abs())
    mirrored = torch.where(odd, pattern - 2 * offset, pattern + 2 * offset)
    average = (torch.polar(torch.ones_like(pattern), pattern) + torch.polar(torch.ones_like(pattern), mirrored)) / 2
    assert torch.allclose(average, field, atol=1e-5)


def test_quantisation_round_trips():
    display = Display.create("dpac")
    levels = torch.arange(256)
    assert torch.equal(quantise(level_phases(display)[levels], display), levels)
    phase = torch.linspace(-7.0, 13.0, 10_001)
    error = circular_distance(level_phases(display)[quantise(phase, display)], phase)
    assert error.abs().max() <= math.pi / 256 + 1e-6
    assert quantise(torch.tensor([2 * math.pi - 1e-4]), display).item() == 0  # wraps, never 256
    assert quantise(torch.tensor([math.pi]), Display.create("dpac", levels=1024)).item() == 512
    with pytest.raises(ConfigError, match="phase levels"):
        Display.create("dpac", levels=1)


def test_pattern_is_centred_on_the_slm_canvas():
    pattern = torch.ones(1, 3, 4)
    canvas = place_on_canvas(pattern, (7, 10))
    assert canvas.shape == (1, 7, 10) and canvas.sum() == 12
    assert torch.equal(canvas[0, 2:5, 3:7], pattern[0])
    with pytest.raises(ConfigError, match="smaller than"):
        Display.create("dpac", canvas=(7, 3)).canvas_for(3, 4)


def smooth_field(height: int, width: int) -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                            indexing="ij")
    amplitude = 0.25 + 0.6 * torch.exp(-((xs - width / 2) ** 2 + (ys - height / 2) ** 2) / (2 * (width / 5) ** 2))
    phase = 2 * math.pi * (xs / 40 + (ys / 50) ** 2)
    return torch.polar(amplitude, phase)[None]


def correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(np.corrcoef(a.flatten().numpy(), b.flatten().numpy())[0, 1])


def test_aperture_filtered_dpac_reconstructs_like_the_field_itself():
    config = FitConfig.create(width=64, height=48, color="gray", guard_band_px=32)
    field = smooth_field(config.targets.height, config.targets.width)
    own = reconstruct(field, config.replace(display=Display(canvas=(48, 64))))
    shown = {encoding: reconstruct(field, config.replace(display=Display.create(encoding, aperture=0.5)))
             for encoding in ("dpac", "phase")}
    for plane in range(config.targets.num_planes):
        assert correlation(shown["dpac"][plane], own[plane]) > 0.95
        assert correlation(shown["phase"][plane], own[plane]) < correlation(shown["dpac"][plane], own[plane])


def test_float16_model_round_trips_within_half_precision(tmp_path):
    config = FitConfig.create(width=40, height=30, num_gaussians=50)
    g = torch.Generator().manual_seed(3)
    u = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    primitives = Primitives(position_px=u(50, 2) * 40, scale_px=0.2 + 4 * u(50, 2), rotation_rad=u(50) * 6 - 3,
                            amplitude=u(50, 3), phase_rad=u(50, 3) * 6.28, opacity=u(50),
                            curvature_per_m=(u(50) - 0.5) * 4000)
    save_model(tmp_path / "half.safetensors", primitives, config, dtype="float16")
    loaded, loaded_config = load_model(tmp_path / "half.safetensors")
    assert loaded_config == config
    for name, tensor in primitives.tensors().items():
        got = loaded.tensors()[name]
        assert got.dtype == torch.float32
        if name == "position_px":
            assert torch.equal(got, tensor)  # kept in float32: float16 spacing is 2 px above 2048 px
        else:
            assert torch.all((got - tensor).abs() <= tensor.abs() * 2**-11 + 1e-7), name
    full = tmp_path / "full.safetensors"
    save_model(full, primitives, config)
    assert (tmp_path / "half.safetensors").stat().st_size < full.stat().st_size


def test_rescaled_model_is_the_same_physical_hologram():
    config = FitConfig.create(width=32, height=24, color="gray", guard_band_px=32, num_gaussians=40)
    g = torch.Generator().manual_seed(4)
    u = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    primitives = Primitives(position_px=u(40, 2) * torch.tensor([32.0, 24.0]), scale_px=1.5 + 3 * u(40, 2),
                            rotation_rad=u(40) * 6 - 3, amplitude=0.3 + 0.5 * u(40, 1), phase_rad=u(40, 1) * 6.28,
                            opacity=0.3 + 0.5 * u(40), curvature_per_m=(u(40) - 0.5) * 200)
    double, double_config = rescaled(primitives, config, 64, 48)
    back, back_config = rescaled(double, double_config, 32, 24)
    for name, tensor in primitives.tensors().items():
        assert torch.allclose(back.tensors()[name], tensor, atol=1e-5), name
    assert back_config.optics.pixel_pitch == pytest.approx(config.optics.pixel_pitch)
    _, recon = render(primitives, config)
    _, fine = render(double, double_config)
    pooled = torch.nn.functional.avg_pool2d(fine.flatten(0, 1), 2).reshape(recon.shape)
    assert correlation(pooled, recon) > 0.95
    with pytest.raises(ConfigError, match="aspect ratio"):
        rescaled(primitives, config, 64, 64)


@pytest.fixture(scope="module")
def fitted_run(finished_run, tmp_path_factory):
    """The shared 32×24 px run, copied: `export` and `info --half` write into it."""
    return Path(shutil.copytree(finished_run, tmp_path_factory.mktemp("export") / "run"))


def test_export_writes_patterns_display_and_metrics(fitted_run, capsys):
    assert main(["export", str(fitted_run), "--slm", "64", "50"]) == 0
    out = fitted_run / "export"
    for label in ("red_639nm", "green_532nm", "blue_473nm"):
        image = Image.open(out / f"phase_{label}.png")
        assert image.mode == "L" and image.size == (64, 50)
        phase = np.load(out / f"phase_{label}.npy")
        assert phase.shape == (50, 64) and phase.dtype == np.float32
        gray = np.asarray(image)
        assert np.all(gray[:10] == 0) and np.all(phase[:10] == 0)  # the canvas beyond the hologram
        quantised = np.round(phase / (2 * np.pi) * 256) % 256
        assert np.array_equal(gray, quantised.astype(np.uint8))
    record = json.loads((out / "metrics.json").read_text())
    assert record["encoding"] == "dpac" and record["levels"] == 256 and record["slm_px"] == [64, 50]
    for key in ("phase_only_display", "complex_display", "complex_field"):
        assert len(record[key]["per_plane"]["psnr"]) == 2
    fitted = json.loads((fitted_run / "metrics.json").read_text())
    assert record["complex_field"]["mean"]["psnr"] == pytest.approx(fitted["mean"]["psnr"], abs=1e-6)
    assert Image.open(out / "display_plane1.png").size == (32, 24)
    assert "phase-only display" in capsys.readouterr().out


def test_export_with_more_levels_writes_16_bit_patterns(fitted_run, tmp_path):
    assert main(["export", str(fitted_run), "--levels", "1024", "--encoding", "phase", "--out", str(tmp_path)]) == 0
    gray = np.asarray(Image.open(tmp_path / "phase_red_639nm.png"))
    assert gray.dtype == np.uint16 and gray.max() < 1024 and gray.max() > 255


def test_info_reports_size_and_bits_per_pixel(fitted_run, capsys):
    assert main(["info", str(fitted_run), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    count = round(0.2 * 32 * 24 / 2)
    assert info["num_primitives"] == count and info["learnable_params"] == count * 13
    assert info["stored_values"] == count * 13 and info["dtype"] == "float32"
    size = (fitted_run / "model.safetensors").stat().st_size
    assert info["file_bytes"] == size
    assert info["bits_per_pixel"] == pytest.approx(8 * size / (32 * 24))
    assert "compression_ratio" not in info


def test_info_half_stores_float16_and_reports_the_psnr_change(fitted_run, capsys):
    assert main(["info", str(fitted_run), "--half"]) == 0
    shown = capsys.readouterr().out
    assert "float16" in shown and "PSNR" in shown
    half = fitted_run / "model.f16.safetensors"
    assert half.stat().st_size < (fitted_run / "model.safetensors").stat().st_size
    assert main(["info", str(half), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["dtype"] == "float16"


def test_render_refocuses_a_saved_model(fitted_run, tmp_path, capsys):
    assert main(["render", str(fitted_run), "--distance", "0.001", "0.003", "--out", str(tmp_path / "r")]) == 0
    assert {p.name for p in (tmp_path / "r").iterdir()} == {"amplitude.png", "phase.png", "recon_1mm.png",
                                                             "recon_3mm.png"}
    first = np.asarray(Image.open(tmp_path / "r" / "recon_1mm.png"))
    assert np.array_equal(first, np.asarray(Image.open(fitted_run / "recon_plane0.png")))
    assert main(["render", str(fitted_run / "model.safetensors"), "--size", "80", "60",
                 "--out", str(tmp_path / "big")]) == 0
    assert Image.open(tmp_path / "big" / "recon_1mm.png").size == (80, 60)
    capsys.readouterr()
