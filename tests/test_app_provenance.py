"""A run record names cvqpg's version, and a commit only where the package is cvqpg's own checkout."""

from __future__ import annotations

import torch

from cvqpg import __version__
from cvqpg.app.provenance import PACKAGE_ROOT, code_commit, is_own_checkout, machine_record


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
