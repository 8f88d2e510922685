"""The 0.2.0 release: former names that work for one release, with a warning that names the new one, and the
process-wide allocator setting made only by the commands that fit."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

from cvqpg.cli import build_parser, main
from cvqpg.deprecations import MOVED_MODULES
from cvqpg.errors import InputError

DATA = Path(__file__).parent / "data"


@pytest.mark.parametrize("command", ["fit", "encode", "bench"])
def test_the_former_warmup_option_works_and_names_its_new_name(capsys, command):
    args = build_parser().parse_args([command, "--warmup", "7"])
    assert args.curvature_warmup == 7
    err = capsys.readouterr().err
    assert "--warmup is deprecated" in err and "use --curvature-warmup" in err


def test_the_former_warmup_command_compiles_and_names_compile(capsys, monkeypatch):
    monkeypatch.setattr("cvqpg.app.compilation.compile_all", lambda: 0.0)
    assert main(["warmup"]) == 0
    captured = capsys.readouterr()
    assert "cvqpg warmup is deprecated" in captured.err and "use cvqpg compile" in captured.err
    assert captured.out.startswith("cvqpg compile: CPU kernels compiled")
    assert "warmup" not in build_parser().format_help()


@pytest.mark.parametrize(("old", "new"), sorted(MOVED_MODULES.items()))
def test_a_moved_module_imports_at_its_former_path_with_a_warning(monkeypatch, old, new):
    monkeypatch.delitem(sys.modules, old, raising=False)
    with pytest.warns(DeprecationWarning, match=f"`{old}` moved to `{new}`"):
        module = importlib.import_module(old)
    assert module is importlib.import_module(new) and module.__spec__.name == new


def test_a_moved_function_reads_at_its_former_place_with_a_warning():
    import cvqpg.optics
    from cvqpg.ops.propagation import transfer_function

    with pytest.warns(DeprecationWarning, match="cvqpg.ops.propagation.transfer_function"):
        assert cvqpg.optics.transfer_function is transfer_function
    with pytest.raises(AttributeError):
        cvqpg.optics.never_existed


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
