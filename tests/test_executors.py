"""Executors: a bench grid on Ray is bit-identical to the local one, a killed node's cell resumes from its
checkpoint, fractional GPUs give each task its device, a stop reaches every task, and Ray stays optional."""

import csv
import functools
import json
import os
import socket
import subprocess
import sys
import threading
import time
import types
from pathlib import Path

import pytest
import ray
import torch
from safetensors.torch import load_file

from cvqpg.app.executors import (DONE, FAILED, INTERRUPTED, NOT_STARTED, PROBE_PREFIX, ExecutorError, ExecutorOptions,
                                 Task, run_tasks, _Relay)
from cvqpg.campaign.bench import BenchError, Overrides, check_cells_device, make_plan, run_plan
from cvqpg.cli import main
from cvqpg.control import SILENT, RunControl
from cvqpg.storage import load_checkpoint

# Under pytest-xdist one worker runs the whole module, with every other test that may start Ray (test_batch.py,
# test_hostile.py): their Ray sessions and clusters are the machine's, one at a time.
pytestmark = pytest.mark.xdist_group("ray")


GRID = Overrides(size=(48, 36), steps=4, curvature_warmup=1)  # the quick preset: four cells
CELL_FILES = ("config.json", "metrics.json", "model.safetensors", "history.csv", "spectrum.json")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The quick grid fitted in this process, one thread per fit: what every executor must reproduce."""
    plan = make_plan("quick", tmp_path_factory.mktemp("reference") / "bench", GRID)
    assert run_plan(plan, control=SILENT, threads=1).count(DONE) == len(plan.cells) == 4
    return plan


LOCAL_RAY_RESOURCES = {"CPU": 4.0, "GPU": 2.0}


@pytest.fixture
def local_ray():
    """A Ray instance of this process, shared by the module's tests that connect to no cluster of their own:
    started once (two GPUs declared on a machine that may have none), stopped when the module ends."""
    if not ray.is_initialized() or {name: ray.cluster_resources().get(name)
                                    for name in LOCAL_RAY_RESOURCES} != LOCAL_RAY_RESOURCES:
        # Another session (a command of an earlier test that connected to a cluster left on this machine) is not
        # this module's: its tests count on four CPUs. "local": a new instance, whatever RAY_ADDRESS says.
        ray.shutdown()
        ray.init(address="local", num_cpus=4, num_gpus=2, include_dashboard=False, logging_level="ERROR")
    yield


@pytest.fixture(scope="module", autouse=True)
def _stop_ray_at_the_end():
    yield
    ray.shutdown()


def same_fit(folder: Path, other: Path) -> bool:
    """Bit-identical parameters, history (loss and PSNR) and metrics of two finished cell folders."""
    first, second = load_file(folder / "model.safetensors"), load_file(other / "model.safetensors")
    if first.keys() != second.keys() or not all(torch.equal(first[k], second[k]) for k in first):
        return False

    def history(path: Path) -> list[tuple[str, str]]:
        with open(path / "history.csv") as file:
            return [(row["loss"], row["psnr"]) for row in csv.DictReader(file)]

    def metrics(path: Path) -> dict:
        return json.loads((path / "metrics.json").read_text())["mean"]

    return history(folder) == history(other) and metrics(folder) == metrics(other)


def leftovers(folder: Path) -> list[Path]:
    """Files that a finished bench folder must not hold: partial writes, checkpoints, probe files."""
    return [p for p in folder.rglob("*") if p.is_file() and (".partial" in p.name or p.name.endswith(".tmp")
                                                             or p.name in ("checkpoint.pt", "error.log")
                                                             or p.name.startswith(PROBE_PREFIX))]


def parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def node_running(cluster: object, task: str) -> object | None:
    """The node of a `ray.cluster_utils.Cluster` whose worker process runs the Ray task named `task` (Ray titles
    the process `ray::<task name>`), found through the process tree of this machine."""
    raylets = {node.all_processes["raylet"][0].process.pid: node for node in cluster.worker_nodes}
    for process in Path("/proc").glob("[0-9]*"):
        try:
            if not (process / "cmdline").read_bytes().startswith(f"ray::{task}".encode()):
                continue
            pid = int(process.name)
            while pid > 1 and pid not in raylets:
                pid = parent(pid)
        except OSError:
            continue  # gone meanwhile
        if pid in raylets:
            return raylets[pid]
    return None


@pytest.mark.slow
def test_a_killed_node_s_cell_resumes_from_its_checkpoint_bit_identical(tmp_path):
    """Two worker nodes of one CPU, one cell; the node fitting it is killed mid-fit, after the cell's first
    checkpoint. Ray reruns the task on the idle node, the fit continues from the checkpoint (never from an earlier
    step), and the cell ends as the uninterrupted fit does, with no file half-written. (That every cell of a grid
    on Ray ends as the local executor's is `test_ray_fits_the_grid_bit_identical_to_the_local_executor`'s.)"""
    from ray.cluster_utils import Cluster

    ray.shutdown()  # this test's driver belongs to its own cluster
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
    for _ in range(2):
        cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    overrides = Overrides(size=(48, 36), steps=300, curvature_warmup=1, scene_names=["star"], methods=["cvqpg"])
    plan, uninterrupted = (make_plan("quick", tmp_path / name, overrides) for name in ("bench", "reference"))
    killed = plan.cell_dir(plan.cells[0])
    seen: list[int] = []
    at_kill: list = []  # the checkpoint's step, and whether the cell had finished
    finished = threading.Event()

    def kill_then_watch() -> None:
        node = None
        while node is None and not finished.is_set():
            time.sleep(0.05)
            if (killed / "checkpoint.pt").is_file():
                node = node_running(cluster, plan.cells[0].name)
        if node is None:
            return
        at_kill.extend([load_checkpoint(killed / "checkpoint.pt")["step"], (killed / "metrics.json").exists()])
        cluster.remove_node(node, allow_graceful=False)
        while not finished.is_set():
            try:
                seen.append(load_checkpoint(killed / "checkpoint.pt")["step"])
            except (OSError, ValueError, RuntimeError):
                pass  # not there (yet, or any more)
            time.sleep(0.05)

    watcher = threading.Thread(target=kill_then_watch)
    watcher.start()
    try:
        outcome = run_plan(plan, control=SILENT, executor=ExecutorOptions(
            "ray", threads=1, ray_address=cluster.address, checkpoint_every=5))
    finally:
        finished.set()
        watcher.join()
        ray.shutdown()
        cluster.shutdown()
    assert outcome.count(DONE) == len(plan.cells) == 1 and not outcome.failures
    step, finished_before = at_kill
    assert step > 0 and not finished_before  # killed mid-fit, after a checkpoint
    assert seen and all(later >= step for later in seen), (step, seen)
    assert run_plan(uninterrupted, control=SILENT, threads=1).count(DONE) == 1
    for cell in plan.cells:
        assert all((plan.cell_dir(cell) / name).is_file() for name in CELL_FILES)
        assert same_fit(plan.cell_dir(cell), uninterrupted.cell_dir(cell))
    assert leftovers(plan.folder) == []


@pytest.mark.slow
def test_ray_fits_the_grid_bit_identical_to_the_local_executor(reference, local_ray, tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["bench", "--preset", "quick", "--size", "48", "36", "--steps", "4", "--curvature-warmup", "1",
                 "--out", str(out), "--executor", "ray", "--threads", "1", "--quiet"]) == 0
    assert "4 done" in capsys.readouterr().out
    for cell in reference.cells:
        assert same_fit(out / "cells" / cell.name, reference.cell_dir(cell)), cell.name
    assert leftovers(out) == []


@pytest.mark.slow
def test_a_stopped_ray_grid_keeps_checkpoints_and_resumes_to_the_same_fits(local_ray, tmp_path):
    overrides = Overrides(size=(48, 36), steps=100, curvature_warmup=1, scene_names=["star"])
    plan, uninterrupted = (make_plan("quick", tmp_path / name, overrides) for name in ("bench", "reference"))
    executor = ExecutorOptions("ray", threads=1, checkpoint_every=5)
    checkpoints = [plan.cell_dir(cell) / "checkpoint.pt" for cell in plan.cells]
    control = RunControl(progress=False, stop_requested=lambda: any(p.is_file() for p in checkpoints))
    stopped = run_plan(plan, control=control, executor=executor)
    assert stopped.count(INTERRUPTED) >= 1 and stopped.count(DONE) < 2 and not stopped.failures
    assert all(plan.cell_dir(c).joinpath("checkpoint.pt").is_file() for c in plan.cells
               if stopped.statuses[c.name] == INTERRUPTED)
    resumed = run_plan(plan, control=SILENT, executor=executor)
    assert resumed.count(DONE) == 2 - stopped.count(DONE) and not resumed.failures
    assert run_plan(uninterrupted, control=SILENT, threads=1).count(DONE) == 2
    assert all(same_fit(plan.cell_dir(cell), uninterrupted.cell_dir(cell)) for cell in plan.cells)
    assert leftovers(plan.folder) == []


@pytest.mark.slow
def test_fractional_gpus_give_four_concurrent_tasks_two_devices_each_twice(local_ray, tmp_path):
    """The node declares two GPUs; at 0.5 GPU per task four tasks run at once, two on each device, and each sees
    the device Ray gave it (its tasks record what they see instead of fitting)."""
    def record(folder: str, name: str, control: RunControl) -> tuple[str, None]:
        Path(folder, f"{name}.json").write_text(json.dumps({"visible": os.environ.get("CUDA_VISIBLE_DEVICES"),
                                                            "ids": [str(i) for i in ray.get_gpu_ids()]}))
        deadline = time.monotonic() + 120
        while len(list(Path(folder).glob("*.json"))) < 4 and time.monotonic() < deadline:
            time.sleep(0.05)  # all four at once, or none waits for ever
        return ("done" if len(list(Path(folder).glob("*.json"))) == 4 else "alone"), None

    tasks = [Task(f"t{i}", functools.partial(record, str(tmp_path), f"t{i}")) for i in range(4)]
    outcome = run_tasks(tasks, ExecutorOptions("ray", threads=1, gpus_per_fit=0.5), SILENT, "gpus", tmp_path)
    assert outcome == {f"t{i}": (DONE, None) for i in range(4)}
    seen = [json.loads((tmp_path / f"t{i}.json").read_text()) for i in range(4)]
    assert sorted(s["visible"] for s in seen) == ["0", "0", "1", "1"]
    assert all([s["visible"]] == s["ids"] for s in seen)


@pytest.mark.slow
def test_a_stop_reaches_running_ray_tasks_and_those_not_started(local_ray, tmp_path):
    """Six tasks on four CPUs: once the first four run, the stop request reaches them through the monitor actor;
    the queued ones then start, hear it at once and do nothing."""
    def wait_for_stop(folder: str, name: str, control: RunControl) -> tuple[str, None]:
        if control.should_stop():
            return NOT_STARTED, None
        Path(folder, name).touch()
        for step in range(6000):  # a Ray worker of a busy machine may take a minute to start
            control.report(step, 0.0, 0.0)
            if control.should_stop():
                return INTERRUPTED, None
            time.sleep(0.1)
        return DONE, None

    tasks = [Task(f"t{i}", functools.partial(wait_for_stop, str(tmp_path), f"t{i}"), steps=6000) for i in range(6)]
    control = RunControl(progress=False, stop_requested=lambda: len(list(tmp_path.glob("t*"))) >= 4)
    outcome = run_tasks(tasks, ExecutorOptions("ray", threads=1), control, "stop", tmp_path)
    started = {path.name for path in tmp_path.glob("t*")}
    assert outcome == {name: (INTERRUPTED if name in started else NOT_STARTED, None) for name in outcome}
    # At least the four that the stop waited for. Ray lends the CPU of a task blocked in `ray.get` (a running one's
    # poll of the monitor) to a queued one, so on a busy machine a fifth may start before the stop reaches it; it
    # then hears it at its first poll.
    assert len(started) >= 4, f"{sorted(started)} started on {ray.cluster_resources()}"


@pytest.mark.slow
def test_a_task_that_raises_fails_once_with_one_line(local_ray, tmp_path):
    calls = tmp_path / "calls"

    def broken(control: RunControl) -> tuple[str, None]:
        with open(calls, "a") as file:
            file.write("x")
        raise ValueError("bad input\nsecond line")

    outcome = run_tasks([Task("broken", broken)], ExecutorOptions("ray"), SILENT, "fail", tmp_path)
    assert outcome == {"broken": (FAILED, "ValueError: bad input")} and calls.read_text() == "x"


@pytest.mark.slow
def test_a_folder_that_the_cluster_s_nodes_do_not_see_is_refused(local_ray, tmp_path, monkeypatch):
    """The driver does not see the probe file (as where the task's node writes to a disk of its own): one line,
    and no probe file left."""
    from cvqpg.app import executors

    monkeypatch.setattr(executors, "_sees", lambda path, token: False)
    with pytest.raises(ExecutorError, match="every Ray node sees") as error:
        run_tasks([Task("never", lambda control: (DONE, None))], ExecutorOptions("ray"), SILENT, "probe", tmp_path)
    assert "\n" not in str(error.value)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_no_node_offering_a_task_s_resources_is_one_line_not_a_hang(local_ray, tmp_path):
    with pytest.raises(ExecutorError, match="no node of the Ray cluster offers a task's 1 CPUs .* and 3 GPUs"):
        run_tasks([Task("never", lambda control: (DONE, None))], ExecutorOptions("ray", gpus_per_fit=3), SILENT,
                  "gpus", tmp_path)


def test_without_ray_the_ray_executor_is_one_line_naming_the_extra(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)
    assert main(["bench", "--preset", "quick", "--out", str(tmp_path / "b"), "--executor", "ray", "--quiet"]) == 2
    error = capsys.readouterr().err
    assert 'pip install "cvqpg[ray]"' in error and error.count("\n") == 1
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize("arguments, message", [
    (["--jobs", "2", "--executor", "ray"], "--jobs is for --executor local"),
    (["--gpus-per-fit", "0.5"], "--gpus-per-fit is for --executor ray"),
    (["--ray-address", "auto"], "--ray-address is for --executor ray"),
    (["--executor", "ray", "--gpus-per-fit", "-1"], "--gpus-per-fit -1: give a number ≥ 0"),
    (["--executor", "ray", "--gpus-per-fit", "1.5"], "--gpus-per-fit 1.5: above 1, give a whole number"),
    (["--checkpoint-every", "-3"], "--checkpoint-every -3: give a number of steps ≥ 1"),
    (["--jobs", "0"], "--jobs 0: need at least 1"),
])
def test_executor_flags_of_another_executor_or_out_of_range_are_one_line(arguments, message, tmp_path, capsys):
    assert main(["bench", "--preset", "quick", "--out", str(tmp_path / "b"), "--quiet", *arguments]) == 2
    error = capsys.readouterr().err
    assert message in error and error.count("\n") == 1


def test_the_local_executor_never_imports_ray():
    probe = ("import sys\n"
             "from cvqpg.app.executors import ExecutorOptions, Task, run_tasks\n"
             "from cvqpg.control import SILENT\n"
             "import cvqpg.campaign.bench, cvqpg.cli\n"
             "out = run_tasks([Task('a', lambda control: ('done', None))], ExecutorOptions(), SILENT, 'a', '.')\n"
             "assert out == {'a': ('done', None)}, out\n"
             "print('ray' in sys.modules)\n")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "False"


def test_cuda_cells_need_a_gpu_here_unless_a_cluster_elsewhere_fits_them(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cells = make_plan("quick", tmp_path / "b", Overrides(device="cuda")).cells
    check_cells_device(cells, ExecutorOptions("ray", ray_address="auto", gpus_per_fit=1))  # its nodes have the GPUs
    for here in (ExecutorOptions(), ExecutorOptions("ray", gpus_per_fit=1)):
        with pytest.raises(BenchError, match="--device cuda: no CUDA GPU is visible to PyTorch"):
            check_cells_device(cells, here)


def test_the_bar_shows_a_fits_last_step_as_its_step_count(monkeypatch):
    # a fit of S steps runs the indices 0..S; the bar's total is S
    monkeypatch.setattr("cvqpg.app.executors.POLL_SECONDS", 0.0)
    reported = []
    control = _Relay("cell", lambda name, step: reported.append(step) or False).control()
    for step in range(21):
        control.report(step, 0.0, 0.0)
    assert reported[-1] == 20


def test_a_cluster_that_accepts_and_never_answers_is_one_line_within_the_bound(monkeypatch):
    """Something listens at the address but Ray's connection never completes (Ray would retry for minutes): one
    line once the bound has passed, and the command is free to exit (the connecting thread is a daemon)."""
    from cvqpg.app import executors

    monkeypatch.setattr(executors, "RAY_CONNECT_SECONDS", 0.2)
    never = types.SimpleNamespace(init=lambda **settings: time.sleep(60))
    with socket.create_server(("127.0.0.1", 0)) as server:
        address = f"127.0.0.1:{server.getsockname()[1]}"
        started = time.monotonic()
        with pytest.raises(ExecutorError, match=f"--ray-address {address}: Ray did not connect within 0.2 s"):
            executors._connect(never, ExecutorOptions("ray", ray_address=address))
    assert time.monotonic() - started < 10
    assert all(thread.daemon for thread in threading.enumerate() if thread.name == "ray-connect")
