"""Cost of one fitting step at 640×480, by stage, against the FFT floor, measured side by side.

    python benchmarks/step.py                        # RGB 20% and grayscale 10%, ~5 minutes on 2 cores
    python benchmarks/step.py --quick                # smaller, for a smoke test
    python benchmarks/step.py --model runs/bento     # the primitives of a fitted model instead
    python benchmarks/step.py --device cuda --whole-fit   # on the GPU, and whole 2000-step fits
    python benchmarks/step.py --phase axes+tilt      # a step with those phase terms against CVQPG's, side by side
    python benchmarks/step.py --threads 1            # on one thread: steadier on a shared machine

Primitives at initialisation are small and round. They are measured twice for RGB: flat, as in the
baseline and during CVQPG's warm-up (curvature frozen at zero), and curved, as after the warm-up
(each curvature a random fraction of its Nyquist bound). A fitted model's primitives are not small
and round (a few grow to hundreds of pixels, some become needles), and its rasterizer costs more;
`--model` measures a step of that model's configuration on its own primitives. `--phase` measures the
rasterizer and whole steps of RGB 10% with the phase terms of that name (cvqpg/phase.py, each parameter a random
fraction of its bound) against CVQPG's curved step, the two taking turns in each round, and their ratio.

A display step is a whole step of the same primitives through the DPAC display (`Display.create("dpac")`:
double-phase coding, 256 levels, its 4f aperture folded into the transfer functions); its ratio to the complex
step is formed round by round like the others, and so is that of its propagation stage (the shown field, the same
transforms and the intensity) to the complex one's (the guard band, the transforms and the intensity). The two
stages that differ are also timed alone: the guard band's field and the display's encoding, forward and backward.

The floor is the Fourier transforms that BLASM propagation cannot avoid, as 2D transforms of the
zero-padded grid, timed alone in the same process: per step one forward FFT per channel and one
inverse per channel and plane, and as many again in the backward pass. This package prunes them
(only the rows each 1D pass needs); the same 1D transforms, timed alone, are printed next to it.
The stages and the floor take turns round by round, and the ratios are the medians of the rounds'
ratios: the machine is shared and has slow spells, and only ratios of the same round are meaningful.

With `--device cuda` everything runs on the GPU, each timed region between two `torch.cuda.synchronize`
calls, and the floor is the same transforms (cuFFT) timed alone on the GPU. The step's propagation
there is full-grid; one more stage times the pruned transforms in its place, through PyTorch's
operations. `--whole-fit` also times whole fits (RGB 20% and grayscale 10% at 640×480, RGB 20% at
3840×2160) on the device: the fit loop's seconds, the warm-up apart (a 2-step fit of the same
configuration first: kernel compilation, FFT plans, allocator growth), and the peak memory
(`torch.cuda.max_memory_allocated` on CUDA, RSS on the CPU).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numba
import torch

import cvqpg
from cvqpg import FitConfig
from cvqpg.app.allocator import keep_freed_memory
from cvqpg.app.runner import fit_in_folder
from cvqpg.config import RunOptions, default_curvature_warmup
from cvqpg.control import SILENT
from cvqpg.display import Display
from cvqpg.fitting import apply_gradients, initial_state, optimisation_step, render_hologram
from cvqpg.ops.display import shown_field
from cvqpg.ops.field import Grid, clamped_intensity, guarded_field
from cvqpg.ops.loss import multiplane_loss, noisy_targets, standard_normal
from cvqpg.ops.propagation import propagate_content
from cvqpg.optics import display_grid, reconstruct
from cvqpg.primitives import MIN_SCALE_PX, Gaussians, Primitives, curvature_bound
from cvqpg.runs import model_path
from cvqpg.scenes import builtin_pictures
from cvqpg.storage import load_model
from cvqpg.targets import Scene, load_scene

OPEN_INTERVAL_MARGIN = 1e-6  # keeps atanh and logit finite at saturated values
PRUNED_STAGE = "pruned propagation f+b"  # where the step's propagation is full-grid


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA); the CPU runs its work as it is called."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def interleaved_seconds(actions: dict[str, Callable[[], object]], rounds: int,
                        device: torch.device = torch.device("cpu")) -> dict[str, list[float]]:
    """Seconds of each action in each of `rounds` rounds, the actions taking turns within a round
    (after one untimed call each), each timed from a synchronised device to its work's end. The machine
    is shared and has slow spells lasting seconds; taken in turns, a round's stages and floor see the
    same machine, so ratios are formed round by round."""
    for action in actions.values():
        action()
    times: dict[str, list[float]] = {name: [] for name in actions}
    for _ in range(rounds):
        for name, action in actions.items():
            synchronize(device)
            started = time.perf_counter()
            action()
            synchronize(device)
            times[name].append(time.perf_counter() - started)
    return times


def transform_actions(config: FitConfig, run: RunOptions) -> dict[str, Callable[[], object]]:
    """A step's transforms alone, forward pass only (the backward pass has as many): the floor's 2D
    transforms batched over channels and planes and one array at a time (which one is faster depends
    on the machine's caches: here a single 1536×1920 transform takes about half the time per array of
    a batch of three), and the pruned 1D transforms that `propagate_content` runs instead."""
    grid = Grid.for_config(config)
    rows, cols = 2 * grid.padded_height, 2 * grid.padded_width
    shape = (config.channels, rows, cols)
    options = {"dtype": torch.complex64, "device": run.device}
    field = torch.randn(shape, **options)
    spectra = torch.randn((config.targets.num_planes, *shape), **options)
    field_rows = torch.randn(grid.padded_height, cols, **options)
    content_rows = torch.randn(grid.height, cols, **options)
    columns = torch.randn(cols, rows, **options)

    def batched():
        torch.fft.fft2(field)
        torch.fft.ifft2(spectra)

    def one_at_a_time():
        for channel in range(config.channels):
            torch.fft.fft2(field[channel])
            for plane in range(config.targets.num_planes):
                torch.fft.ifft2(spectra[plane, channel])

    def pruned():  # x pass over the rows needed, y pass over all columns
        for _ in range(config.channels):
            torch.fft.fft(field_rows), torch.fft.fft(columns)
            for _ in range(config.targets.num_planes):
                torch.fft.ifft(columns), torch.fft.ifft(content_rows)

    return {"floor, batched": batched, "floor, one at a time": one_at_a_time, "pruned transforms": pruned}


def load_raw_parameters(gaussians: Gaussians, primitives: Primitives, config: FitConfig) -> None:
    """Set raw parameters so that they activate to `primitives` (method.md §2's activations inverted)."""
    inside = 1 - OPEN_INTERVAL_MARGIN
    extent = torch.tensor([config.targets.width, config.targets.height], dtype=primitives.position_px.dtype)
    share = primitives.curvature_per_m / curvature_bound(primitives.scale_px, config)
    with torch.no_grad():
        gaussians.position.copy_(torch.atanh((2 * primitives.position_px / extent - 1).clamp(-inside, inside)))
        gaussians.scale.copy_(torch.log((primitives.scale_px - MIN_SCALE_PX).clamp(min=OPEN_INTERVAL_MARGIN)))
        gaussians.rotation.copy_(primitives.rotation_rad)
        gaussians.amplitude.copy_(primitives.amplitude)
        gaussians.phase.copy_(primitives.phase_rad)
        gaussians.opacity.copy_(torch.logit(primitives.opacity, eps=OPEN_INTERVAL_MARGIN))
        gaussians.curvature.copy_(torch.atanh(share.clamp(-inside, inside)).view_as(gaussians.curvature))


def demo_scene(config: FitConfig, run: RunOptions) -> Scene:
    """The built-in demo scene at `config`'s size, its tensors on `run`'s device."""
    builtin = builtin_pictures("demo", config.targets.width, config.targets.height)
    scene = load_scene(builtin.image, builtin.depth, config)
    return Scene(*(t.to(run.device) for t in (scene.image, scene.masks, scene.targets)))


def stage_actions(config: FitConfig, run: RunOptions, primitives: Primitives | None = None,
                  curved: bool = True) -> dict[str, Callable[[], object]]:
    """Each stage of a step, and whole steps. `curved` unlocks the curvature (at initialisation, each
    a random fraction of its bound); otherwise it stays frozen at zero, as in the warm-up, through the
    whole steps too."""
    scene = demo_scene(config, run)
    backend = run.backend
    config = config.replace(curvature_warmup=0 if curved else config.optimisation.steps + 1)
    state = initial_state(config, scene, run)
    if primitives is not None:
        load_raw_parameters(state.gaussians, primitives, config)
    elif curved:
        with torch.no_grad():
            generator = torch.Generator().manual_seed(1)
            for tensor in (state.gaussians.curvature, *state.gaussians.terms.values()):
                tensor.copy_(2 * torch.rand(tensor.shape, generator=generator) - 1)
    state.gaussians.curvature.requires_grad_(curved and config.phase.has("quadratic"))
    display_config = config.replace(display=Display.create("dpac"))
    display_state = initial_state(display_config, scene, run)
    with torch.no_grad():
        for name, tensor in display_state.gaussians.tensors().items():
            tensor.copy_(state.gaussians.tensors()[name])
    display_state.gaussians.curvature.requires_grad_(curved and config.phase.has("quadratic"))
    gaussians, optimizer, generator = state.gaussians, state.optimizer, state.generator
    hologram_grad = torch.randn(config.channels, config.targets.height, config.targets.width, dtype=torch.complex64,
                                device=run.device)

    def raster_forward():
        with torch.no_grad():
            return render_hologram(gaussians, config, backend)

    def raster_forward_backward():
        render_hologram(gaussians, config, backend).backward(hologram_grad)

    leaf = raster_forward().requires_grad_(True)
    recon_grad = torch.rand(config.targets.num_planes, config.channels, config.targets.height, config.targets.width,
                            device=run.device)

    def propagation():
        reconstruct(leaf, config, backend=backend).backward(recon_grad)

    def display_propagation():
        reconstruct(leaf, display_config, backend=backend).backward(recon_grad)

    grid = Grid.for_config(config)
    field_grad = torch.randn(config.channels, grid.padded_height, grid.padded_width, dtype=torch.complex64,
                             device=run.device)

    def guard_band():
        guarded_field(leaf, grid, backend).backward(field_grad)

    def display_encoding():
        shown_field(leaf, display_grid(display_config), display_config.display, backend).backward(field_grad)

    def pruned_propagation():  # the step's propagation with the pruned transforms, through PyTorch's operations
        grid = Grid.for_config(config)
        field = guarded_field(leaf, grid, backend)
        planes = propagate_content(field, grid, config.plane_distances, config.wavelengths, config.optics.pixel_pitch,
                                   fused=False)
        clamped_intensity(planes, backend).backward(recon_grad)

    recon = reconstruct(leaf, config, backend=backend).detach().requires_grad_(True)

    def loss():
        noise = standard_normal(scene.targets.shape, generator, backend)
        value, _ = multiplane_loss(recon, scene.targets, scene.masks,
                                   noisy_targets(scene.targets, noise, config.loss.target_noise),
                                   config.loss.ssim_weight, backend, config.loss.focus_weight,
                                   config.loss.product_weight)
        value.backward()

    render_hologram(gaussians, config, backend).backward(hologram_grad)
    actions = {"raster forward": raster_forward, "raster forward+backward": raster_forward_backward,
               "propagation forward+backward": propagation, "loss forward+backward": loss,
               "optimizer": lambda: apply_gradients(optimizer, config, state.step),
               "whole step": lambda: optimisation_step(state, scene, config, backend),
               "display propagation f+b": display_propagation,
               "display step": lambda: optimisation_step(display_state, scene, display_config, backend),
               "guard band f+b": guard_band, "display encoding f+b": display_encoding}
    if run.kernels != "numba":  # the numba step's propagation is the pruned one
        actions[PRUNED_STAGE] = pruned_propagation
    return actions


def peak_rss_gib(config: FitConfig, steps: int) -> float:
    """Peak resident memory (GiB) of `cvqpg fit` in a fresh process, read by that process itself from
    the high-water mark of its own address space (`VmHWM`). Linux carries `ru_maxrss` over `exec`
    from the forked copy of the parent, so both RUSAGE_CHILDREN and the child's RUSAGE_SELF would
    report at least the parent's size at the fork. The child starts in the folder that holds this
    process's `cvqpg`, so that it imports the same code (a worktree on PYTHONPATH, for instance)."""
    targets = config.targets
    arguments = ["fit", "--size", str(targets.width), str(targets.height), "--color", targets.color, "--ratio",
                 str(config.primitives.ratio), "--steps", str(steps), "--curvature-warmup", "1",
                 "--out", f"/tmp/cvqpg-bench-rss-{config.targets.color}", "--overwrite", "--quiet"]
    program = ("import sys; from cvqpg.cli import main; main(sys.argv[1:]); "
               "print(next(line.split()[1] for line in open('/proc/self/status') if line.startswith('VmHWM:')))")
    output = subprocess.run([sys.executable, "-c", program, *arguments], check=True, capture_output=True,
                            text=True, cwd=Path(cvqpg.__file__).parents[1]).stdout
    return int(output.split()[-1]) / 2**20


def whole_fit(config: FitConfig, run: RunOptions) -> dict[str, float]:
    """A whole fit of the demo scene on `run`, as `cvqpg fit` runs it (`app.runner`, kernels
    compiled ahead, peak memory measured): the first fit (a 2-step fit of the same configuration, run
    first), the fit loop's seconds and the whole call's, the peak memory (GiB) and the final PSNR (dB)."""
    scene = demo_scene(config, run)
    device = torch.device(run.device)
    with tempfile.TemporaryDirectory() as folder:
        synchronize(device)
        started = time.perf_counter()
        fit_in_folder(Path(folder), scene, config.replace(steps=2, curvature_warmup=min(
            config.optimisation.curvature_warmup, 1)), run, SILENT, checkpoint_every_seconds=None,
                      source={"scene": "demo"})
        synchronize(device)
        first = time.perf_counter() - started
        started = time.perf_counter()
        result = fit_in_folder(Path(folder), scene, config, run, SILENT, checkpoint_every_seconds=None,
                               source={"scene": "demo"})
        synchronize(device)
    return {"first fit s": first, "fit loop s": result.seconds, "fit call s": time.perf_counter() - started,
            "kernel compile s": result.compile_seconds,
            "peak GiB": result.peak_memory.get("peak_memory_bytes", 0) / 2**30,
            "peak kind": result.peak_memory.get("peak_memory_kind"), "psnr dB": result.metrics.mean["psnr"]}


def fast_backend(device: str) -> str:
    """The backend a fit picks on `device` by default: the fused CPU kernels, or `auto`'s choice."""
    return "numba" if torch.device(device).type == "cpu" else "auto"


def report(label: str, config: FitConfig, run: RunOptions, rounds: int, reference_rounds: int,
           primitives: Primitives | None = None, curved: bool = True) -> dict[str, float]:
    fast = RunOptions(run.device, fast_backend(run.device))
    device = torch.device(run.device)
    times = interleaved_seconds({**stage_actions(config, fast, primitives, curved),
                                 **transform_actions(config, fast)}, rounds, device)
    per_round = {name: torch.tensor(values, dtype=torch.float64) for name, values in times.items()}
    per_round["raster backward"] = per_round["raster forward+backward"] - per_round["raster forward"]
    per_round["FFT floor"] = 2 * torch.minimum(per_round["floor, batched"], per_round["floor, one at a time"])
    per_round["pruned transforms"] = 2 * per_round["pruned transforms"]
    step = per_round["whole step"]
    median = {name: float(values.median()) for name, values in per_round.items()}
    ratios = {"step / floor": float((step / per_round["FFT floor"]).median()),
              "pruned / floor": float((per_round["pruned transforms"] / per_round["FFT floor"]).median()),
              "raster / step": float((per_round["raster forward+backward"] / step).median()),
              "display step / step": float((per_round["display step"] / step).median()),
              "display propagation / propagation": float((per_round["display propagation f+b"]
                                                          / per_round["propagation forward+backward"]).median())}
    reference = None
    if reference_rounds:
        reference_times = interleaved_seconds(
            {name: action for name, action in stage_actions(config, RunOptions(run.device, "torch"), primitives,
                                                            curved).items()
             if name in ("raster forward+backward", "whole step")}, reference_rounds, device)
        reference = {name: statistics.median(values) for name, values in reference_times.items()}
    count = config.primitive_count if primitives is None else primitives.position_px.shape[0]
    where = f"{torch.get_num_threads()} threads" if device.type == "cpu" else torch.cuda.get_device_name(device)
    print(f"\n## {label}: {config.targets.width}×{config.targets.height}, N = {count}, "
          f"{config.targets.num_planes} planes, {run.device} ({where}), medians of {rounds} rounds")
    for name in ("raster forward", "raster backward", "propagation forward+backward", PRUNED_STAGE,
                 "loss forward+backward", "optimizer", "whole step", "guard band f+b", "display encoding f+b",
                 "display propagation f+b", "display step", "FFT floor"):
        if name in median:
            print(f"{name:>30}: {1000 * median[name]:9.1f} ms")
    print(f"{'step / floor':>30}: {ratios['step / floor']:9.2f}")
    print(f"{'pruned transforms alone':>30}: {1000 * median['pruned transforms']:9.1f} ms = "
          f"{ratios['pruned / floor']:.2f} × floor")
    print(f"{'raster / step':>30}: {ratios['raster / step']:9.1%}")
    print(f"{'display step / step':>30}: {ratios['display step / step']:9.3f}")
    print(f"{'display propagation / propagation':>30}: {ratios['display propagation / propagation']:9.3f}")
    if reference:
        torch_raster = reference["raster forward+backward"]
        print(f"{'torch-backend raster f+b':>30}: {1000 * torch_raster:9.1f} ms")
        print(f"{'torch-backend step':>30}: {1000 * reference['whole step']:9.1f} ms")
        print(f"{'raster speed-up':>30}: {torch_raster / median['raster forward+backward']:9.1f}×")
        print(f"{'step speed-up':>30}: {reference['whole step'] / median['whole step']:9.1f}×")
    return {**median, **ratios, "torch backend": reference}


def phase_report(config: FitConfig, phase: str, run: RunOptions, rounds: int) -> dict[str, float]:
    """The rasterizer's and whole steps' seconds of `config` with the phase terms `phase` against CVQPG's own
    (both curved), taking turns in every round, and the medians of the rounds' ratios."""
    fast = RunOptions(run.device, fast_backend(run.device))
    kept = ("raster forward+backward", "whole step")
    actions = {}
    for label, variant in (("quadratic", config), (phase, config.replace(phase=phase))):
        actions.update({f"{label}: {name}": action for name, action in stage_actions(variant, fast).items()
                        if name in kept})
    per_round = {name: torch.tensor(values, dtype=torch.float64)
                 for name, values in interleaved_seconds(actions, rounds, torch.device(run.device)).items()}
    print(f"\n## phase {phase} against quadratic (CVQPG): {config.targets.width}×{config.targets.height} "
          f"{config.targets.color}, N = {config.primitive_count}, {run.device}, medians of {rounds} rounds")
    numbers = {}
    for name in kept:
        ours, theirs = per_round[f"{phase}: {name}"], per_round[f"quadratic: {name}"]
        numbers[name] = float((ours / theirs).median())
        print(f"{name:>30}: {1000 * float(theirs.median()):9.1f} ms → {1000 * float(ours.median()):9.1f} ms = "
              f"{numbers[name]:.3f} ×")
    return numbers


def print_whole_fits(base: FitConfig, run: RunOptions, big: tuple[int, int], steps: int, which: str
                     ) -> dict[str, dict[str, float]]:
    """`whole_fit` of RGB 20% and grayscale 10% at `base`'s size (`which` small or all) and of RGB 20% at
    `big` (W, H) px (big or all)."""
    fits = {}
    if which in ("small", "all"):
        size = f"{base.targets.width}×{base.targets.height}"
        fits[f"RGB 20%, {size}"] = base.replace(color="rgb", ratio=0.2)
        fits[f"grayscale 10%, {size}"] = base.replace(color="gray", ratio=0.1)
    if which in ("big", "all"):
        fits[f"RGB 20%, {big[0]}×{big[1]}"] = base.replace(color="rgb", ratio=0.2, width=big[0], height=big[1])
    print(f"\n## whole fits of the demo scene on {run.device}, {steps} steps (indices 0..{steps}), "
          f"curvature warm-up {default_curvature_warmup(steps)}, 2 planes")
    print(f"{'fit':>28}  {'first fit':>9}  {'fit loop':>9}  {'whole call':>10}  {'peak':>9}  {'PSNR':>9}")
    results = {}
    for label, config in fits.items():
        numbers = whole_fit(config.replace(steps=steps, curvature_warmup=default_curvature_warmup(steps)), run)
        results[label] = numbers
        print(f"{label:>28}  {numbers['first fit s']:8.1f}s  {numbers['fit loop s']:8.1f}s  "
              f"{numbers['fit call s']:9.1f}s  {numbers['peak GiB']:5.2f} GiB  {numbers['psnr dB']:6.2f} dB"
              f"  ({numbers['peak kind']})")
    return results


def main() -> None:
    keep_freed_memory()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="320×240, for a smoke test")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where everything runs")
    parser.add_argument("--rounds", type=int, default=7, help="rounds in which every stage and the floor take turns")
    parser.add_argument("--reference-rounds", type=int, default=1, help="rounds of the torch backend (slow)")
    parser.add_argument("--rss-steps", type=int, default=5, help="steps of the fit whose peak RSS is measured (CPU)")
    parser.add_argument("--model", help="a fitted model (run folder or .safetensors): measure its configuration "
                                            "on its primitives instead of RGB 20%% and grayscale 10%% at initialisation")
    parser.add_argument("--whole-fit", nargs="?", const="all", choices=["small", "big", "all"],
                        help="also time whole fits: small (RGB 20%% and grayscale 10%% at the table's size), big "
                        "(RGB 20%% at --big-size) or all (without a value): warm-up, fit loop, peak memory")
    parser.add_argument("--fits-only", action="store_true", help="with --whole-fit: no stage tables")
    parser.add_argument("--fit-steps", type=int, default=2000, help="steps of each whole fit")
    parser.add_argument("--big-size", type=int, nargs=2, default=(3840, 2160), metavar=("W", "H"),
                        help="size of the large whole fit")
    parser.add_argument("--phase", help="measure a step of RGB 10%% with these phase terms against CVQPG's, "
                                        "side by side (cvqpg/phase.py: tilt, axes+tilt, ...)")
    parser.add_argument("--threads", type=int, help="CPU threads of PyTorch and Numba (default: the environment's)")
    parser.add_argument("--json", help="also write the numbers here")
    args = parser.parse_args()
    if args.threads is not None:
        if not 1 <= args.threads <= numba.config.NUMBA_NUM_THREADS:
            parser.error(f"--threads takes 1 to {numba.config.NUMBA_NUM_THREADS} (NUMBA_NUM_THREADS)")
        torch.set_num_threads(args.threads)
        numba.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA GPU is visible to PyTorch")
    width, height = (320, 240) if args.quick else (640, 480)
    rgb = FitConfig.create(width=width, height=height, color="rgb", ratio=0.2)
    run = RunOptions(args.device)
    if args.model and args.quick:
        parser.error("--quick sets the size, --model brings its own; pass one of them")
    gray = rgb.replace(color="gray", ratio=0.1)
    if args.phase:
        results = phase_report(rgb.replace(ratio=0.1), args.phase, run, args.rounds)
        if args.json:
            Path(args.json).write_text(json.dumps(results, indent=2))
        return
    if args.model:
        primitives, config = load_model(model_path(args.model))
        settings = {f"fitted model {args.model}": (config, primitives, True)}
    else:
        settings = {"RGB 20%, at initialisation, flat (warm-up)": (rgb, None, False),
                    "RGB 20%, at initialisation, curved": (rgb, None, True),
                    "grayscale 10%, at initialisation, curved": (gray, None, True)}
    results = {}
    if args.fits_only and not args.whole_fit:
        parser.error("--fits-only goes with --whole-fit")
    for label, (config, primitives, curved) in settings.items():
        if not args.fits_only:
            results[label] = report(label, config, run, args.rounds, args.reference_rounds, primitives, curved)
    if args.device == "cpu" and not args.fits_only:
        rss = peak_rss_gib(rgb, args.rss_steps)
        print(f"\npeak RSS of an RGB 20% fit ({args.rss_steps} steps, separate process): {rss:.2f} GiB")
        results["peak rss gib"] = rss
    if args.whole_fit:
        results["whole fits"] = print_whole_fits(rgb, run, tuple(args.big_size), args.fit_steps, args.whole_fit)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(results, handle, indent=2)

if __name__ == "__main__":
    main()
