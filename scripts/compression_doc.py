"""Paste the rate–distortion table of a compression bench folder's `summary.md`, and its RGB 10%
figure, into docs/compression.md between its `generated` markers. Run after
`cvqpg bench --preset compression --scenes ../shared/scenes --out results/compression --summary-only`:

    python scripts/compression_doc.py results/compression
"""

import shutil
import sys
from pathlib import Path

TITLE = "### Rate–distortion: the .cvq codec against JPEG 2000 and JPEG XL on the same field"
START, END = "<!-- generated: rd table -->\n", "<!-- end generated -->\n"
FIGURE, DOC = "compression_rd_rgb10.png", Path("docs/compression.md")


def main(folder: Path) -> None:
    summary = (folder / "summary.md").read_text()
    section = summary[summary.index(TITLE) + len(TITLE):]
    table = section[:section.index("\n### ")].strip()
    shutil.copy(folder / "rd_rgb-10.png", DOC.parent / FIGURE)
    doc = DOC.read_text()
    block = f"{START}{table}\n\n![R-D curves, RGB 10%]({FIGURE})\n{END}"
    DOC.write_text(doc[:doc.index(START)] + block + doc[doc.index(END) + len(END):])


if __name__ == "__main__":
    main(Path(sys.argv[1]))
