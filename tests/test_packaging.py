"""Packaging: cvqpg's declared requirements leave a user's own (supported) torch in place."""

import json
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

import cvqpg
from cvqpg.cli import main

tomllib = pytest.importorskip("tomllib")  # Python ≥ 3.11

REPO = Path(cvqpg.__file__).resolve().parent.parent
OTHER_TORCH = "2.5.0"  # supported, and not the version constraints.txt pins


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


def resolve(python: Path, requirements: list[str]) -> subprocess.CompletedProcess:
    """pip's resolution of `requirements` in `python`'s environment, from what is installed only."""
    return subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--dry-run", "--no-index",
                           "--quiet", "--report", "-", *requirements], capture_output=True, text=True, timeout=300)


def test_installing_beside_another_supported_torch_keeps_that_torch(tmp_path):
    python = environment_with_torch(tmp_path / "env", OTHER_TORCH)
    requirements = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    kept = resolve(python, requirements)
    assert kept.returncode == 0, kept.stderr
    assert json.loads(kept.stdout)["install"] == []  # nothing replaced, torch included
    # The former pin, by contrast, replaces it (or fails where no torch 2.13.0 is at hand without an index).
    pinned = resolve(python, ["torch==2.13.0"])
    assert pinned.returncode != 0 or [item["metadata"]["name"] for item in json.loads(pinned.stdout)["install"]] == ["torch"]


def test_version_is_the_package_version(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out == f"cvqpg {cvqpg.__version__}\n"
    assert tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["dynamic"]["version"] == {
        "attr": "cvqpg.__version__"}
