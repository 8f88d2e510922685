"""Errors of the machine, not of the input: a refused write exits 3 and an allocation that fails exits 4, each in one
line that names the path or the need, and leaves no half-written output."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest
import torch

from cvqpg.cli import main

DATA = Path(__file__).parent / "data"
TINY_FIT = ["fit", "--size", "32", "24", "--num-gaussians", "20", "--steps", "2", "--quiet"]


def one_line(capsys) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in captured.err and "bug" not in captured.err, captured.err
    return lines[0]


@pytest.mark.parametrize(("code", "words"), [(errno.ENOSPC, "no space left"), (errno.EDQUOT, "quota"),
                                             (errno.EACCES, "permission denied"), (errno.EPERM, "not permitted"),
                                             (errno.EROFS, "read-only")])
def test_a_refused_write_names_the_file_and_exits_3(tmp_path, capsys, monkeypatch, code, words):
    def refuse(_descriptor: int) -> None:  # as a full disk fails the flush to disk: the error names no file
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr("os.fsync", refuse)
    out = tmp_path / "model.safetensors"
    assert main(["decompress", str(DATA / "format_v3.cvq"), "--out", str(out)]) == 3
    line = one_line(capsys)
    assert line.startswith(f"cvqpg decompress: error: {out}: ") and words in line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("error", [
    RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: you tried "
                 "to allocate 1073741824 bytes. Error code 12 (Cannot allocate memory)"),
    torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 1.00 GiB. GPU 0 has a total capacity of ..."),
    MemoryError("Unable to allocate 1.00 GiB for an array with shape (268435456,) and data type float32")])
def test_a_failed_allocation_says_what_was_needed_and_exits_4(tmp_path, capsys, monkeypatch, error):
    def fit_in_folder(*_args: object, **_kwargs: object) -> None:
        raise error

    monkeypatch.setattr("cvqpg.app.runner.fit_in_folder", fit_in_folder)
    out = tmp_path / "run"
    assert main([*TINY_FIT, "--out", str(out)]) == 4
    line = one_line(capsys)
    assert line.startswith("cvqpg fit: error: out of memory") and "1.00 GiB" in line and "--size" in line
    assert list(tmp_path.iterdir()) == []


def test_a_fit_whose_disk_fills_leaves_no_run_behind(tmp_path, capsys, monkeypatch):
    def fit_in_folder(work: Path, *_args: object, **_kwargs: object) -> None:
        (work / "model.safetensors").write_bytes(b"half")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(work / "model.safetensors"))

    monkeypatch.setattr("cvqpg.app.runner.fit_in_folder", fit_in_folder)
    out = tmp_path / "runs" / "demo"
    assert main([*TINY_FIT, "--out", str(out)]) == 3
    assert "model.safetensors: no space left on the device" in one_line(capsys)
    assert list(tmp_path.iterdir()) == []


def test_a_bug_is_still_a_bug(tmp_path, capsys, monkeypatch):
    """An OSError that is no refusal of the file system (here, a missing file) stays exit 1."""
    def fit_in_folder(*_args: object, **_kwargs: object) -> None:
        raise OSError(errno.ENOENT, os.strerror(errno.ENOENT), "somewhere")

    monkeypatch.setattr("cvqpg.app.runner.fit_in_folder", fit_in_folder)
    assert main([*TINY_FIT, "--out", str(tmp_path / "run")]) == 1
    assert "this is a bug in cvqpg" in capsys.readouterr().err
