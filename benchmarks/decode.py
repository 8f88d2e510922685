"""Decoding and rendering a `.cvq` file against one optimisation step, measured side by side.

    python benchmarks/decode.py --model runs/bento              # a fitted model, e.g. RGB 10% at 640×480
    python benchmarks/decode.py                                 # RGB 10% at 640×480, at initialisation
    python benchmarks/decode.py --model runs/bento --bits 6     # another budget (as `cvqpg compress --bits`)

The model is encoded once at the budget given (default: `BitDepths()`, the codec's default). Then,
in turns within each round (as `benchmarks/step.py` takes its stages): decoding the file's bytes;
decoding and rendering (the hologram, and its reconstruction at every plane: what `cvqpg render`
and a viewer need); and one whole optimisation step of the same configuration on the same
primitives (the demo scene's targets at that size). The machine is shared, so the ratio
decode+render / step is formed round by round and its median printed.
"""

from __future__ import annotations

import argparse
import statistics

import torch

from cvqpg import FitConfig
from cvqpg.config import RunOptions
from cvqpg.app.allocator import keep_freed_memory
from cvqpg.codec import BitDepths, decode, encode
from cvqpg.fitting import hologram
from cvqpg.optics import reconstruct
from cvqpg.primitives import activate, init_gaussians
from cvqpg.runs import model_path
from cvqpg.storage import load_model
from step import interleaved_seconds, stage_actions


def main() -> None:
    keep_freed_memory()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", help="a fitted model (run folder or .safetensors) [default: RGB 10%% at "
                        "640×480 at initialisation]")
    parser.add_argument("--bits", nargs="+", default=None, metavar="SPEC", help="budget as `cvqpg compress "
                        "--bits` takes it [default: the codec's default]")
    parser.add_argument("--rounds", type=int, default=5, help="rounds in which the actions take turns")
    args = parser.parse_args()
    if args.model:
        primitives, config = load_model(model_path(args.model))
    else:
        config = FitConfig.create(width=640, height=480, color="rgb", ratio=0.1)
        primitives = activate(init_gaussians(config.primitive_count, config.channels, config.targets.width,
                                             config.targets.height, config.optimisation.seed), config)
    bits = BitDepths() if args.bits is None else BitDepths.parse(args.bits)
    data = encode(primitives, config, bits)

    def decode_and_render():
        decoded = decode(data)
        with torch.no_grad():
            return reconstruct(hologram(decoded.primitives, decoded.config), decoded.config)

    step = stage_actions(config, RunOptions(backend="numba"), primitives)["whole step"]
    times = interleaved_seconds({"decode": lambda: decode(data), "decode + render": decode_and_render,
                                 "optimisation step": step}, args.rounds)
    ratios = [render / one_step for render, one_step in zip(times["decode + render"], times["optimisation step"])]
    targets = config.targets
    print(f"{targets.width}×{targets.height} {targets.color}, N = {primitives.count}, {targets.num_planes} planes, "
          f"file {len(data):,} B ({8 * len(data) / (targets.width * targets.height):.2f} bpp), "
          f"{torch.get_num_threads()} threads, medians of {args.rounds} rounds")
    for name, values in times.items():
        print(f"{name:>20}: {1000 * statistics.median(values):9.1f} ms")
    print(f"{'decode+render / step':>20}: {statistics.median(ratios):9.2f} (rounds: "
          f"{', '.join(f'{r:.2f}' for r in ratios)})")


if __name__ == "__main__":
    main()
