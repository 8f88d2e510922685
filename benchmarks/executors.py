"""Ray's overhead against the local pool: one grid fitted by each at the same concurrency, side by side.

    python benchmarks/executors.py                     # 8 cells of about 30 s here, 2 at once; about 5 minutes
    python benchmarks/executors.py --rounds 3          # each executor three times, in turns

The grid is the built-in `demo` scene at 320×240 (2 planes), grayscale 10%, baseline and CVQPG, seeds 100–103:
eight cells. The local pool runs `--jobs C --threads 1`; Ray runs on an instance of this machine with C CPUs,
each task one thread, its start-up and shutdown inside the timed span as in `cvqpg bench --executor ray`. The two
alternate which goes first in each round, so that both meet the same slow spells of a shared machine. Each round
prints both wall times and their ratio (Ray / local; the target is at most 1.05), and checks that both fitted
the same models bit for bit.

Measured on the 2-core development machine (`Intel(R) Xeon(R) Processor`, 150 steps, concurrency 2) while other
jobs held its cores (load average 6–20, once above 100), so that a cell took about 100 s instead of 30: local pool
391 s and 399 s, Ray 216 s, 188 s and 183 s, every Ray grid's models bit-identical to the local one's (docs/scale.md
discusses the gap).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import ray
import torch
from safetensors.torch import load_file

from cvqpg.app.executors import ExecutorOptions
from cvqpg.campaign.bench import Overrides, make_plan, run_plan
from cvqpg.control import SILENT


def fit_grid(kind: str, folder: Path, steps: int, concurrency: int) -> float:
    """Wall seconds of the whole grid on `kind` (`local` or `ray`)."""
    plan = make_plan("quick", folder, Overrides(scene_names=["demo"], size=(320, 240), steps=steps,
                                                seeds=[100, 101, 102, 103]))
    assert len(plan.cells) == 8 and all(cell.config.targets.num_planes == 2 for cell in plan.cells)
    start = time.perf_counter()
    if kind == "local":
        outcome = run_plan(plan, control=SILENT, jobs=concurrency, threads=1)
    else:
        ray.init(num_cpus=concurrency, include_dashboard=False, logging_level="ERROR")
        try:
            outcome = run_plan(plan, control=SILENT, executor=ExecutorOptions("ray", threads=1))
        finally:
            ray.shutdown()
    seconds = time.perf_counter() - start
    assert outcome.count("done") == 8, outcome.statuses
    return seconds


def same_models(first: Path, second: Path) -> bool:
    models = sorted(first.glob("cells/*/model.safetensors"))
    for model in models:
        a, b = load_file(model), load_file(second / model.relative_to(first))
        if a.keys() != b.keys() or not all(torch.equal(a[k], b[k]) for k in a):
            return False
    return len(models) == 8


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=150, help="steps of each cell (about 30 s at one thread here)")
    parser.add_argument("--concurrency", type=int, default=2, help="cells at once, on either executor")
    parser.add_argument("--rounds", type=int, default=1, help="times each executor fits the grid")
    args = parser.parse_args()
    ratios = []
    for round_ in range(args.rounds):
        order = ("local", "ray") if round_ % 2 == 0 else ("ray", "local")
        with tempfile.TemporaryDirectory() as scratch:
            seconds = {}
            for kind in order:
                seconds[kind] = fit_grid(kind, Path(scratch) / kind, args.steps, args.concurrency)
                print(f"round {round_ + 1}: {kind} {seconds[kind]:.1f} s", flush=True)
            identical = same_models(Path(scratch) / "local", Path(scratch) / "ray")
        ratios.append(seconds["ray"] / seconds["local"])
        print(f"round {round_ + 1} ({' then '.join(order)}): local {seconds['local']:.1f} s, "
              f"ray {seconds['ray']:.1f} s, ray/local {ratios[-1]:.3f}, identical fits: {'yes' if identical else 'NO'}",
              flush=True)
    print(f"median ray/local over {args.rounds} round(s): {statistics.median(ratios):.3f} (target ≤ 1.05)")


if __name__ == "__main__":
    main()
