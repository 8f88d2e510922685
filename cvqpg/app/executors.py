"""Where the tasks of a grid or a batch run: in this process, in a pool of processes on this machine (`local`),
or as the tasks of a Ray cluster (`ray`), one progress bar and one stop request for all of them.

A task is any picklable `work(control) -> (status, error)`; `bench` and `batch` make one per cell or item. Its
`control` relays the command's stop request (a fit then saves its checkpoint) and reports its steps to the bar.
Ray is imported only by the Ray executor, and it is an optional extra: `pip install "cvqpg[ray]"`.
"""

from __future__ import annotations

import importlib.util
import logging
import math
import multiprocessing
import os
import queue
import signal
import socket
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import torch
from tqdm.auto import tqdm

from ..control import RunControl
from ..defaults import EXECUTORS
from ..errors import CvqpgError, UsageError
from ..files import gated
from . import signals
from .allocator import keep_freed_memory
from .provenance import available_cores

log = logging.getLogger("cvqpg")

# What became of a task: its work finished, or found its result there already, or stopped on request (keeping its
# checkpoint), or never started because of a stop request, or failed (with a one-line error).
DONE, SKIPPED, INTERRUPTED, NOT_STARTED, FAILED = "done", "skipped", "interrupted", "not started", "failed"
POLL_SECONDS = 0.5  # how often a task reports its step and hears of a stop, and the driver looks at its tasks
RAY_RETRIES = 3  # reruns of a Ray task whose worker process or node died (not of one whose work raised)
STOP_GRACE_SECONDS = 120.0  # how long an aborted command waits for its Ray tasks to save their checkpoints
RAY_EXTRA = 'pip install "cvqpg[ray]"'
PROBE_PREFIX = ".cvqpg-probe-"
RAY_CONNECT_SECONDS = 30.0  # the longest a command waits for a Ray cluster to answer
RAY_CLIENT_PORT = 10001  # Ray Client's port, where a ray:// address gives none


class ExecutorError(CvqpgError):
    """An executor that cannot run as asked: a bad option, Ray missing, or a cluster that cannot run the tasks."""


StepReport = Callable[[str, "int | None"], bool]  # (task name, last step or None) → whether to stop


@dataclass(frozen=True)
class ExecutorOptions:
    """How the tasks run. `kind`: `local` (this machine) or `ray`. `jobs` (local): tasks at once, in this process
    for 1, in a spawn process pool above. `threads`: PyTorch and Numba threads of each task, and its CPUs on Ray
    (default: cores // jobs locally, 1 on Ray). `ray_address`: the cluster to connect to (`auto`, `HOST:PORT`,
    `ray://HOST:PORT`); None starts a Ray instance on this machine for the command. `gpus_per_fit` (Ray): GPUs
    reserved per task (0.25: four tasks share a GPU). `checkpoint_every`: steps between the checkpoints of each
    fit (0: only when stopped; None: every few minutes of work; `runner.checkpoint_policy`)."""

    kind: str = "local"
    jobs: int = 1
    threads: int | None = None
    ray_address: str | None = None
    gpus_per_fit: float = 0.0
    checkpoint_every: int | None = None

    def validate(self) -> "ExecutorOptions":
        """These options, or a one-line `ExecutorError` naming the flag at fault (and the extra, where Ray is
        missing)."""
        if self.kind not in EXECUTORS:
            raise ExecutorError(f"--executor {self.kind}: choose one of {', '.join(EXECUTORS)}")
        if self.jobs < 1:
            raise ExecutorError(f"--jobs {self.jobs}: need at least 1")
        if self.threads is not None and self.threads < 1:
            raise ExecutorError(f"--threads {self.threads}: need at least 1")
        if not (math.isfinite(self.gpus_per_fit) and self.gpus_per_fit >= 0):
            raise ExecutorError(f"--gpus-per-fit {self.gpus_per_fit:g}: give a number ≥ 0 (e.g. 0.25: four fits "
                                "share a GPU)")
        if self.gpus_per_fit > 1 and not float(self.gpus_per_fit).is_integer():
            raise ExecutorError(f"--gpus-per-fit {self.gpus_per_fit:g}: above 1, give a whole number of GPUs")
        if self.checkpoint_every is not None and self.checkpoint_every < 0:
            raise ExecutorError(f"--checkpoint-every {self.checkpoint_every}: give a number of steps ≥ 1, or 0 "
                                "for checkpoints only when interrupted")
        if self.kind == "local" and (self.ray_address is not None or self.gpus_per_fit):
            flag = "--ray-address" if self.ray_address is not None else "--gpus-per-fit"
            raise ExecutorError(f"{flag} is for --executor ray")
        if self.kind == "ray" and self.jobs != 1:
            raise ExecutorError(f"--jobs {self.jobs} is for --executor local; on Ray, tasks run as the cluster's "
                                "CPUs (--threads per task) and GPUs (--gpus-per-fit) allow")
        if self.kind == "ray" and importlib.util.find_spec("ray") is None:
            raise ExecutorError(f"--executor ray needs Ray, which is not installed: {RAY_EXTRA}")
        return self

    def task_threads(self) -> int:
        """Threads of each task: `threads` (capped, with a note, at this machine's cores when they run here), else
        cores // jobs locally and 1 on Ray."""
        machine = os.cpu_count() or 1
        here = self.kind == "local" or self.ray_address is None
        if self.threads is not None and self.threads > machine and here:
            # PyTorch crashes on a thread pool far beyond the machine's
            log.warning(f"--threads {self.threads}: this machine offers {machine} cores; each fit runs on "
                        f"{machine} threads")
            return machine
        if self.threads is not None:
            return self.threads
        return max(1, available_cores() // self.jobs) if self.kind == "local" else 1

    def fits_at_once(self, device: str) -> int:
        """How many tasks may fit at once on one device of this machine: `jobs` locally; on a Ray instance of this
        machine 1 / `gpus_per_fit` per GPU (CUDA), else its cores over `threads`; 0 on a cluster given by its
        address, whose machines this one does not know."""
        if self.kind == "local":
            return self.jobs
        if self.ray_address is not None:
            return 0
        if torch.device(device).type == "cuda" and self.gpus_per_fit:
            return max(1, math.floor(1 / self.gpus_per_fit))
        return max(1, available_cores() // self.task_threads())


@dataclass(frozen=True)
class ExecutorFlags:
    """The executor flags of `cvqpg bench` and `batch` as given (None where not given), which `options` turns
    into `ExecutorOptions`."""

    executor: str = "local"
    jobs: int | None = None
    threads: int | None = None
    ray_address: str | None = None
    gpus_per_fit: float | None = None
    checkpoint_every: int | None = None

    def options(self, device: str | None, command: str) -> ExecutorOptions:
        """The executor the flags ask for, its fits on `device`, validated: a one-line `UsageError` for a flag
        that is not its executor's (`command` names the command's tasks in it)."""
        ray = self.executor == "ray"
        if ray and self.jobs is not None:
            raise UsageError(f"--jobs is for --executor local; on Ray, the {command} runs as many fits at once as "
                             "the cluster's CPUs (--threads each) and GPUs (--gpus-per-fit each) allow")
        for flag, given in (("--ray-address", self.ray_address is not None),
                            ("--gpus-per-fit", self.gpus_per_fit is not None)):
            if given and not ray:
                raise UsageError(f"{flag} is for --executor ray")
        gpus = self.gpus_per_fit if self.gpus_per_fit is not None else float(ray and device == "cuda")
        return ExecutorOptions(self.executor, 1 if self.jobs is None else self.jobs, self.threads, self.ray_address,
                               gpus, self.checkpoint_every).validate()


@dataclass(frozen=True)
class Task:
    """One unit of work: `name` (unique; the key of its outcome, shown on the bar), `work(control)` (picklable: a
    module-level function or a `functools.partial` of one) returning (status, error or None), and its `steps` for
    the bar (0: unknown)."""

    name: str
    work: Callable[[RunControl], tuple[str, str | None]]
    steps: int = 0


class TaskStopped(Exception):
    """A task's output held back because the task was told to stop (`unless_stopped`): its work stays where it
    is, to resume, and the task ends `interrupted`."""


@contextmanager
def unless_stopped(control: RunControl, *outputs: Path) -> Iterator[None]:
    """Within the block, nothing is moved into place at `outputs` (`files.gated`) once the task's `control` asks it
    to stop, or, for a task in the command's own process, once the command received a stop signal
    (`signals.received`, which the relay reads at most every `POLL_SECONDS`): `TaskStopped` instead, so that a
    task told to stop during its last step, or while it wrote its files, never publishes its output as
    finished."""
    def check() -> None:
        if signals.received() is not None or control.should_stop():
            raise TaskStopped("told to stop before its output was moved into place")

    with ExitStack() as stack:
        for output in outputs:
            stack.enter_context(gated(output, check))
        yield


def limit_threads(threads: int) -> None:
    """Torch and Numba threads of this process; Numba would otherwise use every core of a shared node."""
    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


@contextmanager
def limited_threads(threads: int) -> Iterator[None]:
    """`limit_threads` for the block; the caller's thread counts after it."""
    before = torch.get_num_threads(), numba.get_num_threads()
    limit_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])


def one_line(error: BaseException) -> str:
    """An error as one line: its type and the first line of its message."""
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0]}" if text else type(error).__name__


class _Relay:
    """A task's side of the bar and the stop request: its last step and the stop flag travel through `report` at
    most every `POLL_SECONDS`, never once per step."""

    def __init__(self, name: str, report: StepReport) -> None:
        self.name, self.report = name, report
        self.step: int | None = None
        self.stopped = False
        self.last = -math.inf

    def on_step(self, step: int, _loss: float, _psnr: float) -> None:
        self.step = step  # the fit loop runs indices 0..steps: its last step shows as steps/steps
        self._exchange()

    def should_stop(self) -> bool:
        self._exchange()
        return self.stopped

    def _exchange(self) -> None:
        now = time.monotonic()
        if now - self.last >= POLL_SECONDS:
            self.last = now
            self.stopped = self.report(self.name, self.step) or self.stopped

    def control(self) -> RunControl:
        return RunControl(progress=False, stop_requested=self.should_stop, on_step=self.on_step)


class _Board:
    """The driver's bar: a tick per finished task, the running tasks' steps in its postfix."""

    def __init__(self, bar: tqdm, tasks: Sequence[Task]) -> None:
        self.bar = bar
        self.totals = {task.name: task.steps for task in tasks}
        self.steps: dict[str, int] = {}
        self.outcomes: dict[str, tuple[str, str | None]] = {}
        self.shown = ""

    def show_steps(self, steps: dict[str, int]) -> None:
        self.steps = {name: step for name, step in steps.items() if name not in self.outcomes}
        self._show()

    def finish(self, name: str, status: str, error: str | None) -> None:
        self.outcomes[name] = (status, error)
        self.steps.pop(name, None)
        self.bar.update()
        self._show(f"{name}: {status}")

    def _show(self, last: str = "") -> None:
        running = " · ".join(f"{name} {step}/{self.totals[name]}" if self.totals[name] else f"{name} {step}"
                             for name, step in self.steps.items())
        if (running or last) != self.shown:
            self.shown = running or last
            self.bar.set_postfix_str(self.shown, refresh=True)


def run_tasks(tasks: Sequence[Task], options: ExecutorOptions, control: RunControl, description: str,
              shared_folder: Path, unit: str = "task") -> dict[str, tuple[str, str | None]]:
    """Run every task on the executor of `options`; returns {name: (status, error or None)}.

    One bar (`control.progress`) counts the tasks, `unit` each, and shows the running ones' steps. A stop request
    (`control.should_stop()`) reaches every task: running fits save a checkpoint and stop, those not started
    return `not started`. A task whose worker dies is `failed`, with a one-line error; on Ray it is first rerun
    (`RAY_RETRIES` times), the rerun resuming from what the task's folder holds. `shared_folder` is where the
    tasks write: on Ray every node must see it (`ray_probe`). A process already connected to Ray (`ray.init`)
    runs the tasks there and stays connected; otherwise the command's own connection ends with it."""
    options = options.validate()
    threads = options.task_threads()
    if not tasks:
        return {}
    with tqdm(total=len(tasks), desc=description, unit=unit, disable=not control.progress,
              dynamic_ncols=True) as bar:
        board = _Board(bar, tasks)
        if options.kind == "ray":
            _run_ray(tasks, options, threads, control, board, Path(shared_folder))
        elif options.jobs == 1:
            _run_here(tasks, threads, control, board)
        else:
            _run_pool(tasks, options.jobs, threads, control, board)
    return board.outcomes


def _run_here(tasks: Sequence[Task], threads: int, control: RunControl, board: _Board) -> None:
    steps: dict[str, int] = {}

    def report(name: str, step: int | None) -> bool:
        if step is not None:
            steps[name] = step
            board.show_steps(steps)
        return control.should_stop()

    with limited_threads(threads):
        for task in tasks:
            try:
                status, error = task.work(_Relay(task.name, report).control())
            except Exception as failure:  # one broken task must not cost the others; it is reported
                status, error = FAILED, one_line(failure)
            steps.pop(task.name, None)
            board.finish(task.name, status, error)


_worker_stop: Any = None
_worker_steps: Any = None


def _init_worker(threads: int, stop_event: Any, steps: Any) -> None:
    """Pool worker set-up: its share of the cores, the allocator setting of the command line (a spawned process
    does not inherit it), and signals left to the parent, which relays a stop."""
    global _worker_stop, _worker_steps
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    limit_threads(threads)
    keep_freed_memory()
    _worker_stop, _worker_steps = stop_event, steps


def _report_from_worker(name: str, step: int | None) -> bool:
    if step is not None:
        _worker_steps.put((name, step))
    return _worker_stop.is_set()


def _work_in_worker(task: Task) -> tuple[str, str | None]:
    return task.work(_Relay(task.name, _report_from_worker).control())


def _run_pool(tasks: Sequence[Task], jobs: int, threads: int, control: RunControl, board: _Board) -> None:
    context = multiprocessing.get_context("spawn")
    stop_event, reports = context.Event(), context.Queue()
    steps: dict[str, int] = {}
    with ProcessPoolExecutor(jobs, mp_context=context, initializer=_init_worker,
                             initargs=(threads, stop_event, reports)) as pool:
        futures = {pool.submit(_work_in_worker, task): task.name for task in tasks}
        pending = set(futures)
        try:
            while pending:
                finished, pending = wait(pending, timeout=POLL_SECONDS, return_when=FIRST_COMPLETED)
                while True:
                    try:
                        name, step = reports.get_nowait()
                    except queue.Empty:
                        break
                    steps[name] = step
                board.show_steps(steps)
                for future in finished:
                    try:
                        status, error = future.result()
                    except Exception as error:  # a worker that died (out of memory, killed)
                        status, error = FAILED, one_line(error)
                    board.finish(futures[future], status, error)
                if control.should_stop():
                    stop_event.set()
        finally:
            # also on a second Ctrl-C: running fits checkpoint and queued tasks return at once
            stop_event.set()


def _import_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise ExecutorError(f"--executor ray needs Ray, which is not installed: {RAY_EXTRA}") from None
    return ray


class _Monitor:
    """The Ray actor between the driver and its tasks: the stop flag, and each task's last step."""

    def __init__(self) -> None:
        self.stopped = False
        self.steps: dict[str, int] = {}

    def stop(self) -> None:
        self.stopped = True

    def report(self, name: str, step: int | None) -> bool:
        if step is not None:
            self.steps[name] = step
        return self.stopped

    def progress(self) -> dict[str, int]:
        return dict(self.steps)


def _work_on_ray(task: Task, threads: int, monitor: Any) -> tuple[str, str | None]:
    """A Ray task: `task.work` on `threads` threads, its steps and the stop flag through the `monitor` actor."""
    import ray

    def report(name: str, step: int | None) -> bool:
        try:
            return ray.get(monitor.report.remote(name, step))
        except ray.exceptions.RayError:  # the driver is gone: the work finishes, and a rerun would skip it
            return False

    limit_threads(threads)
    keep_freed_memory()
    return task.work(_Relay(task.name, report).control())


def _run_ray(tasks: Sequence[Task], options: ExecutorOptions, threads: int, control: RunControl, board: _Board,
             shared_folder: Path) -> None:
    with _ray_session(options, threads, shared_folder) as ray:
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
        here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
        monitor = ray.remote(_Monitor).options(num_cpus=0, scheduling_strategy=here).remote()
        remote = ray.remote(_work_on_ray)
        references = {remote.options(num_cpus=threads, num_gpus=options.gpus_per_fit, max_retries=RAY_RETRIES,
                                     retry_exceptions=False, name=task.name).remote(task, threads, monitor): task.name
                      for task in tasks}
        pending = list(references)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1, timeout=POLL_SECONDS)
                if ready and pending:
                    more, pending = ray.wait(pending, num_returns=len(pending), timeout=0)
                    ready += more
                for reference in ready:
                    board.finish(references[reference], *_ray_outcome(ray, reference))
                if control.should_stop():
                    monitor.stop.remote()
                board.show_steps(ray.get(monitor.progress.remote()))
        finally:
            if pending:  # also on a second Ctrl-C: running fits save their checkpoints before Ray goes
                monitor.stop.remote()
                ray.wait(pending, num_returns=len(pending), timeout=STOP_GRACE_SECONDS)


# The checks of a Ray session already made in this process: (threads, GPUs, folder) (`ready`).
_checked_sessions: set[tuple[int, float, str]] = set()


@contextmanager
def ready(options: ExecutorOptions, shared_folder: Path) -> Iterator[None]:
    """For the block, the executor of `options` ready to run tasks that write into `shared_folder`: on Ray,
    connected (unless this process is already) and checked (`check_cluster`, `ray_probe`, on the folder's nearest
    existing one where it is still to be made), so that a command refuses before it writes anything; `run_tasks`
    in the block runs on this connection. Nothing to do for the local executor."""
    options = options.validate()
    if options.kind != "ray":
        yield
        return
    with _ray_session(options, options.task_threads(), Path(shared_folder)):
        yield


@contextmanager
def _ray_session(options: ExecutorOptions, threads: int, shared_folder: Path) -> Iterator[Any]:
    """Ray, connected and checked for tasks of `threads` CPUs and `options.gpus_per_fit` GPUs that write into
    `shared_folder`; the connection ends with the block where the block made it."""
    ray = _import_ray()
    connected_here = not ray.is_initialized()
    if connected_here:
        _connect(ray, options)
    key = (threads, options.gpus_per_fit, os.path.abspath(shared_folder))
    try:
        if key not in _checked_sessions:
            check_cluster(ray, threads, options.gpus_per_fit)
            ray_probe(ray, shared_folder)
        if connected_here:
            _checked_sessions.add(key)
        yield ray
    finally:
        if connected_here:
            _checked_sessions.discard(key)
            ray.shutdown()


def _ended_within(work: Callable[[], None], seconds: float) -> bool:
    """Run `work` in a thread of its own (a daemon, which ends with the command where `work` never does, as
    Ray connecting to a cluster that accepts and never answers), its standard error sent nowhere (Ray's core warns
    there, a line every few seconds, while it retries an address): whether it ended within `seconds`."""
    thread = threading.Thread(target=work, name="ray-connect", daemon=True)
    with _quiet_stderr():
        thread.start()
        thread.join(seconds)
    return not thread.is_alive()


@contextmanager
def _quiet_stderr() -> Iterator[None]:
    """The process's standard error (its file descriptor, which Ray's C++ core writes to) sent nowhere for the
    block."""
    try:
        sys.stderr.flush()
        kept = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no descriptor 2 to redirect
        yield
        return
    try:
        with open(os.devnull, "w") as nowhere:
            os.dup2(nowhere.fileno(), 2)
        yield
    finally:
        os.dup2(kept, 2)
        os.close(kept)


def _where(options: ExecutorOptions) -> str:
    return f"--ray-address {options.ray_address}" if options.ray_address else "a Ray instance of this machine"


def check_reachable(address: str, timeout: float = RAY_CONNECT_SECONDS) -> None:
    """A one-line `ExecutorError` unless something answers at the Ray cluster's `address` (`auto`, `HOST:PORT`,
    `ray://HOST:PORT`) within `timeout` seconds: Ray itself would retry for minutes, warning as it goes."""
    target = address
    if address == "auto":
        try:  # where `ray start` recorded this machine's cluster
            from ray._private.services import canonicalize_bootstrap_address
            target = canonicalize_bootstrap_address(address) or ""
        except ConnectionError:
            raise ExecutorError(f"--ray-address auto: no Ray cluster runs on this machine (start one with `ray "
                                "start --head`, or give its HOST:PORT)") from None
        except Exception:  # Ray's own lookup moved: ray.init tells
            return
    client = target.startswith("ray://")
    host, _, port = target.removeprefix("ray://").rpartition(":")
    if not host and client:
        host, port = port, str(RAY_CLIENT_PORT)
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except ValueError:
        raise ExecutorError(f"--ray-address {address}: give auto, HOST:PORT or ray://HOST:PORT") from None
    except OSError as error:
        reason = error.strerror or type(error).__name__
        if isinstance(error, socket.gaierror):
            reason = f"the host {host} is not known"
        elif isinstance(error, TimeoutError):
            reason = f"no answer within {timeout:g} s"
        raise ExecutorError(f"--ray-address {address}: no Ray cluster answered there ({reason}); start one (`ray "
                            "start --head`), or give the address it printed") from None


def _connect(ray: Any, options: ExecutorOptions) -> None:
    """`ray.init` for `options`, within `RAY_CONNECT_SECONDS` (else a one-line `ExecutorError`), with Ray's own
    start-up lines kept off the terminal."""
    if options.ray_address is not None:
        check_reachable(options.ray_address)
    # Ray's own start-up lines and notes would break the one bar; its errors and the tasks' notes still show
    settings: dict[str, Any] = {"logging_level": logging.ERROR, "include_dashboard": False}
    if options.ray_address is None:
        settings["num_cpus"] = available_cores()
    sigterm = signal.getsignal(signal.SIGTERM)
    outcome: dict[str, BaseException] = {}

    def init() -> None:
        try:
            ray.init(address=options.ray_address, **settings)
        except BaseException as error:  # Ray exits (SystemExit) where no cluster answers at the address
            outcome["error"] = error

    if options.ray_address is None:  # a Ray instance of this machine, started here: no address to wait on
        init()
    elif not _ended_within(init, RAY_CONNECT_SECONDS):
        raise ExecutorError(f"{_where(options)}: Ray did not connect within {RAY_CONNECT_SECONDS:g} s; check that "
                            "the address is a Ray cluster's (`ray status` there)")
    error = outcome.get("error")
    if error is not None:
        if not isinstance(error, (ConnectionError, RuntimeError, ValueError, SystemExit)):
            raise error
        reason = "no Ray cluster answered there" if isinstance(error, SystemExit) else one_line(error)
        raise ExecutorError(f"{_where(options)}: Ray did not start or connect ({reason})")
    if sigterm is not None and threading.current_thread() is threading.main_thread():
        # A Ray instance of this process takes SIGTERM to kill its tasks at once: the command's own stop
        # request (its tasks checkpoint) comes back.
        signal.signal(signal.SIGTERM, sigterm)


def _ray_outcome(ray: Any, reference: Any) -> tuple[str, str | None]:
    try:
        return ray.get(reference)
    except ray.exceptions.RayTaskError as error:  # the work raised: once, not retried
        cause = error.cause if isinstance(error.cause, BaseException) else error
        return FAILED, one_line(cause)
    except ray.exceptions.RayError as error:  # its worker or node died more often than Ray retries
        return FAILED, one_line(error)


def check_cluster(ray: Any, threads: int, gpus: float) -> None:
    """A one-line `ExecutorError` unless some live node of the cluster offers a task's `threads` CPUs and `gpus`
    GPUs (else Ray would wait for such a node for ever)."""
    nodes = [node["Resources"] for node in ray.nodes() if node["Alive"]]
    if any(node.get("CPU", 0) >= threads and node.get("GPU", 0) >= gpus for node in nodes):
        return
    offered = "; ".join(f"{node.get('CPU', 0):g} CPUs, {node.get('GPU', 0):g} GPUs" for node in nodes)
    raise ExecutorError(f"no node of the Ray cluster offers a task's {threads} CPUs (--threads) and {gpus:g} GPUs "
                        f"(--gpus-per-fit); its nodes offer: {offered or 'none'}")


def _probe_write(folder: str, name: str, token: str) -> str:
    Path(folder, name).write_text(token)
    return socket.gethostname()


def _probe_remove(folder: str, name: str) -> None:
    Path(folder, name).unlink(missing_ok=True)


def _sees(path: Path, token: str) -> bool:
    """Whether this process sees the probe file at `path` as a task wrote it."""
    try:
        return path.read_text() == token
    except OSError:
        return False


def ray_probe(ray: Any, folder: Path) -> None:
    """Check that the driver sees a file that a task on each live node writes into `folder` (the tasks' results go
    there), or where it is still to be made, into its nearest existing folder; a one-line `ExecutorError`
    otherwise. The probe files are removed either way."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy as strategy

    folder = Path(os.path.abspath(folder))
    folder = next(place for place in (folder, *folder.parents) if place.is_dir())
    token = uuid.uuid4().hex
    write, remove = ray.remote(_probe_write), ray.remote(_probe_remove)
    nodes = [node["NodeID"] for node in ray.nodes() if node["Alive"]]
    names = {node: f"{PROBE_PREFIX}{token}-{index}" for index, node in enumerate(nodes)}
    def on(node: str) -> dict[str, Any]:
        return {"num_cpus": 0, "max_retries": 0, "scheduling_strategy": strategy(node, soft=False)}

    written = {node: write.options(**on(node)).remote(str(folder), name, token) for node, name in names.items()}
    unseen = []
    for node, reference in written.items():
        try:
            host = ray.get(reference)
        except ray.exceptions.RayError as error:
            unseen.append(f"the node {node[:8]} could not write there ({one_line(getattr(error, 'cause', error))})")
            continue
        seen = _sees(folder / names[node], token)
        (folder / names[node]).unlink(missing_ok=True)
        if not seen:
            ray.get(remove.options(**on(node)).remote(str(folder), names[node]))
            unseen.append(f"a file that a task on {host} wrote is not visible here")
    if unseen:
        raise ExecutorError(f"the output folder must be on a filesystem that every Ray node sees, and {folder} is "
                            f"not: {'; '.join(unseen)}; give a folder on a shared filesystem (NFS, Lustre, ...)")
