"""Cold compile of the CPU kernels a fit calls, with an empty Numba cache: CPU seconds per kernel.

    python benchmarks/compile.py                         # the README's demo fit (RGB, 2 planes, CVQPG)
    python benchmarks/compile.py --color gray --planes 1

Runs `compilation.compile_kernels` (what a fit runs before its progress bar) twice, each time in a
fresh process whose NUMBA_CACHE_DIR is an empty temporary folder. First in one process, listening
to Numba's compile events: per function, the CPU seconds of its own compilation (less those of the
functions compiled while typing it, listed apart) and the type signatures it compiled (more than
one: the same code compiled twice). Then as a fit runs it, with the rasterizer's loops over the
primitives compiled here and every other kernel alongside in a second process: CPU seconds of each
process, the functions this one compiled, and the wall time. CPU seconds compare across runs on a
loaded machine; wall time only on a quiet one."""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections import defaultdict

from numba.core import event

CHILD_FLAG = "--in-empty-cache"


class CompileTimes(event.Listener):
    """A Numba compile-event listener: each compiled function's own thread CPU seconds and signatures."""

    def __init__(self) -> None:
        super().__init__()
        self._open: list[list[float]] = []  # [start, seconds of nested compiles] per open event
        self.seconds: dict[str, float] = defaultdict(float)
        self.signatures: dict[str, int] = defaultdict(int)

    def on_start(self, ev) -> None:
        self._open.append([time.thread_time(), 0.0])

    def on_end(self, ev) -> None:
        started, nested = self._open.pop()
        total = time.thread_time() - started
        if self._open:
            self._open[-1][1] += total
        function = ev.data["dispatcher"].py_func
        name = f"{function.__module__}.{function.__qualname__}"
        self.seconds[name] += total - nested
        self.signatures[name] += 1


def process_cpu_seconds() -> tuple[float, float]:
    """CPU seconds of this process, and of its children that have ended."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


def measure(color: str, planes: int, alongside: bool) -> None:
    """Compile a fit's kernels in this process (its cache must be empty) and print the breakdown."""
    from cvqpg.app.compilation import compile_kernels
    from cvqpg.config import FitConfig

    times = CompileTimes()
    (own, children), wall = process_cpu_seconds(), time.perf_counter()
    with event.install_listener("numba:compile", times):
        compile_kernels(FitConfig.create(color=color, num_planes=planes), alongside=alongside)
    own, children = (after - before for after, before in zip(process_cpu_seconds(), (own, children)))
    wall = time.perf_counter() - wall
    how = "alongside another process" if alongside else "in one process"
    print(f"{color}, {planes} plane(s), empty cache, {how}: {own + children:.1f} CPU s, {wall:.1f} s wall")
    ours = {name: seconds for name, seconds in times.seconds.items() if name.startswith("cvqpg.")}
    if alongside:
        print(f"  this process {own:.1f} CPU s, compiling {sum(times.seconds.values()):.1f} s of it "
              f"({', '.join(sorted(name.rsplit('.', 1)[1] for name in ours))}); the other process {children:.1f} s")
        return
    print(f"  cvqpg's functions {sum(ours.values()):.1f} s, Numba's library functions "
          f"{sum(times.seconds.values()) - sum(ours.values()):.1f} s")
    for name, seconds in sorted(ours.items(), key=lambda item: -item[1]):
        print(f"  {seconds:6.2f} s  {times.signatures[name]} signature(s)  {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--color", default="rgb", choices=("rgb", "gray"))
    parser.add_argument("--planes", type=int, default=2)
    parser.add_argument("--alongside", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument(CHILD_FLAG, action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.in_empty_cache:
        measure(args.color, args.planes, args.alongside)
        return
    for alongside in (False, True):
        with tempfile.TemporaryDirectory(prefix="cvqpg-numba-cache-") as cache:
            subprocess.run([sys.executable, __file__, "--color", args.color, "--planes", str(args.planes),
                            *(["--alongside"] if alongside else []), CHILD_FLAG], check=True,
                           env={**os.environ, "NUMBA_CACHE_DIR": cache})

if __name__ == "__main__":
    main()
