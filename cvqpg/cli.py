"""Command line: `cvqpg fit`, `eval`, `export`, `info`, `render`, `view`, `compress`, `decompress`, `encode`,
`bench`, `results` and `compile`, thin wrappers over the library API."""

from __future__ import annotations

import argparse
import functools
import json
import logging
import math
import os
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn, Sequence

# Only light modules here: `cvqpg --version` and every `--help` answer without PyTorch or Numba; each command
# imports what it runs.
from . import __version__
from .app import signals
from .app.threads import bad_thread_variable, cap_thread_variables
from .bitdepths import BitDepths
from .campaign.presets import METHODS, PRESETS
from .config import (BACKENDS, BOUNDS, COLORS, CURVATURES, DEVICE_TYPES, PIXEL_RECIPE, PRIMITIVES, QPFS, RECIPES,
                     FitConfig, RunOptions, default_curvature_warmup)
from .control import RunControl
from .defaults import (CHECKPOINT_SECONDS, DEFAULT_APERTURE, DEFAULT_LEVELS, DEFAULT_SWEEP, DEPTH_FILE, DEPTH_MODEL,
                       DISPLAY_ENCODINGS,
                       ENCODE_FINETUNE_STEPS, ENCODE_STEPS, ENCODINGS, EXECUTORS, PARTIAL_SUFFIX, RATE_FINETUNE_STEPS,
                       SCENE_NAMES, SUFFIX, VIEW_FILE)
from .errors import CvqpgError, allocation_failure, filesystem_refusal
from .phase import PHASES

if TYPE_CHECKING:
    from .app.executors import ExecutorFlags
    from .app.inputs import FitInputs
    from .view import ViewRecord

DEFAULTS = FitConfig.create()  # the default recipe's
RUN_DEFAULTS = RunOptions()
# Exit codes besides 0 (success), 128 + N (stopped by signal N) and 130 (Ctrl-C).
EXIT_BUG, EXIT_USAGE, EXIT_FILESYSTEM, EXIT_MEMORY = 1, 2, 3, 4
MEMORY_HINT = ("try a smaller --size, fewer primitives (--ratio, --num-gaussians) or planes (--planes), or another "
               "--device")

# The library's parameter names (in backticks in its messages) as the command line spells them.
FLAGS = {"width": "--size", "height": "--size", "size": "--size", "num_planes": "--planes", "pixel_pitch": "--pitch",
         "wavelengths_m": "--wavelengths", "num_gaussians": "--num-gaussians", "curvature_warmup": "--curvature-warmup",
         "plane_center": "--plane-center", "plane_span": "--plane-span", "resize_depth": "--resize-depth",
         **{name: f"--{name.replace('_', '-')}" for name in (
             "color", "primitive", "ratio", "steps", "seed", "bound", "qpf", "curvature", "phase", "device", "backend",
             "depth", "image", "max_drop", "bits", "prune", "finetune", "levels", "aperture", "slm", "distance",
             "encoding", "distances", "out")},
         "finetune_steps": "--finetune", "prune_fraction": "--prune", "overwrite": "--overwrite", "bpp": "--bpp",
         "max_bytes": "--max-bytes", "rate_loss": "--rate-loss", "time": "--time", "recipe": "--recipe", "canvas": "--slm",
         "lut": "--lut", "display": "--display"}


class DefaultsFormatter(argparse.HelpFormatter):
    """Help that ends an option's text with its default, "[default: X]", unless the text gives it already (a
    default that other options decide) or the option has none to show (a flag, or None)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text, default = action.help or "", action.default
        if "[default" in text or any(default is none for none in (None, False, argparse.SUPPRESS)) or default == []:
            return text
        shown = " ".join(map(_shown, default)) if isinstance(default, (list, tuple)) else _shown(default)
        return f"{text} [default: {shown.replace('%', '%%')}]"


def _shown(value: object) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line, like every other error (`cvqpg fit -h` shows the usage), and
    whose help shows every default one way (`DefaultsFormatter`)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        kwargs.setdefault("formatter_class", DefaultsFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_args(self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
                   ) -> argparse.Namespace:
        """As argparse's, but an unknown argument is reported by the subcommand it was given to."""
        namespace, extras = self.parse_known_args(args, namespace)
        if extras:
            command = getattr(namespace, "command", None)
            prog = f"{self.prog} {command}" if command else self.prog
            self.exit(2, f"{prog}: error: unrecognized arguments: {' '.join(extras)} (see {prog} --help)\n")
        return namespace


def finite(text: str) -> float:
    """An argparse type: a finite number (inf and nan are refused where they are given)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


INT64 = (-2**63, 2**63 - 1)


def whole(text: str) -> int:
    """An argparse type: a whole number that a 64-bit integer holds (what the libraries below compute with)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not INT64[0] <= value <= INT64[1]:
        raise argparse.ArgumentTypeError(f"{text} lies beyond the 64-bit integers [-2**63, 2**63 - 1]")
    return value


def _overwrite_argument(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--overwrite", action="store_true", help=f"replace {what} if it exists (only once the command "
                   "has succeeded; never the command's input or a run's own files)")


def flag_message(message: str) -> str:
    """A library message with its backticked parameter names replaced by the command line's flags."""
    def flag(match: re.Match) -> str:
        name = re.sub(r"\[\d+\]$", "", match.group(1))  # `wavelengths_m[0]`: the flag of the whole list
        return FLAGS.get(name, match.group(1))

    return re.sub(r"`([\w.\[\]]+)`", flag, message)


def _fit_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="fit a hologram of Gaussian primitives to an image and its depth",
                       description="Fit N complex-valued 2D Gaussians so that the hologram they sum to "
                       "reproduces defocus-aware targets at every depth plane (method.md §2–§7).")
    _fit_inputs(p)
    _fit_options(p)
    p.add_argument("--time", type=finite, metavar="MINUTES", help="instead of --steps: fit for about this long; "
                   "a few steps are timed on this machine and fix the step count, which the run records (a --resume "
                   "or a rerun with that --steps is exact)")
    _count_options(p)
    p.add_argument("--out", metavar="DIR", help="run folder [default: runs/<time>-<input>-<color>-"
                   "<primitive>]")
    p.add_argument("--overwrite", action="store_true", help="replace a run already in --out, as a whole, once the "
                   "new fit has succeeded")
    p.add_argument("--resume", metavar="RUN_DIR", help="continue an interrupted run from its last "
                   "checkpoint with its own settings (other options are ignored)")
    p.add_argument("--checkpoint-every", type=whole, metavar="K", help="save a checkpoint every K steps "
                   "(0: only when interrupted) [default: every 3 minutes of work]")
    p.add_argument("--view", action="store_true", help=f"at the end, also write the run's view page "
                   f"(RUN_DIR/{VIEW_FILE}, see `cvqpg view`)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")


def _fit_inputs(p: argparse.ArgumentParser) -> None:
    """What `fit` and `encode` fit: an image and its depth map, or a built-in scene."""
    p.add_argument("image", nargs="?", help="input image file (any format Pillow reads); "
                   "without it the built-in --scene is used")
    p.add_argument("--depth", metavar="PATH|auto", help="depth map (0 = near); needed for --planes > 1. 'auto' "
                   f"estimates it with Depth Anything V2 ({DEPTH_MODEL}; needs the depth extra, fetches the weights "
                   f"on first use); `cvqpg fit` saves it as {DEPTH_FILE} in the run folder")
    p.add_argument("--scene", choices=SCENE_NAMES, help="built-in scene, generated at --size: "
                   "'demo' (RGB, 2 planes; the default without IMAGE) or 'star' (grayscale Siemens "
                   "star, single plane)")


def _fit_options(p: argparse.ArgumentParser, steps: int = DEFAULTS.optimisation.steps,
                 defaults: dict[str, str] | None = None) -> None:
    """How to fit (`_fit_settings` reads them): shared by `fit`, `encode` (whose fit takes `steps` by default) and
    `batch`; `defaults` replaces the help's default of `--color`, `--steps`, `--curvature-warmup` or `--planes`."""
    shown = {"color": "rgb; gray for --scene star", "steps": str(steps), "curvature-warmup": f"steps/5, "
             f"{default_curvature_warmup(steps)} of {steps}", "planes": "2; 1 for --scene star", **(defaults or {})}
    p.add_argument("--color", choices=COLORS, help="colour mode: RGB at 639/532/473 nm or "
                   f"grayscale at 639 nm [default: {shown['color']}]")
    p.add_argument("--primitive", choices=PRIMITIVES, default=DEFAULTS.primitives.kind,
                   help="flat-phase baseline, CVQPG with learnable curvature, or the per-pixel hologram (the W×H "
                   "hologram itself; a phase pattern with --display phase)")
    p.add_argument("--recipe", choices=tuple(RECIPES),
                   help="how to fit: " + "; ".join(f"'{r.name}': {r.summary}" for r in RECIPES.values())
                   + f" [default: {DEFAULTS.recipe}; {PIXEL_RECIPE} with --primitive pixel]")
    p.add_argument("--steps", type=whole, help="optimisation steps (the loop runs indices 0..steps, as the "
                   f"reference) [default: {shown['steps']}]")
    p.add_argument("--curvature-warmup", type=whole, metavar="W", help="steps with curvature frozen at 0 (CVQPG "
                   f"only) [default: {shown['curvature-warmup']}]")
    p.add_argument("--size", type=whole, nargs=2, metavar=("W", "H"),
                   default=(DEFAULTS.targets.width, DEFAULTS.targets.height), help="hologram size in px")
    p.add_argument("--planes", type=whole, metavar="M", help="depth planes at linspace(1 mm, 5 mm, M) "
                   f"[default: {shown['planes']}]")
    p.add_argument("--seed", type=int, default=DEFAULTS.optimisation.seed, help="random seed")
    p.add_argument("--device", default=RUN_DEFAULTS.device, choices=DEVICE_TYPES, help="torch device")
    p.add_argument("--backend", default=RUN_DEFAULTS.backend, choices=BACKENDS,
                   help="kernels: Numba (CPU), Triton (GPU), PyTorch only (the reference, everywhere), "
                   "or auto (Numba on CPU, Triton on GPU)")
    p.add_argument("--bound", choices=BOUNDS, default=DEFAULTS.primitives.bound,
                   help="curvature bound: per-primitive Nyquist (γ_max = ηλ/(6σΔx²)) or global "
                   f"{DEFAULTS.primitives.global_bound:g} 1/m (ablation)")
    p.add_argument("--qpf", choices=QPFS, default=DEFAULTS.primitives.qpf,
                   help="quadratic phase: follows the Gaussian's ellipse, or circular (ablation)")
    p.add_argument("--curvature", choices=CURVATURES, default=DEFAULTS.primitives.curvature,
                   help="CVQPG curvature in colour: one γ for all channels bounded by the shortest "
                   "wavelength (the paper), one γ_c per channel bounded by its own λ_c (15 parameters "
                   "per RGB primitive), or one shared raw value scaled by each channel's own bound")
    p.add_argument("--phase", choices=PHASES, help="a primitive's phase as a sum of terms: constant (the flat "
                   "primitive, as --primitive flat), quadratic (CVQPG's curvature), tilt (a carrier frequency per "
                   "primitive), axes (two curvatures along the ellipse's axes), or their sums [default: "
                   "--primitive's, quadratic for cvqpg]")
    p.add_argument("--pitch", type=finite, default=DEFAULTS.optics.pixel_pitch, metavar="M",
                   help="SLM pixel pitch in m")
    p.add_argument("--wavelengths", type=finite, nargs="+", metavar="M",
                   help="wavelength per channel in m [default: 639e-9 532e-9 473e-9 (rgb), 639e-9 (gray)]")
    p.add_argument("--plane-center", type=finite, default=DEFAULTS.targets.plane_center, metavar="M",
                   help="middle of the plane range d in m (planes span d ± V/2)")
    p.add_argument("--plane-span", type=finite, default=DEFAULTS.targets.plane_span, metavar="M",
                   help="plane range V in m")
    p.add_argument("--resize-depth", action="store_true",
                   help="accept a depth map whose aspect ratio differs from the image's (it is stretched)")
    _display_options(p, "what the fit's loss sees (method.md §8): an ideal complex SLM (the paper's fit), "
                     "double-phase amplitude coding on a phase-only SLM, or the field's bare phase on one",
                     "complex")


def _display_options(p: argparse.ArgumentParser, what: str, default: str | None,
                     choices: tuple[str, ...] = DISPLAY_ENCODINGS, flag: str = "--display") -> None:
    """The display a hologram is shown on (`display.Display.from_options` reads them): `fit`, `encode` and
    `batch` fit through it, `export` writes its patterns."""
    p.add_argument(flag, choices=choices, default=default, help=what)
    p.add_argument("--levels", type=whole, help="a phase-only SLM's phase levels, gray level g showing 2πg/LEVELS "
                   f"[default: {DEFAULT_LEVELS}, or the --lut's]")
    p.add_argument("--lut", metavar="FILE", help="a phase-only SLM's measured lookup table: the phase in rad that "
                   "each gray level shows, one row per level from 0 (the phase, or `gray, phase`; CSV or text) "
                   "[default: uniform levels]")
    p.add_argument("--aperture", type=finite, help="radius of the 4f filter's circular Fourier aperture as a "
                   f"fraction of the Nyquist frequency, 0 for none [default: {DEFAULT_APERTURE:g} for dpac, none "
                   "otherwise]")
    p.add_argument("--slm", type=whole, nargs=2, metavar=("W", "H"), help="SLM size in px: the hologram is "
                   "centred on it, the rest at gray level 0 (e.g. 4096 2400) [default: the hologram's size]")


def _count_options(p: argparse.ArgumentParser) -> None:
    """The primitive count of `fit` and `batch` (`encode` takes it from the budget)."""
    count = p.add_mutually_exclusive_group()
    count.add_argument("--ratio", type=finite, default=DEFAULTS.primitives.ratio,
                       help="primitive count as a fraction of W·H/2 (RGB) or W·H/4 (grayscale)")
    count.add_argument("--num-gaussians", type=whole, metavar="N", help="explicit primitive count N")


def _device_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default=RUN_DEFAULTS.device, choices=DEVICE_TYPES, help="torch device to render on")


def _display_parsers(sub: argparse._SubParsersAction) -> None:
    x = sub.add_parser("export", help="phase-only SLM patterns of a run, and their simulated display",
                       description="Encode RUN_DIR's hologram as phase-only patterns (method.md §8), one per colour "
                       "channel (PNG gray levels, g ↔ 2πg/LEVELS, and the unquantised phase in rad as .npy), "
                       "then simulate showing them through a 4f system and compare with the complex field.")
    x.add_argument("run_dir", metavar="RUN_DIR|MODEL", help="folder written by `cvqpg fit`, or a model file "
                   f"(.safetensors or {SUFFIX}) inside one")
    _display_options(x, "double-phase amplitude coding, or the bare phase of the field (drops the amplitude; for "
                     "comparison); each option not given is the display's the run was fitted through, if phase-only "
                     "[default: the run's display, else dpac]", None, ENCODINGS, "--encoding")
    x.add_argument("--out", metavar="DIR", help="output folder [default: RUN_DIR/export]")
    _overwrite_argument(x, "the output folder")
    _device_argument(x)
    i = sub.add_parser("info", help="size of a saved model: bits per pixel, and bits per attribute if compressed",
                       description="Print N, parameters, file size and bits per hologram pixel of a model file "
                       f"(.safetensors or {SUFFIX}); for a compressed file also the bits of each attribute.")
    i.add_argument("target", metavar="RUN_DIR|MODEL", help="run folder or model file")
    i.add_argument("--half", action="store_true", help="also store the model in float16 "
                   "(RUN_DIR/model.f16.safetensors) and report the PSNR change (needs a run folder)")
    i.add_argument("--json", action="store_true", help="print the numbers as JSON")
    _overwrite_argument(i, "an existing float16 copy (with --half)")
    r = sub.add_parser("render", help="render a saved model's hologram and reconstructions without fitting",
                       description="Render a model's hologram (amplitude.png, phase.png) and its reconstruction "
                       "at the model's planes or at --distance, optionally resampled to --size.")
    r.add_argument("target", metavar="RUN_DIR|MODEL", help="run folder or model file")
    r.add_argument("--size", type=whole, nargs=2, metavar=("W", "H"), help="resample the same physical "
                   "hologram to W×H px (same aspect ratio; the pixel pitch scales accordingly)")
    r.add_argument("--distance", type=finite, nargs="+", metavar="M", help="reconstruction distances in m "
                   "(e.g. 0.001 0.002 0.003 to refocus) [default: the model's planes]")
    r.add_argument("--out", metavar="DIR", help="output folder [default: RUN_DIR/render, or next to MODEL]")
    _overwrite_argument(r, "the output folder")
    _device_argument(r)


def _view_parser(sub: argparse._SubParsersAction) -> None:
    v = sub.add_parser("view", help="one HTML page to refocus a run's hologram and compare it with another run",
                       description="Write one self-contained HTML page (no server, no network): a focal sweep of "
                       "RUN_DIR's reconstructions with a slider, side by side with RUN_DIR_2's and a linked zoom, "
                       "PSNR at the training planes, the hologram's amplitude and phase, the phase-only display "
                       "of `cvqpg export`, and the runs' settings and metrics.")
    v.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="one or two folders written by `cvqpg fit` "
                   "(of the same size and optics)")
    v.add_argument("--distances", type=finite, nargs=3, default=DEFAULT_SWEEP, metavar=("START", "STOP", "COUNT"),
                   help="sweep COUNT distances from START to STOP in m, plus the training planes")
    _overwrite_argument(v, "the page")
    v.add_argument("--out", metavar="PAGE", help=f"the page [default: RUN_DIR/{VIEW_FILE}, or "
                   "RUN_DIR/view_vs_<RUN_DIR_2>.html for two runs]")
    v.add_argument("--quiet", action="store_true", help="no progress bar")


def _compression_parsers(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser("compress", help=f"compress a model into a {SUFFIX} file",
                       description=f"Quantise and entropy-code a model into one {SUFFIX} file (docs/format.md, "
                       "docs/compression.md). A model in a run folder is scored against the run's targets; a bare "
                       "model file against its own reconstruction.")
    c.add_argument("target", metavar="RUN_DIR|MODEL", help="run folder or float model file")
    c.add_argument("--out", metavar="FILE", help=f"[default: the model's path with suffix {SUFFIX}]")
    _overwrite_argument(c, "the output file")
    budget = c.add_mutually_exclusive_group()
    budget.add_argument("--max-drop", type=finite, metavar="DB", help="smallest budget whose decoded render stays "
                        "within DB dB of the float model's PSNR [default: 0.1]")
    budget.add_argument("--bits", nargs="+", metavar="ATTR=B", help="fixed budget: ATTR=B for position "
                        "(fractional bits), scale, rotation, amplitude, phase, curvature; or one number for all "
                        f"but position [default of each: {' '.join(f'{k}={v}' for k, v in vars(BitDepths()).items())}]")
    _rate_arguments(budget)
    c.add_argument("--finetune", type=whole, metavar="STEPS", help="quantisation-aware fine-tuning steps on the "
                   "run's own targets (needs a run folder); kept only if it pays [default: 0; with --bpp or "
                   f"--max-bytes {RATE_FINETUNE_STEPS} in a run folder]")
    c.add_argument("--prune", type=finite, default=0.0, metavar="FRACTION", help="with --finetune: first remove "
                   "this fraction (0 ≤ FRACTION < 1) of the primitives, those of least field energy, and let the "
                   "fine-tuning make up for them")
    _rate_loss_argument(c, "with --bpp or --max-bytes: the fine-tuning also weighs the file's bits")
    e = sub.add_parser("encode", help=f"fit an image straight into a {SUFFIX} file of a given size",
                       description=f"Fit an image (or a built-in --scene) with as many primitives as the budget "
                       "holds at the default bit depths (bytes per primitive measured with the codec, plus headroom), "
                       f"then write a {SUFFIX} file of at most --bpp bits per hologram pixel or --max-bytes bytes, as "
                       "`cvqpg compress --bpp` does. The fit keeps a checkpoint in the folder FILE.partial (every "
                       f"{CHECKPOINT_SECONDS / 60:g} minutes of work, and when Ctrl-C stops it), from which --resume "
                       "continues it; once FILE is written that folder is removed.")
    _fit_inputs(e)
    _fit_options(e, steps=ENCODE_STEPS)
    _rate_arguments(e.add_mutually_exclusive_group())
    _encode_finetune_argument(e)
    _rate_loss_argument(e, "fit with the file's bits in the loss, quantisation-aware from the first step, and tune "
                        "with them")
    e.add_argument("--out", metavar="FILE", help=f"the {SUFFIX} file (required, but with --resume)")
    e.add_argument("--resume", metavar=f"FILE{PARTIAL_SUFFIX}", help="continue an interrupted encode from the "
                   "checkpoint in its folder, with its own settings and budget (other options are ignored)")
    _overwrite_argument(e, "the output file")
    e.add_argument("--quiet", action="store_true", help="no progress bars or summary")
    # the count follows from the budget
    e.set_defaults(ratio=DEFAULTS.primitives.ratio, num_gaussians=None, steps=ENCODE_STEPS)
    d = sub.add_parser("decompress", help=f"turn a {SUFFIX} file back into a model file",
                       description=f"Decode a {SUFFIX} file into a float32 model file (model.safetensors format).")
    d.add_argument("file", metavar="FILE", help=f"{SUFFIX} file")
    d.add_argument("--out", metavar="MODEL", help="[default: FILE's stem + .decoded.safetensors]")
    _overwrite_argument(d, "the output file")


def _encode_finetune_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--finetune", type=whole, default=ENCODE_FINETUNE_STEPS, metavar="STEPS",
                   help="quantisation-aware fine-tuning steps after the fit's --steps, at the chosen bit depths; "
                   "kept only if it pays")


def _rate_loss_argument(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--rate-loss", action="store_true", help=f"{what}: distortion + λ·rate, λ steered to the budget "
                   "(docs/compression.md, \"The rate in the fit\") [default: off]")


def _rate_arguments(group: argparse._MutuallyExclusiveGroup) -> None:
    group.add_argument("--bpp", type=finite, metavar="B", help="the file at most B bits per hologram pixel "
                       "(8·bytes / (W·H), all channels, as `cvqpg info` reports): the primitives kept and their bit "
                       "depths are searched, fine-tuned, and every size measured")
    group.add_argument("--max-bytes", type=whole, metavar="N", help="the file at most N bytes (as --bpp)")


def _bench_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="fit a grid of scenes × settings × methods and tabulate it against the paper",
                       description="Fit every cell of a grid (scenes × colour × ratio × method × seed), one run "
                       "folder per cell in OUT/cells: finished cells (metrics.json) are skipped, interrupted ones "
                       "resume from their checkpoint. Then (re)write summary.md, summary.csv, cells.csv, "
                       "frequency.csv/png, figures/ and report.html in OUT from whatever cells are finished.")
    # argparse expands %-formats in help strings, and the presets' descriptions name percentages.
    p.add_argument("--preset", default="quick", metavar="NAME", help="the grid: " + "; ".join(
        f"{name}: {preset.description}" for name, preset in PRESETS.items()).replace("%", "%%"))
    p.add_argument("--scenes", metavar="DIR", help="folder of <name>/image.* + <name>/depth.png (e.g. "
                   "../shared/scenes); needed by paper and ablation, replaces the built-in scenes of star and quick")
    p.add_argument("--out", metavar="DIR",
                   help="bench folder [default: runs/bench-<preset>; runs/bench-rate for encode]")
    p.add_argument("--scene-names", nargs="+", metavar="NAME", help="only these scenes [default: all]")
    p.add_argument("--colors", nargs="+", metavar="COLOR", help="rgb and/or gray [default: the preset's]")
    p.add_argument("--ratios", nargs="+", type=finite, metavar="R", help="primitive ratios [default: the preset's]")
    p.add_argument("--methods", nargs="+", metavar="METHOD", help=f"any of {', '.join(METHODS)} "
                   "[default: the preset's]")
    seeds = p.add_mutually_exclusive_group()
    seeds.add_argument("--seed", type=int, help=f"random seed [default: {DEFAULTS.optimisation.seed}]")
    seeds.add_argument("--seeds", type=int, nargs="+", metavar="SEED", help="several seeds: every cell once "
                       "per seed (seed spread)")
    p.add_argument("--steps", type=whole, help="optimisation steps [default: the preset's]")
    p.add_argument("--curvature-warmup", type=whole, metavar="W",
                   help="curvature warm-up steps [default: steps/5]")
    p.add_argument("--size", type=whole, nargs=2, metavar=("W", "H"), help="hologram size in px [default: the "
                   "preset's]")
    p.add_argument("--device", choices=DEVICE_TYPES, help="torch device [default: cpu]")
    p.add_argument("--backend", choices=BACKENDS, help="kernels [default: auto]")
    p.add_argument("--shard", metavar="I/N", help="fit only cells I, I+N, I+2N, ... of the grid (1 ≤ I ≤ N), "
                   "e.g. ${SLURM_ARRAY_TASK_ID}/${SLURM_ARRAY_TASK_COUNT} in a job array")
    _executor_arguments(p, "cells")
    p.add_argument("--reuse", nargs="+", default=[], metavar="DIR", help="other bench folders whose finished "
                   "cells with the same settings are copied instead of fitted (e.g. the chromatic grid reuses "
                   "results/paper's baseline and CVQPG cells)")
    p.add_argument("--fits", nargs="+", default=[], metavar="DIR", help="rate–distortion grids (--preset "
                   "compression or rate): bench folders whose finished cells with the same settings kept their "
                   "model.safetensors; a cell takes its model from the first that has it instead of fitting it "
                   "(e.g. runs/bench-paper)")
    p.add_argument("--finetune", type=whole, default=0, metavar="STEPS", help="rate–distortion grids: also record "
                   "the codec after STEPS steps of quantisation-aware fine-tuning at each budget whose drop without it "
                   "is 0.1–4 dB (docs/compression.md)")
    p.add_argument("--summary-only", action="store_true", help="fit nothing; rebuild the tables, figures "
                   "and report from the finished cells")
    p.add_argument("--dry-run", action="store_true", help="list the cells (of the shard) and their status")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _executor_arguments(p: argparse.ArgumentParser, tasks: str) -> None:
    """Where the `tasks` (cells, items) of `bench` and `batch` run: this machine or a Ray cluster
    (`_executor_flags` reads them)."""
    p.add_argument("--executor", choices=EXECUTORS, default="local", help=f"local: the {tasks} run on this "
                   f"machine (--jobs at once); ray: each of the {tasks} is a task of a Ray cluster (--ray-address), "
                   'retried where its worker or node dies (the extra: pip install "cvqpg[ray]"; docs/scale.md)')
    p.add_argument("--jobs", type=whole, metavar="K", help=f"--executor local: {tasks} fitted at once, in "
                   "worker processes above 1 [default: 1]")
    p.add_argument("--threads", type=whole, metavar="T", help="threads of each fit (PyTorch and Numba), and its "
                   "CPUs on Ray [default: local: cores/K, at least 1, cores being those this process may use, at "
                   "most OMP_NUM_THREADS; ray: 1]")
    p.add_argument("--ray-address", metavar="ADDRESS", help="--executor ray: the cluster to run on: auto (the one "
                   "`ray start` made this machine part of), HOST:PORT or ray://HOST:PORT [default: a Ray instance "
                   "on this machine, started and stopped by the command]")
    p.add_argument("--gpus-per-fit", type=finite, metavar="F", help="--executor ray: GPUs reserved for each fit "
                   "(0.25: four fits share a GPU) [default: 1 with --device cuda, else 0]")
    p.add_argument("--checkpoint-every", type=whole, metavar="K", help="save each fit's checkpoint every K steps "
                   "(0: only when interrupted), from which a rerun or a Ray retry resumes [default: every "
                   f"{CHECKPOINT_SECONDS / 60:g} minutes of work]")


BATCH_EXIT_CODES = ("Exit code: 0 when every item is finished; else 130 (128 + N for signal N) when a stop "
                    "request ended the batch (interrupted items keep their checkpoints), else 1 when an item hit a "
                    "bug, 3 when the file system refused an item's write, 4 when an item ran out of memory, and 2 "
                    "when items failed on their input only (a bad file or row option); 2 also for bad INPUTS or "
                    "options, before anything is fitted.")


def _batch_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("batch", help=f"fit every image of a folder of scenes or a CSV manifest into run folders or "
                       f"{SUFFIX} files", epilog=BATCH_EXIT_CODES,
                       description="Fit every item of INPUTS into the batch folder DIR: a run folder DIR/NAME, as "
                       f"`cvqpg fit` makes, or with --bpp or --max-bytes a file DIR/NAME{SUFFIX}, as `cvqpg encode` "
                       "makes. A rerun into DIR skips finished items, resumes interrupted ones from their checkpoints "
                       "and tries failed ones again. One item's failure is recorded in one line and the others go "
                       f"on (a bug's traceback goes to DIR/NAME.error.log). DIR/summary.csv and DIR/summary.md "
                       "list every item: status, PSNR, size, steps, seconds, device and the error line; they are "
                       "rewritten as items finish (at most every 10 s) and at the end.")
    p.add_argument("inputs", metavar="INPUTS", help="a folder of scene folders, NAME/image.* with an optional "
                   f"NAME/{DEPTH_FILE} (0 = near; without one the item is fitted at one plane), or a CSV manifest: a "
                   "header line, then one row per item with the columns image (required), depth and name (by "
                   "default the image's stem, or its folder's name for image.*), and optional columns that override "
                   "the options below for the row: color, primitive, recipe, ratio, num_gaussians, steps, seed, "
                   "planes, bpp, max_bytes; paths relative to the manifest's folder")
    p.add_argument("--out", metavar="DIR", required=True, help="the batch folder: new, empty, or a batch folder to "
                   "continue")
    _fit_options(p, defaults={"color": "rgb", "steps": f"{DEFAULTS.optimisation.steps}; {ENCODE_STEPS} for a "
                              f"{SUFFIX} file", "curvature-warmup": "steps/5", "planes": "2; 1 for an item "
                              "without a depth map"})
    _count_options(p)
    _rate_arguments(p.add_mutually_exclusive_group())
    _encode_finetune_argument(p)
    _rate_loss_argument(p, "with --bpp or --max-bytes: each item's fit has the file's bits in its loss")
    _executor_arguments(p, "items")
    p.add_argument("--overwrite", action="store_true", help="fit finished items again, each replaced once its new "
                   "output is finished (never anything in DIR that is not one of the batch's)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


@functools.cache  # built once per process: tests and notebooks call `main` many times, 12 ms a build
def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="cvqpg", description="Holograms as complex-valued "
                                     "quadratic-phase Gaussian primitives (CVQPG).")
    parser.add_argument("--version", action="version", version=f"cvqpg {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    _fit_parser(sub)
    _batch_parser(sub)
    _bench_parser(sub)
    p = sub.add_parser("results", help="write docs/results.md (and its figures) from the cell records in results/",
                       description="Tabulate the recorded cells of results/ (Table 1, per scene, ablation, "
                       "chromatic, frequency, runtime) beside the paper's numbers, with one line per claim.")
    p.add_argument("--root", default="results", metavar="DIR", help="the recorded bench folders")
    p.add_argument("--out", default="docs/results.md", metavar="FILE", help="the document")
    _overwrite_argument(p, "the document")
    e = sub.add_parser("eval", help="recompute the metrics of a saved run",
                       description="Recompute PSNR/SSIM/FLIP/LPIPS/CVVDP of RUN_DIR's model against "
                       "its targets and rewrite RUN_DIR/metrics.json.")
    e.add_argument("run_dir", metavar="RUN_DIR|MODEL", help="folder written by `cvqpg fit`, or a model file "
                   f"(.safetensors or {SUFFIX}) inside one: its metrics go to <model stem>.metrics.json")
    _device_argument(e)
    _display_parsers(sub)
    _view_parser(sub)
    _compression_parsers(sub)
    sub.add_parser("compile", help="compile the CPU kernels ahead of the first fit (for clusters and images)",
                   description="Compile the Numba CPU kernels that fits call (with 1 or 2 planes, the defaults) into "
                   "Numba's on-disk cache (next to the package, or NUMBA_CACHE_DIR), so that the first fit "
                   "starts at once.")
    return parser


def _fit_settings(args: argparse.Namespace) -> dict:
    """`FitConfig.create`'s settings that `_fit_options` and `_count_options` give; `color`, `num_planes` and
    `steps` None where not given (the input decides them)."""
    from .display import Display
    width, height = args.size
    return dict(width=width, height=height, color=args.color, primitive=args.primitive, ratio=args.ratio,
                num_gaussians=args.num_gaussians, steps=args.steps, curvature_warmup=args.curvature_warmup,
                seed=args.seed, num_planes=args.planes, bound=args.bound, qpf=args.qpf, curvature=args.curvature,
                phase=args.phase, pixel_pitch=args.pitch, plane_center=args.plane_center, plane_span=args.plane_span,
                wavelengths_m=tuple(args.wavelengths) if args.wavelengths else None,
                display=Display.from_options(args.display, args.levels, args.lut, args.aperture, _size(args.slm)))


def _fit_inputs_of(args: argparse.Namespace) -> FitInputs:
    """What `fit` and `encode` are asked to fit (`_fit_inputs`, `_fit_options`)."""
    from .app.inputs import FitInputs
    return FitInputs(args.image, args.scene, args.depth, args.resize_depth, args.recipe, _fit_settings(args),
                     args.device, args.backend)


def _executor_flags(args: argparse.Namespace) -> ExecutorFlags:
    """The flags of `_executor_arguments`."""
    from .app.executors import ExecutorFlags
    return ExecutorFlags(args.executor, args.jobs, args.threads, args.ray_address, args.gpus_per_fit,
                         args.checkpoint_every)


def _size(values: Sequence[int] | None) -> tuple[int, int] | None:
    return tuple(values) if values else None


def _summary(record: dict) -> str:
    mean = record["mean"]
    shown = "  ".join(f"{k.upper()} {'n/a' if v is None else f'{v:.4f}'}" for k, v in mean.items())
    return f"{shown}  (N = {record['num_gaussians']}, {record['seconds']:.0f} s)"


def _print_view(record: ViewRecord) -> None:
    print(f"{record.path}: {record.frames} distances, {record.bytes / 2**20:.1f} MiB, {record.seconds:.0f} s; "
          "open it in a browser")


def run_fit(args: argparse.Namespace) -> int:
    from .app.fitplan import finished_note, fit_planned, new_plan, resume_plan, run_finished
    from .app.runfolders import view_of_run
    if args.resume and run_finished(args.resume):
        print(finished_note(args.resume))
        return 0
    if args.resume:
        plan = resume_plan(args.resume, args.overwrite)
    else:
        plan = new_plan(_fit_inputs_of(args), args.out, args.overwrite, args.time, args.checkpoint_every,
                        progress=not args.quiet)
        if args.time is not None and not args.quiet:
            print(f"--time {args.time:g}: {plan.config.optimisation.steps} steps at "
                  f"{plan.source['time_budget']['seconds_per_step'] * 1e3:.0f} ms each, measured here",
                  file=sys.stderr)
    code, record = fit_planned(plan, args.checkpoint_every, progress=not args.quiet, overwrite=args.overwrite)
    if code:
        return code
    folder = plan.final
    if plan.depth is not None and not args.quiet:
        print(f"{folder / DEPTH_FILE}: depth estimated by {plan.source['depth_model']} (0 = near)")
    if not args.quiet:
        print(f"{folder}: {_summary(record)}")
    if args.view:
        view = view_of_run(folder, progress=not args.quiet)
        if not args.quiet:
            _print_view(view)
    return 0


def run_export(args: argparse.Namespace) -> int:
    from .app.runfolders import export
    out, record = export(args.run_dir, args.encoding, args.levels, _size(args.slm), args.aperture, args.out,
                         args.overwrite, args.device, args.lut)
    print(f"{out}: {len(record['files'])} files; mean PSNR against the targets:")
    for label, key in (("phase-only display", "phase_only_display"), ("complex field, same display", "complex_display"),
                       ("complex field, as fitted", "complex_field")):
        print(f"  {label:28s} {record[key]['mean']['psnr']:.3f} dB")
    return 0


def run_info(args: argparse.Namespace) -> int:
    from .app.runfolders import info as model_info
    from .codec import IMPORTANCE_VERSION, ROTATION_DEPTH_VERSION
    info = model_info(args.target, args.half, args.overwrite)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    width, height = info["hologram_px"]
    print(f"{info['file']}\n"
          f"  primitives       {info['num_primitives']} ({info['primitive']}, {info['channels']} channel(s))\n"
          f"  parameters       {info['learnable_params']} learnable ({info['params_per_primitive']} per primitive"
          f"{', phase ' + info['phase'] if info.get('phase') else ''}), {info['stored_values']} stored "
          f"({info['dtype']})\n"
          f"  file             {info['file_bytes'] / 2**10:.1f} KiB\n"
          f"  bits per pixel   {info['bits_per_pixel']:.3f} (of the {width}×{height} hologram, all channels)")
    if "bits" in info:
        version = info["format_version"]
        notes = (f"; rotation: for an anisotropy a − 1/a in [0.5, 1), a bit more per doubling, "
                 f"{8 * info['streams']['rotation']['bytes'] / info['num_primitives']:.1f} on average"
                 if version >= ROTATION_DEPTH_VERSION else "")
        if version >= IMPORTANCE_VERSION:
            notes += ("; position, amplitude, rotation, phase, curvature: for a value of median weight in the field, "
                      "a bit more per fourfold weight")
        print("  bits             " + ", ".join(f"{name} {value}" for name, value in info["bits"].items())
              + f" (position: fractional bits, a grid of 2^-b px{notes})")
    if args.half:
        print(f"  PSNR             {info['psnr_float16']:.3f} dB in float16, {info['psnr_float32']:.3f} dB in "
              f"float32 ({info['psnr_change']:+.4f} dB)")
    return 0


def run_render(args: argparse.Namespace) -> int:
    from .app.runfolders import render
    out, record = render(args.target, _size(args.size), args.distance, args.out, args.overwrite, args.device)
    width, height = record["hologram_px"]
    print(f"{out}: {width}×{height} px at {record['pixel_pitch_m'] * 1e6:.3f} µm, planes at "
          + ", ".join(f"{d * 1e3:g} mm" for d in record["distances_m"]))
    return 0


def run_view(args: argparse.Namespace) -> int:
    from .app.runfolders import view
    _print_view(view(args.run_dirs, tuple(args.distances), args.out, args.overwrite, progress=not args.quiet))
    return 0


def run_eval(args: argparse.Namespace) -> int:
    from .app.runfolders import evaluate
    folder, record = evaluate(args.run_dir, args.device)
    print(f"{folder}: {_summary(record)}")
    for name, reason in record["unavailable"].items():
        print(f"  {name}: n/a ({reason})")
    return 0


def run_compile(_args: argparse.Namespace) -> int:
    from .app.compilation import compile_all
    seconds = compile_all()
    print(f"cvqpg compile: CPU kernels compiled and cached in {seconds:.0f} s")
    return 0


def run_compress(args: argparse.Namespace) -> int:
    from .app.compression import compress_to
    from .search import ASSUMED_FIT_PSNR_DB, CompressionSettings
    settings = CompressionSettings(bits=BitDepths.parse(args.bits) if args.bits else None, max_drop=args.max_drop,
                                   bpp=args.bpp, max_bytes=args.max_bytes, finetune_steps=args.finetune,
                                   prune_fraction=args.prune, rate_loss=args.rate_loss)
    r = compress_to(args.target, settings, args.out, args.overwrite, RunControl())
    if settings.budgeted:
        print(f"{r['file']}: {_rate_summary(r)}")
        return 0
    scored = (f", float {r['psnr_float']:.3f} dB" if r["psnr_float"] is not None
              else f" (drop estimated for a fit at {ASSUMED_FIT_PSNR_DB:g} dB)")
    print(f"{r['file']}: {r['bytes'] / 2**10:.1f} KiB, {r['bits_per_pixel']:.3f} bpp, {r['ratio']:.1f}× smaller than "
          f"{Path(r['model']).name}; PSNR {r['psnr']:.3f} dB against {r['reference']}{scored}, drop "
          f"{r['drop']:.3f} dB; bits "
          + " ".join(f"{k}={v}" for k, v in r["bits"].items())
          + (f"; fine-tuned {r['finetune_steps']} steps"
             + (f" after pruning {r['prune_fraction']:.0%} of the primitives" if r["prune_fraction"] else "")
             + f" ({'kept' if r['finetune_kept'] else 'did not pay, dropped'}); {r['num_primitives']} primitives"
             if r["finetune_steps"] else ""))
    return 0


def _rate_summary(r: dict) -> str:
    """A rate-controlled file (`compress_model` within a budget, `encode_in_folder`) in one line."""
    from .search import ASSUMED_FIT_PSNR_DB
    budget = r["max_bytes"]
    return (f"{r['bytes']} bytes of a budget of {budget} ({r['bytes'] / budget:.1%}), {r['bits_per_pixel']:.3f} bpp; "
            f"{r['num_primitives']} primitives at bits " + " ".join(f"{k}={v}" for k, v in r["bits"].items())
            + f"; PSNR {r['psnr']:.3f} dB against {r['reference']}"
            + (f" (float {r['psnr_float']:.3f} dB)" if r["psnr_float"] is not None
               else f" (drop estimated for a fit at {ASSUMED_FIT_PSNR_DB:g} dB)")
            + (f"; fine-tuned {r['finetune_steps']} steps ({'kept' if r['finetune_kept'] else 'did not pay, dropped'})"
               if r["finetune_steps"] else "; not fine-tuned"))


def run_encode(args: argparse.Namespace) -> int:
    from .app.encoding import encode_plan, encode_planned, resumed_encode_plan
    if args.resume:
        plan = resumed_encode_plan(args.resume, args.overwrite)
    else:
        plan = encode_plan(_fit_inputs_of(args), args.out, args.bpp, args.max_bytes, args.finetune, args.overwrite,
                           args.rate_loss)
    code, record = encode_planned(plan, args.overwrite, progress=not args.quiet)
    if record is not None and not args.quiet:
        print(f"{plan.out}: {_rate_summary(record)}")
    return code


def run_decompress(args: argparse.Namespace) -> int:
    from .app.compression import decompress_to
    print(f"{decompress_to(args.file, args.out, args.overwrite)}")
    return 0


def run_bench(args: argparse.Namespace) -> int:
    from .campaign.bench import Overrides
    from .campaign.commands import BenchRequest, describe_bench, fit_bench, plan_bench, summarise_bench
    seeds = [args.seed] if args.seed is not None else args.seeds
    overrides = Overrides(scenes_dir=args.scenes, scene_names=args.scene_names, colors=args.colors,
                          ratios=args.ratios, methods=args.methods, seeds=seeds, size=args.size, steps=args.steps,
                          curvature_warmup=args.curvature_warmup, device=args.device, backend=args.backend)
    request = BenchRequest(args.preset, args.out, overrides, _executor_flags(args), args.shard,
                           tuple(Path(d) for d in args.reuse), tuple(Path(d) for d in args.fits), args.finetune,
                           args.summary_only)
    planned = plan_bench(request)
    if args.dry_run:
        print("\n".join(describe_bench(planned, request)))
        return 0
    code = 0
    if not args.summary_only:
        outcome, stopped_by = fit_bench(planned, request, progress=not args.quiet)
        print(f"cvqpg bench: {outcome.describe()}")
        for name, error in outcome.failures.items():
            print(f"  {name}: {error}", file=sys.stderr)
        code = 128 + stopped_by if stopped_by else (1 if outcome.failures else 0)
    print(f"cvqpg bench: {summarise_bench(request)}")
    return code


def run_batch(args: argparse.Namespace) -> int:
    from .app.batch import BUG, FILESYSTEM, INPUT, MEMORY, SUMMARY_MD, BatchSettings, fit_batch
    settings = BatchSettings(args.recipe, _fit_settings(args), RunOptions(args.device, args.backend).validate(),
                             args.bpp, args.max_bytes, args.finetune, args.resize_depth, args.overwrite,
                             args.rate_loss)
    outcome, folder, stopped_by = fit_batch(args.inputs, args.out, settings, _executor_flags(args),
                                            progress=not args.quiet)
    print(f"cvqpg batch: {outcome.describe()}; summary in {folder / SUMMARY_MD}")
    for name, error in outcome.failures.items():
        print(f"  {name}: {flag_message(error)}", file=sys.stderr)
    if stopped_by:
        return 128 + stopped_by
    kinds = set(outcome.kinds.values())
    return next((code for kind, code in ((BUG, EXIT_BUG), (FILESYSTEM, EXIT_FILESYSTEM), (MEMORY, EXIT_MEMORY),
                                         (INPUT, EXIT_USAGE)) if kind in kinds), 0)


def run_results(args: argparse.Namespace) -> int:
    from .campaign.commands import write_results
    print(f"cvqpg results: {', '.join(map(str, write_results(args.root, args.out, args.overwrite)))}")
    return 0


class _NoteHandler(logging.Handler):
    """Prints the library's notes (resized depth, dropped alpha, ...) to the current stderr."""

    def emit(self, record: logging.LogRecord) -> None:
        print(f"cvqpg: note: {record.getMessage()}", file=sys.stderr)


def _show_notes() -> None:
    logger = logging.getLogger("cvqpg")
    if not any(isinstance(h, _NoteHandler) for h in logger.handlers):
        logger.addHandler(_NoteHandler())
        logger.propagate = False


def _machine_or_bug(command: str, error: Exception) -> int:
    """Report an error that is not the input's: the file system's refusal (exit 3) or a failed allocation (4),
    each in one line that says what to do; anything else is a bug (1), with where to report it."""
    if (refusal := filesystem_refusal(error)) is not None:
        print(f"cvqpg {command}: error: {refusal}", file=sys.stderr)
        return EXIT_FILESYSTEM
    if (failure := allocation_failure(error)) is not None:
        print(f"cvqpg {command}: error: {failure}; {MEMORY_HINT}", file=sys.stderr)
        return EXIT_MEMORY
    print(f"cvqpg {command}: internal error ({type(error).__name__}: {error}); this is a bug in cvqpg: "
          "please report it with the command you ran (CVQPG_TRACEBACK=1 shows the traceback)", file=sys.stderr)
    return EXIT_BUG


POSITIONALS = {"image": "IMAGE", "run_dir": "RUN_DIR", "run_dirs": "RUN_DIR", "target": "RUN_DIR|MODEL",
               "file": "FILE", "inputs": "INPUTS"}


# The arguments that name inputs, which a command reads (its outputs are checked where they are written).
INPUT_PATHS = ("image", "run_dir", "run_dirs", "target", "file", "inputs", "depth", "lut", "resume", "root", "reuse",
               "fits", "scenes")


def _input_paths(args: argparse.Namespace) -> dict[str, list[str]]:
    """The input paths given (`INPUT_PATHS`), by their flags."""
    paths = {}
    for name in INPUT_PATHS:
        values = getattr(args, name, None)
        given = [v for v in (values if isinstance(values, list) else [values]) if isinstance(v, str)]
        if given:
            paths[POSITIONALS.get(name, f"--{name}")] = given
    return paths


def _empty_argument(args: argparse.Namespace) -> str | None:
    """The first argument given as an empty string (`--out ""` would otherwise mean the default place, or the
    current folder), by its flag; None where there is none."""
    for name, value in vars(args).items():
        if value == "" or (isinstance(value, list) and "" in value):
            return POSITIONALS.get(name, f"--{name.replace('_', '-')}")
    return None


COMMANDS = {"fit": run_fit, "batch": run_batch, "eval": run_eval, "export": run_export, "info": run_info,
            "render": run_render, "bench": run_bench, "results": run_results, "compile": run_compile,
            "view": run_view, "compress": run_compress, "decompress": run_decompress, "encode": run_encode}


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as stop:  # --help, --version, or a usage error already printed in one line
        return stop.code if isinstance(stop.code, int) else 2
    _show_notes()
    if (empty := _empty_argument(args)) is not None:
        print(f"cvqpg {args.command}: error: {empty} is empty; give a value (see cvqpg {args.command} --help)",
              file=sys.stderr)
        return EXIT_USAGE
    if (variable := bad_thread_variable()) is not None:
        print(f"cvqpg {args.command}: error: the environment variable {variable}={os.environ[variable]!r} is not a "
              f"thread count (a whole number ≥ 1); unset it, or set it to one", file=sys.stderr)
        return EXIT_USAGE
    for note in cap_thread_variables():
        print(f"cvqpg: note: {note}", file=sys.stderr)
    from .app.inputs import long_input_path
    if (problem := long_input_path(_input_paths(args))) is not None:
        print(f"cvqpg {args.command}: error: {problem}", file=sys.stderr)
        return EXIT_USAGE
    try:
        with signals.handled():
            code = COMMANDS[args.command](args)
            if code == 0:  # a stop whose exception a callback swallowed ends the command here
                signals.check_not_stopped()
        return code
    except signals.Terminated as stop:
        print(f"cvqpg {args.command}: terminated", file=sys.stderr)
        return 128 + stop.signum
    except CvqpgError as error:
        print(f"cvqpg {args.command}: error: {flag_message(str(error))}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as error:
        if os.environ.get("CVQPG_TRACEBACK") == "1":
            raise
        return _machine_or_bug(args.command, error)
    except KeyboardInterrupt:
        print(f"cvqpg {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
