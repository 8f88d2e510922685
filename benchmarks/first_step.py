"""Seconds from starting the README's demo fit with an empty Numba cache until its first step is shown.

    python benchmarks/first_step.py                                        # this tree, 3 runs
    python benchmarks/first_step.py --trees ../cvqpg-before . --rounds 3   # two checkouts, alternating

Each run starts `python -m cvqpg.cli fit --size 320 240 --steps 300 --out TMP` in a source tree (its
`cvqpg` first on PYTHONPATH), with NUMBA_CACHE_DIR an empty temporary folder, reads the progress
output as it comes, and stops the fit once the bar shows step 1 (tqdm's `1/301`). With several trees
the rounds alternate between them (tree A, tree B, tree A, ...), so that a drift of the machine's
speed falls on both. Per run it prints the wall seconds until the compile's status line, the compile's
seconds as that line counted them (`COMPILE_ESTIMATE_SECONDS` estimates them), the wall seconds until
the first step, and the CPU seconds the fit had used by then, its own and those of the compile process
it had waited for (from /proc). Wall seconds compare on an idle machine only; CPU seconds also compare
on a loaded one.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

DEMO = ["fit", "--size", "320", "240", "--steps", "300"]
FIRST_STEP = re.compile(rb"\b([1-9]\d*)/\d+ \[")  # tqdm's "n/total [" once n ≥ 1
STATUS = b"compiling CPU kernels"
COMPILED = re.compile(rb"compiling CPU kernels [^\r\n]*: (\d+) s, done")  # the status line's last count


@dataclass
class Run:
    tree: Path
    status_s: float | None  # wall seconds until the compile's status line (None: no compile)
    compile_s: int | None  # the compile's seconds, as its status line counted them
    first_step_s: float  # wall seconds until the bar showed step 1
    cpu_s: float  # CPU seconds of the fit process by then
    children_cpu_s: float  # CPU seconds of the compile processes it had waited for


def cpu_seconds(pid: int) -> tuple[float, float]:
    """The CPU seconds of process `pid` (user + system) and of its children that it has waited for."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    utime, stime, cutime, cstime = (int(value) for value in fields[11:15])
    return (utime + stime) / ticks, (cutime + cstime) / ticks


def first_step(tree: Path, python: str, timeout_s: float) -> Run:
    """One cold start of the demo fit in `tree`, stopped after its first step."""
    with tempfile.TemporaryDirectory(prefix="cvqpg-first-step-") as scratch:
        env = {**os.environ, "NUMBA_CACHE_DIR": str(Path(scratch) / "numba"),
               "PYTHONPATH": os.pathsep.join(filter(None, (str(tree), os.environ.get("PYTHONPATH"))))}
        started = time.perf_counter()
        process = subprocess.Popen([python, "-m", "cvqpg.cli", *DEMO, "--out", str(Path(scratch) / "run")],
                                   cwd=tree, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.PIPE, bufsize=0)
        shown, status_s = b"", None
        try:
            while not FIRST_STEP.search(shown):
                chunk = process.stderr.read(65536)
                if not chunk:
                    raise RuntimeError(f"{tree}: the fit ended (exit code {process.wait()}) before its first step:\n"
                                       + shown.decode(errors="replace")[-2000:])
                shown += chunk
                if status_s is None and STATUS in shown:
                    status_s = time.perf_counter() - started
                if time.perf_counter() - started > timeout_s:
                    raise RuntimeError(f"{tree}: no first step within {timeout_s:.0f} s")
            elapsed = time.perf_counter() - started
            own, children = cpu_seconds(process.pid)
            compiled = COMPILED.search(shown)
        finally:
            process.send_signal(signal.SIGINT)  # the fit saves a checkpoint and exits; the folder goes with `scratch`
            try:
                process.wait(60)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            process.stderr.close()
    return Run(tree, status_s, int(compiled[1]) if compiled else None, elapsed, own, children)


def summary(runs: list[Run]) -> str:
    seconds = [run.first_step_s for run in runs]
    cpu = [run.cpu_s + run.children_cpu_s for run in runs]
    return (f"{runs[0].tree}: first step after {statistics.median(seconds):.1f} s (median of {len(runs)}, "
            f"{min(seconds):.1f}–{max(seconds):.1f}), {statistics.median(cpu):.1f} CPU s in all (median)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trees", nargs="+", type=Path, default=[Path(__file__).resolve().parents[1]],
                        help="source trees to compare (default: this one)")
    parser.add_argument("--rounds", type=int, default=3, help="runs per tree, alternating between trees")
    parser.add_argument("--python", default=sys.executable, help="the interpreter (default: this one)")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds before a run counts as failed")
    args = parser.parse_args()
    runs: dict[Path, list[Run]] = {tree.resolve(): [] for tree in args.trees}
    for round_ in range(args.rounds):
        for tree in runs:
            run = first_step(tree, args.python, args.timeout)
            runs[tree].append(run)
            status = ("no compile" if run.status_s is None
                      else f"status line {run.status_s:.1f} s, compile {run.compile_s} s")
            print(f"round {round_ + 1}  {tree}: {status}, first step {run.first_step_s:.1f} s; CPU s by then: "
                  f"fit {run.cpu_s:.1f}, compile process {run.children_cpu_s:.1f}", flush=True)
    for tree_runs in runs.values():
        print(summary(tree_runs))


if __name__ == "__main__":
    main()
