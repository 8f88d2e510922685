"""The rate in the fit, one lever at a time (docs/compression.md, "Each lever alone, measured").

    python benchmarks/rate_levers.py ../shared/scenes/sushi --color gray --bpp 0.5 --levers plain
    python benchmarks/rate_levers.py ../shared/scenes/sushi --color gray --bpp 0.5 --levers noise+rate+prune

Fits the scene (`--size`, default 320×240, the default recipe, `--steps` float steps) at the primitive count
`cvqpg encode` takes for the budget, with the levers of `ratefit.RateFit` named in `--levers` (`plain`: none,
today's float fit; else `+`-joined names out of `noise`, `rate`, `prune`, `depths`), removes the silent primitives
where `prune`, then rate-controls the model into the budget with `--finetune` steps of today's tuning (so that every
row differs by its fit alone), and prints one JSON line: the file's bytes and PSNR against the scene's targets,
the primitives fitted and kept, the depths, the fit's and rate control's seconds, the last λ, and the rate
model's estimate of the chosen file against its bytes as the codec writes them. `--out FILE` also writes it.

    python benchmarks/rate_levers.py ../shared/scenes/sushi --time-steps 10

times, in turns, rounds of 10 optimisation steps of today's fit and of the fit with every lever (`ratefit.FULL`)
at the same primitive count, and prints the median seconds per step of each and their ratio.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from cvqpg import FitConfig
from cvqpg.app.encoding import encode_config
from cvqpg.codec import encode
from cvqpg.control import RunControl
from cvqpg.fitting import fit_scene, initial_state, update
from cvqpg.rate import estimate
from cvqpg.ratefit import FULL, RateFit, RateObjective, silent_removed
from cvqpg.search import Budget, rate_control, reference_for
from cvqpg.targets import load_scene

LEVERS = ("noise", "rate", "prune", "depths")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", help="a scene folder: image.* and depth.png")
    parser.add_argument("--color", default="gray", choices=("gray", "rgb"))
    parser.add_argument("--size", nargs=2, type=int, default=(320, 240), metavar=("W", "H"))
    parser.add_argument("--bpp", type=float, default=0.5)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--finetune", type=int, default=120)
    parser.add_argument("--levers", default="plain", help="plain, or +-joined names of " + ", ".join(LEVERS))
    parser.add_argument("--out", type=Path)
    parser.add_argument("--time-steps", type=int, default=0, metavar="K",
                        help="time rounds of K steps of both fits in turns instead")
    args = parser.parse_args()
    chosen = set(args.levers.split("+")) - {"plain"}
    if not chosen <= set(LEVERS):
        parser.error(f"--levers {args.levers}: give plain or +-joined names of {', '.join(LEVERS)}")
    folder = Path(args.scene)
    config = FitConfig.create(width=args.size[0], height=args.size[1], color=args.color, steps=args.steps)
    scene = load_scene(next(folder.glob("image.*")), folder / "depth.png", config)
    budget = Budget.of(config, bpp=args.bpp)
    config = encode_config(config, budget)
    if args.time_steps:
        print(json.dumps(step_times(scene, config, budget, args.time_steps)))
        return
    settings = RateFit(**{lever: lever in chosen for lever in LEVERS}, target_bytes=budget.max_bytes)
    started = time.perf_counter()
    fitted = fit_scene(scene, config, control=RunControl(progress=False),
                       objective=RateObjective(settings, config) if settings.active else None)
    fit_seconds = time.perf_counter() - started
    primitives = fitted.primitives
    if settings.prune:
        primitives = silent_removed(primitives, config, settings.bits)
    reference = reference_for(primitives, config, scene.targets)
    started = time.perf_counter()
    chosen_file = rate_control(primitives, config, reference, budget, scene, args.finetune)
    choice = chosen_file.choice
    record = {"scene": folder.name, "color": args.color, "size": list(args.size), "bpp": args.bpp,
              "levers": args.levers, "steps": args.steps, "finetune": args.finetune,
              "fitted": fitted.config.primitive_count, "after_prune": primitives.count, "kept": choice.decoded.count,
              "bytes": len(choice.data), "max_bytes": budget.max_bytes, "psnr": choice.psnr,
              "fit_psnr": reference.fit_psnr, "bits": choice.bits.__dict__, "finetune_kept": chosen_file.finetune_kept,
              "fit_seconds": fit_seconds, "rate_seconds": time.perf_counter() - started,
              "lambda_last": fitted.history.get("rate_lambda", [None])[-1],
              "estimate_last": fitted.history.get("rate_bytes", [None])[-1],
              "estimate_of_file": estimate(choice.decoded, config, choice.bits).file_bytes,
              "file_rewritten": len(encode(choice.decoded, config, choice.bits))}
    line = json.dumps(record)
    print(line)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(line + "\n")


def step_times(scene, config: FitConfig, budget: Budget, steps: int, rounds: int = 5) -> dict:
    """Median seconds per step of today's fit and of the fit with every lever, rounds of `steps` in turns, past
    the curvature warm-up, after a first untimed round of each."""
    plain, rated = initial_state(config, scene), initial_state(config, scene)
    objective = RateObjective(RateFit(**FULL, target_bytes=budget.max_bytes), config)
    first = config.optimisation.curvature_warmup
    times: dict[str, list[float]] = {"plain": [], "rate": []}
    for round_index in range(rounds + 1):
        for name, state, rate in (("plain", plain, None), ("rate", rated, objective)):
            started = time.perf_counter()
            for step in range(steps):
                state.step = first + step
                update(state, scene, config, objective=rate).loss.item()
            if round_index:
                times[name].append((time.perf_counter() - started) / steps)
    median = {name: sorted(values)[len(values) // 2] for name, values in times.items()}
    return {"primitives": config.primitive_count, "size": [config.targets.width, config.targets.height],
            "plain_s_per_step": median["plain"], "rate_s_per_step": median["rate"],
            "ratio": median["rate"] / median["plain"]}


if __name__ == "__main__":
    main()
