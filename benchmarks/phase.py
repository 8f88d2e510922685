"""Phase terms screened one change at a time against CVQPG (docs/beyond.md, "Phase terms beyond the curvature").

    python benchmarks/phase.py SCENE_DIR... --out results/phase-screening/screening.jsonl
    python benchmarks/phase.py SCENE_DIR --color rgb --variants quadratic tilt --steps 300

Each variant is CVQPG (`--phase quadratic`, the default recipe) with one change: another phase (`cvqpg/phase.py`),
or a phase with one learning rate or warm-up of its new terms changed. Every fit is 320×240 unless `--size`, 10%,
seed 100, on each SCENE_DIR's image.* and depth.png. Prints and appends one JSON line per fit (PSNR, SSIM, the
difference to `quadratic` on the same scene and colour); fits already in `--out` are not refitted. Run it with
OMP_NUM_THREADS and NUMBA_NUM_THREADS set: a fit's numbers depend on the CPU and the thread count only.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

from cvqpg import FitConfig
from cvqpg.config import LearningRates
from cvqpg.control import SILENT
from cvqpg.fitting import fit_scene
from cvqpg.targets import load_scene

DEFAULT_LR = LearningRates()


def rates(**factors: float) -> LearningRates:
    """The default learning rates with some multiplied by a factor."""
    return dataclasses.replace(DEFAULT_LR, **{k: getattr(DEFAULT_LR, k) * v for k, v in factors.items()})


VARIANTS = {
    "quadratic": {},
    "tilt": {"phase": "tilt"},
    "quadratic+tilt": {"phase": "quadratic+tilt"},
    "axes": {"phase": "axes"},
    "axes+tilt": {"phase": "axes+tilt"},
    "quadratic+tilt, tilt lr ×5": {"phase": "quadratic+tilt", "lr": rates(tilt=5)},
    "quadratic+tilt, tilt lr ×0.2": {"phase": "quadratic+tilt", "lr": rates(tilt=0.2)},
    "quadratic+tilt, no tilt warm-up": {"phase": "quadratic+tilt", "terms_warmup": 0},
    "axes, axes lr ×5": {"phase": "axes", "lr": rates(axes=5)},
    "axes, no warm-up": {"phase": "axes", "terms_warmup": 0},
    "quadratic, equal parameters as quadratic+tilt": {"params_of": "quadratic+tilt"},
    "quadratic, equal parameters as axes+tilt": {"params_of": "axes+tilt"},
}


def variant_config(base: FitConfig, name: str) -> FitConfig:
    """The fit of variant `name`; `params_of` a phase: CVQPG with that phase's parameter count, as the bench's
    `cvqpg@PHASE` methods."""
    changes = dict(VARIANTS[name])
    other = changes.pop("params_of", None)
    config = base.replace(**changes)
    if other is not None:
        matched = config.replace(phase=other)
        config = config.replace(num_gaussians=round(
            matched.primitive_count * matched.params_per_primitive / config.params_per_primitive))
    return config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", type=Path, nargs="+", help="folders with image.* and depth.png")
    parser.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--color", nargs="+", default=["gray", "rgb"], choices=["gray", "rgb"])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--out", type=Path, help="append each fit's line here; fits already there are skipped")
    args = parser.parse_args()
    done = {}
    if args.out and args.out.exists():
        for line in args.out.read_text().splitlines():
            record = json.loads(line)
            done[(record["scene"], record["color"], record["variant"])] = record
    for color in args.color:
        base = FitConfig.create(width=args.size[0], height=args.size[1], color=color, ratio=0.1, steps=args.steps)
        for folder in args.scenes:
            scene = load_scene(next(folder.glob("image.*")), folder / "depth.png", base)
            for name in dict.fromkeys(["quadratic", *args.variants]):
                key = (folder.name, color, name)
                if key not in done:
                    config = variant_config(base, name)
                    started = time.perf_counter()
                    result = fit_scene(scene, config, control=SILENT)
                    done[key] = {"variant": name, "scene": folder.name, "color": color, "size": list(args.size),
                                 "steps": args.steps, "primitives": config.primitive_count,
                                 "parameters": config.primitive_count * config.params_per_primitive,
                                 "psnr": round(result.metrics.mean["psnr"], 4),
                                 "ssim": round(result.metrics.mean["ssim"], 4),
                                 "seconds": round(time.perf_counter() - started, 1)}
                    if args.out:
                        with args.out.open("a") as handle:
                            handle.write(json.dumps(done[key]) + "\n")
                reference = done[(folder.name, color, "quadratic")]["psnr"]
                print(json.dumps({**done[key], "delta_db": round(done[key]["psnr"] - reference, 4)}), flush=True)


if __name__ == "__main__":
    main()
