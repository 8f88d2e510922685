"""Packaging: the requirements leave a user's own (supported) torch in place; the version is the changelog's."""

import json
import os
import re
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

import cvqpg
from cvqpg.cli import main

tomllib = pytest.importorskip("tomllib")  # Python ≥ 3.11

REPO = Path(cvqpg.__file__).resolve().parent.parent
OTHER_TORCH = "2.5.0"  # supported, and not the version constraints.txt pins
NEWER_TORCH = "2.13.0"  # what the former pin asked for


def environment_with_torch(root: Path, version: str) -> Path:
    """A venv whose own torch is `version` (its metadata only: pip decides from metadata alone) and
    which sees the running environment's other packages after its own."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root)], check=True)
    python = root / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    info = site / f"torch-{version}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: torch\nVersion: {version}\n")
    (info / "RECORD").write_text("")
    (site / "parent.pth").write_text("\n".join({sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}))
    return python


def torch_wheel(folder: Path, version: str) -> Path:
    """A wheel of torch `version` holding its metadata only (pip resolves from metadata), in `folder`:
    what an index offers, without a network."""
    folder.mkdir()
    info = f"torch-{version}.dist-info"
    with zipfile.ZipFile(folder / f"torch-{version}-py3-none-any.whl", "w") as wheel:
        wheel.writestr(f"{info}/METADATA", f"Metadata-Version: 2.1\nName: torch\nVersion: {version}\n")
        wheel.writestr(f"{info}/WHEEL", "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n")
        wheel.writestr(f"{info}/RECORD", "")
    return folder


def resolve(python: Path, requirements: list[str], links: Path) -> list[tuple[str, str]]:
    """What pip would install for `requirements` into `python`'s environment, offered only what is
    installed and the wheels in `links`: (name, version) pairs. The machine's pip configuration
    (its files and PIP_* variables: a find-links folder, an index) is left out."""
    environment = {name: value for name, value in os.environ.items() if not name.startswith("PIP_")}
    done = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--dry-run", "--no-index",
                           "--find-links", str(links), "--quiet", "--report", "-", *requirements],
                          capture_output=True, text=True, timeout=300,
                          env={**environment, "PIP_CONFIG_FILE": os.devnull, "PIP_DISABLE_PIP_VERSION_CHECK": "1"})
    assert done.returncode == 0, done.stderr
    return [(item["metadata"]["name"], item["metadata"]["version"]) for item in json.loads(done.stdout)["install"]]


@pytest.mark.slow
def test_installing_beside_another_supported_torch_keeps_that_torch(tmp_path):
    python = environment_with_torch(tmp_path / "env", OTHER_TORCH)
    links = torch_wheel(tmp_path / "links", NEWER_TORCH)  # a newer torch on offer, as on PyPI
    requirements = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    assert resolve(python, requirements, links) == []  # nothing replaced, torch included
    # The former pin, by contrast, replaces the user's torch with the one on offer.
    assert resolve(python, [f"torch=={NEWER_TORCH}"], links) == [("torch", NEWER_TORCH)]


def test_version_is_the_package_version(capsys):
    assert main(["--version"]) == 0 and capsys.readouterr().out == f"cvqpg {cvqpg.__version__}\n"
    assert tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["dynamic"]["version"] == {
        "attr": "cvqpg.__version__"}


def test_the_changelog_s_newest_release_is_the_package_version():
    # a release's heading is `## [X.Y.Z] - date`; the one in the making, `## X.Y.Z (unreleased)`
    releases = re.findall(r"^## \[?(\d+\.\d+\.\d+)[\] ]", (REPO / "CHANGELOG.md").read_text(), re.MULTILINE)
    assert releases and releases[0] == cvqpg.__version__
