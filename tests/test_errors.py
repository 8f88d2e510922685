"""The error family at the command line: library messages name parameters, the CLI names flags; a model
fitted on another device or backend works or fails in one line; a bug exits 1 in one line."""

from __future__ import annotations

import json

import pytest

from cvqpg import load_model, save_model
from cvqpg.cli import flag_message, main
from cvqpg.errors import ConfigError, CvqpgError, InputError, ModelFileError


@pytest.fixture(scope="module")
def foreign_run(tmp_path_factory):
    """A finished run whose config and model say it was fitted on CUDA with the Triton kernels."""
    out = tmp_path_factory.mktemp("foreign") / "run"
    assert main(["fit", "--size", "32", "24", "--num-gaussians", "20", "--steps", "2", "--quiet", "--out",
                 str(out)]) == 0
    config_file = out / "config.json"
    recorded = json.loads(config_file.read_text())
    config_file.write_text(json.dumps({**recorded, "device": "cuda", "backend": "triton"}))
    primitives, config = load_model(out / "model.safetensors")
    save_model(out / "model.safetensors", primitives, config.replace(device="cuda", backend="triton"))
    return out


def one_line_error(capsys, code: int) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in captured.err, captured.err
    return lines[0]


def test_the_family_is_one():
    for error in (ConfigError, InputError, ModelFileError):
        assert issubclass(error, CvqpgError)


def test_parameter_names_become_flags():
    assert flag_message("`num_planes` must be positive; lower `pixel_pitch`") == \
        "--planes must be positive; lower --pitch"
    assert flag_message("`unknown_name` stays") == "unknown_name stays"


@pytest.mark.parametrize(("argv", "flag"), [(["--planes", "0"], "--planes"), (["--pitch", "inf"], "--pitch"),
                                             (["--ratio", "nan"], "--ratio"), (["--steps", "0"], "--steps"),
                                             (["--curvature-warmup", "99"], "--curvature-warmup")])
def test_a_bad_fit_option_is_named_by_its_flag(tmp_path, capsys, argv, flag):
    code = main(["fit", "--size", "32", "24", "--steps", "5", "--quiet", "--out", str(tmp_path / "run"), *argv])
    line = one_line_error(capsys, code)
    assert flag in line and "`" not in line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("command", [["eval"], ["export"], ["render"], ["info"], ["view", "--distances", "0.001",
                                                                                   "0.002", "2", "--quiet"]])
def test_a_model_fitted_with_the_gpu_kernels_renders_on_the_cpu(foreign_run, tmp_path, capsys, command, monkeypatch):
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    out = [] if command[0] in ("eval", "info") else ["--out", str(tmp_path / ("page.html" if command[0] == "view"
                                                                               else "out"))]
    device = ["--device", "cpu"] if command[0] in ("eval", "export", "render") else []
    assert main([command[0], str(foreign_run), *command[1:], *out, *device]) == 0, capsys.readouterr().err


def test_resuming_a_gpu_run_without_a_gpu_is_one_line(foreign_run, capsys, monkeypatch):
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    (foreign_run / "metrics.json").rename(foreign_run / "metrics.saved")
    try:
        line = one_line_error(capsys, main(["fit", "--resume", str(foreign_run), "--quiet"]))
    finally:
        (foreign_run / "metrics.saved").rename(foreign_run / "metrics.json")
    assert "no CUDA GPU" in line


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
