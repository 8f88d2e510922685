"""The code cites the method's own description (docs/method.md) by sections that exist."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def cited_sections() -> dict[str, set[int]]:
    cited: dict[str, set[int]] = {}
    for path in sorted((ROOT / "cvqpg").rglob("*.py")):
        for first, last in re.findall(r"method\.md §(\d+)(?:–§(\d+))?", path.read_text()):
            cited.setdefault(str(path.relative_to(ROOT)), set()).update(range(int(first), int(last or first) + 1))
    return cited


def test_code_cites_the_method_document_by_existing_sections():
    sections = {int(n) for n in re.findall(r"^## (\d+)\. ", (ROOT / "docs" / "method.md").read_text(), re.MULTILINE)}
    cited = cited_sections()
    assert len(cited) >= 10  # the kernels, optics, loss, fitting and metrics all cite it
    assert {path: numbers - sections for path, numbers in cited.items() if numbers - sections} == {}


def test_no_code_cites_a_document_outside_the_repository():
    assert [str(p) for p in (ROOT / "cvqpg").rglob("*.py") if re.search(r"\bSPEC\b(?!TRUM)", p.read_text())] == []
