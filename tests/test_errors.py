"""The error family at the command line: library messages name parameters, the CLI names flags; a model
fitted on another device or backend renders here; a bug exits 1 in one line (refusals: test_hostile.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from cvqpg import load_model, save_model
from cvqpg.cli import flag_message, main


@pytest.fixture(scope="module")
def foreign_run(finished_run, tmp_path_factory):
    """The shared finished run, its config and model changed to say it was fitted on CUDA with the Triton kernels."""
    out = Path(shutil.copytree(finished_run, tmp_path_factory.mktemp("foreign") / "run"))
    config_file = out / "config.json"
    recorded = json.loads(config_file.read_text())
    config_file.write_text(json.dumps({**recorded, "run": {"device": "cuda", "backend": "triton"}}))
    return out


def test_parameter_names_become_flags():
    assert flag_message("`num_planes` must be positive; lower `pixel_pitch`") == \
        "--planes must be positive; lower --pitch"
    assert flag_message("`unknown_name` stays") == "unknown_name stays"


@pytest.mark.parametrize("command", [["eval"], pytest.param(["export"], marks=pytest.mark.slow), ["render"], ["info"],
                                     pytest.param(["view", "--distances", "0.001", "0.002", "2", "--quiet"],
                                                  marks=pytest.mark.slow)])
def test_a_model_fitted_with_the_gpu_kernels_renders_on_the_cpu(foreign_run, tmp_path, capsys, command, monkeypatch):
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    out = [] if command[0] in ("eval", "info") else ["--out", str(tmp_path / ("page.html" if command[0] == "view"
                                                                               else "out"))]
    device = ["--device", "cpu"] if command[0] in ("eval", "export", "render") else []
    assert main([command[0], str(foreign_run), *command[1:], *out, *device]) == 0, capsys.readouterr().err


def test_a_bug_exits_1_in_one_line_asking_for_a_report(tmp_path, capsys, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr("cvqpg.app.compilation.compile_all", broken)
    assert main(["compile"]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "bug" in lines[0] and "boom" in lines[0]
    monkeypatch.setenv("CVQPG_TRACEBACK", "1")
    with pytest.raises(RuntimeError):
        main(["compile"])
