"""Interruptions, odd but valid input and numerical safety, driven as a user would drive them (refusals of bad
input at the command line: test_hostile.py)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from safetensors.torch import load_file

from cvqpg import FitConfig, builtin_pictures, fit
from cvqpg import fitting
from cvqpg.cli import main
from cvqpg.config import RunOptions
from cvqpg.control import SILENT, RunControl
from cvqpg.fitting import blank_state, fit_scene, initial_state, optimisation_step, readback_due
from cvqpg.optics import reconstruct
from cvqpg.primitives import Gaussians, activate, inverse_covariance
from cvqpg.ops.rasterize import rasterize
from cvqpg.runs import write_run
from cvqpg.targets import build_scene, load_scene, prepare_depth

SMALL = ["--size", "48", "36", "--steps", "4", "--curvature-warmup", "1", "--quiet"]


@pytest.fixture
def photo(tmp_path) -> Path:
    rng = np.random.default_rng(1)
    path = tmp_path / "photo.png"
    Image.fromarray(rng.integers(0, 256, (36, 48, 3), dtype=np.uint8)).save(path)
    return path


def gradient_depth(path: Path, size=(48, 36), levels=255) -> Path:
    ramp = np.round(np.linspace(0, 1, size[0]) * levels) / levels * 255
    Image.fromarray(np.tile(ramp.astype(np.uint8), (size[1], 1))).save(path)
    return path


@pytest.mark.slow
def test_depth_of_other_size_is_resized_with_a_note(tmp_path, photo, capsys):
    depth = gradient_depth(tmp_path / "d.png", size=(96, 72))
    assert main(["fit", str(photo), "--depth", str(depth), *SMALL, "--out", str(tmp_path / "r")]) == 0
    assert "resized to match" in capsys.readouterr().err


@pytest.mark.slow
def test_resize_depth_fits_a_depth_of_another_aspect_ratio_and_records_it(tmp_path, photo):
    depth = gradient_depth(tmp_path / "d.png", size=(40, 40))
    assert main(["fit", str(photo), "--depth", str(depth), "--resize-depth", *SMALL,
                 "--out", str(tmp_path / "r")]) == 0
    assert json.loads((tmp_path / "r" / "config.json").read_text())["source"]["resize_depth"] is True


def test_sixteen_bit_depth_keeps_its_precision(tmp_path):
    ramp = np.tile(np.linspace(0, 65535, 400).astype(np.uint16), (30, 1))
    Image.fromarray(ramp).save(tmp_path / "d16.png")
    picture = Image.open(tmp_path / "d16.png")
    assert picture.mode.startswith("I")
    depth = prepare_depth(picture, 400, 30)
    assert torch.unique(depth[15]).numel() > 300  # 8 bits would leave at most 256 levels
    assert depth.min() >= 0 and depth.max() == pytest.approx(1.0, abs=1e-3)
    assert depth[15, 200] == pytest.approx(200 / 399, abs=2e-3)


def test_float_depth_is_normalised(tmp_path):
    values = np.tile(np.linspace(2.0, 7.0, 64, dtype=np.float32), (16, 1))
    Image.fromarray(values, "F").save(tmp_path / "d.tiff")
    depth = prepare_depth(Image.open(tmp_path / "d.tiff"), 64, 16)
    assert depth.min() == pytest.approx(0.0, abs=1e-3) and depth.max() == pytest.approx(1.0, abs=1e-3)


@pytest.mark.slow
def test_alpha_is_dropped_with_a_note(tmp_path, capsys):
    rgba = np.random.default_rng(0).integers(0, 256, (36, 48, 4), dtype=np.uint8)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    assert main(["fit", str(tmp_path / "a.png"), "--planes", "1", *SMALL, "--out", str(tmp_path / "r")]) == 0
    assert "alpha channel" in capsys.readouterr().err


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("model") / "run"
    assert main(["fit", *SMALL, "--out", str(out)]) == 0
    return out


def cli_command(out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "cvqpg.cli", "fit", "--size", "48", "36", "--steps", "40", "--curvature-warmup", "10",
            "--quiet", "--out", str(out), *extra]


def wait_for(path: Path, process: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.time() + timeout
    while not path.exists():
        assert process.poll() is None, process.stderr.read()
        assert time.time() < deadline, "no checkpoint appeared"
        time.sleep(0.05)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("whole") / "run"
    subprocess.run(cli_command(out), check=True)
    return load_file(out / "model.safetensors")


def assert_same_model(run: Path, expected: dict) -> None:
    got = load_file(run / "model.safetensors")
    assert got.keys() == expected.keys()
    for name in expected:
        assert torch.equal(got[name], expected[name]), name
    assert not (run / "checkpoint.pt").exists()


@pytest.mark.slow
@pytest.mark.parametrize("signum, code", [(signal.SIGTERM, 128 + signal.SIGTERM),
                                          (signal.SIGINT, 128 + signal.SIGINT)])
def test_signal_saves_a_checkpoint_and_resume_ends_bit_identical(tmp_path, uninterrupted, signum, code):
    out = tmp_path / "run"
    work = tmp_path / "run.partial"  # a fit works beside its --out until the run is written
    process = subprocess.Popen(cli_command(out, "--checkpoint-every", "5"), stderr=subprocess.PIPE, text=True)
    wait_for(work / "checkpoint.pt", process)
    process.send_signal(signum)
    _, error = process.communicate(timeout=120)
    assert process.returncode == code, error
    assert f"--resume {work}" in error and "Traceback" not in error
    assert not out.exists() and not (work / "model.safetensors").exists()
    step = torch.load(work / "checkpoint.pt", weights_only=True)["step"]
    assert 0 < step < 41
    subprocess.run([sys.executable, "-m", "cvqpg.cli", "fit", "--resume", str(work), "--quiet"], check=True)
    assert not work.exists()
    assert_same_model(out, uninterrupted)


@pytest.mark.slow
def test_sigkill_leaves_the_previous_checkpoint_and_resume_ends_bit_identical(tmp_path, uninterrupted):
    out = tmp_path / "run"
    work = tmp_path / "run.partial"
    process = subprocess.Popen(cli_command(out, "--checkpoint-every", "1"), stderr=subprocess.PIPE, text=True)
    wait_for(work / "checkpoint.pt", process)
    time.sleep(0.5)
    os.kill(process.pid, signal.SIGKILL)
    process.wait(timeout=60)
    payload = torch.load(work / "checkpoint.pt", weights_only=True)
    assert payload["step"] >= 1
    subprocess.run([sys.executable, "-m", "cvqpg.cli", "fit", "--resume", str(work), "--quiet"], check=True)
    assert_same_model(out, uninterrupted)


@pytest.mark.slow
def test_resume_of_a_finished_run_changes_nothing(finished_run, capsys):
    before = (finished_run / "model.safetensors").read_bytes()
    assert main(["fit", "--resume", str(finished_run)]) == 0
    assert "finished" in capsys.readouterr().out
    assert (finished_run / "model.safetensors").read_bytes() == before


def tiny_scene(config):
    g = torch.Generator().manual_seed(3)
    return build_scene(torch.rand(3, config.targets.height, config.targets.width, generator=g),
                       torch.rand(config.targets.height, config.targets.width, generator=g), config)


def test_non_finite_loss_skips_the_step():
    config = FitConfig.create(width=24, height=20, steps=5, curvature_warmup=1, num_gaussians=30, guard_band_px=8)
    scene = tiny_scene(config)
    scene.targets[0, 0, 0, 0] = float("nan")
    state = initial_state(config, scene)
    before = {k: v.detach().clone() for k, v in state.gaussians.tensors().items()}
    optimisation_step(state, scene, config)
    assert state.skipped_steps == 1
    for name, tensor in state.gaussians.tensors().items():
        assert torch.equal(tensor.detach(), before[name]), name


def optimiser_snapshot(state):
    """Parameters, Adan's moments and step counters, copied."""
    optimizer = state.optimizer
    return ({k: v.detach().clone() for k, v in state.gaussians.tensors().items()},
            {id(p): {k: v.clone() for k, v in optimizer.state[p].items()} for p in optimizer.state},
            [group.get("step", 0) for group in optimizer.param_groups])  # Adan starts a missing counter at 0


def assert_same_snapshot(before, after):
    for name in before[0]:
        assert torch.equal(before[0][name], after[0][name]), name
    assert before[1].keys() == after[1].keys()
    for key, moments in before[1].items():
        assert all(torch.equal(moments[k], after[1][key][k]) for k in moments)
    assert before[2] == after[2]


@pytest.mark.parametrize("ordinary_steps", [0, 2])
def test_a_nan_step_leaves_parameters_and_optimiser_state_as_they_were(ordinary_steps):
    """On the first step (no optimiser state yet) and after two ordinary ones (moments and counters)."""
    config = FitConfig.create(width=24, height=20, steps=5, curvature_warmup=1, num_gaussians=30, guard_band_px=8)
    scene = tiny_scene(config)
    state = initial_state(config, scene)
    for _ in range(ordinary_steps):
        optimisation_step(state, scene, config)
        state.step += 1
    before = optimiser_snapshot(state)
    scene.targets[0, 0, 0, 0] = float("nan")
    loss, _ = optimisation_step(state, scene, config)
    assert np.isnan(loss) and state.skipped_steps == 1 and state.sanitised_steps == 0
    assert_same_snapshot(before, optimiser_snapshot(state))


def test_an_update_that_leaves_a_parameter_non_finite_is_undone_with_the_optimiser_state(monkeypatch):
    config = FitConfig.create(width=24, height=20, steps=5, curvature_warmup=1, num_gaussians=30, guard_band_px=8)
    scene = tiny_scene(config)
    state = initial_state(config, scene)
    optimisation_step(state, scene, config)
    state.step += 1
    before = optimiser_snapshot(state)
    original = state.optimizer.step

    def overflowing_step():
        original()
        state.gaussians.scale.data[3, 0] = float("inf")

    monkeypatch.setattr(state.optimizer, "step", overflowing_step)
    loss, _ = optimisation_step(state, scene, config)
    assert np.isfinite(loss) and state.skipped_steps == 1
    assert_same_snapshot(before, optimiser_snapshot(state))


@pytest.mark.slow
def test_reading_steps_back_in_batches_gives_the_same_fit_and_counts(monkeypatch):
    """The CUDA cadence (steps queued, read back now and then) on the CPU, with a skipped step (non-finite
    loss) read back right after it: the same history, counts, parameters and `on_step` calls as reading
    back after every step."""
    config = FitConfig.create(width=24, height=20, steps=7, curvature_warmup=2, num_gaussians=30, guard_band_px=8)
    scene = tiny_scene(config)
    loss_of = fitting.multiplane_loss
    results, calls = [], []
    for every in (1, 3):
        reads, losses = iter(range(10**6)), iter(range(10**6))
        monkeypatch.setattr(fitting, "readback_due", lambda device, seconds, every=every: next(reads) % every == 0)

        def poisoned(recon, targets, *rest, losses=losses):
            loss, mse = loss_of(recon, targets, *rest)
            return (loss * float("nan"), mse) if targets is scene.targets and next(losses) == 3 else (loss, mse)

        monkeypatch.setattr(fitting, "multiplane_loss", poisoned)
        steps = []
        control = RunControl(progress=False, on_step=lambda *a, steps=steps: steps.append(a))
        results.append(fit_scene(scene, config, control=control))
        calls.append(steps)
    single, batched = results
    assert np.isnan(single.history["loss"][3]) and single.skipped_steps == batched.skipped_steps == 1
    for name in ("loss", "psnr"):
        np.testing.assert_array_equal(batched.history[name], single.history[name])  # NaN equals NaN here
    np.testing.assert_array_equal(np.array(calls[1]), np.array(calls[0]))
    assert [c[0] for c in calls[1]] == list(range(config.optimisation.steps + 1))
    for name, tensor in single.gaussians.tensors().items():
        assert torch.equal(tensor, batched.gaussians.tensors()[name]), name


def test_steps_are_read_back_after_each_on_the_cpu_and_every_half_second_on_cuda():
    assert readback_due(torch.device("cpu"), 0.0)
    assert not readback_due(torch.device("cuda"), 0.1) and readback_due(torch.device("cuda"), 0.6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_propagation_loss_and_update_read_nothing_back_on_cuda():
    """Everything of a step after the rasterizer, under CUDA's sync debug mode set to fail on a host read."""
    config = FitConfig.create(width=24, height=20, steps=5, curvature_warmup=0, num_gaussians=30, guard_band_px=8)
    state = blank_state(config, RunOptions("cuda"))
    with torch.no_grad():
        hologram = fitting.render_hologram(state.gaussians, config).requires_grad_(True)
    scene = tiny_scene(config)
    targets, masks = scene.targets.cuda(), scene.masks.cuda()
    grads = {p: torch.randn_like(p) for group in state.optimizer.param_groups for p in group["params"]}
    reconstruct(hologram, config)  # builds and keeps the transfer functions
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        recon = reconstruct(hologram, config)
        noise = fitting.standard_normal(targets.shape, state.generator)
        loss, mse = fitting.multiplane_loss(recon, targets, masks, fitting.noisy_targets(targets, noise, 1e-3))
        loss.backward()
        for parameter, grad in grads.items():
            parameter.grad = grad
        sanitised, skipped = fitting.apply_gradients(state.optimizer, config, 0, torch.isfinite(loss.detach()))
        fitting.psnr_from_mse(mse)
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert not skipped.item() and not sanitised.item()


def test_non_finite_gradient_entries_are_zeroed_and_counted():
    config = FitConfig.create(width=24, height=20, steps=5, curvature_warmup=1, num_gaussians=30, guard_band_px=8)
    scene = tiny_scene(config)
    state = initial_state(config, scene)
    poison = torch.zeros(30, 3)
    poison[4, 1] = float("inf")
    state.gaussians.amplitude.register_hook(lambda grad: grad + poison)
    optimisation_step(state, scene, config)
    assert state.sanitised_steps == 1 and state.skipped_steps == 0
    assert all(torch.isfinite(t).all() for t in state.gaussians.tensors().values())


extreme = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False) | st.sampled_from([-80.0, 0.0, 80.0])


@pytest.mark.slow
@settings(max_examples=40, deadline=None)
@given(data=st.data(), backend=st.sampled_from(["numba", "torch"]), qpf=st.sampled_from(["mahalanobis", "standard"]))
def test_extreme_primitives_render_finite_fields_and_gradients(data, backend, qpf):
    count, width, height = 5, 20, 16
    config = FitConfig.create(width=width, height=height, num_gaussians=count, qpf=qpf, guard_band_px=8)

    def tensor(*shape, bound=1e4):
        size = int(np.prod(shape))
        values = data.draw(st.lists(extreme, min_size=size, max_size=size))
        return torch.tensor(values, dtype=torch.float32).clamp(-bound, bound).reshape(shape).requires_grad_(True)

    raw = Gaussians(position=tensor(count, 2), scale=tensor(count, 2), rotation=tensor(count),
                    amplitude=tensor(count, 3, bound=100), phase=tensor(count, 3), opacity=tensor(count),
                    curvature=tensor(count))
    hologram = rasterize(activate(raw, config), width, height, config.wavelengths, config.optics.pixel_pitch, qpf,
                         backend)
    recon = reconstruct(hologram, config, backend=backend)
    assert torch.isfinite(torch.view_as_real(hologram)).all() and torch.isfinite(recon).all()
    recon.sum().backward()
    for name, leaf in raw.tensors().items():
        assert leaf.grad is not None and torch.isfinite(leaf.grad).all(), name


@pytest.mark.slow
def test_checkpoint_stays_until_the_finished_run_is_marked(tiny_config, tmp_path, monkeypatch):
    """A run killed while its files are written must resume, not restart: the checkpoint goes last."""
    builtin = builtin_pictures("demo", tiny_config.targets.width, tiny_config.targets.height)
    result = fit(builtin.image, builtin.depth, tiny_config, control=SILENT)
    scene = load_scene(builtin.image, builtin.depth, tiny_config)
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "checkpoint.pt").write_bytes(b"loop state")

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("cvqpg.runs.save_curve", killed)
    with pytest.raises(KeyboardInterrupt):
        write_run(folder, result, scene, {"scene": "demo"})
    assert (folder / "checkpoint.pt").read_bytes() == b"loop state" and not (folder / "metrics.json").exists()
    monkeypatch.undo()
    write_run(folder, result, scene, {"scene": "demo"})
    assert (folder / "metrics.json").is_file() and not (folder / "checkpoint.pt").exists()


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_needle_thousands_of_pixels_long_stays_finite(backend):
    """Σ of an 8000 px × 1 px primitive cancels to a zero or negative determinant in float32 when
    formed as Σxx·Σyy − Σxy², which made its inverse 1e17 and the field NaN; the inverse must use
    the exact determinant (found by the test above)."""
    config = FitConfig.create(width=20, height=16, num_gaussians=1, guard_band_px=8)
    raw = Gaussians(position=torch.zeros(1, 2), scale=torch.tensor([[0.0, 9.0]]),
                    rotation=torch.tensor([1415.6461917095712]), amplitude=torch.full((1, 3), 0.5),
                    phase=torch.zeros(1, 3), opacity=torch.zeros(1), curvature=torch.zeros(1))
    prims = activate(raw, config)
    a, b, c = inverse_covariance(prims.scale_px, prims.rotation_rad)
    assert (a > 0).all() and (c > 0).all() and torch.isfinite(b).all()
    hologram = rasterize(prims, 20, 16, config.wavelengths, config.optics.pixel_pitch, backend=backend)
    assert torch.isfinite(torch.view_as_real(hologram)).all()
    assert torch.isfinite(reconstruct(hologram, config, backend=backend)).all()
