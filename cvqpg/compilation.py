"""First-run compilation of the Numba CPU kernels, kept out of the fit's progress bar and timings.

Numba compiles a kernel on its first call and caches the machine code on disk (`cache=True`), so
only the first fit after installing (or after the kernels' source changed) pays for it. A fit on
the CPU therefore starts with one optimisation step of a tiny scene with the same settings
(`compile_kernels`): it compiles, or loads from the cache, exactly the kernel specialisations that
the fit calls, before the progress bar and the fit's clock start. When Numba compiles (rather
than loads from its cache), a status line says so and counts the seconds. `warmup` does the same ahead of time for
every kind of fit (`cvqpg warmup`, run by `scripts/install.sh`).
"""

from __future__ import annotations

import sys
import threading
import time
from typing import TextIO

import numpy as np
import torch
from numba.core import event
from PIL import Image

from .config import FitConfig

COMPILE_ESTIMATE_SECONDS = 60  # a fit's cold compile on the shared 2-core development machine (README)
PROBE_SIZE_PX = (32, 24)  # above the SSIM window (11 px), so that every loss kernel runs
PROBE_PRIMITIVES = 24

# Fits whose kernels differ in their argument types differ in their plane count only (the
# propagation takes one array per plane; colour, primitive, curvature and QPF change values, not
# types). One probe each covers the built-in scenes, the bench presets and every default; another
# --planes compiles its few propagation kernels on its first run.
WARMUP_KINDS = tuple(FitConfig(num_planes=planes) for planes in (1, 2))


def uses_cpu_kernels(config: FitConfig) -> bool:
    """Whether a fit of `config` runs Numba kernels (the optics and noise ones run on the CPU with any backend)."""
    return torch.device(config.device).type == "cpu"


def probe_config(config: FitConfig) -> FitConfig:
    """A tiny fit with `config`'s kind (colour, planes, primitive, curvature, QPF, backend): the same
    kernel specialisations, a few milliseconds per step once compiled."""
    width, height = PROBE_SIZE_PX
    return config.replace(width=width, height=height, num_gaussians=PROBE_PRIMITIVES, steps=1,
                          warmup=0, guard_band_px=8, device="cpu").validate()


def compile_kernels(config: FitConfig) -> None:
    """Compile (or load from Numba's cache) every kernel that a CPU fit of `config` calls, by running
    one optimisation step and one render of a tiny scene of the same kind."""
    from .fitting import initial_state, optimisation_step, render
    from .primitives import activate
    from .scenes import builtin_scene
    from .targets import load_scene

    probe = probe_config(config)
    demo = builtin_scene("demo", probe.width, probe.height)
    # A depth ramp over all pixels puts some on every plane, however many --planes asks for.
    ramp = Image.fromarray(np.linspace(0.0, 1.0, probe.width * probe.height, dtype=np.float32)
                           .reshape(probe.height, probe.width), "F")
    scene = load_scene(demo.image, ramp if probe.num_planes > 1 else None, probe)
    state = initial_state(probe)
    optimisation_step(state, scene, probe)
    render(activate(state.gaussians.detached(), probe), probe)


class CompileStatus(event.Listener):
    """A status line on `stream` while the block compiles kernels (Numba's compile events; loads from
    the cache raise none): what is compiling, the usual time and the seconds so far, then the total."""

    def __init__(self, stream: TextIO | None = None, enabled: bool = True) -> None:
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.seconds = 0.0
        self._compiling = threading.Event()
        self._done = threading.Event()

    def on_start(self, ev: event.Event) -> None:
        self._compiling.set()

    def on_end(self, ev: event.Event) -> None:
        pass

    def _line(self, elapsed: float) -> str:
        return f"compiling CPU kernels (first run only, about {COMPILE_ESTIMATE_SECONDS} s on 2 cores): {elapsed:.0f} s"

    def _show(self) -> None:
        """On a terminal the line is redrawn every second; in a log file it is written once."""
        while not self._compiling.wait(0.1):
            if self._done.is_set():
                return
        if not self.stream.isatty():
            self.stream.write(self._line(time.perf_counter() - self._start) + "\n")
            self.stream.flush()
            return
        while not self._done.is_set():
            self.stream.write("\r" + self._line(time.perf_counter() - self._start))
            self.stream.flush()
            self._done.wait(1.0)

    def __enter__(self) -> "CompileStatus":
        self._start = time.perf_counter()
        self._thread = threading.Thread(target=self._show, daemon=True) if self.enabled else None
        if self._thread is not None:
            event.register("numba:compile", self)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.seconds = time.perf_counter() - self._start
        self._done.set()
        if self._thread is not None:
            self._thread.join()
            event.unregister("numba:compile", self)
        if self._compiling.is_set() and self.enabled:
            self.stream.write(("\r" if self.stream.isatty() else "") + f"{self._line(self.seconds)}, done\n")
            self.stream.flush()


def prepare_kernels(config: FitConfig, show_status: bool = True) -> float:
    """Compile or load the kernels a fit of `config` calls, with a status line when it compiles;
    returns the seconds it took (0 where the fit runs no Numba kernel)."""
    if not uses_cpu_kernels(config):
        return 0.0
    with CompileStatus(enabled=show_status) as status:
        compile_kernels(config)
    return status.seconds


def warmup(show_status: bool = True) -> float:
    """Compile the kernel specialisations of every default fit (`WARMUP_KINDS`) into Numba's cache,
    ahead of the first fit; returns the seconds it took."""
    with CompileStatus(enabled=show_status) as status:
        for kind in WARMUP_KINDS:
            compile_kernels(kind)
    return status.seconds
