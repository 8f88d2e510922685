"""First-run compilation: the probe covers every kernel a fit calls, its time is reported apart from
the fit's, and a compile that takes a while shows a status line."""

import io
import json
import subprocess
import sys
import time

import pytest
from numba.core import event
from numba.core.dispatcher import Dispatcher

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


KINDS = pytest.mark.parametrize("config", [FitConfig(width=48, height=36, steps=2, curvature_warmup=1),
                                           FitConfig(width=40, height=30, steps=2, curvature_warmup=1, color="gray",
                                                     num_planes=1, primitive="flat", qpf="standard"),
                                           FitConfig(width=48, height=36, steps=2, curvature_warmup=1, curvature="per-channel")],
                                ids=["demo", "gray-flat-one-plane", "per-channel"])


@KINDS
def test_after_the_probe_a_fit_needs_no_other_kernel_specialisation(config):
    compile_kernels(config)
    probed = kernel_signatures()
    demo = builtin_pictures("demo", config.width, config.height)
    scene = load_scene(demo.image, demo.depth if config.num_planes > 1 else None, config)
    fit_scene(scene, config, progress=False)
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


def test_the_probe_serves_more_planes_than_the_demo_depth_separates():
    compile_kernels(FitConfig(num_planes=5, color="gray"))  # the demo's depth at the probe's size separates 3


def test_compile_time_is_reported_apart_from_the_fit(tmp_path, monkeypatch):
    compiled_at = []

    def slow_compile(config):
        compile_kernels(config)
        time.sleep(2.0)
        compiled_at.append(time.perf_counter())

    monkeypatch.setattr(compilation, "compile_kernels", slow_compile)
    out = tmp_path / "run"
    assert main(["fit", "--size", "48", "36", "--steps", "1", "--quiet", "--out", str(out)]) == 0
    after_fit = time.perf_counter()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["run"]["compile_seconds"] >= 2.0
    assert metrics["seconds"] == metrics["run"]["loop_seconds"] <= after_fit - compiled_at[0]


class Terminal(io.StringIO):
    def isatty(self):
        return True


def compile_for(seconds, stream):
    with CompileStatus(stream) as status:
        with event.trigger_event("numba:compile", data={}):
            time.sleep(seconds)
    return status, stream.getvalue()


def test_a_compile_shows_a_status_line_counting_the_seconds_on_a_terminal():
    status, shown = compile_for(2.5, Terminal())
    redrawn = shown.split("\r")[1:]
    assert len(redrawn) >= 3 and all(line.startswith("compiling CPU kernels (first run only, about") for line in redrawn)
    assert shown.endswith(f"{status.seconds:.0f} s, done\n")


def test_a_log_file_gets_the_status_once_and_the_total():
    status, shown = compile_for(2.5, io.StringIO())
    first, last = shown.splitlines()
    assert first.startswith("compiling CPU kernels (first run only, about") and first.endswith(": 0 s")
    assert last.endswith(f"{status.seconds:.0f} s, done") and "\r" not in shown


def test_a_slow_cache_load_shows_nothing():
    stream = io.StringIO()
    with CompileStatus(stream):
        time.sleep(1.5)
    assert stream.getvalue() == ""


def test_warmup_command_compiles_every_kind(capsys):
    assert main(["compile"]) == 0
    assert "CPU kernels compiled and cached" in capsys.readouterr().out


def sleeping(seconds: float) -> list[str]:
    return [sys.executable, "-c", f"import time; time.sleep({seconds})"]


def test_a_compile_starts_the_helper_processes_and_the_block_waits_for_them():
    with CompileAlongside([sleeping(1.0), sleeping(0.5)]) as alongside:
        with event.trigger_event("numba:compile", data={}):
            pass
        with event.trigger_event("numba:compile", data={}):
            pass  # a second compile starts no more processes
        started = list(alongside.processes)
    assert len(started) == 2 and all(process.returncode == 0 for process in started)


def test_without_a_compile_no_helper_process_starts():
    compile_kernels(FitConfig(width=48, height=36))
    with CompileAlongside([sleeping(1.0)]) as alongside:
        compile_kernels(FitConfig(width=48, height=36), alongside=False)  # now loads from the cache
    assert alongside.processes == []


def test_an_interrupted_block_stops_the_helper_processes_instead_of_waiting():
    started = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        with CompileAlongside([sleeping(60.0)]) as alongside:
            with event.trigger_event("numba:compile", data={}):
                pass
            raise KeyboardInterrupt
    assert alongside.processes[0].returncode is not None and time.perf_counter() - started < 30.0


def test_the_alongside_process_compiles_its_parts():
    probe = compilation.probe_config(FitConfig(width=48, height=36))
    done = subprocess.run(compilation.alongside_command(probe), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
