"""Command line: `cvqpg fit` and `cvqpg eval`, thin wrappers over the library API."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Sequence

import torch

from . import __version__
from .config import FitConfig
from .fitting import fit_scene
from .runs import CONFIG_FILE, evaluate_run, write_run
from .scenes import SCENES, builtin_scene
from .storage import ModelFileError
from .targets import load_scene

DEFAULTS = FitConfig()


class UsageError(Exception):
    """Bad input: printed as one line, exit code 2."""


def _fit_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="fit a hologram of Gaussian primitives to an image and its depth",
                       description="Fit N complex-valued 2D Gaussians so that the hologram they sum to "
                       "reproduces defocus-aware targets at every depth plane (SPEC §2–§7).",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("image", nargs="?", help="input image file (any format Pillow reads); "
                   "without it the built-in --scene is used")
    p.add_argument("--depth", metavar="PATH", help="depth map (0 = near); needed for --planes > 1")
    p.add_argument("--scene", choices=sorted(SCENES), help="built-in scene, generated at --size: "
                   "'demo' (RGB, 2 planes; the default without IMAGE) or 'star' (grayscale Siemens "
                   "star, single plane)")
    p.add_argument("--color", choices=["rgb", "gray"], help="colour mode: RGB at 639/532/473 nm or "
                   "grayscale at 639 nm [default: rgb; gray for --scene star]")
    p.add_argument("--primitive", choices=["flat", "cvqpg"], default=DEFAULTS.primitive,
                   help="flat-phase baseline or CVQPG with learnable curvature")
    count = p.add_mutually_exclusive_group()
    count.add_argument("--ratio", type=float, default=DEFAULTS.ratio,
                       help="primitive count as a fraction of W·H/2 (RGB) or W·H/4 (grayscale)")
    count.add_argument("--num-gaussians", type=int, metavar="N", help="explicit primitive count N")
    p.add_argument("--steps", type=int, default=DEFAULTS.steps,
                   help="optimisation steps (the loop runs indices 0..steps, as the reference)")
    p.add_argument("--warmup", type=int, default=DEFAULTS.warmup,
                   help="steps with curvature frozen at 0 (CVQPG only)")
    p.add_argument("--size", type=int, nargs=2, metavar=("W", "H"),
                   default=(DEFAULTS.width, DEFAULTS.height), help="hologram size in px")
    p.add_argument("--planes", type=int, metavar="M", help="depth planes at linspace(1 mm, 5 mm, M) "
                   "[default: 2; 1 for --scene star]")
    p.add_argument("--seed", type=int, default=DEFAULTS.seed, help="random seed")
    p.add_argument("--device", default=DEFAULTS.device, choices=["cpu", "cuda"], help="torch device")
    p.add_argument("--backend", default=DEFAULTS.backend, choices=["auto", "numba", "torch"],
                   help="rasterizer: fused Numba kernels (CPU), the PyTorch reference, or auto "
                   "(Numba on CPU, PyTorch on GPU)")
    p.add_argument("--bound", choices=["adaptive", "global"], default=DEFAULTS.bound,
                   help="curvature bound: per-primitive Nyquist (γ_max = ηλ/(6σΔx²)) or global "
                   f"{DEFAULTS.global_bound:g} 1/m (ablation)")
    p.add_argument("--qpf", choices=["mahalanobis", "standard"], default=DEFAULTS.qpf,
                   help="quadratic phase: follows the Gaussian's ellipse, or circular (ablation)")
    p.add_argument("--out", metavar="DIR", help="run folder [default: runs/<time>-<input>-<color>-"
                   "<primitive>]")
    p.add_argument("--overwrite", action="store_true", help="replace a run already in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cvqpg", description="Holograms as complex-valued "
                                     "quadratic-phase Gaussian primitives (CVQPG).")
    parser.add_argument("--version", action="version", version=f"cvqpg {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    _fit_parser(sub)
    e = sub.add_parser("eval", help="recompute the metrics of a saved run",
                       description="Recompute PSNR/SSIM/FLIP/LPIPS/CVVDP of RUN_DIR's model against "
                       "its targets and rewrite RUN_DIR/metrics.json.")
    e.add_argument("run_dir", metavar="RUN_DIR", help="folder written by `cvqpg fit`")
    return parser


def _config_and_source(args: argparse.Namespace) -> tuple[FitConfig, dict, object, object]:
    width, height = args.size
    if args.image is not None and args.scene is not None:
        raise UsageError("give either an IMAGE or --scene, not both")
    if args.image is None:
        name = args.scene or "demo"
        if args.depth is not None:
            raise UsageError(f"--depth applies to an IMAGE; the built-in scene {name!r} has its own")
        builtin = builtin_scene(name, width, height)
        color = args.color or builtin.default_color
        planes = args.planes or builtin.default_planes
        source, image, depth = {"scene": name}, builtin.image, builtin.depth
    else:
        for label, path in (("image", args.image), ("depth map", args.depth)):
            if path is not None and not Path(path).is_file():
                raise UsageError(f"{label} {path!r} does not exist; check the path")
        color, planes = args.color or "rgb", args.planes or 2
        image, depth = args.image, args.depth
        source = {"image": str(Path(args.image).resolve())}
        if args.depth is not None:
            source["depth"] = str(Path(args.depth).resolve())
    if planes > 1 and depth is None:
        raise UsageError(f"--planes {planes} needs a depth map (--depth PATH), or use --planes 1")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise UsageError("--device cuda: no CUDA GPU is visible to PyTorch; use --device cpu")
    config = FitConfig(width=width, height=height, color=color, primitive=args.primitive,
                       ratio=args.ratio, num_gaussians=args.num_gaussians, steps=args.steps,
                       warmup=args.warmup, seed=args.seed, num_planes=planes, bound=args.bound,
                       qpf=args.qpf, device=args.device, backend=args.backend)
    return config, source, image, depth


def _default_out(source: dict, config: FitConfig) -> Path:
    label = source.get("scene") or Path(source["image"]).stem
    return Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{label}-{config.color}-{config.primitive}"


def _summary(record: dict) -> str:
    mean = record["mean"]
    shown = "  ".join(f"{k.upper()} {'n/a' if v is None else f'{v:.4f}'}" for k, v in mean.items())
    return f"{shown}  (N = {record['num_gaussians']}, {record['seconds']:.0f} s)"


def run_fit(args: argparse.Namespace) -> int:
    config, source, image, depth = _config_and_source(args)
    out = Path(args.out) if args.out else _default_out(source, config)
    if (out / CONFIG_FILE).exists() and not args.overwrite:
        raise UsageError(f"{out} already holds a run; choose another --out or pass --overwrite")
    scene = load_scene(image, depth, config)
    result = fit_scene(scene, config, progress=not args.quiet)
    write_run(out, result, scene, source)
    if not args.quiet:
        record = json.loads((out / "metrics.json").read_text())
        print(f"{out}: {_summary(record)}")
    return 0


def run_eval(args: argparse.Namespace) -> int:
    folder = Path(args.run_dir)
    if not (folder / CONFIG_FILE).is_file():
        raise UsageError(f"{folder} is not a run folder (no {CONFIG_FILE}); give a folder written by "
                         "`cvqpg fit`")
    record = evaluate_run(folder)
    print(f"{folder}: {_summary(record)}")
    for name, reason in record["unavailable"].items():
        print(f"  {name}: n/a ({reason})")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return {"fit": run_fit, "eval": run_eval}[args.command](args)
    except (UsageError, ModelFileError) as error:
        print(f"cvqpg {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"cvqpg {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
