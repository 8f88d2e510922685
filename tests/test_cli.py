"""The command line as a user drives it: the outputs of `fit` and `eval`, help, devices and memory (refusals of
bad input: test_hostile.py)."""

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cvqpg.cli import main
from cvqpg.config import FitConfig
from cvqpg.fitting import estimated_peak_bytes

SMALL = ["--size", "48", "36", "--steps", "3", "--curvature-warmup", "1", "--quiet"]
RUN_FILES = {"config.json", "metrics.json", "model.safetensors", "target_plane0.png", "target_plane1.png",
             "recon_plane0.png", "recon_plane1.png", "amplitude.png", "phase.png", "curve.png", "history.csv"}


@pytest.fixture(scope="module")
def demo_run(finished_run, tmp_path_factory):
    """The shared run (`cvqpg fit --size 32 24 --steps 2`), copied: `eval` writes into it."""
    return Path(shutil.copytree(finished_run, tmp_path_factory.mktemp("runs") / "demo"))


def test_fit_writes_the_whole_run_folder(demo_run):
    assert RUN_FILES <= {p.name for p in demo_run.iterdir()}
    history = (demo_run / "history.csv").read_text().splitlines()
    assert history[0] == "step,seconds,loss,psnr" and [row.split(",")[0] for row in history[1:]] == ["0", "1", "2"]
    config = json.loads((demo_run / "config.json").read_text())
    assert config["optimisation"]["seed"] == 100 and config["cvqpg_version"] and config["source"] == {"scene": "demo"}
    assert config["optics"]["pixel_pitch"] == 3.74e-6 and config["targets"]["width"] == 32
    assert config["run"] == {"device": "cpu", "backend": "auto"} and config["recipe"] == "beyond"
    metrics = json.loads((demo_run / "metrics.json").read_text())
    assert set(metrics["mean"]) == {"psnr", "ssim", "flip", "lpips", "cvvdp"}
    assert len(metrics["per_plane"]["psnr"]) == 2
    assert metrics["steps"] == 2 and metrics["num_gaussians"] == round(0.2 * 32 * 24 / 2)
    assert metrics["num_params"] == metrics["num_gaussians"] * 13
    assert metrics["skipped_steps"] == 0 and metrics["sanitised_steps"] == 0 and metrics["updates"] == 3
    for name in ("lpips", "cvvdp"):
        assert (metrics["mean"][name] is None) == (name in metrics["unavailable"])
    assert Image.open(demo_run / "recon_plane1.png").size == (32, 24)


@pytest.mark.slow
def test_fewer_steps_scale_the_warm_up_as_the_paper_does(tmp_path):
    """The README's demo command sets --steps alone: the warm-up follows (400 of 2000 → steps/5)."""
    out = tmp_path / "short"
    assert main(["fit", "--size", "48", "36", "--steps", "10", "--quiet", "--out", str(out)]) == 0
    recorded = json.loads((out / "config.json").read_text())
    assert recorded["optimisation"]["curvature_warmup"] == 2


def test_eval_recomputes_the_saved_metrics(demo_run, capsys):
    before = json.loads((demo_run / "metrics.json").read_text())
    assert main(["eval", str(demo_run)]) == 0
    after = json.loads((demo_run / "metrics.json").read_text())
    assert after["mean"]["psnr"] == pytest.approx(before["mean"]["psnr"], abs=1e-9)
    assert after["seconds"] == before["seconds"]
    assert "PSNR" in capsys.readouterr().out


@pytest.mark.slow
def test_fit_on_image_and_depth_files(tmp_path):
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)).save(tmp_path / "photo.jpg")
    Image.fromarray(np.tile(np.linspace(0, 255, 40, dtype=np.uint8), (30, 1))).save(tmp_path / "d.png")
    out = tmp_path / "run"
    code = main(["fit", str(tmp_path / "photo.jpg"), "--depth", str(tmp_path / "d.png"), "--color", "gray",
                 "--primitive", "flat", *SMALL, "--out", str(out)])
    assert code == 0
    config = json.loads((out / "config.json").read_text())
    assert config["targets"]["color"] == "gray" and config["primitives"]["kind"] == "flat"
    assert config["source"]["depth"].endswith("d.png")


@pytest.mark.slow
def test_per_channel_curvature_is_a_fit_option_and_counts_its_parameters(tmp_path, capsys):
    out = tmp_path / "chromatic"
    assert main(["fit", "--curvature", "per-channel", *SMALL, "--out", str(out)]) == 0
    assert json.loads((out / "config.json").read_text())["primitives"]["curvature"] == "per-channel"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_params"] == metrics["num_gaussians"] * 15
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["learnable_params"] == info["stored_values"] == metrics["num_gaussians"] * 15


@pytest.mark.slow
def test_star_scene_runs_single_plane_grayscale(tmp_path):
    out = tmp_path / "star"
    assert main(["fit", "--scene", "star", *SMALL, "--out", str(out)]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["targets"]["num_planes"] == 1 and config["targets"]["color"] == "gray"
    assert (out / "recon_plane0.png").exists() and not (out / "recon_plane1.png").exists()


def test_help_explains_options_with_units_and_defaults(capsys):
    assert main(["fit", "--help"]) == 0
    text = capsys.readouterr().out
    for expected in ("--primitive", "--bound", "--qpf", "px", "default: 2000", "1 mm", "--curvature-warmup"):
        assert expected in text, expected


def test_every_command_prints_its_help(capsys):
    assert main(["--help"]) == 0
    commands = re.search(r"\{([a-z,]+)\}", capsys.readouterr().out).group(1).split(",")
    assert "fit" in commands
    for command in commands:
        assert main([command, "--help"]) == 0
        assert f"usage: cvqpg {command}" in capsys.readouterr().out, command


def test_render_takes_a_device_and_renders_there(demo_run, tmp_path, capsys):
    assert main(["render", str(demo_run), "--device", "cpu", "--out", str(tmp_path / "r")]) == 0
    assert (tmp_path / "r" / "amplitude.png").is_file()


def test_a_cuda_fit_larger_than_the_gpus_free_memory_is_refused_before_writing(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("torch.cuda.is_available", lambda: True)
    monkeypatch.setattr("torch.cuda.mem_get_info", lambda device=None: (2 * 2**30, 80 * 2**30))
    out = tmp_path / "r"
    assert main(["fit", "--device", "cuda", "--size", "3840", "2160", "--quiet", "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert "GiB are free on the GPU" in error and "reduce --size or --planes" in error and error.count("\n") == 1
    assert not out.exists()


@pytest.mark.parametrize(("device", "width", "height", "measured_gib"), [
    ("cpu", 640, 480, 0.93), ("cpu", 3840, 2160, 7.63),  # peak RSS, docs/performance.md
    ("cuda", 640, 480, 0.67), ("cuda", 3840, 2160, 11.38),  # max_memory_allocated on an H200, results/gpu/
])
def test_the_memory_estimate_of_each_device_sits_above_the_peak_measured_there(device, width, height, measured_gib):
    config = FitConfig.create(width=width, height=height, ratio=0.2)
    assert measured_gib * 2**30 < estimated_peak_bytes(config, device) < 1.5 * measured_gib * 2**30
