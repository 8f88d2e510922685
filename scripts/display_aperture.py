"""PSNR of a run's simulated display for several 4f aperture radii, full frame and away from the edges.

    python scripts/display_aperture.py RUN_DIR [--margin 40] [--apertures 0.2 0.3 0.5 0.7 1.0]

The interior figure leaves out `--margin` px on every side, where the SLM's hard edge diffracts.
"""

from __future__ import annotations

import argparse

from cvqpg.export import DEFAULT_LEVELS, Display, phase_pattern, simulate_display
from cvqpg.fitting import render
from cvqpg.metrics import mean_psnr
from cvqpg.ops.field import slm_field
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
    hologram, fitted = render(primitives, config)
    canvas = (config.targets.height, config.targets.width)
    pattern = phase_pattern(hologram, "dpac", DEFAULT_LEVELS, canvas)
    m = args.margin
    inner = (..., slice(m, config.targets.height - m), slice(m, config.targets.width - m))

    def both(recon) -> str:
        return f"{mean_psnr(recon, targets):7.3f} {mean_psnr(recon[inner], targets[inner]):9.3f}"

    print(f"{'':28s} {'full':>7s} {'interior':>9s}  (PSNR dB, margin {m} px)")
    print(f"{'complex field, as fitted':28s} {both(fitted)}")
    for aperture in args.apertures:
        display = Display(canvas, aperture)
        for label, field in (("DPAC 8-bit", pattern.displayed_field), ("complex field", slm_field(hologram))):
            print(f"aperture {aperture:4.2f}  {label:16s} {both(simulate_display(field, display, config))}")


if __name__ == "__main__":
    main()
