"""The thread counts that Numba, OpenMP (PyTorch) and MKL read from the environment as they load, checked before
any of them loads: 0 or garbage makes Numba fail, or warn in several lines, before cvqpg could say anything, and a
count far above the machine's cores makes every step crawl."""

from __future__ import annotations

import os

# Whether the variable takes a list of counts (OpenMP: one per nesting level).
THREAD_VARIABLES = {"NUMBA_NUM_THREADS": False, "OMP_NUM_THREADS": True, "MKL_NUM_THREADS": False}


def bad_thread_variable() -> str | None:
    """The first thread-count variable of the environment (`THREAD_VARIABLES`) set to something other than a
    whole number ≥ 1 (or a list of them, where a list is taken); None where all are fine or unset."""
    for name, listed in THREAD_VARIABLES.items():
        value = os.environ.get(name)
        if value is None:
            continue
        counts = value.split(",") if listed else [value]
        if not all(count.strip().isdigit() and int(count) >= 1 for count in counts):
            return name
    return None


def cap_thread_variables() -> list[str]:
    """Lower a thread count of the environment (`THREAD_VARIABLES`, one number) above the cores this process may
    use to their number (Numba starts as many threads as it is told: 9999 took minutes for one step); a note for
    each one lowered."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    notes = []
    for name in THREAD_VARIABLES:
        value = os.environ.get(name, "")
        if value.isdigit() and int(value) > cores:
            os.environ[name] = str(cores)
            notes.append(f"{name}={value} lowered to {cores}, the cores this process may use")
    return notes
