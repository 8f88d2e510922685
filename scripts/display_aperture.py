"""Which 4f aperture a DPAC display should take: fits through it at several radii, against a complex fit exported.

    python scripts/display_aperture.py SCENE_DIR [SCENE_DIR ...] [--size 320 240] [--steps 300]
        [--apertures 0.35 0.5 0.7 1.0] [--json OUT]

Per scene (a folder with image.* and depth.*), grayscale 10%, recipe `beyond-short`: one complex fit, whose DPAC
display (8-bit) is simulated at every radius, and one fit through the DPAC display of each radius. Prints the
display PSNR of both and the display fit's complex field, in dB against the targets.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from cvqpg.config import FitConfig
from cvqpg.control import RunControl
from cvqpg.display import Display
from cvqpg.fitting import fit_scene, render
from cvqpg.metrics import mean_psnr
from cvqpg.optics import reconstruct
from cvqpg.targets import load_scene


def picture(folder: Path, stem: str) -> Path:
    return next(p for p in sorted(folder.iterdir()) if p.stem == stem)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+", type=Path)
    parser.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--apertures", type=float, nargs="+", default=[0.35, 0.5, 0.7, 1.0])
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args()
    results = {}
    for folder in args.scenes:
        base = FitConfig.create(recipe="beyond-short", width=args.size[0], height=args.size[1], color="gray",
                                ratio=0.1, steps=args.steps)
        scene = load_scene(picture(folder, "image"), picture(folder, "depth"), base)
        fitted = fit_scene(scene, base, control=RunControl(progress=False))
        with torch.no_grad():
            hologram, _ = render(fitted.primitives, base)
        row = {"complex fit": fitted.metrics.mean["psnr"]}
        for aperture in args.apertures:
            display = Display.create("dpac", aperture=aperture)
            with torch.no_grad():
                exported = mean_psnr(reconstruct(hologram, base.replace(display=display)), scene.targets)
            through = fit_scene(scene, base.replace(display=display), control=RunControl(progress=False))
            _, field = render(through.primitives, base)
            row[f"aperture {aperture:g}"] = {"complex fit, exported": exported,
                                             "fit through the display": through.metrics.mean["psnr"],
                                             "its complex field": mean_psnr(field, scene.targets)}
            print(f"{folder.name:10s} aperture {aperture:4.2f}: complex fit exported {exported:6.2f} dB, fit "
                  f"through the display {through.metrics.mean['psnr']:6.2f} dB (its complex field "
                  f"{mean_psnr(field, scene.targets):6.2f} dB); complex fit {row['complex fit']:6.2f} dB", flush=True)
        results[folder.name] = row
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
