"""The per-pixel hologram's learning rates, optimiser and initialisation, screened one change at a time
(docs/beyond.md, "The per-pixel hologram").

    python benchmarks/pixel_screening.py ../shared/scenes --scenes sushi dragon flower
    python benchmarks/pixel_screening.py ../shared/scenes --variants adam-0.01 adam-0.01-init-zero --display dpac

Every fit is grayscale, 320×240, 300 steps, seed 100, `--primitive pixel` with the `pixel` recipe's loss and noise,
changed by one variant: the optimiser (Adan with the paper's betas, or Adam with its usual β1 0.9 and β2 0.999),
the learning rate of every group (amplitude and phase alike), the initialisation. `--display` names the display the loss sees (complex, dpac or phase, with its
defaults; `--aperture` replaces its 4f aperture). Prints one JSON line per fit (and appends it to `--out`/screening.jsonl): scene, display, variant, PSNR
and SSIM (mean over the planes) of what the display shows, seconds. Run it with
OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1: the fits then depend on the CPU only.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from cvqpg import FitConfig
from cvqpg.config import ADAM_BETAS, PAPER_BETAS, PIXEL_RECIPE, LearningRates
from cvqpg.control import SILENT
from cvqpg.display import ENCODINGS, Display
from cvqpg.fitting import fit_scene
from cvqpg.targets import load_scene


def rates(lr: float) -> LearningRates:
    return LearningRates(amplitude=lr, phase=lr)


ADAM = {"optimizer": "adam", "betas": ADAM_BETAS}
ADAN = {"optimizer": "adan", "betas": PAPER_BETAS}
VARIANTS: dict[str, dict] = {
    **{f"adan-{lr:g}": {**ADAN, "lr": rates(lr), "init": "uniform"} for lr in (0.001, 0.003, 0.01, 0.03)},
    **{f"adam-{lr:g}": {**ADAM, "lr": rates(lr), "init": "uniform"} for lr in (0.003, 0.01, 0.03, 0.05)},
    **{f"adam-{lr:g}-init-{init}": {**ADAM, "lr": rates(lr), "init": init}
       for lr in (0.01,) for init in ("zero", "targets")},
}


def screen(scene_dir: Path, variant: str, base: FitConfig) -> dict:
    config = base.replace(**VARIANTS[variant]).validate()
    scene = load_scene(next(scene_dir.glob("image.*")), scene_dir / "depth.png", config)
    start = time.perf_counter()
    result = fit_scene(scene, config, control=SILENT)
    settings = config.optimisation
    return {"scene": scene_dir.name, "display": config.display.label(), "variant": variant, "optimizer": settings.optimizer, "lr": settings.lr.phase,
            "init": settings.init, "psnr": round(result.metrics.mean["psnr"], 3),
            "ssim": round(result.metrics.mean["ssim"], 4), "seconds": round(time.perf_counter() - start, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", type=Path, help="folder of <scene>/image.* and <scene>/depth.png")
    parser.add_argument("--scenes", dest="names", nargs="+", default=["sushi", "dragon", "flower"])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    parser.add_argument("--display", choices=ENCODINGS, default="complex",
                        help="the display the fits' loss sees (`display.Display.create`'s defaults)")
    parser.add_argument("--aperture", type=float, help="the 4f aperture (fraction of Nyquist) [default: the "
                        "display's]")
    parser.add_argument("--out", type=Path, help="a folder to append screening.jsonl to")
    args = parser.parse_args()
    display = Display.create(args.display, aperture="auto" if args.aperture is None else args.aperture)
    base = FitConfig.create(PIXEL_RECIPE, primitive="pixel", color="gray", width=args.size[0], height=args.size[1],
                            steps=args.steps).replace(display=display)
    for variant in args.variants:
        for name in args.names:
            line = json.dumps(screen(args.scenes / name, variant, base))
            print(line, flush=True)
            if args.out is not None:
                args.out.mkdir(parents=True, exist_ok=True)
                with open(args.out / "screening.jsonl", "a") as handle:
                    handle.write(line + "\n")


if __name__ == "__main__":
    main()
