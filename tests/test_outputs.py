"""The one rule for outputs (`cvqpg.app.outputs`): what `overwrite` may replace, what it never may, and one writer
at a time."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from cvqpg.app.outputs import (BENCH, CVQ, DOCUMENT, EXPORT, MODEL, PAGE, RENDER, RUN, check_continued, check_output,
                               claimed, claimed_in_run, output, staged_output)
from cvqpg.codec import MAGIC
from cvqpg.errors import InputError
from cvqpg.files import replace_folder, staged_folder

IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


@pytest.fixture
def place(tmp_path, monkeypatch) -> Path:
    """A folder with a run, a render folder, a page, a .cvq file and a user's folder and file; the current folder."""
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.json").write_text("{}")
    (tmp_path / "run" / "target_plane0.png").write_bytes(b"\x89PNG\r\n\x1a\nrest")
    (tmp_path / "render").mkdir()
    for name in ("amplitude.png", "phase.png", "recon_1mm.png"):
        (tmp_path / "render" / name).write_bytes(b"\x89PNG\r\n\x1a\n")
    (tmp_path / "page.html").write_text("<!DOCTYPE html><title>a page</title>")
    (tmp_path / "model.cvq").write_bytes(MAGIC + b"rest")
    (tmp_path / "user").mkdir()
    (tmp_path / "user" / "thesis.tex").write_text("years of work")
    (tmp_path / "notes.txt").write_text("a user's file")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def snapshot(root: Path) -> dict[str, bytes | None]:
    return {p.relative_to(root).as_posix(): (p.read_bytes() if p.is_file() and not p.is_symlink() else None)
            for p in sorted(root.rglob("*"))}


@pytest.mark.parametrize("path, kind", [("render", RENDER), ("page.html", PAGE), ("model.cvq", CVQ), ("run", RUN)])
def test_overwrite_accepts_an_output_of_the_commands_own_kind(place, path, kind):
    assert check_output(path, kind, overwrite=True) == Path(path)
    with pytest.raises(InputError, match="exists; .*`overwrite`"):
        check_output(path, kind)


@pytest.mark.parametrize("path, kind, message", [
    ("user", RENDER, "is not a render folder"),
    ("user", EXPORT, "is not an export folder"),
    ("user", RUN, "is not a run folder"),
    ("notes.txt", CVQ, r"is not a compressed model \(.cvq\) file"),
    ("notes.txt", PAGE, "is not an HTML page"),
    ("notes.txt", DOCUMENT, "is not a Markdown"),
    ("model.cvq", MODEL, "is not a safetensors model file"),
    ("page.html", CVQ, "is not a compressed model"),
    ("run", RENDER, "is a run folder"),
    ("run/target_plane0.png", PAGE, "the run's own target_plane0.png"),
    ("run/config.json", DOCUMENT, "the run's own config.json"),
    ("render", PAGE, "is a folder"),
    ("notes.txt", RENDER, "is a file"),
    (".", RENDER, "the current folder"),
    ("..", RENDER, "the current folder"),
    ("user/..", RUN, "the current folder"),
])
def test_overwrite_never_replaces_what_is_not_the_commands_kind(place, path, kind, message):
    before = snapshot(place)
    with pytest.raises(InputError, match=message):
        check_output(path, kind, overwrite=True)
    assert snapshot(place) == before


def test_an_empty_file_or_folder_counts_as_any_kind(place):
    (place / "empty.txt").write_bytes(b"")
    (place / "hollow").mkdir()
    assert check_output("empty.txt", CVQ, overwrite=True) == Path("empty.txt")
    assert check_output("hollow", RENDER) == Path("hollow")


def test_a_render_folder_that_holds_a_folder_is_not_replaced(place):
    (place / "render" / "kept").mkdir()
    with pytest.raises(InputError, match="holds a folder \\(kept\\)"):
        check_output("render", RENDER, overwrite=True)


@pytest.mark.parametrize("target", ["user", "render", "page.html", "elsewhere"])
def test_a_symbolic_link_is_refused_wherever_it_points(place, target):
    (place / "link").symlink_to(place / target)
    kind = PAGE if target == "page.html" else RENDER
    with pytest.raises(InputError, match="is a symbolic link"):
        check_output("link", kind, overwrite=True)


def test_an_input_and_a_folder_that_holds_it_are_refused(place):
    with pytest.raises(InputError, match="own input"):
        check_output("model.cvq", CVQ, [Path("model.cvq")], overwrite=True)
    with pytest.raises(InputError, match="holds this command's input"):
        check_output("render", RENDER, [Path("render/phase.png")], overwrite=True)


def test_a_bench_folder_is_continued_and_a_users_folder_is_not(place):
    (place / "bench" / "cells").mkdir(parents=True)
    assert check_continued("bench", BENCH) == Path("bench")
    assert check_continued("new/deeper", BENCH) == Path("new/deeper")
    for path, message in (("user", "a folder of other files"), ("run", "a run folder"), ("notes.txt", "a file")):
        with pytest.raises(InputError, match=message):
            check_continued(path, BENCH)


@pytest.mark.skipif(IS_ROOT, reason="running as root: file permissions do not apply")
def test_an_unwritable_place_is_refused(place):
    (place / "locked").mkdir()
    (place / "locked").chmod(0o555)
    try:
        with pytest.raises(InputError, match="not writable"):
            check_output("locked/out.cvq", CVQ)
    finally:
        (place / "locked").chmod(0o755)


def test_a_second_claim_of_one_output_is_refused_and_the_lock_goes_with_the_first(place):
    with claimed(place / "out.cvq"):
        with pytest.raises(InputError, match="being written by another cvqpg command"):
            with claimed(place / "out.cvq"):
                pass
        assert (place / ".out.cvq.cvqpg-lock").exists()
    assert not (place / ".out.cvq.cvqpg-lock").exists()
    with claimed(place / "out.cvq"):  # free again
        pass


def test_shared_claims_of_a_run_coexist_and_keep_out_an_exclusive_one(place):
    run, lock = place / "run", place / ".run.cvqpg-lock"
    with claimed(run, shared=True), claimed(run, shared=True):
        with pytest.raises(InputError, match="being written by another cvqpg command"):
            with claimed(run):
                pass
        assert lock.exists()
    assert not lock.exists(), "the last shared holder removes the lock file"
    with claimed(run):
        with pytest.raises(InputError, match="being written by another cvqpg command"):
            with claimed(run, shared=True):
                pass


def test_an_output_inside_a_run_holds_the_run_while_a_fit_holds_it_exclusively(place):
    with claimed(place / "run"):  # a fit resuming or replacing the run
        for path in ("run/metrics.json", "run/export/metrics.json"):
            with pytest.raises(InputError, match=r"its run folder .*run is being written by another cvqpg command"):
                with claimed_in_run(place / path):
                    pass
        with pytest.raises(InputError, match="its run folder"):
            with output("run/model.cvq", CVQ):
                pass
    with claimed_in_run("run/metrics.json"), output("run/model.cvq", CVQ):  # two writers into one run at once
        with pytest.raises(InputError, match="being written by another cvqpg command"):
            with claimed(place / "run"):
                pass
        with pytest.raises(InputError, match="run/metrics.json is being written by another cvqpg command"):
            with claimed_in_run("run/metrics.json"):
                pass
    assert not list(place.rglob("*.cvqpg-lock"))


def test_another_process_holding_the_claim_refuses_this_one(place):
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from cvqpg.app.outputs import claimed\n"
        "with claimed(sys.argv[1]):\n    print('held', flush=True); time.sleep(30)\n"), str(place / "out.cvq")],
        stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])})
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(InputError, match="being written by another cvqpg command"):
            with output(place / "out.cvq", CVQ):
                pass
    finally:
        holder.kill()
        holder.wait()
    with output(place / "out.cvq", CVQ):  # a killed holder holds nothing
        pass


def test_a_failed_claim_removes_the_folders_it_made(place):
    with pytest.raises(RuntimeError):
        with claimed(place / "a" / "b" / "run"):
            assert (place / "a" / "b").is_dir()
            raise RuntimeError("the command failed")
    assert not (place / "a").exists()
    with claimed(place / "a" / "b" / "run"):
        (place / "a" / "b" / "run").mkdir()
    assert (place / "a" / "b" / "run").is_dir()


def test_a_staged_output_replaces_its_own_kind_as_a_whole(place):
    (place / "render" / "stray.txt").write_text("left by an earlier run")
    with staged_output("render", RENDER, overwrite=True) as staged:
        (staged / "amplitude.png").write_bytes(b"new")
    assert sorted(p.name for p in (place / "render").iterdir()) == ["amplitude.png"]
    assert not [p for p in place.iterdir() if p.name.startswith(".")]


def test_replace_folder_never_replaces_a_file_or_a_link(place):
    for name, make in (("file", lambda p: p.write_text("user")), ("link", lambda p: p.symlink_to(place / "user"))):
        staged = place / f".{name}.partial"
        staged.mkdir()
        make(place / name)
        before = snapshot(place)
        with pytest.raises(InputError, match="appeared while the command ran"):
            replace_folder(staged, place / name)
        assert snapshot(place) == before


def test_a_staged_folder_leaves_what_appeared_meanwhile(place):
    with pytest.raises(InputError, match="appeared while the command ran"):
        with staged_folder(place / "later") as staged:
            (staged / "a.png").write_bytes(b"new")
            (place / "later").mkdir()
            (place / "later" / "mine.txt").write_text("the user's")
    assert [p.name for p in (place / "later").iterdir()] == ["mine.txt"]
    assert not [p for p in place.iterdir() if p.name.startswith(".later")]
