"""How many steps of the per-pixel hologram take the time of one CVQPG step, both fitted through the DPAC display
as the display grid fits them (`cvqpg bench --preset display`): the grid's `pixel-dpac-time` row runs that many
times the steps (`PIXEL_STEPS_PER_CVQPG_STEP` in cvqpg/campaign/presets.py, docs/bench.md).

    python benchmarks/display_time.py ../shared/scenes/sushi
    python benchmarks/display_time.py ../shared/scenes/sushi --size 320 240 --rounds 1 --colors gray

The two fits are timed side by side, in alternating rounds (`fitting.seconds_per_step`: a dozen steps after one
untimed, past the curvature warm-up), so that the machine's load weighs on both alike; the ratio is the median
round's. Prints one JSON line per colour.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from cvqpg import FitConfig
from cvqpg.campaign.bench import BenchScene, cell_config
from cvqpg.campaign.presets import PRESETS
from cvqpg.fitting import seconds_per_step
from cvqpg.runs import scene_from_source


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="a folder with image.* and depth.png")
    parser.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    parser.add_argument("--colors", nargs="+", default=["gray", "rgb"], choices=["gray", "rgb"])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    preset = PRESETS["display"]
    source = {"image": str(next(args.scene.glob("image.*")).resolve()), "depth": str((args.scene / "depth.png").resolve())}
    scene = BenchScene(args.scene.name, source, 2)
    base = FitConfig.create(preset.recipe, width=args.size[0], height=args.size[1], steps=preset.steps)
    for color in args.colors:
        configs = {method: cell_config(base, scene, color, preset.ratios[0], method, base.optimisation.seed)
                   for method in ("cvqpg-dpac", "pixel-dpac")}
        scenes = {method: scene_from_source(source, config) for method, config in configs.items()}
        seconds = {method: [] for method in configs}
        for _ in range(args.rounds):
            for method, config in configs.items():
                seconds[method].append(seconds_per_step(scenes[method], config))
        ratios = [c / p for c, p in zip(seconds["cvqpg-dpac"], seconds["pixel-dpac"])]
        print(json.dumps({"color": color, "size": args.size, "cvqpg_seconds_per_step": seconds["cvqpg-dpac"],
                          "pixel_seconds_per_step": seconds["pixel-dpac"],
                          "pixel_steps_per_cvqpg_step": round(statistics.median(ratios), 2)}), flush=True)


if __name__ == "__main__":
    main()
