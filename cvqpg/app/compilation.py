"""First-run compilation of the Numba CPU kernels, kept out of the fit's progress bar and timings.

Numba compiles a kernel on its first call and caches the machine code on disk (`cache=True`), so
only the first fit after installing (or after the kernels' source changed) pays for it. A fit on
the CPU therefore starts with one optimisation step of a tiny scene with the same settings
(`compile_kernels`): it compiles, or loads from the cache, exactly the kernel specialisations that
the fit calls, before the progress bar and the fit's clock start. Cold, the fit compiles most of the
rasterizer's kernels while another process compiles the rest into the cache (`CompileAlongside`,
`ALONGSIDE_PARTS`). When Numba compiles (rather than loads from its cache), a status line says so
and counts the seconds. `compile_all` does the same ahead of time for every kind of fit (`cvqpg compile`,
run by `scripts/install.sh`).
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from typing import TYPE_CHECKING, Sequence, TextIO

import torch
from numba.core import event

from ..config import FitConfig, RunOptions
from ..display import Display
from ..ops.propagation import SPECTRUM_BLOCK_ROWS, plane_groups

if TYPE_CHECKING:
    from ..targets import Scene

# Shown on the status line: a demo fit's cold compile on 2 idle cores, the rasterizer's loops here and the
# rest alongside, as `benchmarks/first_step.py` measures it (docs/performance.md, "First run")
COMPILE_ESTIMATE_SECONDS = 23
REDRAW_SECONDS = 1.0  # how often the status line's count is redrawn on a terminal
PROBE_SIZE_PX = (32, 24)  # above the SSIM window (11 px), so that every loss kernel runs
PROBE_PRIMITIVES = 24
# With this guard band the probe's padded grid spans more than one block of the propagation's
# spectrum rows, as every real fit's does: its transposes and copies take the same strided views
# (array layouts), so the probe compiles the specialisations a fit calls, not those of a one-block grid.
PROBE_GUARD_BAND_PX = SPECTRUM_BLOCK_ROWS // 4

# Fits whose kernels differ in their argument types differ in their plane count (the propagation takes one array
# per plane; colour, primitive, curvature and QPF change values, not types), their display (a phase-only display
# runs its encoding's kernels) and their phase terms (`cvqpg.phase`: the rasterizer's loops take the terms'
# arrays). One probe each covers the built-in scenes, the bench presets and every default; another --planes
# compiles its few propagation kernels on its first run.
PRECOMPILED_KINDS = (*(FitConfig.create(num_planes=planes) for planes in (1, 2)),
                     FitConfig.create(num_planes=2, display=Display.create("dpac")),
                     FitConfig.create(num_planes=2, phase="axes+tilt"))


def probe_config(config: FitConfig) -> FitConfig:
    """A tiny fit with `config`'s kind (colour, planes, primitive, curvature, QPF): the same
    kernel specialisations, a few milliseconds per step once compiled."""
    width, height = PROBE_SIZE_PX
    return config.replace(width=width, height=height, num_gaussians=PROBE_PRIMITIVES, steps=1,
                          curvature_warmup=0, guard_band_px=PROBE_GUARD_BAND_PX,
                          num_planes=probe_planes(config.targets.num_planes)).validate()


def probe_planes(planes: int) -> int:
    """Fewest planes whose groups (`plane_groups`) have every length that `planes` planes' groups have: the
    same kernel specialisations, whatever the plane count (101 planes, 12 groups of 8 and one of 5: 13)."""
    return sum({group.stop - group.start for group in plane_groups(planes)})


def probe_scene(probe: FitConfig) -> Scene:
    """The demo scene at the probe's size, with a depth ramp over all pixels that puts some on every
    plane, however many --planes asks for."""
    from ..scenes import builtin_pictures
    from ..targets import load_scene

    demo = builtin_pictures("demo", probe.targets.width, probe.targets.height)
    # a tensor, not a float picture: a picture would print the note meant for a user's float depth map
    ramp = torch.linspace(0.0, 1.0, probe.targets.width * probe.targets.height).reshape(probe.targets.height,
                                                                                        probe.targets.width)
    return load_scene(demo.image, ramp if probe.targets.num_planes > 1 else None, probe)


def compile_rasterizer_kernels(probe: FitConfig, per_primitive: bool = False) -> None:
    """Compile (or load) the fused rasterizer's kernels from their types (`KERNEL_TYPES`), without
    running them: its kernels other than the two loops over the primitives, or only those loops
    (`per_primitive`, `PER_PRIMITIVE_KERNELS`: the fit's own process's share of a cold compile).
    `probe` only gives the kind of fit: the probe runs on the CPU with the Numba kernels."""
    from ..ops.rasterize import KERNEL_TYPES, PER_PRIMITIVE_KERNELS

    for kernel, types in KERNEL_TYPES.items():
        if (kernel in PER_PRIMITIVE_KERNELS) == per_primitive:
            kernel.compile(types)


def compile_propagation_and_loss(probe: FitConfig) -> None:
    """Compile (or load) the propagation's and the loss's kernels for fits of `probe`'s kind: the
    loss of a random hologram, and its gradient."""
    from ..fitting import hologram_loss

    generator = torch.Generator().manual_seed(0)
    field = torch.randn(probe.channels, probe.targets.height, probe.targets.width, dtype=torch.complex64,
                        generator=generator)
    loss, _ = hologram_loss(field.requires_grad_(True), probe_scene(probe), probe, generator, "numba")
    loss.backward()


# What another process compiles while a cold fit compiles the rasterizer's loops over the primitives
# (docs/performance.md, "First run"): the rasterizer's other kernels, then the propagation's and the
# loss's. The fit loads them from the cache in its probe step.
ALONGSIDE_PARTS = (compile_rasterizer_kernels, compile_propagation_and_loss)


def compile_alongside(probe_json: str) -> None:
    """Entry point of the compile process: compile `ALONGSIDE_PARTS` for the probe configuration given
    as JSON."""
    probe = FitConfig.from_dict(json.loads(probe_json))
    for part in ALONGSIDE_PARTS:
        part(probe)


def alongside_command(probe: FitConfig) -> list[str]:
    """The command of the process that compiles `ALONGSIDE_PARTS` for fits of `probe`'s kind. A fresh
    interpreter imports only the modules the parts need (not the CLI, as a multiprocessing child would)."""
    return [sys.executable, "-c", "import sys; from cvqpg.app.compilation import compile_alongside; "
            "compile_alongside(sys.argv[1])", json.dumps(probe.to_dict())]


class CompileAlongside(event.Listener):
    """Within the block, at the first kernel that Numba compiles (on a warm cache there is none),
    starts one process per command, each compiling other kernels into Numba's disk cache on another
    core; waits for them at the end of the block, or stops them if the block raised (an interrupted
    fit does not wait). A process that fails costs nothing but time: the fit compiles what it
    left out itself."""

    def __init__(self, commands: Sequence[Sequence[str]]) -> None:
        self.commands = [list(command) for command in commands]
        self.processes: list[subprocess.Popen] = []

    def on_start(self, ev: event.Event) -> None:
        if not self.processes:
            self.processes = [subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                               stderr=subprocess.DEVNULL) for command in self.commands]

    def on_end(self, ev: event.Event) -> None:
        pass

    def __enter__(self) -> "CompileAlongside":
        event.register("numba:compile", self)
        return self

    def __exit__(self, exc_type: type | None, *exc: object) -> None:
        event.unregister("numba:compile", self)
        for process in self.processes:
            if exc_type is not None:
                process.terminate()
            process.wait()


def compile_kernels(config: FitConfig, alongside: bool = True) -> None:
    """Compile (or load from Numba's cache) every kernel that a CPU fit of `config` calls, by running
    one optimisation step and one render of a tiny scene of the same kind.

    The rasterizer's loops over the primitives compile first, from their types; cold and `alongside`,
    another process compiles the other kernels meanwhile (`ALONGSIDE_PARTS`), and the step waits for
    it and loads them from the cache. Otherwise the step compiles them."""
    from ..fitting import initial_state, optimisation_step, render
    from ..representation import representation

    probe = probe_config(config)
    with CompileAlongside([alongside_command(probe)] if alongside else []):
        compile_rasterizer_kernels(probe, per_primitive=True)
        scene = probe_scene(probe)
        state = initial_state(probe, scene)  # the optimiser's imports, before waiting for the other process
    optimisation_step(state, scene, probe, "numba")
    render(representation(probe).activate(state.gaussians.detached(), probe), probe, backend="numba")


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
        """On a terminal the line is redrawn every `REDRAW_SECONDS`; in a log file it is written once."""
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
            self._done.wait(REDRAW_SECONDS)

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


def prepare_kernels(config: FitConfig, run: RunOptions = RunOptions(), show_status: bool = True) -> float:
    """Compile or load the kernels a fit of `config` on `run` calls, with a status line when it compiles;
    returns the seconds it took (0 where the fit runs no Numba kernel)."""
    if run.kernels != "numba":
        return 0.0
    with CompileStatus(enabled=show_status) as status:
        compile_kernels(config)
    return status.seconds


def compile_all(show_status: bool = True) -> float:
    """Compile the kernel specialisations of every default fit (`PRECOMPILED_KINDS`) into Numba's cache,
    ahead of the first fit; returns the seconds it took."""
    with CompileStatus(enabled=show_status) as status:
        for kind in PRECOMPILED_KINDS:
            compile_kernels(kind)
    return status.seconds
