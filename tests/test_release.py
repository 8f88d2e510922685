"""The 0.4.0 release: the former names that 0.2.0 and 0.3.0 kept for one release each fail as any unknown name
does. Also the process-wide allocator setting, made only by the commands that fit."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

import cvqpg.campaign.bench
from cvqpg.app import executors
from cvqpg.cli import main
from cvqpg.errors import InputError

DATA = Path(__file__).parent / "data"


@pytest.mark.parametrize("argv", [["fit", "--warmup", "5"], ["bench", "--warmup", "5"], ["warmup"]])
def test_a_former_option_or_command_of_0_2_0_is_a_usage_error(capsys, argv):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert ("unrecognized arguments: --warmup" in err if len(argv) > 1 else "invalid choice: 'warmup'" in err)
    assert "deprecated" not in err


@pytest.mark.parametrize("old", ["cvqpg.compression", "cvqpg.ratecontrol", "cvqpg.bench", "cvqpg.rasterization"])
def test_a_former_module_of_0_2_0_is_not_found(old):
    with pytest.raises(ModuleNotFoundError, match=f"No module named '{old}'"):
        importlib.import_module(old)


def test_a_former_function_of_0_2_0_is_no_attribute():
    import cvqpg.optics

    with pytest.raises(AttributeError, match="transfer_function"):
        cvqpg.optics.transfer_function


@pytest.mark.parametrize("name", ["limit_threads", "limited_threads", "POLL_SECONDS"])
def test_a_name_that_moved_in_0_3_0_is_no_attribute_of_its_former_module(name):
    assert hasattr(executors, name)
    with pytest.raises(AttributeError, match=f"has no attribute '{name}'"):
        getattr(cvqpg.campaign.bench, name)


def test_only_the_commands_that_fit_keep_freed_memory(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr("cvqpg.app.allocator.keep_freed_memory", lambda: calls.append(True))
    assert main(["info", str(DATA / "format_v3.cvq")]) == 0
    assert main(["decompress", str(DATA / "format_v3.cvq"), "--out", str(tmp_path / "model.safetensors")]) == 0
    assert calls == []

    def fit_in_folder(*_args: object, **_kwargs: object) -> None:
        raise InputError("stopped before fitting")

    monkeypatch.setattr("cvqpg.app.runner.fit_in_folder", fit_in_folder)
    assert main(["fit", "--size", "32", "24", "--steps", "2", "--quiet", "--out", str(tmp_path / "run")]) == 2
    assert calls == [True]
