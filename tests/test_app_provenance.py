"""A run record names cvqpg's version, and a commit only where the package is cvqpg's own checkout."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
import torch

from cvqpg import __version__
from cvqpg.app import provenance
from cvqpg.app.provenance import PACKAGE_ROOT, code_commit, is_own_checkout, machine_record


@pytest.fixture(autouse=True)
def fresh_commit_cache():
    provenance.code_commit.cache_clear()
    yield
    provenance.code_commit.cache_clear()


def test_a_users_git_project_around_an_installed_package_is_not_our_checkout(tmp_path):
    project = tmp_path / "their-project"
    package = project / "venv" / "lib" / "site-packages" / "cvqpg"
    package.mkdir(parents=True)
    (project / "pyproject.toml").write_text('[project]\nname = "their-project"\n')
    assert not is_own_checkout(project, package)
    (project / "pyproject.toml").write_text('[project]\nname = "cvqpg"\n')
    assert not is_own_checkout(project, package)  # named cvqpg, but the package is not at its top


def test_our_checkout_is_recognised(tmp_path):
    package = tmp_path / "cvqpg"
    package.mkdir()
    (tmp_path / "pyproject.toml").write_text('[build-system]\n\n[project]\nname = "cvqpg"\ndynamic = ["version"]\n')
    assert is_own_checkout(tmp_path, package)
    (tmp_path / "pyproject.toml").unlink()
    assert not is_own_checkout(tmp_path, package)


def test_the_record_holds_the_version_and_this_checkouts_commit():
    record = machine_record(torch.device("cpu"))
    assert record["cvqpg_version"] == __version__
    assert is_own_checkout(PACKAGE_ROOT.parent)  # the tests run from the repository
    if (PACKAGE_ROOT.parent / ".git").exists():
        assert record["commit"] == code_commit() and len(record["commit"].split("+")[0]) == 40
    else:  # an unpacked sdist: a checkout's layout without git
        assert record["commit"] is None


def git(folder: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(folder), "-c", "user.name=test", "-c", "user.email=test@example.org",
                           *args], capture_output=True, text=True, check=True).stdout.strip()


def commit_now() -> str | None:
    provenance.code_commit.cache_clear()  # asked once per process otherwise
    return provenance.code_commit()


def test_the_commit_is_head_dirty_after_changes_to_the_package_and_none_outside_git(tmp_path, monkeypatch):
    package = tmp_path / "checkout" / "cvqpg"
    package.mkdir(parents=True)
    (package / "code.py").write_text("one = 1\n")
    (package.parent / "pyproject.toml").write_text('[project]\nname = "cvqpg"\n')
    (package.parent / "README.md").write_text("notes\n")
    git(package.parent, "init", "--quiet")
    git(package.parent, "add", ".")
    git(package.parent, "commit", "--quiet", "-m", "first")
    head = git(package.parent, "rev-parse", "HEAD")
    monkeypatch.setattr(provenance, "PACKAGE_ROOT", package)
    assert re.fullmatch(r"[0-9a-f]{40}", head) and commit_now() == head
    (package.parent / "README.md").write_text("other notes\n")  # outside the package
    (package / "new.py").write_text("")  # untracked
    assert commit_now() == head
    (package / "code.py").write_text("one = 2\n")
    assert commit_now() == f"{head}+dirty"
    monkeypatch.setattr(provenance, "PACKAGE_ROOT", tmp_path / "installed" / "cvqpg")  # a wheel's: no git
    provenance.PACKAGE_ROOT.mkdir(parents=True)
    assert commit_now() is None


@pytest.mark.parametrize("asked, expected", [("1", 1), ("", None), ("0", None), ("many", None), ("999999", None)])
def test_the_cores_a_run_uses_are_its_affinity_capped_by_omp_num_threads(monkeypatch, asked, expected):
    """A bench run's threads (`--jobs 1`) follow OMP_NUM_THREADS where the user set it; otherwise the affinity."""
    monkeypatch.setattr(provenance.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", asked)
    assert provenance.available_cores() == (4 if expected is None else expected)
