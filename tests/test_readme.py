"""The README's Python snippets run as written, at a smaller size and fewer steps."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
# What makes a snippet a test: the same calls, on a grid and step count that finish in seconds.
SHRINK = {"width=320, height=240": "width=48, height=36", "steps=300": "steps=4",
          'builtin_pictures("demo", 320, 240)': 'builtin_pictures("demo", 48, 36)'}


def python_snippets() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), re.DOTALL)


def test_the_readme_has_python_snippets():
    assert python_snippets()


@pytest.mark.parametrize("index", range(len(python_snippets())))
def test_readme_python_snippet_runs(index, tmp_path, monkeypatch):
    code = python_snippets()[index]
    for original, small in SHRINK.items():
        code = code.replace(original, small)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, f"README.md python snippet {index + 1}", "exec"), namespace)
    assert namespace["result"].metrics.mean["psnr"] > 0
