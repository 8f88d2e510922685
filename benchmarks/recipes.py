"""Recipe changes measured one at a time against the paper's recipe (docs/beyond.md).

    python benchmarks/recipes.py SCENE_DIR                        # every variant, 320×240, 2000 steps
    python benchmarks/recipes.py SCENE_DIR --size 640 480 --variants paper init-targets
    python benchmarks/recipes.py SCENE_DIR --steps 300 --variants paper init-targets
    python benchmarks/recipes.py SCENE_DIR --steps 300 --variants beyond beyond-short

Each variant is the paper's recipe with one set of `FitConfig` changes (`beyond`, `beyond-short`: the whole recipe;
`beyond-lr-*`: the beyond recipe with one more change); every fit is grayscale 10%,
CVQPG, seed 100, on SCENE_DIR's image.* and depth.png. The fits' PSNR does not depend on the machine's
load, only on its CPU and thread count; run it with OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 to compare
with docs/beyond.md's table. Prints one JSON line per variant: its PSNR, SSIM and difference to `paper`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from cvqpg import FitConfig
from cvqpg.config import BEYOND_RECIPE, BEYOND_SHORT_RECIPE, RECIPES, LearningRates
from cvqpg.control import SILENT
from cvqpg.fitting import fit_scene
from cvqpg.targets import load_scene

PAPER_LR = LearningRates()


def rates(**factors: float) -> LearningRates:
    """The paper's learning rates with some multiplied by a factor."""
    return dataclasses.replace(PAPER_LR, **{k: getattr(PAPER_LR, k) * v for k, v in factors.items()})


VARIANTS = {
    "paper": {},
    "position-lr-half": {"lr": rates(position=0.5, position_final=0.5)},
    "position-final-lr-0.3": {"lr": rates(position_final=0.3)},
    "position-lr-constant": {"lr": rates(position_final=10)},
    "scale-lr-2": {"lr": rates(scale=2)},
    "amplitude-phase-lr-2": {"lr": rates(amplitude=2, phase=2)},
    "phase-lr-4": {"lr": rates(phase=4)},
    "opacity-rotation-lr-2": {"lr": rates(opacity=2, rotation=2)},
    "opacity-lr-4": {"lr": rates(opacity=4)},
    "curvature-lr-5": {"lr": rates(curvature=5)},
    "curvature-lr-15": {"lr": rates(curvature=15)},
    "curvature-warmup-5pct": {"curvature_warmup": "5%"},
    "no-target-noise": {"target_noise": 0.0},
    "grad-clip-100": {"grad_clip_norm": 100.0},
    "adan-beta1-0.9": {"betas": (0.9, 0.92, 0.99)},
    "adan-beta2-0.99": {"betas": (0.98, 0.99, 0.99)},
    "adan-beta2-0.999": {"betas": (0.98, 0.999, 0.99)},
    "adan-beta3-0.999": {"betas": (0.98, 0.92, 0.999)},
    "init-targets": {"init": "targets"},
    "init-edges": {"init": "edges"},
    "adan-beta2-0.99-init-edges": {"betas": (0.98, 0.99, 0.99), "init": "edges"},
    "loss-mse-ssim": {"focus_weight": 0.0, "product_weight": 0.0},
    "loss-mse-only": {"focus_weight": 0.0, "product_weight": 0.0, "ssim_weight": 0.0},
    "loss-mse-ssim-3x": {"focus_weight": 0.0, "product_weight": 0.0, "ssim_weight": 0.015},
    "beyond": RECIPES[BEYOND_RECIPE].settings(),  # the whole recipe
    "beyond-short": RECIPES[BEYOND_SHORT_RECIPE].settings(),
    "beyond-lr-1.5": {**RECIPES[BEYOND_RECIPE].settings(), "lr": rates(**{k: 1.5 for k in vars(PAPER_LR)})},
    "beyond-lr-2": {**RECIPES[BEYOND_RECIPE].settings(), "lr": rates(**{k: 2.0 for k in vars(PAPER_LR)})},
}


def variant_config(base: FitConfig, name: str) -> FitConfig:
    changes = dict(VARIANTS[name])
    if changes.get("curvature_warmup") == "5%":
        changes["curvature_warmup"] = round(0.05 * base.optimisation.steps)
    return base.replace(**changes).validate()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="folder with image.* and depth.png (e.g. ../shared/scenes/sushi)")
    parser.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    args = parser.parse_args()
    base = FitConfig.create("paper", width=args.size[0], height=args.size[1], color="gray", ratio=0.1,
                            steps=args.steps)
    image = next(args.scene.glob("image.*"))
    scene = load_scene(image, args.scene / "depth.png", base)
    reference = None
    for name in dict.fromkeys(["paper", *args.variants]):
        result = fit_scene(scene, variant_config(base, name), control=SILENT)
        psnr = result.metrics.mean["psnr"]
        reference = psnr if name == "paper" else reference
        print(json.dumps({"variant": name, "scene": args.scene.name, "size": list(args.size), "steps": args.steps,
                          "psnr": round(psnr, 4), "ssim": round(result.metrics.mean["ssim"], 4),
                          "delta_db": round(psnr - reference, 4)}), flush=True)


if __name__ == "__main__":
    main()
