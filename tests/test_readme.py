"""The README's shell blocks, in a fresh shell, and the Python snippets of the README and the Python API guide run as
written, at a smaller size and fewer steps."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
PAGES = (ROOT / "README.md", ROOT / "docs" / "python.md")
# What makes a snippet a test: the same calls, on a grid and step count that finish in seconds. Each
# snippet must set its size and steps where a replacement finds them (`shrunk`).
SHRINK = {"width=320, height=240": "width=48, height=36", "steps=300": "steps=4",
          'builtin_pictures("demo", 320, 240)': 'builtin_pictures("demo", 48, 36)'}


def python_snippets() -> list[tuple[str, str]]:
    return [(f"{page.name} snippet {number}", code) for page in PAGES
            for number, code in enumerate(re.findall(r"```python\n(.*?)```", page.read_text(), re.DOTALL), 1)]


def shrunk(code: str) -> str:
    """`code` at the test's size. A snippet whose sizes or step count no replacement matched fails here, rather
    than running at its full size."""
    for original, small in SHRINK.items():
        code = code.replace(original, small)
    numbers = re.findall(r"(?:width|height|steps)=(\d+)|builtin_pictures\([^)]*?(\d+), (\d+)\)", code)
    assert numbers and all(int(n) < 100 for group in numbers for n in group if n), \
        "a size or step count of the snippet is not shrunk: update SHRINK"
    return code


@pytest.mark.parametrize("name, code", python_snippets(), ids=[name for name, _ in python_snippets()])
def test_python_snippet_runs(name, code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(shrunk(code), name, "exec"), namespace)
    assert namespace["result"].metrics.mean["psnr"] > 0


def test_each_page_has_a_python_snippet():
    assert sorted({name.split()[0] for name, _ in python_snippets()}) == sorted(page.name for page in PAGES)


# The README's shell blocks at the test's size. The install is the environment the tests run in (`.venv` links
# to it), and the test command collects one module instead of running the suite.
SHELL_SHRINK = {"scripts/install.sh && ": "",
                "--size 320 240 --steps 300": "--size 32 24 --steps 2",
                "--out runs/photo": "--size 64 48 --steps 2 --out runs/photo",
                "-m pytest -q": f"-m pytest -q --collect-only -p no:cacheprovider {ROOT / 'tests' / 'test_errors.py'}"}


def shell_blocks() -> list[str]:
    return re.findall(r"```bash\n(.*?)```", (ROOT / "README.md").read_text(), re.DOTALL)


def shrunk_shell(block: str) -> str:
    """`block` at the test's size; a block with a size, a step count or an install left fails here."""
    for original, small in SHELL_SHRINK.items():
        block = block.replace(original, small)
    assert "install.sh" not in block and all(int(n) < 100 for n in re.findall(r"--(?:size \d+|steps) (\d+)",
                                                                              block)), block
    return block


@pytest.mark.slow
def test_the_readme_s_shell_blocks_run_as_written_in_a_fresh_shell(tmp_path):
    """Each block in its own fresh shell (no variable but a minimal PATH, a HOME of its own, the checkout under
    test on PYTHONPATH and where the kernels are compiled), in a folder like a checkout's, in order: the first
    hologram, the three commands on a photo of one's own, the tests."""
    assert len(shell_blocks()) >= 3
    (tmp_path / ".venv").symlink_to(sys.prefix)
    (tmp_path / "home").mkdir()
    y, x = np.mgrid[0:48, 0:64]
    Image.fromarray(np.stack([x * 4, y * 5, (x + y) * 2], axis=-1).astype(np.uint8)).save(tmp_path / "photo.jpg")
    Image.fromarray((x * 4).astype(np.uint8)).save(tmp_path / "depth.png")
    environment = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path / "home"), "PYTHONPATH": str(ROOT),
                   **{name: os.environ[name] for name in ("NUMBA_CACHE_DIR",) if name in os.environ}}  # compiled
    for block in shell_blocks():
        done = subprocess.run(["/bin/bash", "-euo", "pipefail", "-c", shrunk_shell(block)], cwd=tmp_path,
                              env=environment, capture_output=True, text=True, timeout=1800)
        assert done.returncode == 0, f"{block}\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
    assert (tmp_path / "runs" / "demo" / "view.html").is_file()
    assert (tmp_path / "runs" / "photo" / "model.cvq").is_file()
