"""Design choices of the CPU code against the alternatives they replaced, measured side by side.

    python benchmarks/choices.py                                         # 2 threads, as a fit; under a minute
    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python benchmarks/choices.py   # where the cores are shared

Each row times our choice and its alternative in turns, so that both meet the same slow spells of a
shared machine: a turn's time is the median of its calls (a mean would take in every stall of a
thread that lost its core), and the row prints the medians over the rounds (ms per call) and the
median of the rounds' ratios, alternative / ours (above 1: ours is faster). Sizes are those of a
640×480 RGB fit with 2 planes. docs/performance.md ("Measured choices") keeps the numbers with the
machine they came from.

Everything runs with `keep_freed_memory`'s allocator setting, as the command line's fits do;
docs/performance.md says which command sets that setting against glibc's default. Where other jobs
hold the cores, a parallel call waits for its threads' turns on them (its times then come in
multiples of the scheduler's slice), and one thread measures the code rather than the scheduler.
"""

from __future__ import annotations

import math
import os
import statistics
import time
from typing import Callable

import numba as nb
import numpy as np
import torch

from cvqpg.app.allocator import keep_freed_memory
from cvqpg.ops.cpu import cosines_and_sines
from cvqpg.ops.loss import standard_normal
from cvqpg.ops.loss.reference import ssim_per_plane, ssim_window
from cvqpg.ops.propagation import cpu as propagation_cpu
from pytorch_msssim import ssim

ROUNDS = 7
CALLS = 5  # timed calls per turn


def turn_ms(run: Callable[[], object]) -> float:
    times = []
    for _ in range(CALLS):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3


def side_by_side(ours: Callable[[], object], alternative: Callable[[], object]) -> tuple[float, float, float]:
    """Median ms of each and the median ratio; the two swap places every round."""
    ours()  # compilation and first touch
    alternative()
    rounds = []
    for r in range(ROUNDS):
        if r % 2:
            alternative_ms, ours_ms = turn_ms(alternative), turn_ms(ours)
        else:
            ours_ms, alternative_ms = turn_ms(ours), turn_ms(alternative)
        rounds.append((ours_ms, alternative_ms, alternative_ms / ours_ms))
    return tuple(statistics.median(column) for column in zip(*rounds))


@nb.njit
def libm_cosines_and_sines(angles, cosines, sines):
    for i in range(angles.shape[0]):
        cosines[i], sines[i] = math.cos(angles[i]), math.sin(angles[i])


def choices() -> list[tuple[str, str, str, Callable[[], object], Callable[[], object]]]:
    generator = torch.Generator().manual_seed(0)
    targets = torch.rand(2, 3 * 480 * 640)
    wide = torch.randn(768, 1920, dtype=torch.complex64)
    field, spectrum = wide[:, :960], torch.empty(768, 960, dtype=torch.complex64)
    transposed = torch.empty(1920, 1536, dtype=torch.complex64)[:, :768]
    angles = np.random.default_rng(0).uniform(-100.0, 100.0, 6 * 3 * 30720)
    cosines, sines = np.empty_like(angles), np.empty_like(angles)
    recon, target = torch.rand(1, 1, 480, 640), torch.rand(1, 1, 480, 640)
    return [
        ("target noise [2, 3, 480, 640]", "standard_normal (numba)", "torch.randn",
         lambda: standard_normal((2, 3, 480, 640), generator, "numba"),
         lambda: torch.randn((2, 3, 480, 640), generator=generator)),
        ("range per plane [2, 921600]", "amax - amin", "torch.aminmax",
         lambda: targets.amax(dim=1) - targets.amin(dim=1),
         lambda: (lambda low, high: high - low)(*torch.aminmax(targets, dim=1))),
        ("copy of a 768×960 complex64 view", "copy_rows", "Tensor.copy_",
         lambda: propagation_cpu.copy_rows(field.numpy(), spectrum.numpy(), False),
         lambda: spectrum.copy_(field)),
        ("transpose 768×1920 complex64 into a view", "transpose", "Tensor.copy_ of .T",
         lambda: propagation_cpu.transpose(wide.numpy(), transposed.numpy()),
         lambda: transposed.copy_(wide.T)),
        ("cos and sin of 552960 angles (1 thread)", "cosines_and_sines", "libm in Numba",
         lambda: cosines_and_sines(angles, cosines, sines),
         lambda: libm_cosines_and_sines(angles, cosines, sines)),
        ("SSIM reference, one 480×640 channel", "oneDNN off", "oneDNN on",
         lambda: ssim_per_plane(recon, target),
         lambda: ssim(recon, target, data_range=1.0, size_average=False,
                      win=ssim_window(1, recon.dtype, recon.device))),
    ]


def main() -> None:
    keep_freed_memory()
    print(f"torch {torch.__version__}, numba {nb.__version__}; threads: torch {torch.get_num_threads()}, numba "
          f"{nb.get_num_threads()}; load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; "
          f"medians of {ROUNDS} rounds, ms per call")
    print(f"{'choice':42s} {'ours':26s} {'alternative':20s} {'ours ms':>8s} {'alt ms':>8s} {'alt/ours':>8s}")
    for choice, ours_name, alternative_name, ours, alternative in choices():
        ours_ms, alternative_ms, ratio = side_by_side(ours, alternative)
        print(f"{choice:42s} {ours_name:26s} {alternative_name:20s} {ours_ms:8.2f} {alternative_ms:8.2f} {ratio:8.2f}")


if __name__ == "__main__":
    main()
