"""Hostile outputs and resumes, in the shape of `test_hostile.py`'s table (and on its template, with a few more
assets): `--overwrite` that would replace what the command did not make, symbolic links as outputs, the current
folder as an output, resumes whose place is taken, a float16 copy of a run that cannot be scored, and two commands
writing one output. Every refusal is exit code 2, one line, and the tree left exactly as it was."""

from __future__ import annotations

import json
import os
import shlex
import shutil
from pathlib import Path
from typing import NamedTuple

import pytest

from cvqpg.app.outputs import claimed
from test_hostile import (BENCH, ENCODE, PLACES, SWEEP, Case, cases, cli, template,  # noqa: F401 (a fixture)
                          tree_changes, tree_state)

pytestmark = pytest.mark.slow

FIT = "--size 32 24 --num-gaussians 20 --steps 2 --quiet"

# Assets beyond the template's, made by `outputs_template`.
MORE = {
    "held": "held",                  # a user's folder, and held.partial an interrupted run that would finish there
    "filed": "filed",                # a user's file, and filed.partial an interrupted run that would finish there
    "linked": "linked",              # a link to the user's folder notarun, and linked.partial an interrupted run
    "encoded": "enc.cvq.partial",    # an interrupted encode's folder
    "foreigncvq": "foreign.cvq",     # a user's text file named .cvq, and foreign.cvq.partial an interrupted encode
    "lost": "lost",                  # a copy of run_a whose image is gone
    "linkdir": "linkdir",            # -> notarun
    "linkrender": "linkrender",      # -> run_a/render
    "linkrun": "linkrun",            # -> run_b
    "linkcvq": "linkcvq.cvq",        # -> run_a/model.cvq
    "linkpage": "linkpage.html",     # -> page.html
    "dangling": "dangling.safetensors",  # -> nowhere
}

ROWS = cases(
    "outputs",
    # --overwrite replaces only the command's own kind of output.
    ("render-overwrite-a-users-folder", "render {run} --out {notarun} --overwrite", "notarun"),
    ("render-overwrite-another-run", "render {run} --out {run2} --overwrite", "run_b"),
    ("render-overwrite-an-export-folder", "render {run} --out {run}/export --overwrite", "export"),
    ("export-overwrite-a-users-folder", "export {run} --out {notarun} --overwrite", "notarun"),
    ("export-overwrite-another-run", "export {run} --out {run2} --overwrite", "run_b"),
    ("export-overwrite-a-render-folder", "export {run} --out {run}/render --overwrite", "render"),
    ("fit-overwrite-a-users-folder", f"fit {FIT} --out {{notarun}} --overwrite", "notarun"),
    ("view-overwrite-a-runs-target", f"view {{run}} --quiet {SWEEP} --out {{run2}}/target_plane0.png --overwrite",
     "target_plane0.png"),
    ("view-overwrite-a-runs-curve", f"view {{run}} --quiet {SWEEP} --out {{run}}/curve.png --overwrite", "curve.png"),
    ("view-overwrite-a-users-file", f"view {{run}} --quiet {SWEEP} --out {{text}} --overwrite", "notes.txt"),
    ("compress-overwrite-a-runs-target", "compress {run} --bits 8 --out {run}/target_plane0.png --overwrite",
     "target_plane0.png"),
    ("compress-overwrite-a-users-file", "compress {run} --bits 8 --out {text} --overwrite", "notes.txt"),
    ("compress-overwrite-an-image", "compress {run} --bits 8 --out {image} --overwrite", "photo.png"),
    ("compress-overwrite-a-page", "compress {run} --bits 8 --out {page} --overwrite", "page.html"),
    ("decompress-overwrite-a-users-file", "decompress {cvq} --out {text} --overwrite", "notes.txt"),
    ("decompress-overwrite-a-runs-recon", "decompress {cvq} --out {run2}/recon_plane0.png --overwrite",
     "recon_plane0.png"),
    ("encode-overwrite-a-users-file", f"{ENCODE} --bpp 8 --out {{text}} --overwrite", "notes.txt"),
    ("results-overwrite-a-users-file", "results --root {records} --out {text} --overwrite", "notes.txt"),
    ("results-overwrite-a-page", "results --root {records} --out {page} --overwrite", "page.html"),
    ("bench-out-a-users-folder", f"bench {BENCH} --out {{notarun}}", "notarun"),
    # A symbolic link is never followed to a place the user did not name.
    ("render-out-a-link-to-a-users-folder", "render {run} --out {linkdir} --overwrite", "linkdir"),
    ("render-out-a-link-to-a-render-folder", "render {run} --out {linkrender} --overwrite", "linkrender"),
    ("export-out-a-link-to-a-users-folder", "export {run} --out {linkdir} --overwrite", "linkdir"),
    ("fit-out-a-link-to-a-run", f"fit {FIT} --out {{linkrun}} --overwrite", "linkrun"),
    ("compress-out-a-link-to-a-cvq", "compress {run} --bits 8 --out {linkcvq} --overwrite", "linkcvq.cvq"),
    ("view-out-a-link-to-a-page", f"view {{run}} --quiet {SWEEP} --out {{linkpage}} --overwrite", "linkpage.html"),
    ("decompress-out-a-dangling-link", "decompress {cvq} --out {dangling}", "dangling.safetensors"),
    ("bench-out-a-link", f"bench {BENCH} --out {{linkdir}}", "linkdir"),
    # The current folder, or one that holds it, is no output.
    ("render-out-the-current-folder", "render {run} --out . --overwrite", "current folder"),
    ("export-out-a-folder-holding-the-current-one", "export {run} --out {run}/.. --overwrite", "current folder"),
    ("fit-out-the-current-folder", f"fit {FIT} --out . --overwrite", "current folder"),
    # A resume whose place is taken stops, naming it, and keeps the interrupted folder.
    ("fit-resume-into-a-users-folder", "fit --resume {held}.partial --quiet", "held"),
    ("fit-resume-into-a-users-folder-with-overwrite", "fit --resume {held}.partial --quiet --overwrite", "held"),
    ("fit-resume-into-a-file", "fit --resume {filed}.partial --quiet --overwrite", "filed"),
    ("fit-resume-into-a-link", "fit --resume {linked}.partial --quiet --overwrite", "linked"),
    ("fit-resume-an-encode", "fit --resume {encoded} --quiet", "encode"),
    ("encode-resume-into-a-users-file", "encode --resume {foreigncvq}.partial --quiet --overwrite", "foreign.cvq"),
    # A failure writes nothing.
    ("info-half-of-a-run-whose-image-is-gone", "info {lost} --half", "lost_photo.png"),
)

PLACES_HERE = {**PLACES, **MORE}


@pytest.fixture(scope="module")
def outputs_template(template, tmp_path_factory) -> Path:
    """`test_hostile`'s template with the assets of `MORE`."""
    t = tmp_path_factory.mktemp("hostile_outputs") / "template"
    shutil.copytree(template.folder, t, symlinks=True)
    (t / "held").mkdir()
    (t / "held" / "thesis.tex").write_text("years of work\n")
    (t / "filed").write_text("a user's file\n")
    for name in ("held", "filed", "linked"):
        (t / f"{name}.partial").mkdir()
        shutil.copy(t / "unfinished" / "config.json", t / f"{name}.partial" / "config.json")
    (t / "linked").symlink_to("notarun")
    for name in ("enc.cvq.partial", "foreign.cvq.partial"):
        (t / name).mkdir()
        shutil.copy(t / "unfinished" / "config.json", t / name / "config.json")
        (t / name / "budget.json").write_text(json.dumps({"max_bytes": 900, "given": "--bpp 8",
                                                           "finetune_steps": 1}))
    (t / "foreign.cvq").write_text("a user's notes, named .cvq\n")
    shutil.copytree(t / "run_a", t / "lost")
    for extra in ("model.f16.safetensors", "model.cvq", "bad.cvq"):
        (t / "lost" / extra).unlink()
    record = json.loads((t / "lost" / "config.json").read_text())
    record["source"] = {"image": "/nonexistent-cvqpg/lost_photo.png"}
    (t / "lost" / "config.json").write_text(json.dumps(record))
    for link, target in (("linkdir", "notarun"), ("linkrender", "run_a/render"), ("linkrun", "run_b"),
                         ("linkcvq.cvq", "run_a/model.cvq"), ("linkpage.html", "page.html"),
                         ("dangling.safetensors", "nowhere/model.safetensors")):
        (t / link).symlink_to(target)
    return t


@pytest.fixture
def work(outputs_template, tmp_path, monkeypatch) -> Path:
    """A private copy of the template, the current folder; no GPU visible, no traceback requested."""
    folder = tmp_path / "w"
    shutil.copytree(outputs_template, folder, symlinks=True)
    monkeypatch.chdir(folder)
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    monkeypatch.delenv("CVQPG_TRACEBACK", raising=False)
    return folder


def expand_here(argv: str, work: Path) -> list[str]:
    return [token.format(tmp=work, **PLACES_HERE) for token in shlex.split(argv)]


def run_case(argv: list[str], tmp_path: Path, capsys, fragment: str = "") -> list[str]:
    """The problems of a refusal: not exit 2, not one line naming the command and `fragment`, or the tree
    changed."""
    before = tree_state(tmp_path)
    code, _out, err = cli(argv, capsys)
    changes = tree_changes(before, tree_state(tmp_path))
    lines = err.splitlines()
    problems = [] if code == 2 else [f"exit code {code}, not 2"]
    if len(lines) != 1 or not lines[0].startswith(f"cvqpg {argv[0]}: error: "):
        problems.append(f"{len(lines)} lines on stderr, not one 'cvqpg {argv[0]}: error: ...'")
    if fragment not in err:
        problems.append(f"{fragment!r} not named")
    if changes:
        problems.append("the tree changed: " + ", ".join(changes[:6]))
    return problems + [f"stderr: {err.strip()[-600:]}"] * bool(problems)


def test_the_rows_cover_every_writing_command():
    commands = {case.values[0].argv.split()[0] for case in ROWS}
    assert commands == {"fit", "export", "info", "render", "view", "compress", "decompress", "encode", "bench",
                        "results"}


@pytest.mark.parametrize("case", ROWS)
def test_a_hostile_output_is_refused_in_one_line_and_changes_nothing(case: Case, work, tmp_path, capsys):
    problems = run_case(expand_here(case.argv, work), tmp_path, capsys, case.fragment)
    assert not problems, "; ".join(problems)


class Success(NamedTuple):
    argv: str
    replaced: str  # the one path that may change; everything else stays byte for byte


SUCCESSES = {
    "view-overwrite-replaces-its-page": Success(f"view {{run}} --quiet {SWEEP} --out {{page}} --overwrite",
                                                "page.html"),
    "render-into-an-empty-folder": Success("render {run} --out {folder}", "folder"),
}


@pytest.mark.parametrize("name", list(SUCCESSES))
def test_a_permitted_overwrite_replaces_that_output_and_nothing_else(name, work, tmp_path, capsys):
    success = SUCCESSES[name]
    before = tree_state(tmp_path)
    code, _out, err = cli(expand_here(success.argv, work), capsys)
    assert code == 0, err
    after = tree_state(tmp_path)
    replaced = f"w/{success.replaced}"

    def outside(state):
        return {p: v for p, v in state.items() if p != replaced and not p.startswith(replaced + "/")}

    assert tree_changes(outside(before), outside(after)) == []
    assert after[replaced] != before[replaced] or any(p.startswith(replaced + "/") for p in after)


@pytest.mark.parametrize("argv, output", [
    ("compress {run} --bits 6 --overwrite", "run_a/model.cvq"),
    ("render {run} --overwrite", "run_a/render"),
    ("decompress {cvq} --overwrite", "run_a/model.decoded.safetensors"),
    (f"fit {FIT} --out {{run}} --overwrite", "run_a"),
    (f"view {{run}} --quiet {SWEEP} --out {{page}} --overwrite", "page.html"),
])
def test_a_second_writer_of_one_output_is_refused_in_one_line(argv, output, work, tmp_path, capsys):
    """Another command holds the output (its lock, as `claimed` takes it): this one stops, and changes nothing."""
    with claimed(work / output):
        problems = run_case(expand_here(argv, work), tmp_path, capsys, "being written by another cvqpg command")
    assert not problems, "; ".join(problems)
    assert not list(work.rglob("*.cvqpg-lock"))


def test_the_resumes_refused_keep_their_interrupted_folders(work, capsys):
    for name in ("held", "filed"):
        code, _out, err = cli(["fit", "--resume", f"{name}.partial", "--quiet", "--overwrite"], capsys)
        assert code == 2 and name in err
        assert (work / f"{name}.partial" / "config.json").is_file()
    assert (work / "held" / "thesis.tex").read_text() == "years of work\n"
    assert (work / "filed").read_text() == "a user's file\n"
    assert not [p for p in os.listdir(work) if ".replaced-" in p]
