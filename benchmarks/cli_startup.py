"""Wall seconds of `cvqpg --version` and `cvqpg fit --help`, each a fresh Python process: median of N runs.

    python benchmarks/cli_startup.py              # this tree, 5 runs of each
    python benchmarks/cli_startup.py --runs 9

Each run starts `python -m cvqpg.cli ARGS` with this tree's `cvqpg` first on PYTHONPATH and times it until it
exits, Python's own start included. The target is under 0.5 s for each; both answer from the parser alone
(no PyTorch, no Numba: `tests/test_cli_startup.py`). Numbers compare on an idle machine only.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

TREE = Path(__file__).resolve().parent.parent
COMMANDS = (["--version"], ["fit", "--help"])
TARGET_S = 0.5


def seconds(args: list[str]) -> float:
    """Wall seconds of one `python -m cvqpg.cli ARGS`, which must succeed."""
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(TREE), os.environ.get("PYTHONPATH")]))}
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cvqpg.cli", *args], check=True, stdout=subprocess.DEVNULL, env=environment)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="runs of each command [default: 5]")
    runs = parser.parse_args().runs
    seconds(["--version"])  # the first start reads the files from disk; the rest find them cached
    for args in COMMANDS:
        times = [seconds(args) for _ in range(runs)]
        median = statistics.median(times)
        print(f"cvqpg {' '.join(args):10s} median {median:.3f} s of {runs} (min {min(times):.3f}, max {max(times):.3f})"
              f"  {'under' if median < TARGET_S else 'OVER'} the {TARGET_S:g} s target")


if __name__ == "__main__":
    main()
