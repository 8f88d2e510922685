"""The Python snippets of the README and the Python API guide run as written, at a smaller size and fewer steps."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

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
