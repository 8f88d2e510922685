"""PSNR of a run's simulated DPAC display for several 4f aperture radii, full frame and away from the edges.

    python scripts/display_aperture.py RUN_DIR [--margin 40] [--apertures 0.2 0.3 0.5 0.7 1.0]

The interior figure leaves out `--margin` px on every side, where the SLM's hard edge diffracts. Each radius is
shown twice: the run's hologram as DPAC on an 8-bit phase-only SLM, and its complex field behind the same filter.
"""

from __future__ import annotations

import argparse

import torch

from cvqpg.display import Display
from cvqpg.fitting import render
from cvqpg.metrics import mean_psnr
from cvqpg.optics import reconstruct
from cvqpg.runs import MODEL_FILE, read_run, scene_from_source
from cvqpg.storage import load_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir")
    parser.add_argument("--margin", type=int, default=40, help="px left out on every side for the interior PSNR")
    parser.add_argument("--apertures", type=float, nargs="+", default=[0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.85, 1.0])
    args = parser.parse_args()
    primitives, config = load_model(f"{args.run_dir}/{MODEL_FILE}")
    _, source = read_run(args.run_dir)
    targets = scene_from_source(source, config).targets
    complex_config = config.replace(display=Display())
    hologram, fitted = render(primitives, complex_config)
    m = args.margin
    inner = (..., slice(m, config.targets.height - m), slice(m, config.targets.width - m))

    def both(recon) -> str:
        return f"{mean_psnr(recon, targets):7.3f} {mean_psnr(recon[inner], targets[inner]):9.3f}"

    print(f"{'':28s} {'full':>7s} {'interior':>9s}  (PSNR dB, margin {m} px)")
    print(f"{'complex field, as fitted':28s} {both(fitted)}")
    for aperture in args.apertures:
        for label, display in (("DPAC 8-bit", Display.create("dpac", aperture=aperture)),
                               ("complex field", Display(aperture=aperture, canvas=config.display.canvas_for(
                                   config.targets.height, config.targets.width)))):
            with torch.no_grad():
                shown = reconstruct(hologram, config.replace(display=display))
            print(f"aperture {aperture:4.2f}  {label:16s} {both(shown)}")


if __name__ == "__main__":
    main()
