"""`cvqpg encode` against a Table 1 fit of the same setting, timed side by side (the encoder's time target).

    python benchmarks/encode_time.py ../shared/scenes/bento                  # RGB 10%, 640×480, 2000 steps, 1 bpp
    python benchmarks/encode_time.py ../shared/scenes/bento --steps 200     # a shorter run of both
    python benchmarks/encode_time.py ../shared/scenes/bento --color gray --bpp 0.5

Times, in turns, the Table 1 fit (the paper's recipe, ratio 0.1, CVQPG, seed 100) for `--steps` and
`app.encoding.encode_scene` at the budget with the default recipe (what `cvqpg encode --bpp B` runs, without
writing the file): `app.encoding.encode_steps(--steps)`, 1500 float and 600 quantisation-aware steps for
2000, in proportion for a shorter run, whose ratio then weighs the encoder's rate search more. Prints
one JSON line per run, then the ratio of the encoder's seconds to the fit's.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from cvqpg.control import SILENT
from cvqpg import FitConfig
from cvqpg.app.compilation import prepare_kernels
from cvqpg.app.encoding import encode_budget, encode_scene, encode_steps
from cvqpg.fitting import fit_scene
from cvqpg.search import CompressionSettings
from cvqpg.targets import load_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="folder with image.* and depth.png (e.g. ../shared/scenes/bento)")
    parser.add_argument("--color", choices=("rgb", "gray"), default="rgb")
    parser.add_argument("--bpp", type=float, default=1.0, help="the encoder's budget in bits per hologram pixel")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    parser.add_argument("--rounds", type=int, default=1, help="turns of (fit, encode); medians are not taken")
    args = parser.parse_args()
    table1 = FitConfig.create(width=args.size[0], height=args.size[1], color=args.color, ratio=0.1,
                              steps=args.steps).with_recipe("paper").validate()
    fit_steps, finetune_steps = encode_steps(args.steps)
    encoder = FitConfig.create(width=args.size[0], height=args.size[1], color=args.color, ratio=0.1,
                               steps=fit_steps).validate()
    scene = load_scene(next(args.scene.glob("image.*")), args.scene / "depth.png", table1)
    prepare_kernels(table1, show_status=False)
    settings = CompressionSettings(bpp=args.bpp, finetune_steps=finetune_steps)
    budget = encode_budget(encoder, settings)
    seconds: dict[str, float] = {"fit": 0.0, "encode": 0.0}
    for _ in range(args.rounds):
        started = time.perf_counter()
        fitted = fit_scene(scene, table1, control=SILENT)
        elapsed = time.perf_counter() - started
        seconds["fit"] += elapsed
        print(json.dumps({"run": "Table 1 fit", "primitives": table1.primitive_count, "seconds": round(elapsed, 1),
                          "psnr": round(fitted.metrics.mean["psnr"], 3)}), flush=True)
        started = time.perf_counter()
        encoded = encode_scene(scene, encoder, settings)
        elapsed = time.perf_counter() - started
        seconds["encode"] += elapsed
        print(json.dumps({"run": f"encode --bpp {args.bpp:g}", "primitives": encoded.fit.config.primitive_count,
                          "seconds": round(elapsed, 1), "fit_seconds": round(encoded.fit.seconds, 1),
                          "bytes": len(encoded.rate.choice.data), "max_bytes": budget.max_bytes,
                          "psnr": round(encoded.rate.choice.psnr, 3)}), flush=True)
    print(f"encode / fit: {seconds['encode'] / seconds['fit']:.3f} ({args.color}, {args.size[0]}×{args.size[1]}, "
          f"{args.steps} steps, {args.bpp:g} bpp)")


if __name__ == "__main__":
    main()
