"""A command told to stop by a signal (Ctrl-C, SIGTERM) never reports success and never publishes an output, even
where the exception its signal handler raises is swallowed, as a C callback does (Numba's compiler ignores what its
callbacks raise): simulated here by delivering the signal inside `try: ... except BaseException: pass`."""

import shutil
import signal
from pathlib import Path

import pytest

from cvqpg import runs
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
