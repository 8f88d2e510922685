"""First-run compilation: the probe covers every kernel a fit calls, its time is reported apart from
the fit's, and a compile that takes a while shows a status line."""

import io
import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from numba.core import event
from numba.core.dispatcher import Dispatcher
from numba.core.types import UniTuple

from cvqpg.control import SILENT
from cvqpg.app import compilation
from cvqpg.ops.field import cpu as field_kernels
from cvqpg.ops.loss import cpu as loss_kernels
from cvqpg.ops.propagation import cpu as propagation_kernels
from cvqpg.ops.rasterize import cpu as rasterize_kernels
from cvqpg.cli import main
from cvqpg.app.compilation import CompileAlongside, CompileStatus, compile_kernels
from cvqpg.config import FitConfig
from cvqpg.fitting import fit_scene
from cvqpg.ops.rasterize import KERNEL_TYPES
from cvqpg.scenes import builtin_pictures
from cvqpg.targets import load_scene


def kernel_signatures():
    """Every type signature that the kernel modules' functions hold, compiled or loaded from the cache."""
    modules = (rasterize_kernels, field_kernels, propagation_kernels, loss_kernels)
    return {(module.__name__, name, signature) for module in modules
            for name, function in vars(module).items() if isinstance(function, Dispatcher)
            for signature in function.signatures}


KINDS = pytest.mark.parametrize("config", [FitConfig.create(width=48, height=36, steps=2, curvature_warmup=1),
                                           FitConfig.create(width=40, height=30, steps=2, curvature_warmup=1,
                                                            color="gray", num_planes=1, primitive="flat",
                                                            qpf="standard"),
                                           FitConfig.create(width=48, height=36, steps=2, curvature_warmup=1,
                                                            curvature="per-channel")],
                                ids=["demo", "gray-flat-one-plane", "per-channel"])


@pytest.mark.slow
@KINDS
def test_after_the_probe_a_fit_needs_no_other_kernel_specialisation(config):
    compile_kernels(config)
    probed = kernel_signatures()
    demo = builtin_pictures("demo", config.targets.width, config.targets.height)
    scene = load_scene(demo.image, demo.depth if config.targets.num_planes > 1 else None, config)
    fit_scene(scene, config, control=SILENT)
    assert kernel_signatures() == probed


@KINDS
def test_the_rasterizer_kernels_are_compiled_from_the_types_a_fit_calls_them_with(config):
    probe = compilation.probe_config(config)
    for per_primitive in (True, False):
        compilation.compile_rasterizer_kernels(probe, per_primitive)
    from_types = {(kernel, signature) for kernel in KERNEL_TYPES for signature in kernel.signatures}
    assert {(kernel, types) for kernel, types in KERNEL_TYPES.items()} <= from_types
    compile_kernels(config, alongside=False)
    assert {(kernel, signature) for kernel in KERNEL_TYPES for signature in kernel.signatures} == from_types


def test_the_probe_serves_more_planes_than_the_demo_depth_separates(caplog):
    config = FitConfig.create(num_planes=5, color="gray")
    probe = compilation.probe_config(config)
    demo = builtin_pictures("demo", probe.targets.width, probe.targets.height)
    with pytest.raises(ValueError, match="separates only 3"):  # the demo's own depth at the probe's size
        load_scene(demo.image, demo.depth, probe)
    with caplog.at_level("INFO", logger="cvqpg"):
        scene = compilation.probe_scene(probe)
    assert scene.masks.shape[0] == 5 and all(mask.any() for mask in scene.masks)
    assert not caplog.records  # the probe's own depth ramp is no user input to note
    compile_kernels(config)
    # The propagation takes a tuple of one array per plane: the probe compiled the five-plane kernels.
    mirrored = (propagation_kernels.mirrored_products, propagation_kernels.mirrored_sum)
    planes_held = {argument.count for kernel in mirrored for signature in kernel.signatures
                   for argument in signature if isinstance(argument, UniTuple)}
    assert 5 in planes_held, planes_held


class SkippingClock:
    """`time.perf_counter` that a test can move forward at once, as if that much time had passed."""

    def __init__(self, clock=time.perf_counter) -> None:
        self.clock = clock
        self.skipped = 0.0

    def __call__(self) -> float:
        return self.clock() + self.skipped


COMPILE_SECONDS = 1000.0  # far longer than the fit below, however slow the machine


def test_compile_time_is_reported_apart_from_the_fit(tmp_path, monkeypatch):
    clock = SkippingClock()
    monkeypatch.setattr(time, "perf_counter", clock)  # every module's clock, the fit's included
    compiled_at = []

    def slow_compile(config):
        compile_kernels(config)
        clock.skipped += COMPILE_SECONDS
        compiled_at.append(time.perf_counter())

    monkeypatch.setattr(compilation, "compile_kernels", slow_compile)
    out = tmp_path / "run"
    assert main(["fit", "--size", "48", "36", "--steps", "1", "--quiet", "--out", str(out)]) == 0
    after_fit = time.perf_counter()
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(compiled_at) == 1 and metrics["run"]["compile_seconds"] >= COMPILE_SECONDS
    assert metrics["seconds"] == metrics["run"]["loop_seconds"] <= after_fit - compiled_at[0] < COMPILE_SECONDS


class FrozenClock:
    """The clock `CompileStatus` reads, standing still until the test moves it."""

    def __init__(self) -> None:
        self.now = 100.0

    def perf_counter(self) -> float:
        return self.now


class Stream(io.StringIO):
    """A status stream that lets the test wait for its `count`-th write; `on_write` runs after each."""

    def __init__(self, on_write=lambda: None) -> None:
        super().__init__()
        self.on_write = on_write
        self.writes = 0
        self.changed = threading.Condition()

    def write(self, text: str) -> int:
        written = super().write(text)
        self.on_write()
        with self.changed:
            self.writes += 1
            self.changed.notify_all()
        return written

    def wait_for_writes(self, count: int) -> None:
        with self.changed:
            assert self.changed.wait_for(lambda: self.writes >= count, timeout=60), self.getvalue()


class Terminal(Stream):
    def isatty(self):
        return True


def compilation_line(seconds: float) -> str:
    return (f"compiling CPU kernels (first run only, about {compilation.COMPILE_ESTIMATE_SECONDS} s on 2 cores): "
            f"{seconds:.0f} s")


@pytest.fixture
def frozen_clock(monkeypatch) -> FrozenClock:
    clock = FrozenClock()
    monkeypatch.setattr(compilation, "time", clock)
    return clock


def test_a_compile_shows_a_status_line_counting_the_seconds_on_a_terminal(frozen_clock, monkeypatch):
    monkeypatch.setattr(compilation, "REDRAW_SECONDS", 0.01)

    def second_passes():  # one second between the redraws, on the status line's clock
        frozen_clock.now += 1.0

    terminal = Terminal(on_write=second_passes)
    with CompileStatus(terminal) as status:
        with event.trigger_event("numba:compile", data={}):
            terminal.wait_for_writes(3)
    redrawn = terminal.getvalue().split("\r")[1:]
    *counting, last = redrawn
    assert len(counting) >= 3 and counting == [compilation_line(seconds) for seconds in range(len(counting))]
    assert status.seconds >= 3 and last == f"{compilation_line(status.seconds)}, done\n"


def test_a_log_file_gets_the_status_once_and_the_total(frozen_clock):
    log = Stream()
    with CompileStatus(log) as status:
        with event.trigger_event("numba:compile", data={}):
            log.wait_for_writes(1)
            frozen_clock.now += 7.0  # the compile goes on for 7 s after the line was written
    assert status.seconds == 7.0
    assert log.getvalue() == f"{compilation_line(0)}\n{compilation_line(7)}, done\n"


class Polls:
    """`threading.Event`s (`event`) that count the waits that ended unset, so that a test can wait
    until a thread has looked at them a given number of times and found them unset."""

    def __init__(self) -> None:
        self.unset = 0
        self.changed = threading.Condition()

    def event(self) -> threading.Event:
        polls = self

        class PolledEvent(threading.Event):
            def wait(self, timeout=None) -> bool:
                is_set = super().wait(timeout)
                if not is_set:
                    with polls.changed:
                        polls.unset += 1
                        polls.changed.notify_all()
                return is_set

        return PolledEvent()

    def wait_for(self, count: int) -> None:
        with self.changed:
            assert self.changed.wait_for(lambda: self.unset >= count, timeout=60), self.unset


@pytest.mark.parametrize("stream", [Terminal, Stream], ids=["terminal", "log file"])
def test_a_slow_cache_load_shows_nothing(stream, frozen_clock, monkeypatch):
    """A load from Numba's cache raises no compile event: however long it takes, no line appears."""
    polls = Polls()
    monkeypatch.setattr(compilation, "threading", SimpleNamespace(Event=polls.event, Thread=threading.Thread))
    shown = stream()
    with CompileStatus(shown) as status:
        frozen_clock.now += 60.0  # a minute of loading, on the status line's clock
        polls.wait_for(3)  # the status thread looked for a compile three times since, and saw none
    assert status.seconds == 60.0 and shown.writes == 0 and shown.getvalue() == ""


def test_warmup_command_compiles_every_kind(capsys):
    assert main(["compile"]) == 0
    assert "CPU kernels compiled and cached" in capsys.readouterr().out


def held_at(gate: Path, give_up_seconds: float | None = None) -> list[str]:
    """A helper process that waits until the test creates `gate`, then exits 0; with `give_up_seconds`,
    one that exits 3 after that long without the gate (so that a block that wrongly waits ends)."""
    return [sys.executable, "-c", "import os, sys, time\n"
            "deadline = None if sys.argv[2] == 'None' else time.monotonic() + float(sys.argv[2])\n"
            "while not os.path.exists(sys.argv[1]):\n"
            "    if deadline is not None and time.monotonic() > deadline:\n"
            "        sys.exit(3)\n"
            "    time.sleep(0.01)\n", str(gate), str(give_up_seconds)]


def test_a_compile_starts_the_helper_processes_and_the_block_waits_for_them(tmp_path):
    gate = tmp_path / "gate"
    with CompileAlongside([held_at(gate), held_at(gate)]) as alongside:
        assert alongside.processes == []
        with event.trigger_event("numba:compile", data={}):
            pass
        with event.trigger_event("numba:compile", data={}):
            pass  # a second compile starts no more processes
        started = list(alongside.processes)
        assert len(started) == 2 and all(process.poll() is None for process in started)  # held at the gate
        gate.touch()
    # Only `wait` (or `poll`) sets a Popen's returncode: the block's end reaped both, let through the gate.
    assert [process.returncode for process in started] == [0, 0]


def test_without_a_compile_no_helper_process_starts():
    compile_kernels(FitConfig.create(width=48, height=36))
    with CompileAlongside([[sys.executable, "-c", "pass"]]) as alongside:
        compile_kernels(FitConfig.create(width=48, height=36), alongside=False)  # now loads from the cache
    assert alongside.processes == []


def test_an_interrupted_block_stops_the_helper_processes_instead_of_waiting(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with CompileAlongside([held_at(tmp_path / "never", give_up_seconds=60)]) as alongside:
            with event.trigger_event("numba:compile", data={}):
                pass
            raise KeyboardInterrupt
    # Terminated at the gate: waiting would have let it run to its own end (status 3).
    assert alongside.processes[0].returncode == -signal.SIGTERM


@pytest.mark.slow
def test_the_alongside_process_compiles_its_parts():
    probe = compilation.probe_config(FitConfig.create(width=48, height=36))
    done = subprocess.run(compilation.alongside_command(probe), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
