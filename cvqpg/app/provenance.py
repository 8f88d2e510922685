"""Where and how a fit ran: code commit, date, machine, threads and peak memory.

A results table is only read correctly beside these facts: times depend on the CPU and its
load, and the numbers on the code that produced them.
"""

from __future__ import annotations

import datetime
import functools
import gc
import os
import platform
import re
import resource
import subprocess
from pathlib import Path
from typing import Any

import numba
import torch

from .. import __version__
from .allocator import release_freed_memory

PACKAGE_ROOT = Path(__file__).resolve().parents[1]
PEAK_RESET_FILE = Path("/proc/self/clear_refs")
STATUS_FILE = Path("/proc/self/status")


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(PACKAGE_ROOT), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def is_own_checkout(top_level: Path, package_root: Path = PACKAGE_ROOT) -> bool:
    """Whether the git work tree at `top_level` is cvqpg's own: the package sits at its top, beside a
    `pyproject.toml` that names the project cvqpg (an install inside a user's git project is not)."""
    project = top_level / "pyproject.toml"
    if package_root.parent != top_level or not project.is_file():
        return False
    try:
        return re.search(r'^name\s*=\s*"cvqpg"\s*$', project.read_text(), re.MULTILINE) is not None
    except OSError:
        return False


@functools.cache
def code_commit() -> str | None:
    """The git commit of cvqpg's own checkout that this process runs, with `+dirty` when tracked files
    under the package differ from it; None for an installed package. Asked once per process: the code a
    process runs is what it imported, whatever is committed later, so `app.runner` asks before a fit's first
    step rather than at its record."""
    top_level = _git("rev-parse", "--show-toplevel")
    if not top_level or not is_own_checkout(Path(top_level), PACKAGE_ROOT):
        return None
    commit = _git("rev-parse", "HEAD")
    if not commit:
        return None
    changed = _git("status", "--porcelain", "--untracked-files=no", "--", str(PACKAGE_ROOT))
    return f"{commit}+dirty" if changed else commit


@functools.cache
def cpu_model() -> str:
    """The CPU's model name as the kernel reports it (Linux), else what `platform` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def reset_peak_memory(device: torch.device) -> None:
    """Start a new peak: the process's resident set (Linux) or the GPU's allocated bytes. On the CPU the
    memory earlier work freed but the process kept is released first, so that it is not counted."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return
    gc.collect()
    release_freed_memory()
    try:
        PEAK_RESET_FILE.write_text("5")  # resets VmHWM to the current RSS (Linux ≥ 4.0)
    except OSError:
        pass


def peak_memory(device: torch.device) -> dict[str, Any]:
    """Peak bytes since `reset_peak_memory`, and what they measure: `rss` since the reset (Linux),
    `rss-process` (the whole process's life, where the peak cannot be reset) or `cuda-allocated`."""
    if device.type == "cuda":
        return {"peak_memory_bytes": int(torch.cuda.max_memory_allocated(device)), "peak_memory_kind": "cuda-allocated"}
    try:
        for line in STATUS_FILE.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return {"peak_memory_bytes": int(line.split()[1]) * 1024, "peak_memory_kind": "rss"}
    except OSError:
        pass
    return {"peak_memory_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
            "peak_memory_kind": "rss-process"}


def device_name(device: torch.device) -> str:
    """`cpu: <model>` or `cuda: <GPU name>`."""
    if device.type == "cuda":
        return f"cuda: {torch.cuda.get_device_name(device)}"
    return f"cpu: {cpu_model()}"


def _load_average() -> float | None:
    """The machine's 15-minute load average at the fit's end: beside its core count, how busy the
    machine was (a fit sharing the cores with other work takes longer)."""
    try:
        return round(os.getloadavg()[2], 2)
    except OSError:
        return None


def available_cores() -> int:
    """Cores this process may use: its share of the node (a Slurm allocation or `taskset`), at most
    `OMP_NUM_THREADS` where the user set it to a positive whole number."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    asked = os.environ.get("OMP_NUM_THREADS", "")
    return min(cores, int(asked)) if asked.isdigit() and int(asked) > 0 else cores


def run_record(device: torch.device, loop_seconds: float, loop_cpu_seconds: float | None, compile_seconds: float,
               peak: dict[str, Any]) -> dict[str, Any]:
    """What a results table needs beside a fit's numbers (`metrics.json`'s `run`); `peak` is what
    `peak_memory` returned; `loop_cpu_seconds` the process's CPU seconds over the loop's wall `loop_seconds`
    (None where a resumed segment went unmeasured); `compile_seconds` compiled or loaded the CPU kernels
    before the loop, whose `loop_seconds` exclude them."""
    return {**machine_record(device), "loop_seconds": loop_seconds, "loop_cpu_seconds": loop_cpu_seconds,
            "compile_seconds": compile_seconds,
            "peak_memory_bytes": peak.get("peak_memory_bytes"), "peak_memory_kind": peak.get("peak_memory_kind")}


def machine_record(device: torch.device) -> dict[str, Any]:
    """Code commit, date, device, threads and the machine's load: what any timed record needs beside
    its seconds."""
    now = datetime.datetime.now(datetime.timezone.utc)
    return {"cvqpg_version": __version__, "commit": code_commit(), "date": now.isoformat(timespec="seconds"), "device": device_name(device),
            "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "numba_threads": numba.get_num_threads(), "load_average": _load_average(), "machine_cores": os.cpu_count()}
