"""A command told to stop by a signal (Ctrl-C, SIGTERM) never reports success and never publishes an output, even
where the exception its signal handler raises is swallowed, as a C callback does (Numba's compiler ignores what its
callbacks raise): simulated here by delivering the signal inside `try: ... except BaseException: pass`."""

import json
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cvqpg import runs, search, view
from cvqpg.app import compression, fitplan, runner, signals
from cvqpg.cli import main

DATA = Path(__file__).parent / "data"
TINY_FIT = ["fit", "--size", "32", "24", "--steps", "3", "--checkpoint-every", "0", "--quiet"]
ENDED = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated"}


def swallowed(signum: int) -> None:
    """Deliver `signum` to this process where whatever its handler raises is swallowed."""
    try:
        signal.raise_signal(signum)
    except BaseException:
        pass


def names(folder: Path) -> list[str]:
    return sorted(path.name for path in folder.iterdir())


@pytest.mark.parametrize("signum", ENDED)
def test_a_swallowed_signal_is_recorded_and_raised_again_by_the_output_rule(signum):
    with signals.handled():
        swallowed(signum)
        assert signals.received() == signum
        with pytest.raises(KeyboardInterrupt if signum == signal.SIGINT else signals.Terminated):
            signals.check_not_stopped()
    signals.check_not_stopped()  # the record is the command's: outside one, nothing is held back
    with signals.handled():
        assert signals.received() is None  # and the next command starts unstopped


def test_within_a_fit_the_first_ctrl_c_asks_and_the_second_raises():
    with signals.handled():
        with signals.StopRequest() as stop_requested:
            signal.raise_signal(signal.SIGINT)
            assert stop_requested() and signals.received() == signal.SIGINT
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGINT)
        with signals.StopRequest() as stop_requested:
            assert stop_requested()  # a signal received before the fit began stops it at once


@pytest.mark.parametrize("signum", ENDED)
@pytest.mark.parametrize("overwrite", [False, True])
def test_a_file_output_is_not_published_once_told_to_stop(tmp_path, monkeypatch, capsys, signum, overwrite):
    source = shutil.copy(DATA / "format_v5.cvq", tmp_path / "model.cvq")
    out = tmp_path / "model.safetensors"
    if overwrite:
        shutil.copy(DATA / "format_v4_decoded.safetensors", out)
    before = out.read_bytes() if overwrite else None
    read = compression.read_compressed
    monkeypatch.setattr(compression, "read_compressed", lambda path: swallowed(signum) or read(path))
    argv = ["decompress", str(source), "--out", str(out), *(["--overwrite"] if overwrite else [])]
    assert main(argv) == 128 + signum
    assert capsys.readouterr().err.strip() == f"cvqpg decompress: {ENDED[signum]}"
    assert (out.read_bytes() if overwrite else out.exists()) == (before if overwrite else False)
    assert names(tmp_path) == ["model.cvq", *(["model.safetensors"] if overwrite else [])]  # no partial, no lock


def test_a_folder_output_is_not_published_once_told_to_stop(finished_run, tmp_path, monkeypatch, capsys):
    render = runs.render_model

    def told_to_stop_midway(*args, **kwargs):
        record = render(*args, **kwargs)
        swallowed(signal.SIGTERM)
        return record

    monkeypatch.setattr(runs, "render_model", told_to_stop_midway)
    assert main(["render", str(finished_run), "--out", str(tmp_path / "render")]) == 128 + signal.SIGTERM
    assert capsys.readouterr().err.strip() == "cvqpg render: terminated"
    assert names(tmp_path) == []


def test_a_fit_told_to_stop_during_its_final_render_keeps_its_checkpoint_and_resumes(tmp_path, monkeypatch, capsys):
    fit_scene = runner.fit_scene

    def told_to_stop_after_the_last_step(*args, **kwargs):
        result = fit_scene(*args, **kwargs)
        swallowed(signal.SIGTERM)
        return result

    out, work = tmp_path / "run", tmp_path / "run.partial"
    with monkeypatch.context() as patch:
        patch.setattr(runner, "fit_scene", told_to_stop_after_the_last_step)
        assert main([*TINY_FIT, "--out", str(out)]) == 128 + signal.SIGTERM
    assert (f"stopped during its final render, after the fit's last step; checkpoint saved. Continue with: cvqpg fit "
            f"--resume {work}") in capsys.readouterr().err
    assert names(tmp_path) == ["run.partial"] and (work / "checkpoint.pt").is_file()
    assert not (work / "metrics.json").exists()
    assert main(["fit", "--resume", str(work), "--quiet"]) == 0
    assert names(tmp_path) == ["run"] and (out / "metrics.json").is_file()


def test_a_fit_told_to_stop_before_it_began_stops_at_its_first_step(tmp_path, monkeypatch, capsys):
    scene_and_depth = fitplan.scene_and_depth
    monkeypatch.setattr(fitplan, "scene_and_depth", lambda *args: swallowed(signal.SIGTERM) or scene_and_depth(*args))
    assert main([*TINY_FIT, "--out", str(tmp_path / "run")]) == 128 + signal.SIGTERM
    assert "stopped before step 0; checkpoint saved" in capsys.readouterr().err
    assert names(tmp_path) == ["run.partial"]


@pytest.mark.slow
def test_a_batch_item_told_to_stop_while_it_writes_its_files_is_not_published_and_a_rerun_moves_it(tmp_path,
                                                                                                    monkeypatch):
    """The stop comes after the item's last step: its finished run stays in NAME.partial, its record says
    interrupted, and the next run moves it into place without fitting it again."""
    from cvqpg.app import batch
    scenes = tmp_path / "scenes"
    for name in ("a", "b"):
        (scenes / name).mkdir(parents=True)
        Image.fromarray(np.random.default_rng(5).integers(0, 256, (24, 32, 3), dtype=np.uint8)).save(
            scenes / name / "image.png")
    written, fitted = batch.write_fitted_run, []
    monkeypatch.setattr(batch, "write_fitted_run", lambda *args: (written(*args), swallowed(signal.SIGTERM)))
    original_fit = batch.fit_in_folder
    monkeypatch.setattr(batch, "fit_in_folder", lambda folder, *a, **k: fitted.append(folder.name)
                        or original_fit(folder, *a, **k))
    out = tmp_path / "out"
    argv = ["batch", str(scenes), "--out", str(out), "--size", "32", "24", "--steps", "2", "--quiet"]
    assert main(argv) == 128 + signal.SIGTERM
    records = {name: json.loads((out / ".batch" / f"{name}.json").read_text()) for name in ("a", "b")}
    assert records["a"]["status"] == "interrupted" and records["a"]["output"] == "a.partial"
    assert records["b"]["status"] == "not started"
    assert not (out / "a").exists() and (out / "a.partial" / "metrics.json").is_file()
    monkeypatch.setattr(batch, "write_fitted_run", written)
    assert main(argv) == 0
    assert fitted == ["a.partial", "b.partial"]  # a was moved, not fitted again
    assert (out / "a" / "metrics.json").is_file() and not (out / "a.partial").exists()


@pytest.mark.slow
def test_a_bench_cell_told_to_stop_while_it_writes_its_files_is_not_marked_finished(tmp_path, monkeypatch, capsys):
    from cvqpg.campaign import bench
    written = bench.write_fitted_run
    monkeypatch.setattr(bench, "write_fitted_run", lambda *args: (swallowed(signal.SIGTERM), written(*args))[1])
    out = tmp_path / "bench"
    argv = ["bench", "--preset", "star", "--size", "32", "24", "--steps", "2", "--methods", "cvqpg", "--quiet",
            "--out", str(out)]
    assert main(argv) == 128 + signal.SIGTERM
    assert "0 done, 0 skipped, 0 reused, 1 interrupted" in capsys.readouterr().out
    cell, = (out / "cells").iterdir()
    assert (cell / "model.safetensors").is_file() and not (cell / "metrics.json").exists()
    monkeypatch.setattr(bench, "write_fitted_run", written)
    assert main(argv) == 0 and (cell / "metrics.json").is_file()


@pytest.mark.parametrize("argv, asked, work", [
    ("render {run} --out {tmp}/out", (runs, "load_run_model"), (runs, "render")),
    ("export {run} --out {tmp}/out", (runs, "load_run_model"), (runs, "render")),
    ("view {run} --quiet --distances 0.001 0.002 2 --out {tmp}/page.html", (view, "load_run_model"),
     (view, "reconstruct")),
    ("compress {run} --bits 8 --out {tmp}/model.cvq", (compression, "reference_for"), (search, "trial")),
])
def test_a_command_told_to_stop_stops_before_its_work_goes_on(argv, asked, work, finished_run, tmp_path, monkeypatch,
                                                               capsys):
    """The signal is swallowed as the command reads its model: its work stops at its next check, not at the end,
    and leaves nothing."""
    (module, name), (work_module, work_name) = asked, work
    original, done = getattr(module, name), []
    monkeypatch.setattr(module, name, lambda *args, **kwargs: (swallowed(signal.SIGTERM),
                                                               original(*args, **kwargs))[1])
    monkeypatch.setattr(work_module, work_name, lambda *args, **kwargs: done.append(work_name))
    assert main(argv.format(run=finished_run, tmp=tmp_path).split()) == 128 + signal.SIGTERM
    assert capsys.readouterr().err.strip().endswith("terminated") and not done
    assert names(tmp_path) == []
