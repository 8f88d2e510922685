"""What the initialisations from the targets add to a fit's time, measured side by side.

    python benchmarks/beyond_cost.py                       # grayscale 10%, 640×480, the demo scene
    python benchmarks/beyond_cost.py --color rgb

Times, in turns over several rounds (medians): an update step, the paper's initialisation and the two from
the targets (their field's energy, their edges). Prints each in ms and what each initialisation from the
targets adds, once, to a 2000-step fit (2001 updates).
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Callable

from cvqpg import FitConfig, builtin_scene
from cvqpg.app.compilation import prepare_kernels
from cvqpg.fitting import initial_state, optimisation_step
from cvqpg.initialisation import initial_gaussians

ROUNDS = 5
STEPS = 2000


def seconds(action: Callable[[], object]) -> float:
    start = time.perf_counter()
    action()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--color", choices=("gray", "rgb"), default="gray")
    args = parser.parse_args()
    config = FitConfig.create("paper", color=args.color, ratio=0.1, steps=STEPS)
    prepare_kernels(config, show_status=False)
    scene = builtin_scene("demo", config)
    state = initial_state(config, scene)
    optimisation_step(state, scene, config)

    def step() -> None:
        optimisation_step(state, scene, config)

    actions = {"update step": step,
               "initialisation, paper": lambda: initial_gaussians(config.replace(init="uniform"), scene),
               "initialisation, from the targets": lambda: initial_gaussians(config.replace(init="targets"), scene),
               "initialisation, at the edges": lambda: initial_gaussians(config.replace(init="edges"), scene)}
    times: dict[str, list[float]] = {name: [] for name in actions}
    for _ in range(ROUNDS):
        for name, action in actions.items():
            times[name].append(seconds(action))
    median = {name: statistics.median(values) for name, values in times.items()}
    for name, value in median.items():
        print(f"{name:34s} {value * 1e3:9.1f} ms")
    fit = (STEPS + 1) * median["update step"]
    extra = {kind: (median[f"initialisation, {kind}"] - median["initialisation, paper"]) / fit
             for kind in ("from the targets", "at the edges")}
    print(f"a {STEPS}-step fit: {fit:.0f} s of updates; the initialisation from the targets adds "
          f"{extra['from the targets']:+.2%}, at the edges {extra['at the edges']:+.2%}")


if __name__ == "__main__":
    main()
